"""The tracking-conversion options and the reading of recordings, shared by ``convert``,
``fit``, ``discrepancy`` and ``improve``.

- :func:`add_conversion_arguments` adds the options of
  :class:`~torchconn.io.tracking.ConversionSettings` (``--format``, ``--fps``, ...);
  :func:`conversion_flags` checks the ones given, :func:`check_conversion_table` a
  ``[convert]`` table, and :func:`conversion_settings` resolves both.
- :func:`add_links` adds ``--links`` and :func:`resolve_links` resolves it: as given, else
  from the joint columns of trajectory CSVs, else :data:`TRACKING_LINKS` for tracking files.
- :func:`load_recordings` reads trajectory CSVs or converts tracking files
  (:class:`Recordings`); :func:`report_checks` prints the checks before work on them.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

from .._cli import InputError, check_center_frame, check_keys
from .._files import check_distinct, check_file
from .._options import check_field
from ..io._table import headerless
from ..io.preflight import Preflight
from ..io.tracking import FORMATS, ConversionReport, ConversionSettings, convert_file, detect_format
from ..io.trajectory_files import joint_count, read_csv
from ..trajectory import Trajectory, pad_trials

__all__ = ["add_conversion_arguments", "conversion_settings", "conversion_flags",
           "check_conversion_table", "warn_unused_conversion", "load_recordings", "Recordings",
           "report_checks", "add_links", "resolve_links", "TRACKING_LINKS"]


#: links ``N`` of the body model for tracking files when ``--links`` is not given: odd (the
#: center body frame), and tracked rather than interpolated from 6 keypoints along the body
TRACKING_LINKS = 5

#: how to choose ``--links`` for a number of keypoints, for help texts and messages
LINKS_GUIDE = ("K keypoints along the body track at most K - 1 links (more are interpolated "
               "between keypoints; fewer, longer links average out tracking noise), and the "
               "center body frame needs an odd number (else --frame com-mean): with 8 "
               "keypoints, 7 or 5")


def add_links(p: argparse.ArgumentParser) -> None:
    """``--links N`` (default: from the inputs, :func:`resolve_links`)."""
    p.add_argument("--links", type=int, metavar="N",
                   help="links of the body model (d = N - 1 joint angles). Default: from the "
                   "joint columns r1..rd of trajectory CSVs (N = d + 1); for tracking files "
                   f"{TRACKING_LINKS}. {LINKS_GUIDE}")


def _kinds(paths: list[Path], fmt: str) -> dict[Path, str]:
    """Each input's format (``torchconn`` for a trajectory CSV), each checked to be a file."""
    kinds = {}
    for p in paths:
        check_file(p, "a trajectory CSV or tracking file")
        kinds[p] = detect_format(p) if fmt == "auto" else fmt
    return kinds


def resolve_links(links: int | None, paths: list[Path], fmt: str = "auto"
                  ) -> tuple[int, str | None]:
    """``--links`` as given, else from the inputs: ``d + 1`` for trajectory CSVs with joint
    columns ``r1..rd``, :data:`TRACKING_LINKS` for tracking files. Returns ``(N, how)``:
    ``how`` says where ``N`` came from (None when given).

    Raises:
        InputError: trajectory CSVs with different numbers of joint columns, or none.
    """
    if links is not None:
        return links, None
    kinds = _kinds(paths, fmt)
    if any(k != "torchconn" for k in kinds.values()):
        return TRACKING_LINKS, (f"--links {TRACKING_LINKS}, the default for tracking files; "
                                f"pass --links to choose: {LINKS_GUIDE}")
    counts = {p: joint_count(p) for p in paths}
    if len(set(counts.values())) > 1 or 0 in counts.values():
        found = ", ".join(f"{p}: {d}" for p, d in counts.items())
        raise InputError(f"cannot infer --links from the joint columns r1..rd of the trajectory "
                         f"CSVs ({found}); files of one body have the same number, at least "
                         "1. Pass --links N (N - 1 joint columns)")
    d = next(iter(counts.values()))
    return d + 1, f"--links {d + 1}, from the joint columns r1..r{d} of the trajectory CSVs"


def add_conversion_arguments(p: argparse.ArgumentParser, *, frame: bool = True,
                             scale: bool = True) -> None:
    """The tracking-conversion options (shared by ``convert``, ``fit``, ``discrepancy`` and
    ``improve propose``; ``frame=False`` when the command has its own ``--frame`` or a fixed
    frame, ``scale=False`` when its ``--scale`` means something else: the body length is then
    the median chain length). ``--scale`` is stored as ``convert_scale`` (:data:`_DEST`), the
    others under their field's name."""
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
    if scale:
        g.add_argument("--scale", type=float, dest="convert_scale",
                       help="file units per body length (default: median)")
    g.add_argument("--min-score", type=float,
                   help="confidence threshold (default: 0.6 for DeepLabCut, none otherwise)")
    g.add_argument("--max-gap", type=float,
                   help="split trials at gaps longer than this many seconds (default: never)")
    g.add_argument("--keypoints", help="comma-separated keypoints to use, head to tail")
    g.add_argument("--track", help="animal to use (track / individual / worm id)")


_FLAG_FIELDS = ("fps", "frame", "curve", "head", "flip_y", "scale", "min_score", "max_gap",
                "keypoints", "track")
#: the fields whose flag stores elsewhere than under its own name
_DEST = {"scale": "convert_scale"}


def conversion_flags(args) -> list[str]:
    """The tracking-conversion flags given (``["--fps", ...]``), each value's range checked
    before any work (:class:`InputError` naming the flag)."""
    given = []
    for name in _FLAG_FIELDS:
        value = getattr(args, _DEST.get(name, name), None)
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
        v = getattr(args, _DEST.get(name, name), None)
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
    kinds = _kinds(paths, fmt)
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


def report_checks(check: Preflight, say, command: str | None = None) -> None:
    """Give the checks before work (:func:`~torchconn.io.preflight.preflight`) of ``command``
    (every command's when None): the measurements and verdicts through ``say`` (the command's
    informer), each warning through :func:`warnings.warn` (``prog: warning: ...`` on
    stderr, under ``--quiet`` too)."""
    say("\n".join(check.lines(command, with_warnings=False)))
    for message in check.warnings:
        warnings.warn(message, stacklevel=2)
