"""``python -m torchconn.datasets NAME --out DIR``: copy a shipped recording out of the package.

Writes the tracking file and ``ATTRIBUTION.md`` (authors, source, licence) into ``DIR`` and
prints the ``torchconn-convert`` command that converts the copy. ``--list`` names the
recordings. Exit codes: 0 done, 2 bad input.
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import sys
from pathlib import Path

from .. import datasets
from .._cli import InputError, prepare_output, run_command
from ..cli.common import add_version

__all__ = ["main"]

PROG = "python -m torchconn.datasets"

#: the shipped recordings, by the name of the function that returns each
RECORDINGS = {"prickleback": datasets.prickleback}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Copy a recording that ships with torchconn, with its attribution, into a "
        "folder, and print the torchconn-convert command for it.",
    )
    p.add_argument("name", nargs="?", help=f"the recording: {', '.join(RECORDINGS)}")
    p.add_argument("--out", type=Path, help="folder to copy it into (created if missing)")
    p.add_argument("--list", action="store_true", help="list the recordings and exit")
    add_version(p)
    args = p.parse_args(argv)

    def body() -> int:
        if args.list:
            for name, make in RECORDINGS.items():
                print(f"{name}: {make().description}")
            return 0
        if args.name is None:
            raise InputError(f"name a recording ({', '.join(RECORDINGS)}), or pass --list")
        if args.name not in RECORDINGS:
            raise InputError(f"unknown recording {args.name!r}; the recordings are "
                             f"{', '.join(RECORDINGS)}")
        if args.out is None:
            raise InputError("--out DIR is required: the folder to copy the recording into")
        rec = RECORDINGS[args.name]()
        out = prepare_output(args.out)
        target = out / rec.path.name
        shutil.copyfile(rec.path, target)
        (out / "ATTRIBUTION.md").write_text(datasets.attribution(), encoding="utf-8")
        flags = rec.convert_args()[1:]
        print(f"wrote {target} ({rec.description}) and {out / 'ATTRIBUTION.md'}")
        print("convert it with:")
        print("  " + shlex.join(["torchconn-convert", str(target), *flags, "--out", "converted/"]))
        return 0

    return run_command(PROG, body)


if __name__ == "__main__":
    sys.exit(main())
