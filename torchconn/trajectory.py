"""The one data container that flows through every stage.

simulate → observe → phase → smooth → regress → evaluate all read and return a
:class:`Trajectory`. Arrays carry leading batch dimensions ``...`` (typically
``(noise_levels, trials)``), then time, then coordinates: ``pose (..., T, 3)``,
``r (..., T, d)``. Stages add fields with :meth:`Trajectory.with_fields` rather than
re-shaping anything, so the batch layout chosen at simulation time survives to evaluation.

Missing samples (marker drop-outs) are NaN. Trials of different lengths are padded with NaN
at the end, on a shared sampling grid.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from ._checks import describe

__all__ = ["Trajectory", "GroundTruth", "SmoothedState", "TIME_AXIS", "COORD_AXIS", "pool_batch",
           "pad_trials", "span_bounds", "span_groups", "over_spans", "for_estimation",
           "power_problem"]

#: axis of time in ``(..., T, C)`` arrays, and of coordinates
TIME_AXIS = -2
COORD_AXIS = -1

#: the conversion behind :meth:`Trajectory.from_movement`, set by
#: :mod:`torchconn.io.tracking.convert` (which builds trajectories, so this module cannot
#: import it; ``import torchconn`` imports it)
_from_movement = None


@dataclass(frozen=True)
class GroundTruth:
    """Hidden values a simulation knows and a motion-capture rig does not.

    Attributes:
        phase: ``(..., T)`` true phase φ(t) of the SDE (unwrapped, rad).
        pose: ``(..., T, 3)`` noise-free recorded pose.
        r: ``(..., T, d)`` noise-free recorded shape.
        xi: ``(..., T, 3)`` true body velocity: the mean of ``g⁻¹ ġ`` over the recording interval
            centred on each sample (``∫ A(r)∘dr / Δt`` on the fine path).
        r_dot: ``(..., T, d)`` the mean shape velocity over the same interval.
        power: ``(..., T)`` noise-free power channel (see :mod:`torchconn.simulation.rollout`), or None.
        delta: ``(..., T, d)`` the SDE's shape offset δ(t) from ``γ_REF(φ(t))``.
    """

    phase: Tensor
    pose: Tensor
    r: Tensor
    xi: Tensor
    r_dot: Tensor
    power: Tensor | None = None
    delta: Tensor | None = None


@dataclass(frozen=True)
class SmoothedState:
    """Smoothed values and time derivatives (the Kalman smoother's output).

    Attributes:
        pose: ``(..., T, 3)`` with the heading unwrapped; ``pose_dot`` its time derivative.
        r: ``(..., T, d)``; ``r_dot`` its time derivative.
        xi: ``(..., T, 3)`` body velocity ``g⁻¹ġ`` from the smoothed pose.
    """

    pose: Tensor
    pose_dot: Tensor
    r: Tensor
    r_dot: Tensor
    xi: Tensor


@dataclass(frozen=True)
class Trajectory:
    """Recorded trials of one swimmer on one shared, uniform time grid.

    Attributes:
        t: ``(T,)`` sample times, uniform spacing ``dt``.
        pose: ``(..., T, 3)`` body-frame origin ``(x, y)`` in body lengths and heading θ (rad).
        r: ``(..., T, d)`` joint angles (rad).
        power: ``(..., T)`` recorded dissipated power, or None.
        truth: hidden ground truth of simulated data, or None.
        meta: free-form metadata (system, seeds, noise levels, source files, ...).
        phase: ``(..., T)`` phase (unwrapped, rad) -- added by the phase stage or supplied.
        smoothed: smoothed state and derivatives -- added by the smoothing stage.
    """

    t: Tensor
    pose: Tensor
    r: Tensor
    power: Tensor | None = None
    truth: GroundTruth | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    phase: Tensor | None = None
    smoothed: SmoothedState | None = None

    def __post_init__(self) -> None:
        _validate(self)

    # ------------------------------------------------------------------ sizes
    @property
    def dt(self) -> float:
        """Sampling interval."""
        return float(self.t[1] - self.t[0])

    @property
    def n_samples(self) -> int:
        return self.t.shape[0]

    @property
    def shape_dim(self) -> int:
        """``d``, the number of joint angles."""
        return self.r.shape[-1]

    @property
    def batch_shape(self) -> torch.Size:
        """Leading batch dimensions ``...`` shared by every array."""
        return self.r.shape[:-2]

    # ------------------------------------------------------------------ from other packages
    @classmethod
    def from_movement(cls, ds, n_links: int, **settings: Any) -> "Trajectory":
        """The trajectory of one animal in a ``movement`` poses dataset (an ``xarray.Dataset``
        with ``position (time, space, keypoint, individual)`` and ``confidence``, as
        ``movement.io.load_dataset`` returns it), converted as ``torchconn-convert`` converts
        a tracking file.

        Args:
            ds: the dataset (2-D poses; ``space`` holds ``x`` and ``y``).
            n_links: links N of the swimmer.
            **settings: the other fields of
                :class:`~torchconn.io.tracking.ConversionSettings` (``fps``, ``keypoints``
                head to tail, ``track`` for the individual, ``frame``, ...). ``fps`` defaults
                to the dataset's ``fps`` attribute.

        Returns:
            Trials of the recording, batch ``(n_trials,)``; ``meta["conversion"]`` is the
            :class:`~torchconn.io.tracking.ConversionReport`.

        Raises:
            TypeError: ``ds`` is not a poses dataset.
            ValueError: bad settings, or data that cannot be converted (the message names the
                dataset's source file, keypoint or frame).
        """
        return _from_movement(ds, n_links, **settings)

    # ------------------------------------------------------------------ updates
    def with_fields(self, **changes: Any) -> "Trajectory":
        """A copy with some fields set (validated); the way stages add what they computed."""
        return dataclasses.replace(self, **changes)

    def __getitem__(self, index) -> "Trajectory":
        """Index the batch dimensions only, e.g. ``traj[level, trial]`` or ``traj[:, :3]``."""
        if not isinstance(index, tuple):
            index = (index,)
        if len(index) > len(self.batch_shape):
            raise IndexError(
                f"trajectory has {len(self.batch_shape)} batch dims {tuple(self.batch_shape)}, "
                f"got an index with {len(index)} entries"
            )
        return _map_arrays(self, lambda x, k: x[index + (slice(None),) * k])

    def slice_time(self, start: int | None = None, stop: int | None = None,
                   step: int | None = None) -> "Trajectory":
        """Samples ``start:stop:step`` of every trial (every array, truth and derived fields)."""
        sl = slice(start, stop, step)
        return _map_arrays(self, lambda x, k: x[(..., sl) + (slice(None),) * k], t=self.t[sl])

    def to(self, *args, **kwargs) -> "Trajectory":
        """Move/cast every array (``torch.Tensor.to`` semantics; ``t`` keeps float64)."""
        return _map_arrays(self, lambda x, k: x.to(*args, **kwargs))


def power_problem(power: Tensor, negative_at: str = "") -> str | None:
    """Why ``power (T,)`` (one trial; NaN missing) cannot be a dissipated power, or None.

    Dissipated power is >= 0 up to noise: a column of zeros, one whose median is <= 0, or one
    whose mean is 0 (its mean removed) is not one. ``negative_at`` says where the negative
    values are (e.g. ``"lines 3, 5"``), for the message.
    """
    p = power[torch.isfinite(power)]
    if p.numel() == 0:
        return None
    if not bool(p.any()):
        return ("every value is 0; the dissipated power is positive while the body moves (a "
                "placeholder?)")
    mean, median = float(p.mean()), float(p.median())
    if median <= 0 or mean <= 1e-6 * float(p.abs().mean()):
        at = f"{negative_at}; " if negative_at else ""
        return (f"{100 * float((p < 0).double().mean()):.0f}% of the values are negative ({at}"
                f"mean {mean:.3g}, median {median:.3g}); power is the dissipated power, >= 0 up "
                "to noise: its sign flipped, or its mean removed?")
    return None


def for_estimation(traj: Trajectory, where: str, phase: Tensor | None = None) -> Trajectory:
    """``traj`` checked and in float64, for an estimator.

    Lower precisions (float32) are converted with a warning naming ``where`` (the normal
    equations need float64's digits). Refused, naming the array, column and trial: ±inf in
    ``pose``, ``r`` or ``power``; a coordinate with no finite sample in a trial; a
    ``phase (..., T)`` of another shape or dtype, with ±inf, or all NaN in a trial
    (``ValueError`` / ``TypeError``).
    """
    if not isinstance(traj, Trajectory):
        raise TypeError(f"{where}: traj must be a torchconn.Trajectory, got {type(traj).__name__}")
    if not (traj.r.dtype == torch.float64 and traj.pose.dtype == torch.float64 and (
            traj.power is None or traj.power.dtype == torch.float64)):
        found = sorted({str(x.dtype) for x in (traj.pose, traj.r, traj.power) if x is not None})
        warnings.warn(f"{where}: the trajectory holds {', '.join(found)} arrays; converted to "
                      "float64 (estimation needs its digits)", stacklevel=3)
        traj = traj.to(torch.float64)
    T = traj.n_samples
    for name, x, columns in (("pose", traj.pose, ("x", "y", "theta")),
                             ("r", traj.r, tuple(f"r{i + 1}" for i in range(traj.shape_dim))),
                             ("power", None if traj.power is None else traj.power[..., None],
                              ("power",))):
        if x is None:
            continue
        x = x.reshape(-1, T, len(columns))
        inf = torch.isinf(x)
        empty = torch.isnan(x).all(-2)  # (trials, columns)
        if bool(inf.any() | (empty.any() if name != "power" else False)):
            if bool(inf.any()):
                k, i, j = (int(v) for v in torch.nonzero(inf)[0])
                raise ValueError(f"{where}: traj.{name} holds ±inf ({columns[j]} of trial {k} "
                                 f"of the flattened batch, sample {i}); missing samples are NaN")
            k, j = (int(v) for v in torch.nonzero(empty)[0])
            raise ValueError(f"{where}: {columns[j]} (traj.{name}) of trial {k} of the flattened "
                             "batch has no finite sample; drop the trial or record the column")
    if phase is not None:
        shape = tuple(traj.batch_shape) + (T,)
        if not isinstance(phase, Tensor) or not phase.is_floating_point() or \
                tuple(phase.shape) != shape:
            raise TypeError(f"{where}: phase must be a floating-point tensor of shape {shape} "
                            f"(the trajectory's batch and samples), got {describe(phase)}")
        if bool(torch.isinf(phase).any() | torch.isnan(phase).reshape(-1, T).all(-1).any()):
            raise ValueError(f"{where}: phase holds ±inf, or a trial without one finite value; "
                             "give the phase in rad (NaN only where samples are missing), or "
                             "phase=None to estimate it")
    return traj


# arrays and how many trailing (non-batch) dims each has
_TRAILING = {"pose": 2, "r": 2, "power": 1, "phase": 1, "xi": 2, "r_dot": 2, "pose_dot": 2, "delta": 2}


def _map_arrays(traj: Trajectory, fn, t: Tensor | None = None) -> Trajectory:
    """Apply ``fn(array, k)`` (``k`` = trailing non-time dims) to every array; ``t`` replaces the
    time grid in the same step (a Trajectory validates its shapes on construction)."""

    def apply(obj):
        changes = {"t": t} if (t is not None and isinstance(obj, Trajectory)) else {}
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if isinstance(v, Tensor) and f.name in _TRAILING:
                changes[f.name] = fn(v, _TRAILING[f.name] - 1)
            elif isinstance(v, (GroundTruth, SmoothedState)):
                changes[f.name] = apply(v)
        return dataclasses.replace(obj, **changes)

    return apply(traj)


def _dtypes(tr: Trajectory) -> None:
    """Complex arrays refused; integer, boolean and float16 ones (and a ``t`` that is not
    float64) converted to float64 with a warning naming them."""
    converted = []

    def fix(obj, prefix: str = "") -> None:
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if isinstance(v, (GroundTruth, SmoothedState)):
                fix(v, f"{f.name}.")
            if not isinstance(v, Tensor):
                continue
            name = prefix + f.name
            if v.is_complex():
                raise TypeError(f"Trajectory: {name} is a complex tensor ({v.dtype}); times, "
                                "poses, joint angles and power are real numbers")
            if (name == "t" and v.dtype != torch.float64) or not v.is_floating_point() or \
                    v.dtype in (torch.float16, torch.bfloat16):
                converted.append(f"{name} ({v.dtype})")
                object.__setattr__(obj, f.name, v.to(torch.float64))

    fix(tr)
    if converted:
        warnings.warn(f"Trajectory: converted {', '.join(converted)} to float64 (torchconn "
                      "computes in floating point, with NaN for missing samples; half "
                      "precision holds too few digits; t is kept in float64)", stacklevel=5)


def _validate(tr: Trajectory) -> None:
    if not isinstance(tr.t, Tensor) or tr.t.ndim != 1:
        raise ValueError(f"t must be a 1-D tensor of sample times (T,), got {_describe(tr.t)}")
    # the rounding of t as given (before a conversion to float64)
    t_eps = torch.finfo(tr.t.dtype).eps if tr.t.is_floating_point() else 0.0
    _dtypes(tr)
    T = tr.t.shape[0]
    if T < 2:
        raise ValueError(f"a trajectory needs at least 2 samples, got T={T}")
    steps = torch.diff(tr.t)
    if not torch.isfinite(tr.t).all() or (steps <= 0).any():
        raise ValueError("t must be finite and strictly increasing")
    # relative jitter of 1e-6, or the rounding of t's magnitude (large time stamps)
    rounding = 4 * t_eps * float(tr.t.abs().max())
    if (steps - steps.mean()).abs().max() > 1e-6 * steps.mean().abs() + 1e-12 + rounding:
        raise ValueError(
            "t must be uniformly sampled; resample the recording onto a uniform grid first "
            f"(spacing ranges from {float(steps.min()):g} to {float(steps.max()):g})"
        )
    if rounding > 1e-6 * float(steps.mean().abs()) + 1e-12:
        # t given in a lower precision: its uniform grid in float64, so that the rounding of
        # the lower precision is not taken for jitter once t is float64
        grid = torch.arange(T, dtype=tr.t.dtype, device=tr.t.device)
        object.__setattr__(tr, "t", tr.t[0] + (tr.t[-1] - tr.t[0]) / (T - 1) * grid)
    if not isinstance(tr.r, Tensor) or tr.r.ndim < 2 or tr.r.shape[-2] != T or tr.r.shape[-1] < 1:
        raise ValueError(f"r must have shape (..., T={T}, d), got {_describe(tr.r)}")
    batch, d = tr.r.shape[:-2], tr.r.shape[-1]
    _expect(tr.pose, "pose", batch + (T, 3))
    if tr.power is not None:
        _expect(tr.power, "power", batch + (T,))
    if tr.phase is not None:
        _expect(tr.phase, "phase", batch + (T,))
    if tr.truth is not None:
        g = tr.truth
        _expect(g.phase, "truth.phase", batch + (T,))
        _expect(g.pose, "truth.pose", batch + (T, 3))
        _expect(g.r, "truth.r", batch + (T, d))
        _expect(g.xi, "truth.xi", batch + (T, 3))
        _expect(g.r_dot, "truth.r_dot", batch + (T, d))
        if g.power is not None:
            _expect(g.power, "truth.power", batch + (T,))
        if g.delta is not None:
            _expect(g.delta, "truth.delta", batch + (T, d))
    if tr.smoothed is not None:
        s = tr.smoothed
        for name, shape in (("pose", (T, 3)), ("pose_dot", (T, 3)), ("r", (T, d)),
                            ("r_dot", (T, d)), ("xi", (T, 3))):
            _expect(getattr(s, name), f"smoothed.{name}", batch + shape)


def _expect(x, name: str, shape: tuple[int, ...]) -> None:
    if not isinstance(x, Tensor) or tuple(x.shape) != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {_describe(x)}")


def _describe(x) -> str:
    return f"shape {tuple(x.shape)}" if isinstance(x, Tensor) else type(x).__name__


def pool_batch(x: Tensor, trailing: int) -> Tensor:
    """Flatten all batch dims into the sample axis: ``(..., T, *c) -> (N·T, *c)``, where
    ``trailing`` counts the dims after ``T`` (pooling trials into one recording)."""
    return x.reshape((-1,) + tuple(x.shape[x.ndim - trailing:]))


def pad_trials(trials: Sequence[Tensor], length: int | None = None) -> Tensor:
    """Stack trials of different lengths on one time grid: ``(T_k, *c)`` each ->
    ``(n_trials, T, *c)``, each trial at the start of the grid and NaN after its end (the
    layout of :class:`Trajectory`), ``T`` the longest trial or ``length`` (at least that).
    Arrays are converted with ``torch.as_tensor``; dtype and device are the first trial's."""
    trials = [torch.as_tensor(x) for x in trials]
    if not trials:
        raise ValueError("pad_trials: no trials given")
    first = trials[0]
    for k, x in enumerate(trials):
        if x.ndim < 1 or x.shape[1:] != first.shape[1:]:
            raise ValueError(f"pad_trials: trial {k} has shape {tuple(x.shape)}; every trial must "
                             f"be (T_k, {', '.join(map(str, first.shape[1:]))}) like trial 0")
    longest = max(x.shape[0] for x in trials)
    if length is None:
        length = longest
    elif length < longest:
        raise ValueError(f"pad_trials: length={length} is shorter than the longest trial "
                         f"({longest} samples)")
    out = torch.full((len(trials), length) + tuple(first.shape[1:]), float("nan"),
                     dtype=first.dtype, device=first.device)
    for k, x in enumerate(trials):
        out[k, : x.shape[0]] = x
    return out


def span_bounds(valid: Tensor) -> tuple[Tensor, Tensor]:
    """Each row's span in ``valid (..., T)`` (bool): the index of its first True sample and one
    past its last, ``(...)`` int64 each; a row with no True sample spans the whole row."""
    T = valid.shape[-1]
    idx = torch.arange(T, device=valid.device)
    start = torch.where(valid, idx, T).amin(-1)
    stop = torch.where(valid, idx + 1, 0).amax(-1)
    empty = stop == 0
    return torch.where(empty, 0, start), torch.where(empty, T, stop)


def span_groups(valid: Tensor) -> list[tuple[Tensor, int, int]]:
    """The rows of ``valid (B, T)`` (bool) grouped by their span, from their first to their
    last True sample: ``(rows, start, stop)`` per distinct span, ``rows`` an index tensor and
    ``stop`` exclusive (a row with no True sample spans the whole row). A statistic of trials
    padded to one grid is computed over each trial's own span as ``x[rows, start:stop]``, so
    that it does not depend on how long the other trials are."""
    start, stop = span_bounds(valid)
    spans = torch.stack([start, stop], -1)
    return [(((start == a) & (stop == b)).nonzero()[:, 0], a, b)
            for a, b in torch.unique(spans, dim=0).tolist()]


def over_spans(valid: Tensor, fn, *, in_time: bool = False):
    """``fn(rows, start, stop)`` for each group of rows of ``valid (B, T)`` that share a span
    (:func:`span_groups`), put together for all ``B`` rows; None where every row spans all of
    ``T`` (nothing to split: the caller computes the batch as it is).

    ``fn`` computes the rows ``rows`` (an index tensor) over the samples ``start:stop`` and
    returns a tensor, or a tuple or dataclass of tensors (None stays None): each
    ``(len(rows), ...)``, one value per row, or with ``in_time`` ``(len(rows), stop - start,
    ...)`` along the span, NaN outside it in the result ``(B, T, ...)``."""
    T = valid.shape[-1]
    groups = span_groups(valid)
    if len(groups) == 1 and groups[0][1:] == (0, T):
        return None
    parts = [(rows, a, b, fn(rows, a, b)) for rows, a, b in groups]

    def merge(items):
        value = items[0][3]
        if value is None:
            return None
        if isinstance(value, tuple):
            return tuple(merge([(r, a, b, v[i]) for r, a, b, v in items])
                         for i in range(len(value)))
        if dataclasses.is_dataclass(value):
            return type(value)(**{f.name: merge([(r, a, b, getattr(v, f.name))
                                                 for r, a, b, v in items])
                                  for f in dataclasses.fields(value)})
        if in_time:
            out = value.new_full((valid.shape[0], T) + value.shape[2:], float("nan"))
        else:
            out = value.new_empty((valid.shape[0],) + value.shape[1:])
        for rows, a, b, v in items:
            if in_time:
                out[rows, a:b] = v
            else:
                out[rows] = v
        return out

    return merge(parts)
