"""From tracked keypoints to an N-link swimmer's trajectory (``t, x, y, theta, r1…rd``).

Per frame, batched over frames:

1. points whose confidence is below ``min_score`` become missing; a frame needs every keypoint;
2. the image y axis is flipped when asked (image trackers count y downwards; the swimmer's
   angles are counter-clockwise in a right-handed frame);
3. a curve through the keypoints, head to tail in the order given: a natural cubic spline in
   the chord-length parameter (``curve="spline"``) or the polyline itself (``"polyline"``, exact
   for markers on a robot's links), resampled to N+1 points at equal arc length;
4. link angles, joint angles ``r_i = α_{i+1} − α_i`` (link 1 is the tail), the body frame at the
   middle link (``"center"``) or ``"com-mean"`` (mean link midpoint, mean link angle);
5. head/tail flips between frames (a tracker swapping the ends) are found by continuity and
   undone; a body that on average moves tail first is reported;
6. lengths in body lengths: the chain's length per frame, its median over frames (or a given
   ``scale`` in file units per body length);
7. time from a frame rate, or from the file's time stamps (put on a uniform grid);
8. missing frames stay as missing samples, or split the recording into trials where a gap is
   longer than ``max_gap`` seconds.

:func:`convert` returns a :class:`Conversion`: the :class:`~torchconn.trajectory.Trajectory`
(batch ``(n_trials,)``) and a :class:`ConversionReport` of everything assumed and found.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from ... import _linalg
from ... import trajectory as _trajectory
from ..._options import Options, option
from ...trajectory import Trajectory, pad_trials
from .readers import FORMATS, Keypoints, TrackingFormatError, keypoints_from_movement, read_tracking

__all__ = ["ConversionSettings", "ConversionReport", "Conversion", "convert", "convert_file",
           "convert_movement", "midline_to_pose", "resample_midline"]

#: DeepLabCut's documented default ``pcutoff``: below it a likelihood marks a point as not found
DLC_PCUTOFF = 0.6
#: dense samples along the whole spline before arc-length resampling (at least 4 per keypoint
#: interval): resampled points within 0.011 px of a 16x denser curve (46 keypoints, 200 px body)
_SPLINE_POINTS = 512
#: frames resampled per block (bounds the memory of the dense curve)
_BLOCK = 4096
#: a frame is a head/tail flip of the previous one when the reversed chain is this much closer
_FLIP_RATIO = 0.5
#: frames further apart than this are not compared for head/tail swaps
_FLIP_MAX_STEP = 3
#: keypoint order whose chain is this much longer than the points sorted along the body axis
_SCRAMBLED = 1.5


@dataclass(frozen=True, kw_only=True)
class ConversionSettings(Options):
    """How tracked points become a swimmer's trajectory (every field lands in the sidecar).

    Attributes:
        n_links: links N of the swimmer (d = N − 1 joint angles).
        frame: body frame, ``"center"`` (middle link; N odd) or ``"com-mean"``.
        curve: ``"spline"`` (natural cubic spline through the keypoints, for animals) or
            ``"polyline"`` (straight segments, for markers on a link chain).
        head: which end of the keypoint list is the head, ``"first"`` or ``"last"``; None: what
            the file says (WCON ``head``), else ``"first"``.
        flip_y: flip the image y axis; None: per format (True for SLEAP and DeepLabCut, whose
            pixel y axis points down; False for WCON and plain points).
        scale: file units (pixels, mm) per body length; None: the median chain length.
        fps: frames per second; None: the file's time stamps (WCON, points with ``t``).
        min_score: points with a lower confidence are missing; None: per format
            (DeepLabCut's ``pcutoff`` 0.6 for its likelihoods, no threshold otherwise).
        max_gap: a run of missing frames longer than this (seconds) splits the recording into
            trials; None: never split (gaps stay missing samples for the smoother).
        keypoints: names of the keypoints to use, head to tail order as listed (default: all,
            in the file's order).
        track: which animal (name or index) when a file has several.
        fix_flips: undo head/tail swaps found between frames (else only report them).
        fill_interior: a frame that lost interior keypoints (not the first or last) keeps them,
            placed on the straight line between their tracked neighbours; default off: the
            frame is missing and the smoother bridges it in time, which is the more accurate
            (docs/tracking.md), though it keeps fewer frames.
        time_origin: ``"first"`` (t = 0 at the first frame read) or ``"frame0"`` (t = frame / fps).
    """

    n_links: int = option(ge=2)
    frame: Literal["center", "com-mean"] = "center"
    curve: Literal["spline", "polyline"] = "spline"
    head: Literal["first", "last"] | None = None
    flip_y: bool | None = None
    scale: float | None = option(None, gt=0)
    fps: float | None = option(None, gt=0)
    min_score: float | None = None
    max_gap: float | None = option(None, gt=0)
    keypoints: tuple[str, ...] | None = None
    track: str | int | None = None
    fix_flips: bool = True
    fill_interior: bool = False
    time_origin: Literal["first", "frame0"] = "first"

    def __post_init__(self) -> None:
        super().__post_init__()  # every field's type and range
        if self.frame == "center" and self.n_links % 2 == 0:
            raise ValueError(f"the 'center' body frame needs an odd number of links (the middle "
                             f"link), got n_links={self.n_links}; use frame='com-mean'")
        if self.keypoints is not None:
            if not isinstance(self.keypoints, (list, tuple)) or not all(
                    isinstance(k, str) for k in self.keypoints):
                raise ValueError(f"ConversionSettings.keypoints must be a list of keypoint names, "
                                 f"got {self.keypoints!r}")
            object.__setattr__(self, "keypoints", tuple(self.keypoints))
            if len(self.keypoints) < 2:
                raise ValueError(f"keypoints must name at least 2 points along the body, got "
                                 f"{list(self.keypoints)}")


@dataclass(frozen=True)
class ConversionReport:
    """What :func:`convert` assumed and found for one file (JSON-ready via :meth:`to_dict`).

    Attributes:
        source, format: the file and its format.
        keypoints: the keypoints used, head to tail.
        settings: the settings with every per-format default resolved.
        scale: file units per body length, and ``scale_source`` (``"median"`` or ``"given"``).
        dt: sampling interval (s); ``frames``: first and last frame read.
        n_frames: frames on the grid from first to last; ``n_valid``: frames converted.
        missing_by_keypoint: frames in which this keypoint was missing or below threshold.
        filled_points: interior points placed between their neighbours (``fill_interior``).
        body_length: median, 10th and 90th percentile of the chain length (body lengths,
            so the median is 1 unless ``scale`` was given).
        flipped_frames: frames whose head and tail were swapped (undone when ``fix_flips``).
        tail_first: the body moved tail first on average (a swapped head/tail, or a reversing
            animal).
        gaps: ``[first missing frame, length]`` of each run of missing frames.
        trials: per trial ``{first_frame, n_samples, t0}``.
        notes: warnings issued.
    """

    source: str
    format: str
    keypoints: tuple[str, ...]
    settings: dict
    scale: float
    scale_source: str
    dt: float
    frames: tuple[int, int]
    n_frames: int
    n_valid: int
    missing_by_keypoint: dict
    filled_points: int
    body_length: dict
    flipped_frames: tuple[int, ...]
    tail_first: bool
    gaps: tuple[tuple[int, int], ...]
    trials: tuple[dict, ...]
    notes: tuple[str, ...]

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["flipped_frames"] = list(self.flipped_frames)
        d["n_flipped_frames"] = len(self.flipped_frames)
        d["gaps"] = [list(g) for g in self.gaps]
        return d


@dataclass(frozen=True, eq=False)
class Conversion:
    """The result of :func:`convert`.

    Attributes:
        trajectory: trials of this file, batch ``(n_trials,)``, NaN-padded to the longest.
        trial_times: per trial its own sample times ``(T_k,)`` (the trajectory's ``t`` is the
            first trial's grid).
        report: the :class:`ConversionReport`.
        body_length: ``(F,)`` chain length per grid frame in body lengths (NaN where missing).
    """

    trajectory: Trajectory
    trial_times: tuple[Tensor, ...]
    report: ConversionReport
    body_length: Tensor

    def trial(self, k: int) -> Trajectory:
        """Trial ``k`` alone, on its own time grid (unpadded)."""
        t = self.trial_times[k]
        return Trajectory(t=t, pose=self.trajectory.pose[k, :len(t)],
                          r=self.trajectory.r[k, :len(t)], meta=self.report.trials[k])


# ============================================================================ geometry
def _natural_spline_dense(p: Tensor, density: int) -> Tensor:
    """Dense points on the natural cubic spline through ``p (..., K, 2)`` in the chord-length
    parameter: ``(..., (K−1)·density + 1, 2)``. Coincident keypoints give a straight segment."""
    K = p.shape[-2]
    h = torch.linalg.vector_norm(torch.diff(p, dim=-2), dim=-1)  # (..., K-1)
    h = h.clamp_min(1e-12 * (h.amax(-1, keepdim=True) + 1e-300))
    slope = torch.diff(p, dim=-2) / h[..., None]  # (..., K-1, 2)
    m = torch.zeros_like(p)  # second derivatives, natural ends m_0 = m_{K-1} = 0
    if K > 2:
        # tridiagonal system for m_1..m_{K-2}: Thomas algorithm, a loop over keypoints only
        a = h[..., :-1]
        b = 2 * (h[..., :-1] + h[..., 1:])
        c = h[..., 1:]
        rhs = 6 * torch.diff(slope, dim=-2)  # (..., K-2, 2)
        n = K - 2
        cp, dp = [None] * n, [None] * n
        cp[0] = c[..., 0] / b[..., 0]
        dp[0] = rhs[..., 0, :] / b[..., 0, None]
        for i in range(1, n):
            den = b[..., i] - a[..., i] * cp[i - 1]
            cp[i] = c[..., i] / den
            dp[i] = (rhs[..., i, :] - a[..., i, None] * dp[i - 1]) / den[..., None]
        sol = [None] * n
        sol[-1] = dp[-1]
        for i in range(n - 2, -1, -1):
            sol[i] = dp[i] - cp[i][..., None] * sol[i + 1]
        m = torch.cat([m[..., :1, :], torch.stack(sol, -2), m[..., -1:, :]], -2)
    u = torch.arange(density, dtype=p.dtype, device=p.device) / density  # (D,) in [0, 1)
    hh = h[..., :, None, None]  # (..., K-1, 1, 1)
    s = u[:, None] * hh  # (..., K-1, D, 1) distance from the interval's start
    p0, p1 = p[..., :-1, None, :], p[..., 1:, None, :]
    m0, m1 = m[..., :-1, None, :], m[..., 1:, None, :]
    rest = hh - s
    val = (m0 * rest**3 + m1 * s**3) / (6 * hh) + (p0 / hh - m0 * hh / 6) * rest \
        + (p1 / hh - m1 * hh / 6) * s
    dense = val.reshape(*p.shape[:-2], (K - 1) * density, 2)
    return torch.cat([dense, p[..., -1:, :]], -2)


def resample_midline(points: Tensor, n_links: int, *, curve: str = "spline") -> Tensor:
    """N+1 points at equal arc length along the curve through each frame's keypoints.

    Args:
        points: ``(..., K, 2)`` keypoints in order along the body (K ≥ 2, finite).
        n_links: N.
        curve: ``"spline"`` or ``"polyline"`` (see :class:`ConversionSettings`).
    Returns:
        ``(..., N+1, 2)``, the first and last keypoints included.
    """
    if points.shape[-2] < 2:
        raise ValueError(f"a midline needs at least 2 points, got {points.shape[-2]}")
    lead = points.shape[:-2]
    flat = points.reshape(-1, *points.shape[-2:])
    out = torch.cat([_resample(flat[i:i + _BLOCK], n_links, curve)
                     for i in range(0, max(flat.shape[0], 1), _BLOCK)]) if flat.shape[0] else \
        flat.new_zeros((0, n_links + 1, 2))
    return out.reshape(*lead, n_links + 1, 2)


def _resample(points: Tensor, n_links: int, curve: str) -> Tensor:
    K = points.shape[-2]
    density = max(4, math.ceil(_SPLINE_POINTS / (K - 1)))
    dense = _natural_spline_dense(points, density) if curve == "spline" else points
    seg = torch.linalg.vector_norm(torch.diff(dense, dim=-2), dim=-1)  # (..., J-1)
    s = torch.cat([torch.zeros_like(seg[..., :1]), torch.cumsum(seg, -1)], -1)  # (..., J)
    target = s[..., -1:] * torch.linspace(0, 1, n_links + 1, dtype=s.dtype, device=s.device)
    idx = torch.searchsorted(s.contiguous(), target.contiguous(), right=True).clamp(1, s.shape[-1] - 1)
    s0, s1 = s.gather(-1, idx - 1), s.gather(-1, idx)
    w = ((target - s0) / (s1 - s0).clamp_min(1e-300)).clamp(0, 1)[..., None]
    g = lambda k: dense.gather(-2, k[..., None].expand(*k.shape, 2))  # noqa: E731
    return g(idx - 1) * (1 - w) + g(idx) * w


def midline_to_pose(q: Tensor, frame: str = "center") -> tuple[Tensor, Tensor, Tensor]:
    """Pose and joint angles of the chain through ``q (..., N+1, 2)`` (tail first).

    Returns:
        ``pose (..., 3)`` (body-frame origin and heading), ``r (..., N−1)`` wrapped to
        (−π, π], and the chain length ``(...)``.
    """
    links = torch.diff(q, dim=-2)  # (..., N, 2)
    alpha = torch.atan2(links[..., 1], links[..., 0])
    r = torch.remainder(torch.diff(alpha, dim=-1) + math.pi, 2 * math.pi) - math.pi
    N = links.shape[-2]
    length = torch.linalg.vector_norm(links, dim=-1).sum(-1)
    mid = (q[..., :-1, :] + q[..., 1:, :]) / 2
    if frame == "center":
        k = N // 2
        xy, theta = mid[..., k, :], alpha[..., k]
    else:
        unwrapped = torch.cat([alpha[..., :1], alpha[..., :1] + torch.cumsum(r, -1)], -1)
        xy, theta = mid.mean(-2), unwrapped.mean(-1)
        theta = torch.remainder(theta + math.pi, 2 * math.pi) - math.pi
    return torch.cat([xy, theta[..., None]], -1), r, length


# ============================================================================ conversion
def _resolve(settings: ConversionSettings, kp: Keypoints) -> ConversionSettings:
    """Per-format defaults made explicit (so the sidecar states them)."""
    changes = {}
    if settings.flip_y is None:
        changes["flip_y"] = kp.format in ("sleap", "dlc")
    if settings.min_score is None and kp.format == "dlc" and kp.scores is not None:
        changes["min_score"] = DLC_PCUTOFF
    if settings.head is None:
        changes["head"] = kp.head or "first"
    return dataclasses.replace(settings, **changes)


def _time_grid(kp: Keypoints, s: ConversionSettings) -> tuple[np.ndarray, float]:
    """Grid index of every frame read and the sampling interval (s)."""
    src = kp.source
    if s.fps is not None:
        return kp.frames - kp.frames[0], 1.0 / s.fps
    if kp.times is None:
        raise TrackingFormatError(f"{src}: the file has frame numbers but no time stamps; give "
                                  "the frame rate (--fps F)")
    t = kp.times
    if t.size < 2:
        raise TrackingFormatError(f"{src}: a single time stamp; a recording needs at least 2")
    steps = np.diff(t)
    dt = float(np.median(steps))
    k = np.round((t - t[0]) / dt).astype(np.int64)
    off = np.abs((t - t[0]) / dt - k)
    if (off > 0.1).any() or (np.diff(k) <= 0).any():
        i = int(np.argmax((off > 0.1) | np.r_[False, np.diff(k) <= 0]))
        raise TrackingFormatError(
            f"{src}: time stamp {t[i]:.6g} s (frame {i}) is off the uniform grid of step "
            f"{dt:.6g} s by {off[i]:.2f} steps; resample the recording or give --fps to use "
            "frame numbers instead"
        )
    return k, dt


def _flips(q: Tensor, valid: Tensor) -> Tensor:
    """``(F,)`` True for frames whose chain ``q (F, N+1, 2)`` is reversed relative to the
    majority orientation, judged by continuity between valid frames at most
    ``_FLIP_MAX_STEP`` frames apart."""
    idx = torch.nonzero(valid).flatten()
    out = torch.zeros_like(valid)
    if idx.numel() < 2:
        return out
    a, b = q[idx[:-1]], q[idx[1:]]
    same = torch.linalg.vector_norm(b - a, dim=-1).mean(-1)
    rev = torch.linalg.vector_norm(b - a.flip(-2), dim=-1).mean(-1)
    # only frames close in time are compared: across a long gap the animal may have turned
    switch = (rev < _FLIP_RATIO * same) & (torch.diff(idx) <= _FLIP_MAX_STEP)
    parity = torch.cat([torch.zeros(1, dtype=torch.long, device=q.device),
                        torch.cumsum(switch.long(), 0)]) % 2
    minority = 1 if int(parity.sum()) * 2 < parity.numel() else 0
    if int(parity.sum()) * 2 == parity.numel():
        minority = 1
    out[idx] = parity == minority
    return out


def convert(kp: Keypoints, settings: ConversionSettings, *, dtype=torch.float64) -> Conversion:
    """Convert one file's keypoints (see the module docstring for the steps).

    Args:
        kp: :class:`~torchconn.io.tracking.readers.Keypoints` from :func:`read_tracking`.
        settings: :class:`ConversionSettings`.
        dtype: floating dtype of the trajectory.

    Raises:
        TrackingFormatError: naming the file, frame or keypoint (too few keypoints, a keypoint
            not in the file, no frame above the confidence threshold, no time base, ...).
    """
    s = _resolve(settings, kp)
    src = kp.source
    notes: list[str] = []

    def note(msg: str) -> None:  # called by the steps below, so the caller of convert is 4 up
        notes.append(msg)
        warnings.warn(f"{src}: {msg}", stacklevel=4)

    sel, used = _select_keypoints(kp, s, note)
    pts, point_ok, frame_ok, filled = _complete_points(kp, s, sel, used, note)
    missing_by_kp = {n: int((~point_ok[:, j]).sum()) for j, n in enumerate(used)}
    pts, used = _chain_order(pts, frame_ok, used, s, note)
    grid, dt = _time_grid(kp, s)
    F = int(grid[-1]) + 1
    P, valid = _on_grid(pts, frame_ok, grid, F, s, dtype)
    pose, r, bl, scale, scale_source, flipped_frames = _pose_from_points(P, valid, kp, s, note)
    tail_first = _moves_tail_first(pose, valid, used, s, note)
    trials, gap_frames = _trial_spans(valid, dt, kp, s, note)

    t_off = 0.0 if s.time_origin == "first" else float(kp.frames[0]) * dt
    if kp.times is not None and s.fps is None:
        t_off = float(kp.times[0])
    n_max = max(b - a for a, b in trials)
    d = s.n_links - 1
    traj_pose = pad_trials([pose[a:b] for a, b in trials])
    traj_r = pad_trials([r[a:b] for a, b in trials]).reshape(len(trials), n_max, d)
    times = tuple(t_off + torch.arange(a, b, dtype=torch.float64) * dt for a, b in trials)
    t = times[0][0] + torch.arange(n_max, dtype=torch.float64) * dt
    trial_info = tuple({"source": src, "trial": k, "first_frame": int(kp.frames[0]) + a,
                        "n_samples": b - a, "t0": float(times[k][0])}
                       for k, (a, b) in enumerate(trials))
    settings_out = dataclasses.asdict(s)
    settings_out["keypoints"] = list(used[::-1]) if s.head == "last" else list(used)
    report = ConversionReport(
        source=src, format=kp.format, keypoints=tuple(used), settings=settings_out,
        scale=scale, scale_source=scale_source, dt=dt,
        frames=(int(kp.frames[0]), int(kp.frames[0]) + F - 1), n_frames=F,
        n_valid=int(valid.sum()), missing_by_keypoint=missing_by_kp, filled_points=filled,
        body_length={"median": float(bl[valid].median()),
                     "p10": float(torch.quantile(bl[valid], 0.1)),
                     "p90": float(torch.quantile(bl[valid], 0.9))},
        flipped_frames=flipped_frames, tail_first=tail_first, gaps=gap_frames,
        trials=trial_info, notes=tuple(notes),
    )
    meta = {"source": [src], "conversion": report.to_dict(), "trials": list(trial_info),
            "dt": dt}
    traj = Trajectory(t=t, pose=traj_pose, r=traj_r, meta=meta)
    return Conversion(trajectory=traj, trial_times=times, report=report, body_length=bl)


def _select_keypoints(kp: Keypoints, s: ConversionSettings, note) -> tuple[list[int], list[str]]:
    """The indices and names of the keypoints used, head first (``s.keypoints`` or all of the
    file's); refuses unknown names and fewer than 2 keypoints, notes fewer than N+1."""
    src = kp.source
    names = list(kp.names)
    if s.keypoints is not None:
        missing = [k for k in s.keypoints if k not in names]
        if missing:
            raise TrackingFormatError(f"{src}: keypoint(s) {', '.join(repr(m) for m in missing)} "
                                      f"not in the file; it has {', '.join(repr(n) for n in names)}")
        sel = [names.index(k) for k in s.keypoints]
    else:
        sel = list(range(len(names)))
    if len(sel) < 2:
        raise TrackingFormatError(f"{src}: only {len(sel)} keypoint ({', '.join(names)}); a midline "
                                  "needs at least 2 points along the body (better: 2 or more per link)")
    used = [names[i] for i in sel]
    if len(sel) < s.n_links + 1:
        note(f"{len(sel)} keypoints for {s.n_links} links: the curve through them bends at "
             f"{max(len(sel) - 2, 0)} of them at most, so the {s.n_links - 1} joint angles are "
             f"interpolated, not tracked (track at least {s.n_links + 1} keypoints, or use "
             "fewer links)")
    return sel, used


def _complete_points(kp: Keypoints, s: ConversionSettings, sel: list[int], used: list[str],
                     note) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The selected points ``(F, K, 2)``, which are usable ``(F, K)`` (finite and at or above
    ``min_score``), which frames are complete ``(F,)``, and how many interior points were
    filled (``fill_interior``). Refuses a file without a frame that has every keypoint."""
    src = kp.source
    pts = kp.points[:, sel].copy()
    scores = None if kp.scores is None else kp.scores[:, sel]
    if s.min_score is not None and scores is None:
        note(f"min_score {s.min_score:g} has no effect: the file holds no confidence scores")
    F_read = pts.shape[0]
    if F_read == 0:
        raise TrackingFormatError(f"{src}: no tracked frames")
    point_ok = np.isfinite(pts).all(-1)
    if s.min_score is not None and scores is not None:
        point_ok &= np.nan_to_num(scores, nan=-np.inf) >= s.min_score
    filled = 0
    if s.fill_interior and pts.shape[1] > 2:
        ends = point_ok[:, 0] & point_ok[:, -1]
        lost = ~point_ok & ends[:, None]
        filled = int(lost.sum())
        if filled:
            pts = _fill_interior(pts, point_ok)
            point_ok = point_ok | lost
    frame_ok = point_ok.all(-1)
    if not frame_ok.any():
        best = {n: float(np.nanmax(scores[:, j])) if scores is not None and np.isfinite(
            scores[:, j]).any() else None for j, n in enumerate(used)}
        worst = min(range(len(used)), key=lambda j: point_ok[:, j].sum())
        thr = (f" at the confidence threshold {s.min_score:g} (best score per keypoint: "
               + ", ".join(f"{n} {b:.3g}" if b is not None else f"{n} none"
                           for n, b in best.items()) + ")") if s.min_score is not None else ""
        raise TrackingFormatError(
            f"{src}: no frame has all {len(used)} keypoints{thr}; keypoint {used[worst]!r} is "
            f"found in {int(point_ok[:, worst].sum())} of {F_read} frames. Lower --min-score or "
            "leave out unreliable keypoints with --keypoints"
        )
    return pts, point_ok, frame_ok, filled


def _chain_order(pts: np.ndarray, frame_ok: np.ndarray, used: list[str],
                 s: ConversionSettings, note) -> tuple[np.ndarray, list[str]]:
    """The points in chain order, tail (link 1) first, and the keypoint names head first; notes
    keypoints that zig-zag in the given order and joints a polyline cannot bend."""
    ratio = _order_ratio(pts[frame_ok])
    if ratio > _SCRAMBLED:
        note(f"the keypoints in the order {', '.join(used)} zig-zag: the chain through them is "
             f"{ratio:.1f} times longer (median over frames) than through the same points "
             "sorted along the body axis. Give their order head to tail with --keypoints "
             "(sleap-io's CSV export, for one, sorts the node columns alphabetically)")
    if len(used) < s.n_links + 1 and s.curve == "polyline":
        note(f"{len(used)} keypoints for {s.n_links} links with curve='polyline': joints between "
             "keypoints fall on straight segments (their angles are 0); use the spline curve "
             "(--curve spline; curve='spline' in Python)")
    if s.head == "last":
        pts = pts[:, ::-1]
        used = used[::-1]
    # the chain runs tail (link 1) to head: reverse the head-first keypoint list
    return pts[:, ::-1].copy(), used


def _on_grid(pts: np.ndarray, frame_ok: np.ndarray, grid: np.ndarray, F: int,
             s: ConversionSettings, dtype) -> tuple[Tensor, Tensor]:
    """The points on the uniform time grid ``(F, K, 2)`` (NaN in frames not complete or not
    read; y flipped when ``flip_y``) and which grid frames are valid ``(F,)``."""
    P = torch.full((F, pts.shape[1], 2), float("nan"), dtype=dtype)
    P[torch.as_tensor(grid)] = torch.as_tensor(pts, dtype=dtype)
    valid = torch.zeros(F, dtype=torch.bool)
    valid[torch.as_tensor(grid)] = torch.as_tensor(frame_ok)
    P[~valid] = float("nan")
    if s.flip_y:
        P = P * torch.tensor([1.0, -1.0], dtype=dtype)
    return P, valid


def _pose_from_points(P: Tensor, valid: Tensor, kp: Keypoints, s: ConversionSettings, note):
    """Midline, head/tail flips and pose per grid frame. Returns ``pose (F, 3)`` (x, y in body
    lengths), ``r (F, N−1)``, the body length per frame ``(F,)`` (in body lengths), the scale
    (file units per body length) and its source (``"median"`` or ``"given"``), and the file
    frames found flipped (NaN rows where a frame is not valid)."""
    dtype = P.dtype
    safe = torch.where(valid[:, None, None], P, torch.zeros((), dtype=dtype))
    q = resample_midline(safe, s.n_links, curve=s.curve)  # (F, N+1, 2)
    flipped = _flips(q, valid)
    flipped_frames = tuple(int(kp.frames[0]) + int(i) for i in torch.nonzero(flipped).flatten())
    if flipped_frames:
        shown = ", ".join(str(f) for f in flipped_frames[:10])
        more = f" and {len(flipped_frames) - 10} more" if len(flipped_frames) > 10 else ""
        note(f"head and tail swapped in {len(flipped_frames)} frame(s) ({shown}{more}) relative "
             "to their neighbours" + ("; reordered" if s.fix_flips else
                                      "; left as tracked (fix_flips=False)"))
        if s.fix_flips:
            q = torch.where(flipped[:, None, None], q.flip(-2), q)
    pose, r, length = midline_to_pose(q, s.frame)
    nan = torch.tensor(float("nan"), dtype=dtype)
    length = torch.where(valid, length, nan)
    if s.scale is None:
        scale, scale_source = float(length[valid].median()), "median"
        if not scale > 0:
            raise TrackingFormatError(f"{kp.source}: the keypoints of every frame coincide (body "
                                      "length 0); check the keypoint columns")
    else:
        scale, scale_source = float(s.scale), "given"
    pose = torch.cat([pose[:, :2] / scale, pose[:, 2:]], -1)
    pose = torch.where(valid[:, None], pose, nan)
    r = torch.where(valid[:, None], r, nan)
    return pose, r, length / scale, scale, scale_source, flipped_frames


def _moves_tail_first(pose: Tensor, valid: Tensor, used: list[str], s: ConversionSettings,
                      note) -> bool:
    """Whether the body moves tail first on average over consecutive valid frames (mean
    forward speed more than 2 standard errors below 0); noted, as head and tail may be
    swapped (a forward swimmer moves head first)."""
    vi = torch.nonzero(valid).flatten()
    if vi.numel() <= 2:
        return False
    dxy = torch.diff(pose[vi, :2], dim=0)
    heading = pose[vi[:-1], 2]
    fwd = dxy[:, 0] * torch.cos(heading) + dxy[:, 1] * torch.sin(heading)
    consecutive = torch.diff(vi) == 1
    f = fwd[consecutive]
    if f.numel() > 2 and float(f.mean()) < -2 * float(f.std()) / math.sqrt(f.numel()):
        note("the body moves tail first on average: if the animal swims forwards, head and "
             f"tail are swapped (the keypoint list runs {used[0]!r} ... {used[-1]!r}, taken "
             f"as head ... tail; pass head='{'last' if s.head == 'first' else 'first'}')")
        return True
    return False


def _trial_spans(valid: Tensor, dt: float, kp: Keypoints, s: ConversionSettings,
                 note) -> tuple[list[tuple[int, int]], tuple[tuple[int, int], ...]]:
    """Trials as grid spans ``(start, stop)`` from first to last valid frame, the recording
    split at gaps longer than ``max_gap`` seconds (a span of one valid frame is dropped, with a
    note), and every gap as ``(first file frame, length in frames)``."""
    F = valid.shape[0]
    miss = (~valid).numpy()
    gaps = _runs(miss)
    gap_frames = tuple((int(kp.frames[0]) + a, n) for a, n in gaps)
    cut = [] if s.max_gap is None else [(a, n) for a, n in gaps if n * dt > s.max_gap]
    bounds, start = [], 0
    for a, n in cut:
        bounds.append((start, a))
        start = a + n
    bounds.append((start, F))
    trials = []
    for a, b in bounds:
        ok = np.flatnonzero(~miss[a:b])
        if ok.size < 2:
            if ok.size:
                note(f"frames {int(kp.frames[0]) + a}..{int(kp.frames[0]) + b - 1} hold a single "
                     "valid frame between long gaps; dropped")
            continue
        trials.append((a + int(ok[0]), a + int(ok[-1]) + 1))
    if not trials:
        raise TrackingFormatError(f"{kp.source}: no stretch of 2 or more valid frames between gaps "
                                  f"longer than max_gap={s.max_gap} s")
    return trials, gap_frames


def _order_ratio(pts: np.ndarray) -> float:
    """Median over frames ``pts (F, K, 2)`` of the chain length in the given keypoint order over
    the chain length with the points sorted along the frame's principal axis (1: in order)."""
    c = pts - pts.mean(1, keepdims=True)
    finite = np.isfinite(c).all((1, 2))  # coordinates so large that they overflow: no order
    pts, c = pts[finite], c[finite]
    if pts.shape[0] == 0 or pts.shape[1] < 3:
        return 1.0
    axis = _linalg.svd(torch.from_numpy(c), "the keypoints' positions")[2][:, 0].numpy()  # (F, 2)
    order = np.argsort((c * axis[:, None, :]).sum(-1), axis=1)
    srt = np.take_along_axis(pts, order[..., None], 1)

    def length(p):
        return np.linalg.norm(np.diff(p, axis=1), axis=-1).sum(-1)

    return float(np.median(length(pts) / np.maximum(length(srt), 1e-300)))


def _fill_interior(pts: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``pts (F, K, 2)`` with each missing point (``~ok``) placed on the segment between the
    nearest tracked points before and after it in the keypoint order (linear in the index)."""
    K = pts.shape[1]
    k = np.arange(K)
    prev = np.maximum.accumulate(np.where(ok, k, -1), axis=1)
    nxt = np.minimum.accumulate(np.where(ok, k, K)[:, ::-1], axis=1)[:, ::-1]
    inside = ~ok & (prev >= 0) & (nxt < K)
    p0 = np.take_along_axis(pts, prev.clip(0)[..., None], 1)
    p1 = np.take_along_axis(pts, nxt.clip(max=K - 1)[..., None], 1)
    w = ((k - prev) / np.maximum(nxt - prev, 1))[..., None]
    return np.where(inside[..., None], p0 * (1 - w) + p1 * w, pts)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``(start, length)`` of each run of True in a 1-D mask."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(m))
    return [(int(a), int(b - a)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def convert_file(path: str | PathLike, settings: ConversionSettings, *,
                 format: str | None = None) -> Conversion:
    """:func:`read_tracking` then :func:`convert`."""
    if format is not None and format not in FORMATS:
        raise TrackingFormatError(f"unknown tracking format {format!r}; known: "
                                  f"{', '.join(FORMATS)}")
    kp = read_tracking(Path(path), format, track=settings.track)
    return convert(kp, settings)


def convert_movement(ds, settings: ConversionSettings) -> Conversion:
    """A ``movement`` poses dataset converted as :func:`convert_file` converts a file:
    :func:`~torchconn.io.tracking.readers.keypoints_from_movement` then :func:`convert`.

    ``settings.track`` selects the individual; without ``settings.fps`` the dataset's ``fps``
    attribute is the frame rate (then the frames are on the grid ``1/fps`` exactly).
    """
    fps = ds.attrs.get("fps") if hasattr(ds, "attrs") else None
    if settings.fps is None and fps is not None:
        settings = dataclasses.replace(settings, fps=float(fps))
    return convert(keypoints_from_movement(ds, settings.track), settings)


def _trajectory_from_movement(ds, n_links: int, **settings) -> Trajectory:
    return convert_movement(ds, ConversionSettings(n_links=n_links, **settings)).trajectory


# Trajectory.from_movement converts through this module, which builds trajectories itself
_trajectory._from_movement = _trajectory_from_movement
