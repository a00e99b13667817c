"""``torchconn-convert SOURCE… [--links N] --out DIR``: tracked video to trajectory CSVs.

Reads SLEAP (analysis .h5/.csv), DeepLabCut (.csv/.h5), WCON (.wcon/.json/.zip) or plain point
arrays (.csv/.npz), fits a curve through each frame's keypoints, resamples it to an N-link
chain and writes one trajectory CSV per trial (``DIR/<file>.csv``, or
``DIR/<file>_trial<k>.csv`` when gaps split the recording; files of one name from different
folders get their folder's name in front, ``DIR/<folder>_<file>.csv``, see
:func:`output_names`) and ``DIR/convert.json``: which source made which files, every setting as
resolved (per-format defaults included), what was found in each file (missing keypoints,
head/tail flips, gaps, body-length spread, scale) and the checks before fitting
(:mod:`torchconn.io.preflight`) for every command. The outputs replace ``DIR`` whole once all
are written (:class:`~torchconn._output.OutputFolder`). Exit codes: 0 done, 2 bad input.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from collections import Counter
from pathlib import Path

from ._cli import InputError, run_command, set_threads
from ._output import OutputFolder
from ._provenance import write_sidecar
from .cli.common import add_common, add_config, config_tables, informer
from .cli.conversion import (
    add_conversion_arguments,
    add_links,
    conversion_flags,
    conversion_settings,
    load_recordings,
    report_checks,
    resolve_links,
)
from .io.preflight import preflight
from .io.trajectory_files import write_csv

__all__ = ["main", "output_names"]


# ============================================================================ the command
PROG = "torchconn-convert"


def output_names(sources: list[Path], n_trials: list[int]) -> list[list[str]]:
    """The trajectory CSV names ``convert`` writes for each source, distinct and deterministic.

    ``<stem>.csv`` (the file name less its last suffix), or ``<stem>_trial<k>.csv`` for a source
    split into several trials. A stem that several sources share (files of one name in
    different folders, or with different suffixes) gets the source's folder name in front,
    ``<folder>_<stem>``; a name still taken (case ignored, as on macOS and Windows) gets
    ``-2``, ``-3``, ... in the order of the sources.

    Args:
        sources: the source files.
        n_trials: the number of trials of each.
    """
    stems = [Path(s).name.rsplit(".", 1)[0] for s in sources]
    shared = Counter(s.casefold() for s in stems)
    stems = [f"{Path(os.path.abspath(src)).parent.name}_{stem}"
             if shared[stem.casefold()] > 1 else stem for src, stem in zip(sources, stems,
                                                                             strict=True)]
    taken, names = set(), []
    for stem, n in zip(stems, n_trials, strict=True):
        mine = []
        for base in [stem] if n == 1 else [f"{stem}_trial{k}" for k in range(n)]:
            name, i = f"{base}.csv", 2
            while name.casefold() in taken:
                name, i = f"{base}-{i}.csv", i + 1
            taken.add(name.casefold())
            mine.append(name)
        names.append(mine)
    return names


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Convert tracked video (SLEAP, DeepLabCut, WCON or plain point arrays) to "
        "trajectory CSV files for torchconn-fit and torchconn-discrepancy: one CSV per trial "
        '(format: docs/conventions.md, section "Trajectory file format") and DIR/convert.json '
        "with the resolved settings and what was found in each file.",
    )
    p.add_argument("sources", nargs="+", type=Path,
                   help="tracking files: SLEAP analysis .h5/.csv, DeepLabCut .csv/.h5, WCON "
                   ".wcon/.json/.zip, point arrays .csv/.npz, or any file the movement package "
                   "loads (pip install 'torchconn[movement]')")
    add_links(p)
    p.add_argument("--out", type=Path, required=True, help="output directory")
    add_conversion_arguments(p)
    add_config(p, "TOML file with a [convert] table",
               "override a config value, e.g. --set convert.max_gap=0.5")
    add_common(p, figures=False, device=False)  # no figures; conversion runs on the CPU
    args = p.parse_args(argv)
    say = informer(args.quiet)

    def body() -> int:
        set_threads(args.threads)
        tables = config_tables(args.config, args.overrides)
        unknown = sorted(set(tables) - {"convert"})
        if unknown:
            raise InputError(f"unknown config section(s) {unknown}; convert reads [convert]")
        if args.links is not None and args.links < 2:
            raise InputError(f"--links must be >= 2, got {args.links}")
        conversion_flags(args)
        args.links, how = resolve_links(args.links, args.sources, args.format)
        if how:
            say(how)
        settings = conversion_settings(args, args.links, tables.get("convert"))
        with OutputFolder(args.out, command=PROG) as folder:
            return convert_into(folder, settings)

    def convert_into(folder: OutputFolder, settings) -> int:
        """Convert the sources; write the outputs into ``folder``, whose contents replace
        ``--out`` when this returns."""
        out = folder.path
        rec = load_recordings(args.sources, fmt=args.format, n_links=args.links,
                              settings=settings)
        if not rec.reports:
            raise InputError("the inputs are already trajectory CSVs; nothing to convert")
        check = preflight(rec.trajectory, body_length=rec.body_length)
        report_checks(check, say)
        trials = [[tr for (path, _, tr) in rec.trials if str(path) == rep.source]
                  for rep in rec.reports]
        names = output_names([Path(rep.source) for rep in rec.reports],
                             [len(mine) for mine in trials])
        files, lines = [], []
        for rep, mine, mine_names in zip(rec.reports, trials, names, strict=True):
            for tr, name in zip(mine, mine_names, strict=True):
                write_csv(tr, out / name)
            outs = [str(folder.final(name)) for name in mine_names]
            files.append({"source": rep.source, "outputs": outs, "report": rep.to_dict()})
            how = "given" if rep.scale_source == "given" else "median chain length"
            lines.append(f"{rep.source}: {rep.n_valid}/{rep.n_frames} frames, {len(outs)} "
                         f"trial(s), {rep.scale:.4g} units per body length ({how}) -> "
                         f"{', '.join(outs)}")
        write_sidecar(out / "convert.json", {
            "command": PROG, "argv": sys.argv[1:] if argv is None else list(argv),
            "settings": dataclasses.asdict(settings), "files": files,
            "preflight": check.to_dict(),
        })
        out = folder.commit()
        say("\n".join(lines))
        say(f"wrote {out / 'convert.json'}")
        return 0

    return run_command(PROG, body)


if __name__ == "__main__":
    sys.exit(main())
