"""``torchconn-convert SOURCE… --links N --out DIR``: tracked video to trajectory CSVs.

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
import math
import os
import sys
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import torch

from ._cli import InputError, add_threads, check_center_frame, check_keys, run_command, set_threads
from ._files import check_distinct, check_file, read_toml
from ._options import check_field
from ._output import OutputFolder
from ._provenance import write_sidecar
from .io._table import headerless
from .io.preflight import preflight
from .io.tracking import FORMATS, ConversionReport, ConversionSettings, convert_file, detect_format
from .io.trajectory_files import read_csv, write_csv
from .trajectory import Trajectory, pad_trials

__all__ = ["main", "add_conversion_arguments", "conversion_settings", "load_recordings",
           "Recordings", "config_tables", "output_names", "check_conversion_table",
           "conversion_flags", "warn_unused_conversion"]


# ============================================================================ shared CLI parts
def add_conversion_arguments(p: argparse.ArgumentParser, *, frame: bool = True) -> None:
    """The tracking-conversion options (shared by ``convert``, ``fit`` and ``discrepancy``;
    ``frame=False`` when the command has its own ``--frame``)."""
    g = p.add_argument_group("tracking files (see torchconn.io.tracking.ConversionSettings)")
    g.add_argument("--format", choices=("auto",) + FORMATS, default="auto",
                   help="input format (default: from the suffix and the first lines)")
    g.add_argument("--fps", type=float, help="frame rate (default: the file's time stamps)")
    if frame:
        g.add_argument("--frame", choices=("center", "com-mean"),
                       help="body frame (default center)")
    g.add_argument("--curve", choices=("spline", "polyline"),
                   help="curve through the keypoints (default spline; polyline for robots)")
    g.add_argument("--head", choices=("first", "last"),
                   help="which end of the keypoint list is the head (default first)")
    g.add_argument("--flip-y", action=argparse.BooleanOptionalAction, default=None,
                   help="flip the image y axis (default: on for SLEAP/DeepLabCut pixels)")
    g.add_argument("--scale", type=float, help="file units per body length (default: median)")
    g.add_argument("--min-score", type=float,
                   help="confidence threshold (default: 0.6 for DeepLabCut, none otherwise)")
    g.add_argument("--max-gap", type=float,
                   help="split trials at gaps longer than this many seconds (default: never)")
    g.add_argument("--keypoints", help="comma-separated keypoints to use, head to tail")
    g.add_argument("--track", help="animal to use (track / individual / worm id)")


_FLAG_FIELDS = ("fps", "frame", "curve", "head", "flip_y", "scale", "min_score", "max_gap",
                "keypoints", "track")


def conversion_flags(args) -> list[str]:
    """The tracking-conversion flags given (``["--fps", ...]``), each value's range checked
    before any work (:class:`InputError` naming the flag)."""
    given = []
    for name in _FLAG_FIELDS:
        value = getattr(args, name, None)
        if value is None:
            continue
        flag = "--" + name.replace("_", "-")
        given.append(flag)
        if name in ("fps", "scale", "max_gap") and not (math.isfinite(value) and value > 0):
            raise InputError(f"{flag} must be a positive number, got {value}")
        if name == "min_score" and not math.isfinite(value):
            raise InputError(f"{flag} must be a finite number, got {value}")
    if args.keypoints is not None and len([k for k in args.keypoints.split(",") if k.strip()]) < 2:
        raise InputError(f"--keypoints must name at least 2 points along the body, head to tail, "
                         f"separated by commas, got {args.keypoints!r}")
    return given


def warn_unused_conversion(rec: Recordings, given: list[str]) -> None:
    """Warn that conversion flags were given for trajectory CSVs, which have no use for them."""
    if given and not rec.reports:
        warnings.warn(f"{', '.join(given)} ignored: conversion options apply to tracking files, "
                      "and the inputs are trajectory CSVs (t, x, y, theta, r1, ...) already",
                      stacklevel=2)


def config_tables(path: Path | None, overrides: list[str]) -> dict:
    """A TOML config (``[estimator]``, ``[convert]``, ...) with ``--set section.key=value``
    overrides applied (the sweep's parser)."""
    from .sweep.config import apply_overrides

    raw = read_toml(path, "--config") if path is not None else {}
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ValueError(f"--set {item!r} must look like section.key=value, e.g. "
                             "estimator.regression.ridge=1e-6 or convert.max_gap=0.5")
    return apply_overrides(raw, list(overrides))


def check_conversion_table(table) -> dict:
    """A ``[convert]`` table's keys and every value's type and range (what
    :class:`ConversionSettings` checks field by field), before any work and whatever the input;
    :class:`InputError` naming the key."""
    if table is None:
        return {}
    if not isinstance(table, dict):
        raise InputError(f"[convert] must be a table of conversion settings, got {table!r}")
    check_keys(table, [f.name for f in dataclasses.fields(ConversionSettings)
                       if f.name != "n_links"], "[convert]")
    for key, value in table.items():
        if key == "keypoints" and isinstance(value, list):
            value = tuple(value)
        try:
            check_field(ConversionSettings, key, value, f"[convert] {key}")
        except ValueError as err:
            raise InputError(str(err)) from None
    return table


def conversion_settings(args, n_links: int, table: dict | None = None) -> ConversionSettings:
    """:class:`ConversionSettings` from a ``[convert]`` table, then the command-line flags."""
    values = dict(check_conversion_table(table))
    for name in _FLAG_FIELDS:
        v = getattr(args, name, None)
        if v is not None:
            values[name] = v
    if isinstance(values.get("keypoints"), str):
        values["keypoints"] = tuple(k.strip() for k in values["keypoints"].split(",") if k.strip())
    if values.get("keypoints") is not None:
        values["keypoints"] = tuple(values["keypoints"])
    check_center_frame(n_links, values.get("frame"),
                       'pass --frame com-mean (or frame = "com-mean" in [convert])')
    return ConversionSettings(n_links=n_links, **values)


@dataclass(frozen=True, eq=False)
class Recordings:
    """Trials read from trajectory CSVs or converted from tracking files.

    Attributes:
        trajectory: all trials, batch ``(n_trials,)``.
        reports: one :class:`ConversionReport` per tracking file (empty for CSVs).
        body_length: ``(F,)`` chain length of every converted frame (None for CSVs).
        trials: per trial its own :class:`Trajectory` on its own time grid (tracking only).
        sources: ``(file, n_trials)`` per input.
    """

    trajectory: Trajectory
    reports: tuple[ConversionReport, ...]
    body_length: torch.Tensor | None
    trials: tuple[tuple[Path, int, Trajectory], ...]


def load_recordings(paths: list[Path], *, fmt: str = "auto", n_links: int,
                    settings=None, read_csv=read_csv) -> Recordings:
    """Trajectory CSVs (docs/conventions.md) or tracking files, all of one kind.

    ``settings`` may be a function returning them, called only when there are tracking files
    (so that CSV input never depends on conversion options); ``read_csv`` reads the CSVs.
    """
    kinds = {}
    for p in paths:
        check_file(p, "a trajectory CSV or tracking file")
        kinds[p] = detect_format(p) if fmt == "auto" else fmt
    if all(k == "torchconn" for k in kinds.values()):
        try:
            traj = read_csv(paths, n_joints=n_links - 1)
        except ValueError as err:
            if "expected n_joints" in str(err):
                raise InputError(f"{err}: the data do not match --links {n_links} (an N-link "
                                 "swimmer has N - 1 joint columns)") from None
            raise
        return Recordings(trajectory=traj, reports=(), body_length=None, trials=())
    if any(k == "torchconn" for k in kinds.values()):
        csvs = [str(p) for p, k in kinds.items() if k == "torchconn"]
        raise ValueError(f"trajectory CSVs ({', '.join(csvs)}) mixed with tracking files; "
                         "convert the tracking files first or pass one kind")
    check_distinct(paths)  # read_csv checks the trajectory CSVs
    for p, kind in kinds.items():
        if kind == "points" and Path(p).suffix.lower() != ".npz" and headerless(p, "a CSV file"):
            warnings.warn(f"{p} has no header row: read as tracked points (x, y pairs per "
                          "frame); a trajectory CSV starts with the header 't, x, y, theta, "
                          "r1, ..., rd[, power]'", stacklevel=2)
    settings = settings() if callable(settings) else settings
    settings = settings or ConversionSettings(n_links=n_links)
    convs = [convert_file(p, settings, format=kinds[p]) for p in paths]
    dt = convs[0].report.dt
    for c in convs[1:]:
        if abs(c.report.dt - dt) > 1e-3 * dt:
            raise ValueError(f"{c.report.source} is sampled every {c.report.dt:g} s but "
                             f"{convs[0].report.source} every {dt:g} s; files fitted together "
                             "must share one frame rate")
    n_max = max(c.trajectory.n_samples for c in convs)
    t0 = convs[0].trajectory.t[0]
    traj = Trajectory(
        t=t0 + torch.arange(n_max, dtype=torch.float64) * dt,
        pose=pad_trials([x for c in convs for x in c.trajectory.pose]),
        r=pad_trials([x for c in convs for x in c.trajectory.r]),
        meta={"source": [str(p) for p in paths], "dt": dt,
              "trials": [tr for c in convs for tr in c.report.trials]},
    )
    trials = tuple((Path(p), k, c.trial(k)) for p, c in zip(paths, convs, strict=True)
                   for k in range(c.trajectory.batch_shape[0]))
    return Recordings(trajectory=traj, reports=tuple(c.report for c in convs),
                      body_length=torch.cat([c.body_length for c in convs]), trials=trials)


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
                   ".wcon/.json/.zip, or point arrays .csv/.npz")
    p.add_argument("--links", type=int, required=True, help="number of links N (odd for the "
                   "center frame)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    add_conversion_arguments(p)
    p.add_argument("--config", type=Path, help="TOML file with a [convert] table")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set convert.max_gap=0.5")
    add_threads(p)
    args = p.parse_args(argv)

    def body() -> int:
        set_threads(args.threads)
        tables = config_tables(args.config, args.overrides)
        unknown = sorted(set(tables) - {"convert"})
        if unknown:
            raise InputError(f"unknown config section(s) {unknown}; convert reads [convert]")
        if args.links < 2:
            raise InputError(f"--links must be >= 2, got {args.links}")
        conversion_flags(args)
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
        print("\n".join(check.lines()))
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
        print("\n".join(lines))
        print(f"wrote {out / 'convert.json'}")
        return 0

    return run_command(PROG, body)


if __name__ == "__main__":
    sys.exit(main())
