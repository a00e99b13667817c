"""Reading and writing trajectories: the CSV trajectory format and a lossless NPZ form.

CSV (docs/conventions.md, "Trajectory file format"): a header row, then one row per sample on a
uniform grid, columns ``t, x, y, theta, r1, …, rd`` and optionally ``power``; several trials may
share a file with an integer ``trial`` column. Empty cells and ``nan`` are missing samples.
``power`` at row ``k`` is the mean power over ``[t_k, t_{k+1})``, so each trial's last ``power``
cell is empty. Column names are matched case-insensitively after stripping blanks; any other
column is ignored with a warning. The layout (separator, quoting, ``#`` comments, a decimal
comma) is found from the file (:func:`torchconn.io._table.read_table`), and the values are
checked for plausibility (units, wrapping, a power that cannot be dissipated) by
:func:`read_csv`.

:func:`read_csv` returns one :class:`~torchconn.trajectory.Trajectory` with batch shape
``(n_trials,)`` (trials ordered by file, then trial id); trials of different lengths are padded
with NaN at the end. :func:`write_csv` flattens any batch shape into trials and writes every
value with ``%.17g``, so reading it back is exact. :func:`save_npz` / :func:`load_npz` keep
everything -- batch shape, dtype, ``truth``, ``phase``, ``smoothed`` and ``meta`` (as JSON).
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import re
import warnings
from collections.abc import Sequence
from os import PathLike
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .. import _checks, _linalg
from .._files import check_distinct
from .._output import savez, write_bytes_atomic
from ..trajectory import GroundTruth, SmoothedState, Trajectory, pad_trials, power_problem
from ._table import first_rows, read_table

__all__ = ["read_csv", "write_csv", "save_npz", "load_npz", "count_cycles", "principal_signal",
           "joint_count"]

_POSE_COLUMNS = ("t", "x", "y", "theta")
_JOINT = re.compile(r"^r(\d+)$")
#: a trial needs this many samples
MIN_SAMPLES = 2
#: tolerated jitter of the sample spacing (fraction of dt), e.g. from rounded time stamps
_DT_JITTER = 1e-2
_NPZ_FORMAT = "torchconn.Trajectory/1"
#: largest plausible magnitude per column, and what a larger value suggests; a value beyond it
#: is an error naming file, line and column (one wild sample would otherwise wreck the
#: smoother's noise estimate and surface far downstream as an unrelated failure)
_PLAUSIBLE = {
    "t": (1e15, "time stamps beyond 1e15 lose the resolution of the sampling interval"),
    "x": (1e6, "positions are in body lengths"),
    "y": (1e6, "positions are in body lengths"),
    "theta": (1e6, "the heading is in radians"),
    "joint": (4 * math.pi, "joint angles are in radians and a joint cannot turn twice around; "
              "degrees?"),
    "power": (1e15, "a corrupted sample?"),
    "trial": (1e9, "trial ids are small integers"),
}


# ============================================================================ cycles
def principal_signal(r: Tensor) -> tuple[Tensor, Tensor]:
    """The centred shapes projected on their leading principal component.

    Args:
        r: ``(..., T, d)`` joint angles; NaN samples (drop-outs, padding) count as the mean.
    Returns:
        ``s (..., T)`` (0 at invalid samples) and ``valid (..., T)``.
    """
    if not isinstance(r, Tensor) or r.ndim < 2:
        raise ValueError(f"r must be a tensor of shape (..., T, d), got {getattr(r, 'shape', r)}")
    r = r.to(torch.float64) if not r.is_floating_point() else r
    valid = torch.isfinite(r).all(-1)  # (..., T)
    n_valid = valid.sum(-1)
    x = torch.where(valid[..., None], r, torch.zeros((), dtype=r.dtype, device=r.device))
    mean = x.sum(-2, keepdim=True) / n_valid.clamp_min(1)[..., None, None]
    x = torch.where(valid[..., None], x - mean, torch.zeros((), dtype=r.dtype, device=r.device))
    cov = x.transpose(-1, -2) @ x
    pc = _linalg.eigh(cov, "the joint angles' covariance")[1][..., -1]  # (..., d) leading eigenvector
    return (x @ pc[..., None])[..., 0], valid


def count_cycles(r: Tensor) -> Tensor:
    """Rough number of gait cycles in each trial, from the dominant frequency of ``r``.

    The peak of the (zero-padded) spectrum of :func:`principal_signal`, in cycles per sample,
    is multiplied by the span of the trial's valid samples.

    Args:
        r: ``(..., T, d)`` joint angles.
    Returns:
        ``(...,)`` cycle counts (float, 0 for trials with fewer than 2 valid samples).
    """
    s, valid = principal_signal(r)
    T = r.shape[-2]
    n_valid = valid.sum(-1)
    n_fft = 1 << max(4, math.ceil(math.log2(8 * T)))
    power = torch.fft.rfft(s, n=n_fft).abs()
    power[..., 0] = 0.0
    k = power.argmax(-1).to(s.dtype)
    idx = torch.arange(T, device=r.device)
    first = torch.where(valid, idx, T).amin(-1)
    last = torch.where(valid, idx, -1).amax(-1)
    span = (last - first + 1).clamp_min(0).to(s.dtype)
    return torch.where(n_valid >= 2, k / n_fft * span, torch.zeros_like(span))


# ============================================================================ CSV reading
@dataclasses.dataclass
class _Trial:
    file: str
    trial: int | None
    t: np.ndarray
    pose: np.ndarray
    r: np.ndarray
    power: np.ndarray | None

    @property
    def label(self) -> str:
        return self.file if self.trial is None else f"trial {self.trial} of {self.file}"


def _parse_column(values: list[str], name: str, lines: list[int], file: str) -> np.ndarray:
    col = np.char.strip(np.asarray(values, dtype=str))
    col = np.where(col == "", "nan", col)
    try:
        out = col.astype(np.float64)
    except ValueError:
        for v, line in zip(col, lines, strict=True):
            try:
                float(v)
            except ValueError:
                raise ValueError(
                    f"{file}, line {line}, column {name!r}: non-numeric value {str(v)!r} "
                    "(missing samples must be empty or 'nan')"
                ) from None
        raise  # pragma: no cover - astype and float disagree
    bad = np.isinf(out)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f"{file}, line {lines[i]}, column {name!r}: infinite value {str(col[i])!r}"
        )
    limit, why = _PLAUSIBLE["joint" if _JOINT.match(name) else name]
    with np.errstate(invalid="ignore"):
        bad = np.abs(out) > limit
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f"{file}, line {lines[i]}, column {name!r}: implausible value {str(col[i])!r} "
            f"(expected magnitude at most {limit:.4g}: {why})"
        )
    return out


def joint_count(path: str | PathLike) -> int:
    """The number of joint columns ``d`` of a trajectory CSV (the highest ``r<i>`` of its
    header row; 0 when it has none), read from the header alone."""
    first = first_rows(path, "a trajectory CSV file (t, x, y, theta, r1, ..., rd)", 1)
    header = [c.strip().strip('"').lower() for c in first[0]] if first else []
    return max((int(m.group(1)) for n in header if (m := _JOINT.match(n))), default=0)


def _read_rows(path: Path) -> tuple[list[str], list[list[str]], list[int]]:
    heads, rows, lines, _ = read_table(path, "a trajectory CSV file (t, x, y, theta, r1, ..., rd)")
    if not heads:
        raise ValueError(f"{path}: the file is empty; expected a header row "
                         "'t, x, y, theta, r1, ..., rd[, power]' and one row per sample")
    return [c.strip().strip('"').lower() for c in heads[0]], rows, lines


def _read_file(path: Path, n_joints: int | None) -> list[_Trial]:
    file = str(path)
    header, rows, lines = _read_rows(path)
    seen = set()
    for name in header:
        if name in seen and name:
            raise ValueError(f"{file}: column {name!r} appears more than once in the header")
        seen.add(name)
    unnamed = [j for j, name in enumerate(header) if not name]
    if unnamed:
        filled = [j + 1 for j in unnamed if any(r[j].strip() for r in rows)]
        if filled:  # an empty one is a trailing separator
            warnings.warn(f"{file}: ignoring column(s) {', '.join(map(str, filled))} (counted "
                          "from 1): values under an empty header cell", stacklevel=3)
    joints = sorted(int(m.group(1)) for n in header if (m := _JOINT.match(n)))
    d = max(joints, default=0)
    expected = list(_POSE_COLUMNS) + [f"r{i}" for i in range(1, max(d, 1) + 1)]
    missing = [c for c in expected if c not in header]
    if missing:
        raise ValueError(
            f"{file}: missing required column(s) {', '.join(repr(c) for c in missing)}; the "
            f"header is {', '.join(header)}, expected t, x, y, theta, r1, ..., rd[, power]"
            "[, trial]"
        )
    if n_joints is not None and d != n_joints:
        raise ValueError(f"{file}: has {d} joint column(s) r1..r{d}, expected n_joints={n_joints}")
    known = set(expected) | {"power", "trial"}
    unknown = [c for c in header if c not in known and c]
    if unknown:
        warnings.warn(f"{file}: ignoring unknown column(s) {', '.join(repr(c) for c in unknown)}",
                      stacklevel=3)
    if len(rows) == 0:
        raise ValueError(f"{file}: no data rows; a trial needs at least {MIN_SAMPLES} samples")

    for row, line in zip(rows, lines, strict=True):
        if row[0].strip().strip('"').lower() == header[0] and \
                [c.strip().strip('"').lower() for c in row] == header:
            raise ValueError(f"{file}, line {line}: the header row again (files joined into "
                             "one?); give each recording its own file, or one file with a "
                             "'trial' column")
    cols = list(zip(*rows, strict=True))
    data = {
        name: _parse_column(list(cols[header.index(name)]), name, lines, file)
        for name in expected + [c for c in ("power", "trial") if c in header]
    }
    lines_arr = np.asarray(lines)
    if "trial" in data:
        ids = data["trial"]
        bad = ~np.isfinite(ids) | (ids != np.round(ids))
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"{file}, line {lines[i]}, column 'trial': trial ids must be "
                             f"integers, got {rows[i][header.index('trial')]!r}")
        groups = [(int(k), np.flatnonzero(ids == k)) for k in np.unique(ids)]
    else:
        groups = [(None, np.arange(len(rows)))]

    trials = []
    for trial_id, idx in groups:
        label = file if trial_id is None else f"trial {trial_id} of {file}"
        if len(idx) < MIN_SAMPLES:
            raise ValueError(f"{label}: {len(idx)} sample(s); at least {MIN_SAMPLES} are needed")
        for name, col in data.items():
            if name != "trial" and np.isnan(col[idx]).all():
                raise ValueError(f"{label}: column {name!r} has no values (all empty or NaN)")
        t = data["t"][idx]
        _check_time(t, lines_arr[idx], label)
        r = np.stack([_unwrapped(data[f"r{i}"][idx], f"r{i}", lines_arr[idx], label)
                      for i in range(1, d + 1)], -1)
        pose = np.stack([data[c][idx] for c in ("x", "y", "theta")], -1)
        power = data["power"][idx] if "power" in data else None
        for i in range(d):
            _check_joint_range(r[:, i], f"r{i + 1}", label)
        _check_pose(pose, r, label)
        if power is not None:
            _check_power(power, lines_arr[idx], label)
        trials.append(_Trial(file=file, trial=trial_id, t=t, pose=pose, r=r, power=power))
    return trials


def _lines_text(lines: np.ndarray, most: int = 5) -> str:
    """``"lines 3, 5, 8 (and 12 more)"``."""
    shown = ", ".join(str(int(x)) for x in lines[:most])
    more = f" (and {len(lines) - most} more)" if len(lines) > most else ""
    return f"line{'s' if len(lines) > 1 else ''} {shown}{more}"


def _unwrapped(col: np.ndarray, name: str, lines: np.ndarray, label: str) -> np.ndarray:
    """A joint column with jumps of about 2π between neighbouring samples undone (angles
    wrapped to (−π, π]), with a warning naming them; the column itself when there are none."""
    valid = np.flatnonzero(np.isfinite(col))
    steps = np.diff(col[valid])
    jumps = np.abs(steps) > math.pi
    if not jumps.any():
        return col
    at = lines[valid[1:][jumps]]
    if (np.abs(np.abs(steps[jumps]) - 2 * math.pi) > math.pi / 2).any():
        warnings.warn(
            f"{label}, column {name!r}: the joint angle jumps by more than π between neighbouring "
            f"samples at {_lines_text(at)}, and not by a whole turn (a joint turns by much less "
            "between samples): tracking glitches, or a frame rate too low for the gait?",
            stacklevel=4)
        return col
    out = col.copy()
    out[valid] = np.unwrap(col[valid])
    # whole turns so that the median angle lies in (−π, π]
    out[valid] -= 2 * math.pi * np.round(np.median(out[valid]) / (2 * math.pi))
    warnings.warn(
        f"{label}, column {name!r}: {int(jumps.sum())} jump(s) of about 2π between neighbouring "
        f"samples ({_lines_text(at)}): joint angles wrapped to (−π, π]; unwrapped (a joint "
        "turns by much less than π between samples)", stacklevel=4)
    return out


#: fraction of a joint column's samples beyond ±π that is evidence of degrees (or an offset):
#: simulated gaits stay within ±3.0 (the optimised 3-link gait, η = 0.1), and a sine of
#: amplitude 3.3 (degrees) lies beyond π 20 % of the time
_BEYOND_PI = 0.05


def _check_joint_range(col: np.ndarray, name: str, label: str) -> None:
    """Warn when more than :data:`_BEYOND_PI` of a joint angle's samples lie beyond ±π: a
    joint angle is the bend between neighbouring links (0 when straight), and beyond ±π the
    links would cross."""
    v = col[np.isfinite(col)]
    beyond = np.abs(v) > math.pi
    if v.size and beyond.mean() > _BEYOND_PI:
        warnings.warn(
            f"{label}, column {name!r}: {100 * beyond.mean():.0f}% of the joint angles lie beyond "
            f"±π (they range from {v.min():.3g} to {v.max():.3g}, median {np.median(v):.3g}); a "
            "joint angle is the bend between neighbouring links in radians, 0 for a straight "
            "body, and beyond ±π the links would cross: degrees? (radians = degrees · π/180), "
            "or an offset (the straight body not at 0)?", stacklevel=4)


#: a body travels at most about a body length per gait cycle, and its origin moves by less than
#: about 0.1 body length per radian of joint motion; positions beyond these limits are not in
#: body lengths
_MAX_BL_PER_CYCLE = 3.0
_MAX_BL_PER_RAD = 2.0
#: joint motion per cycle (rad, norm over the joints) below which no gait is there to fit: a
#: tracker's own joint-angle noise is about 0.01 rad
_MIN_BEND = 1e-3
#: largest plausible range of the heading within one gait cycle (rad): the simulated swimmers
#: swing by 0.36-2.35 (3- and 9-link reference and optimised gaits, both frames, η = 0.1)
_MAX_SWING = 2 * math.pi


def _per_cycle(x: np.ndarray, n: int) -> np.ndarray:
    """``(k, C)`` range (max − min) of ``x (T, C)`` in each of ``k = T // n`` windows of ``n``
    samples (NaN for a window without values)."""
    k = len(x) // n
    w = x[: k * n].reshape(k, n, x.shape[1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows
        return np.nanmax(w, 1) - np.nanmin(w, 1)


def _check_pose(pose: np.ndarray, r: np.ndarray, label: str) -> None:
    """Warn about columns that do not move, positions that move further per gait cycle or per
    radian of joint motion than a body can in body lengths (millimetres or pixels?),
    joints that barely move, and a heading that swings by more than a turn within a cycle
    (degrees?)."""
    names = ["x", "y", "theta"] + [f"r{i + 1}" for i in range(r.shape[1])]
    for name, col in zip(names, np.concatenate([pose, r], 1).T, strict=True):
        v = col[np.isfinite(col)]
        if v.size > 1 and (v == v[0]).all():
            warnings.warn(f"{label}, column {name!r}: the same value ({v[0] + 0.0:g}) in every "
                          "row; a recording moves in every column (a placeholder?)",
                          stacklevel=4)
    cycles = float(count_cycles(torch.as_tensor(r)))
    n = int(round(len(r) / cycles)) if cycles >= 1.5 else 0
    if n < 2:
        return
    moved = np.hypot(*_per_cycle(pose[:, :2], n).T)
    bent = np.linalg.norm(_per_cycle(r, n), axis=-1)
    ok = np.isfinite(moved) & np.isfinite(bent) & (bent > 0)
    if ok.any() and np.median(bent[ok]) < _MIN_BEND:
        warnings.warn(
            f"{label}, columns 'r1'..'r{r.shape[1]}': the joint angles change by only "
            f"{np.median(bent[ok]):.3g} rad within a gait cycle (median over {int(ok.sum())} "
            "cycles), too little shape change to drive or to estimate a motion from: joint "
            "angles in another unit, or scaled?", stacklevel=4)
    elif ok.any():
        per_cycle = float(np.median(moved[ok]))
        per_rad = float(np.median(moved[ok] / bent[ok]))
        if per_cycle > _MAX_BL_PER_CYCLE or per_rad > _MAX_BL_PER_RAD:
            warnings.warn(
                f"{label}, columns 'x', 'y': the body moves {per_cycle:.3g} per gait cycle and "
                f"{per_rad:.3g} per radian of joint motion (medians over {int(ok.sum())} "
                "cycles), but in body lengths a swimmer moves at most about 1 per "
                "cycle and well under 1 per radian (warned above "
                f"{_MAX_BL_PER_CYCLE:g} and {_MAX_BL_PER_RAD:g}): positions in millimetres or "
                "pixels? x and y are in body lengths (divide them by the body length in the "
                "file's units); the connection's A_x, A_y scale with them", stacklevel=4)
    theta = pose[:, 2].copy()
    valid = np.isfinite(theta)
    theta[valid] = np.unwrap(theta[valid])
    swing = _per_cycle(theta[:, None], n)[:, 0]
    swing = swing[np.isfinite(swing)]
    if swing.size and np.median(swing) > _MAX_SWING:
        warnings.warn(
            f"{label}, column 'theta': the heading swings by {np.median(swing):.3g} within a "
            "gait cycle (median), more than a full turn: degrees? (theta is in radians)",
            stacklevel=4)


def _check_power(power: np.ndarray, lines: np.ndarray, label: str) -> None:
    """Refuse a ``power`` column that cannot be a dissipated power (:func:`power_problem`),
    naming the lines of its negative values."""
    negative = np.flatnonzero(power < 0)
    problem = power_problem(torch.as_tensor(power),
                            _lines_text(lines[negative]) if negative.size else "")
    if problem is not None:
        raise ValueError(f"{label}, column 'power': {problem} Remove the column to fit the "
                         "connection alone")


def _check_time(t: np.ndarray, lines: np.ndarray, label: str) -> None:
    if np.isnan(t).any():
        i = int(np.argmax(np.isnan(t)))
        raise ValueError(f"{label}, line {lines[i]}: column 't' is empty; every row needs its "
                         "sample time (write missing samples as empty pose/shape cells)")
    steps = np.diff(t)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0))
        raise ValueError(f"{label}, line {lines[i + 1]}: t must be strictly increasing, got "
                         f"t={float(t[i + 1])!r} after t={float(t[i])!r}")
    dt = (t[-1] - t[0]) / (len(t) - 1)
    jitter = np.abs(steps - dt)
    if (jitter > _DT_JITTER * dt).any():
        i = int(np.argmax(jitter))
        raise ValueError(
            f"{label}, line {lines[i + 1]}: t is not uniformly sampled (step {steps[i]:g} where "
            f"the mean step is {dt:g}); resample onto a uniform grid and write lost samples as "
            "rows with empty cells"
        )


def read_csv(
    paths: str | PathLike | Sequence[str | PathLike],
    *,
    n_joints: int | None = None,
    min_cycles: float | None = None,
) -> Trajectory:
    """Read trials from one or several CSV files (docs/conventions.md, "Trajectory file format").

    Args:
        paths: a file or a sequence of files; a file may hold several trials (``trial`` column).
        n_joints: expected number of joint columns ``d`` (checked when given).
        min_cycles: when given, every trial must hold at least this many gait cycles
            (estimated by :func:`count_cycles`).

    Returns:
        A :class:`~torchconn.trajectory.Trajectory` (float64, CPU) with ``pose (n_trials, T, 3)``,
        ``r (n_trials, T, d)``, ``power (n_trials, T)`` when any file has a power column (NaN
        for files without one), ``T`` the longest trial (shorter ones NaN-padded at the end),
        and ``meta["trials"]`` listing each trial's file, id, length and start time. Times
        too large for float64 to keep ``dt`` to about 1e-9 (Unix time stamps) are taken relative
        to the first trial's start, stored in ``meta["t_offset"]``.

    Joint angles wrapped to (−π, π] (jumps of about 2π between neighbouring samples) are
    unwrapped, with a warning naming column and lines. Warnings also name joint angles beyond
    ±π (degrees?) and positions that move further than a body can in body lengths
    (millimetres or pixels?); a file given twice is refused, two files with identical contents
    are warned about.

    Raises:
        ValueError: naming the file (and line / column) for missing columns, non-numeric
            values, non-increasing or non-uniform ``t``, a wrong number of joints, all-empty
            columns, too few samples, different sampling intervals, too few cycles, a power
            column that cannot be a dissipated power (all zero, mostly negative, zero mean),
            or a file named twice; also for a folder, a binary or compressed file, or text that
            is not UTF-8.
        FileNotFoundError: a file that does not exist.
        TypeError: ``paths`` not a path or a sequence of paths.
    """
    if isinstance(paths, (str, PathLike)):
        paths = [paths]
    elif not isinstance(paths, Sequence) or not all(isinstance(p, (str, PathLike))
                                                    for p in paths):
        raise TypeError("read_csv: paths must be a file path (str or os.PathLike) or a sequence "
                        f"of them, got {paths!r}")
    paths = [Path(p) for p in paths]
    if not paths:
        raise ValueError("read_csv: paths is empty; pass a CSV file or a list of them")
    if n_joints is not None:
        _checks.integer(n_joints, "n_joints", minimum=1, fn="read_csv")
    if min_cycles is not None:
        _checks.check_value("read_csv: min_cycles", min_cycles, float, {"ge": 0})
    check_distinct(paths)

    trials: list[_Trial] = []
    for p in paths:
        trials.extend(_read_file(p, n_joints))

    d = trials[0].r.shape[1]
    for tr in trials[1:]:
        if tr.r.shape[1] != d:
            raise ValueError(f"{tr.label} has {tr.r.shape[1]} joints but {trials[0].label} has "
                             f"{d}; all trials must come from the same swimmer")
    dts = [(tr.t[-1] - tr.t[0]) / (len(tr.t) - 1) for tr in trials]
    dt = dts[0]
    for tr, dti in zip(trials, dts, strict=True):
        if abs(dti - dt) > 1e-3 * dt:
            raise ValueError(
                f"{tr.label} is sampled every {dti:g} but {trials[0].label} every {dt:g}; "
                "trials read together must share one sampling interval (resample first)"
            )

    n_max = max(len(tr.t) for tr in trials)
    longest = max(trials, key=lambda tr: len(tr.t))
    t0s = [float(tr.t[0]) for tr in trials]
    t = torch.as_tensor(longest.t)
    # times so large that their rounding is felt in dt (Unix time stamps): relative to the
    # first trial's start, so that the grid stays uniform to the last digits
    offset = 0.0
    if np.finfo(np.float64).eps * max(max(abs(tr.t[0]), abs(tr.t[-1])) for tr in trials) \
            > 1e-9 * dt:
        offset = t0s[0]
        t0s = [t0 - offset for t0 in t0s]
        t = t - offset
    steps = torch.diff(t)
    same_start = all(abs(t0 - t0s[0]) <= 1e-9 * max(1.0, abs(t0s[0])) for t0 in t0s)
    if not same_start or (steps - steps.mean()).abs().max() > 1e-6 * steps.mean().abs():
        # rounded time stamps, or trials starting at different times: one exact uniform grid
        t = t0s[0] + torch.arange(n_max, dtype=torch.float64) * dt

    pose = pad_trials([tr.pose for tr in trials])
    r = pad_trials([tr.r for tr in trials])
    power = None
    if any(tr.power is not None for tr in trials):
        lacking = sorted({tr.file for tr in trials if tr.power is None})
        if lacking:
            warnings.warn(f"no 'power' column in {', '.join(lacking)}; their power is NaN",
                          stacklevel=2)
        power = pad_trials([tr.power if tr.power is not None else np.full(len(tr.t), np.nan)
                            for tr in trials])

    if min_cycles is not None:
        cycles = count_cycles(r)
        for tr, c in zip(trials, cycles.tolist(), strict=True):
            if c < min_cycles:
                raise ValueError(
                    f"{tr.label}: too few cycles -- found about {c:.1f} gait cycle(s), "
                    f"{min_cycles:g} are needed (min_cycles={min_cycles:g})"
                )

    meta = {
        "source": [str(p) for p in paths],
        "trials": [{"file": tr.file, "trial": tr.trial, "n_samples": len(tr.t),
                    "t0": float(tr.t[0])} for tr in trials],
        "dt": float(dt),
    }
    if offset:
        meta["t_offset"] = offset
    return Trajectory(t=t, pose=pose, r=r, power=power, meta=meta)


# ============================================================================ CSV writing
def write_csv(traj: Trajectory, path: str | PathLike) -> Path:
    """Write a trajectory in the CSV trajectory format (docs/conventions.md).

    Columns ``t, x, y, theta, r1, …, rd`` (+ ``power`` when present); the batch dims are
    flattened (C order) into trials, and a leading integer ``trial`` column ``0 … n−1`` is
    written when there is more than one. Values use ``%.17g`` (exact round trip), missing ones
    ``nan``, except missing ``power`` cells, which are empty (the last row of every trial: its
    interval ``[t_k, t_{k+1})`` ends after the recording). ``truth``, ``phase``, ``smoothed``,
    ``meta`` and the batch shape are not written: use :func:`save_npz` for those. Written
    atomically (a temporary file renamed into place).

    Returns:
        the path written.
    """
    if not isinstance(traj, Trajectory):
        raise TypeError(f"traj must be a Trajectory, got {type(traj).__name__}")
    path = Path(path)
    T, d = traj.n_samples, traj.shape_dim
    t = traj.t.detach().cpu().to(torch.float64).numpy()
    pose = traj.pose.detach().cpu().to(torch.float64).reshape(-1, T, 3).numpy()
    r = traj.r.detach().cpu().to(torch.float64).reshape(-1, T, d).numpy()
    n = pose.shape[0]
    parts = [np.broadcast_to(t, (n, T))[..., None], pose, r]
    names = ["t", "x", "y", "theta"] + [f"r{i}" for i in range(1, d + 1)]
    if traj.power is not None:
        parts.append(traj.power.detach().cpu().to(torch.float64).reshape(n, T, 1).numpy())
        names.append("power")
    fmt = ["%.17g"] * len(names)
    if n > 1:
        trial = np.broadcast_to(np.arange(n, dtype=np.float64)[:, None, None], (n, T, 1))
        parts.insert(0, trial)
        names.insert(0, "trial")
        fmt.insert(0, "%d")
    table = np.concatenate(parts, -1).reshape(n * T, len(names))
    buf = io.StringIO()
    np.savetxt(buf, table, fmt=fmt, delimiter=",", header=",".join(names), comments="")
    text = buf.getvalue()
    if traj.power is not None:
        # power is the last column; its missing cells (at least each trial's last row, whose
        # interval ends after the recording) are written empty, as docs/conventions.md has it
        text = re.sub(r",nan$", ",", text, flags=re.MULTILINE)
    return write_bytes_atomic(path, text.encode())


# ============================================================================ NPZ
def _json_default(obj):
    if isinstance(obj, Tensor):
        return obj.detach().cpu().tolist()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, PathLike):
        return str(obj)
    raise TypeError(f"meta holds a {type(obj).__name__}, which cannot be stored as JSON; "
                    "convert it to a number, string or list before saving")


def save_npz(traj: Trajectory, path: str | PathLike) -> Path:
    """Save a trajectory losslessly (arrays with their dtype and batch shape, meta as JSON),
    atomically.

    Tuples in ``meta`` come back as lists, tensors and arrays inside ``meta`` as lists.
    NumPy appends ``.npz`` to a path without it; the path written is returned.
    """
    if not isinstance(traj, Trajectory):
        raise TypeError(f"traj must be a Trajectory, got {type(traj).__name__}")
    arrays = {"format": np.array(_NPZ_FORMAT),
              "meta": np.array(json.dumps(traj.meta, default=_json_default))}
    for prefix, obj in (("", traj), ("truth.", traj.truth), ("smoothed.", traj.smoothed)):
        if obj is None:
            continue
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if isinstance(v, Tensor):
                arrays[prefix + f.name] = v.detach().cpu().numpy()
    return savez(path, **arrays)


def load_npz(path: str | PathLike) -> Trajectory:
    """Load a trajectory written by :func:`save_npz` (tensors on the CPU)."""
    path = Path(path)
    with np.load(path, allow_pickle=False) as z:
        if "format" not in z.files or str(z["format"]) != _NPZ_FORMAT:
            raise ValueError(f"{path} is not a torchconn trajectory file (no '{_NPZ_FORMAT}' "
                             "format tag); write it with torchconn.io.trajectory_files.save_npz")
        arrays = {k: torch.from_numpy(z[k].copy()) for k in z.files if k not in ("format", "meta")}
        meta = json.loads(str(z["meta"]))

    def part(prefix: str, cls):
        names = {f.name for f in dataclasses.fields(cls)}
        got = {k[len(prefix):]: v for k, v in arrays.items()
               if k.startswith(prefix) and k[len(prefix):] in names}
        return cls(**got) if got else None

    truth = part("truth.", GroundTruth)
    smoothed = part("smoothed.", SmoothedState)
    top = {k: v for k, v in arrays.items() if "." not in k}
    return Trajectory(**top, truth=truth, smoothed=smoothed, meta=meta)
