"""Whole cycles of a phase: which cycle each sample is in, blocks of contiguous whole cycles
(the held-out folds), and windows of a whole number of cycles.

A sample's cycle is ``⌊(φ − φ₀) / 2π⌋``, the whole cycles since an origin ``φ₀`` of its trial
(batch element) (:func:`cycle_number`); a trial's cycles ``0 … n − 1`` go to block
``⌊k · n_folds / n⌋`` (:func:`cycle_blocks`), so block ``f`` holds contiguous whole cycles of
every trial, in time order. Nothing is random: the same phase gives the same blocks. Where the
stages need different rules they are named parameters: the origin ``φ₀`` (``origin``), what a
NaN phase gets (``missing``), how pooled trials' cycles are numbered apart (``offset``), and
whether blocks cover all cycles or a centred window of whole cycles (``span``). Lists of
cycles rather than samples are split by rank (:func:`rank_blocks`) and numbered by
:func:`present_cycles`. The spectral cycle count of a recording
(:func:`torchconn.io.count_cycles`) stays in ``io``: it estimates how many cycles joint angles
hold before any phase exists, and assigns no sample to a cycle.

Shapes: ``phase (..., N)`` is a trial's phase in radians (unwrapped, NaN where missing);
``...`` are the batch dims (trials). Pooled fits flatten the batch dims into the sample axis
(:func:`~torchconn.trajectory.pool_batch`).
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor

from .trajectory import pool_batch, span_bounds

__all__ = [
    "FALLBACK_CYCLES", "cycles_note", "cycles_spanned", "cycle_number", "cycle_index",
    "cycle_blocks", "block_masks", "rank_blocks", "present_cycles", "centred_window",
    "whole_cycle_weights", "whole_cycle_phase", "trials_apart", "few_cycles"]

#: recordings that span at most this many cycles count as few (:func:`few_cycles`)
FALLBACK_CYCLES = 6

#: the origin ``φ₀`` of :func:`cycle_number`
Origin = Literal["min", "first", "grid"]


def cycle_number(phase: Tensor, *, origin: Origin = "min") -> Tensor:
    """``(..., N)`` whole cycles ``⌊(φ − φ₀) / 2π⌋`` of each sample of ``phase (..., N)``
    (radians) since its trial's origin ``φ₀`` (float, NaN where the phase is NaN).

    ``origin``: ``"min"`` (default) the trial's smallest finite phase; ``"first"`` its first
    finite phase in time (earlier cycles are negative); ``"grid"`` cycles start at the
    multiples of 2π, numbered from the trial's lowest: ``⌊φ / 2π⌋ − min ⌊φ / 2π⌋``."""
    if origin == "grid":
        cyc = torch.floor(phase / (2 * math.pi))
        return cyc - torch.nan_to_num(cyc, nan=math.inf).amin(-1, keepdim=True)
    if origin == "first":
        start = phase.gather(-1, span_bounds(torch.isfinite(phase))[0].unsqueeze(-1))
    elif origin == "min":
        start = torch.nan_to_num(phase, nan=float("inf")).amin(-1, keepdim=True)
    else:
        raise ValueError(f"cycle_number: origin must be 'min', 'first' or 'grid', got {origin!r}")
    return torch.floor((phase - start) / (2 * math.pi))


def cycle_index(phase: Tensor, pool: bool, *, origin: Origin = "min",
                missing: Literal["none", "first"] = "none",
                offset: Literal["widest", "cumulative"] = "widest") -> Tensor:
    """int64 index of every sample's cycle (:func:`cycle_number` with ``origin``): ``(..., N)``,
    numbered from 0 per trial; pooled, ``(B·N,)`` (the batch dims flattened as
    :func:`~torchconn.trajectory.pool_batch` flattens them) and distinct across trials.

    ``missing``: where the phase is NaN, ``"none"`` (default) gives -1 (no cycle); ``"first"``
    gives 0, and a sample before ``φ₀`` (``origin="first"``) also goes to cycle 0.
    ``offset``: pooled, trial ``b``'s cycles are offset by ``"widest"`` (default) ``b`` times
    the most cycles of any trial, or ``"cumulative"`` the cycles of the trials before it."""
    cyc = cycle_number(phase, origin=origin)
    if missing == "first":
        index = torch.nan_to_num(cyc, nan=0.0).clamp_min(0).to(torch.int64)
    elif missing == "none":
        index = torch.where(torch.isfinite(cyc), cyc, -1.0).long()
    else:
        raise ValueError(f"cycle_index: missing must be 'none' or 'first', got {missing!r}")
    if offset not in ("widest", "cumulative"):
        raise ValueError(f"cycle_index: offset must be 'widest' or 'cumulative', got {offset!r}")
    if not pool:
        return index
    index = index.reshape(-1, index.shape[-1])  # (B, N)
    if offset == "widest":
        count = (index.amax().clamp_min(0) + 1).expand(index.shape[0])
    else:
        count = index.amax(-1) + 1
    start = (torch.cumsum(count, 0) - count)[:, None]
    return pool_batch(torch.where(index >= 0, index + start, -1), 0)


def cycle_blocks(phase: Tensor, n_folds: int, *, origin: Origin = "min",
                 span: Literal["all", "centred"] = "all") -> Tensor:
    """``(..., N)`` int64 block in ``[0, n_folds)`` of every sample of ``phase (..., N)``:
    each trial's whole cycles ``k`` split into ``n_folds`` contiguous blocks of about equal
    numbers of cycles, ``⌊k · n_folds / n⌋``. A trial of fewer cycles than blocks leaves some
    empty.

    ``span``: ``"all"`` (default) numbers the cycles by :func:`cycle_number` (``origin``),
    ``n`` the trial's highest cycle + 1, and gives -1 where the phase is NaN; ``"centred"``
    takes the cycles of :func:`centred_window` (``origin`` unused; the phase must be finite):
    samples outside the window go to the first or last block."""
    if span == "centred":
        mono, start, n = centred_window(phase)
        cyc = torch.floor((mono - start[..., None]) / (2 * math.pi))
        return torch.floor(cyc * n_folds / n[..., None]).clamp(0, n_folds - 1).long()
    if span != "all":
        raise ValueError(f"cycle_blocks: span must be 'all' or 'centred', got {span!r}")
    cyc = cycle_number(phase, origin=origin)
    n_cyc = torch.nan_to_num(cyc, nan=-1.0).amax(-1, keepdim=True) + 1
    fold = torch.floor(cyc * n_folds / n_cyc)
    return torch.where(torch.isfinite(fold), fold, -1.0).long()


def block_masks(block: Tensor, n_folds: int) -> Tensor:
    """``(..., N, n_folds)`` bool: True where a sample's block ``block (..., N)`` (int64, as
    :func:`cycle_blocks` gives it) is ``f``; a sample of block -1 is in none."""
    return block[..., None] == torch.arange(n_folds, device=block.device)


def rank_blocks(cycle_trial: Tensor, cycle_index: Tensor, n_folds: int) -> Tensor:
    """``(n_cycles,)`` int64 block in ``[0, n_folds)`` of each cycle of a list of cycles, given
    by its trial ``cycle_trial (n_cycles,)`` and its number within the trial ``cycle_index
    (n_cycles,)``: within each trial the cycles present, in time order, are split into
    ``n_folds`` consecutive blocks by rank, ``⌊rank · n_folds / n⌋`` (``n`` the trial's cycles
    present; cycles dropped from the list do not count)."""
    fold = torch.zeros_like(cycle_trial)
    for b in torch.unique(cycle_trial).tolist():
        sel = torch.nonzero(cycle_trial == b).flatten()
        order = sel[torch.argsort(cycle_index[sel])]
        n = order.numel()
        fold[order] = (torch.arange(n, device=fold.device) * n_folds) // max(n, 1)
    return fold


def present_cycles(phase: Tensor, mask: Tensor, *, origin: Literal["start", "mask"] = "start",
                   min_samples: int = 1) -> tuple[Tensor, list[int], list[int]]:
    """The cycles of ``phase (B, T)`` that hold at least ``min_samples`` samples of ``mask
    (B, T)`` (bool), numbered 0, 1, … over all trials in turn (each trial's in time order).

    A sample's cycle within its trial is ``⌊(φ − φ₀) / 2π⌋`` with ``φ₀`` its trial's first
    sample's phase (``origin="start"``, default) or the phase at its first ``mask`` sample
    (``"mask"``).
    Returns the number of each sample's cycle ``(B, T)`` int64 (-1 outside ``mask`` or in a
    cycle of too few samples), and each numbered cycle's trial and cycle within the trial
    (lists). A cycle of too few samples is dropped from ``mask`` (in place)."""
    B = phase.shape[0]
    if origin not in ("start", "mask"):
        raise ValueError(f"present_cycles: origin must be 'start' or 'mask', got {origin!r}")
    if origin == "mask":
        ph0 = torch.stack([phase[b][mask[b]][0] if mask[b].any() else phase[b, 0]
                           for b in range(B)])[:, None]
    else:
        ph0 = phase[:, :1]
    local = torch.floor((phase - ph0) / (2 * math.pi)).long()
    local = torch.where(mask, local, torch.full_like(local, -1))
    cycle = torch.full_like(local, -1)
    trials, index, nxt = [], [], 0
    for b in range(B):
        for k in torch.unique(local[b][mask[b]]).tolist():
            sel = mask[b] & (local[b] == k)
            if int(sel.sum()) < min_samples:
                mask[b] &= ~sel
                continue
            cycle[b][sel] = nxt
            trials.append(b)
            index.append(k)
            nxt += 1
    return cycle, trials, index


def centred_window(theta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The centred window of whole cycles of an unwrapped phase ``theta (..., T)`` (finite):
    its running maximum ``(..., T)`` (tolerating small backward steps of noisy phases), the
    window's start ``(...)`` and its number of whole cycles ``(...)``, ``⌊total cycles⌋`` (at
    least 1), the leftover fraction split evenly before and after it."""
    mono = torch.cummax(theta, dim=-1).values
    total = (mono[..., -1] - mono[..., 0]) / (2 * math.pi)
    n = total.floor().clamp_min(1.0)
    start = mono[..., 0] + math.pi * (total - n).clamp_min(0.0)
    return mono, start, n


def whole_cycle_weights(theta: Tensor) -> Tensor:
    """``(..., T)`` weights in ``[0, 1]`` selecting the whole cycles of :func:`centred_window`
    of an unwrapped phase ``theta (..., T)``: each sample weighs the fraction of its sampling
    cell ``[t, t+1)`` inside the window, so the weighted mean of a periodic function of
    ``theta`` is its cycle average."""
    T = theta.shape[-1]
    mono, start, n = centred_window(theta)
    levels = torch.stack([start, start + 2 * math.pi * n], -1)  # (..., 2)
    a, b = _crossing(mono, levels).unbind(-1)
    t = torch.arange(T, dtype=theta.dtype, device=theta.device)
    cell = torch.minimum(t + 1, b[..., None]) - torch.maximum(t, a[..., None])
    return cell.clamp(0.0, 1.0)


def whole_cycle_phase(phase: Tensor) -> tuple[Tensor, Tensor]:
    """A phase with drop-outs, ``phase (..., T)`` (NaN where missing), made non-decreasing
    (each NaN filled with the phase before it, the first finite phase before that) ``(..., T)``,
    and its :func:`whole_cycle_weights`, 0 at the drop-outs ``(..., T)``."""
    finite = torch.isfinite(phase)
    filled = torch.cummax(torch.where(finite, phase, -math.inf), dim=-1).values
    first = torch.where(finite, phase, math.inf).amin(-1, keepdim=True)
    filled = torch.where(torch.isfinite(filled), filled, first)
    return filled, whole_cycle_weights(filled) * finite.to(phase.dtype)


def trials_apart(phase: Tensor) -> Tensor:
    """``phase (..., N)`` with trial ``b`` (the batch dims flattened) moved ``b · 2πK`` ahead,
    ``K = ⌈(max |φ| + 4π) / 2π⌉`` whole cycles: pooled, no two trials share a cycle, and every
    sample keeps its place within its cycle."""
    span = float(torch.nan_to_num(phase).abs().amax()) + 4 * math.pi
    trial = torch.arange(math.prod(phase.shape[:-1]), dtype=phase.dtype, device=phase.device)
    return phase + (2 * math.pi * math.ceil(span / (2 * math.pi)) * trial).reshape(
        phase.shape[:-1] + (1,))


def _crossing(mono: Tensor, levels: Tensor) -> Tensor:
    """Fractional sample positions where non-decreasing ``mono (..., T)`` reaches ``levels``."""
    T = mono.shape[-1]
    i = torch.searchsorted(mono.contiguous(), levels.contiguous()).clamp(1, T - 1)
    lo, hi = mono.gather(-1, i - 1), mono.gather(-1, i)
    frac = ((levels - lo) / (hi - lo).clamp_min(1e-300)).clamp(0.0, 1.0)
    return (i - 1).to(mono.dtype) + frac


def cycles_spanned(phase: Tensor) -> Tensor:
    """``(...)`` the cycles each trial of ``phase (..., N)`` spans: ``(max φ − min φ) / 2π``
    over its finite phases, not the cycles its samples touch (a recording of 6 cycles spans
    5.9-6.1 cycles of its estimated phase while its samples touch 7 partial cycles). A trial
    without a finite phase spans 0 cycles."""
    finite = torch.isfinite(phase)
    span = (torch.where(finite, phase, -math.inf).amax(-1)
            - torch.where(finite, phase, math.inf).amin(-1)) / (2 * math.pi)
    return span.clamp(min=0)


def few_cycles(phase: Tensor, pool: bool) -> Tensor:
    """``(...)`` bool (pooled: ``()``) True where a trial (pooled: the trials together) spans
    at most :data:`FALLBACK_CYCLES` cycles of ``phase (..., N)`` (:func:`cycles_spanned`),
    rounded to whole cycles."""
    span = cycles_spanned(phase)
    if pool:
        span = span.sum()
    return torch.round(span) <= FALLBACK_CYCLES


def cycles_note(traj, regression, alone: bool = False) -> str:
    """The recording's cycles per trial (``traj``, a phased Trajectory) against those the
    bins' window rule of ``regression`` needs: a window
    holds ``samples_per_regressor`` samples per regressor and spans at most half a cycle
    (:func:`~torchconn.regression.binning.auto_window`; a tricube window of half a cycle
    carries the weight of 0.3 cycles), so ``P`` regressors per bin need
    ``P · samples_per_regressor / 0.3`` samples per trial; ``alone``: also those of the
    connection alone (``1 + d`` regressors), which ``complexity="auto"`` tried in its place."""
    span = traj.phase.nan_to_num(nan=0.0).amax(-1) - traj.phase.nan_to_num(
        nan=float("inf")).amin(-1)
    cycles = float(span.min()) / (2 * math.pi)
    per_cycle = (traj.n_samples - 1) / max(float(span.max()) / (2 * math.pi), 1e-9)
    d = traj.shape_dim
    p = 1 + 2 * d + d * d
    spr = getattr(regression, "samples_per_regressor", 2.5)
    need = p * spr / 0.3 / per_cycle
    note = (f"this recording has {cycles:.1f} cycles per trial at {per_cycle:.0f} samples per "
            f"cycle; {p} regressors per bin (d = {d} joints) at {spr:g} samples per regressor "
            f"need at least {need:.1f} cycles per trial (1.5x that to choose the complexity "
            "on 2 of 3 blocks of cycles)")
    if alone:
        need = (1 + d) * spr / 0.3 / per_cycle
        note += (f"; the connection alone ({1 + d} regressors per bin), tried in its place, "
                 f"needs {need:.1f}, and {1.5 * need:.1f} to be checked on 2 of 3 blocks")
    return note
