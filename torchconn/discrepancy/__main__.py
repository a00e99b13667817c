"""``torchconn-discrepancy DATA.csv [MORE.csv ...] --links N --out DIR``.

Also runs as ``python -m torchconn.discrepancy``. Reads the recordings (the format of
docs/conventions.md, section "Trajectory file format"), compares them with the nominal N-link swimmer,
names the missing effect(s) and writes ``DIR/report.json``, ``DIR/augmented_model.json``,
``DIR/residual_profile.csv`` and the figures; prints a readable summary. Exit codes: 0 done,
2 bad input (a message says what to fix).
"""

from __future__ import annotations

import argparse
import sys
import time
import tomllib
import warnings
from pathlib import Path

import torch

from ..io.trajectory_files import read_csv
from ..physics.systems.swimmer import NLinkSwimmer
from .effects import REGISTRY
from .workflow import DiscrepancySettings, diagnose


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="torchconn-discrepancy",
        description="Find where a recording and the nominal N-link swimmer disagree, name the "
        "missing physical effect, add it and report the gap before and after. Writes "
        "DIR/report.json, DIR/augmented_model.json, DIR/residual_profile.csv and figures. "
        "Also runs as python -m torchconn.discrepancy.",
    )
    p.add_argument("data", nargs="+", type=Path,
                   help="trajectory CSV file(s): columns t, x, y, theta, r1..rd[, power][, trial] "
                   '(format: docs/conventions.md, section "Trajectory file format")')
    p.add_argument("--links", type=int, required=True, help="number of links N (d = N - 1 joints)")
    p.add_argument("--drag-ratio", type=float, default=2.0,
                   help="nominal lateral/longitudinal drag ratio (default 2)")
    p.add_argument("--frame", default=None, choices=("center", "com-mean"),
                   help="body frame of the recorded pose (default: center)")
    p.add_argument("--link-lengths", type=float, nargs="+", default=None,
                   help="nominal link lengths (default: N equal links of total length 1)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--candidates", nargs="+", default=None, choices=sorted(REGISTRY),
                   help="effects to screen (default: all registered)")
    p.add_argument("--config", type=Path, default=None,
                   help="TOML file with a [discrepancy] table of DiscrepancySettings fields")
    p.add_argument("--alpha", type=float, default=None, help="significance level (default 0.01)")
    p.add_argument("--folds", type=int, default=None, help="cross-validation folds (default 5)")
    p.add_argument("--no-terms", action="store_true",
                   help="skip the term-by-term comparison with the Stage 4 local model")
    p.add_argument("--no-figures", action="store_true", help="do not write PNG figures")
    p.add_argument("--quiet", action="store_true", help="print only the verdict line")
    return p


def _settings(args) -> DiscrepancySettings:
    values = {}
    if args.config is not None:
        with args.config.open("rb") as fh:
            table = tomllib.load(fh)
        values.update(table.get("discrepancy", table))
        if "candidates" in values and values["candidates"] is not None:
            values["candidates"] = tuple(values["candidates"])
    if args.candidates is not None:
        values["candidates"] = tuple(args.candidates)
    if args.alpha is not None:
        values["alpha"] = args.alpha
    if args.folds is not None:
        values["n_folds"] = args.folds
    if args.no_terms:
        values["compare_terms"] = False
    known = set(DiscrepancySettings.__dataclass_fields__)
    unknown = set(values) - known
    if unknown:
        raise ValueError(f"unknown setting(s) {sorted(unknown)}; known: {sorted(known)}")
    return DiscrepancySettings(**values)


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    say = (lambda *_: None) if args.quiet else (lambda msg: print(f"  {msg}", flush=True))
    torch.set_num_threads(max(1, min(torch.get_num_threads(), 2)))
    try:
        if args.links < 2:
            raise ValueError(f"--links must be at least 2, got {args.links}")
        frame = args.frame or "center"
        system = NLinkSwimmer(args.links, drag_ratio=args.drag_ratio, frame=frame,
                              link_lengths=args.link_lengths)
        settings = _settings(args)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # unknown columns are reported by io
            try:
                traj = read_csv(args.data, n_joints=args.links - 1)
            except ValueError as err:
                if "expected n_joints" in str(err):
                    raise ValueError(f"{err}: the data do not match --links {args.links} "
                                     f"(an N-link swimmer has N - 1 joint columns)") from None
                raise
        t0 = time.time()
        if not args.quiet:
            print(f"torchconn-discrepancy: {len(args.data)} file(s), {system}")
        report = diagnose(traj, system, settings, log=say)
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    paths = report.save(args.out, figures=not args.no_figures)
    if args.quiet:
        names = ", ".join(e["name"] for e in report.effects)
        print(f"verdict: {report.verdict}" + (f" ({names})" if names else ""))
    else:
        print(report.summary())
        print(f"done in {time.time() - t0:.1f} s; wrote " + ", ".join(str(p) for p in
                                                                      paths.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
