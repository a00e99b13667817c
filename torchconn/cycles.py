"""Whole cycles of a phase, and blocks of contiguous whole cycles for held-out folds.

The rule: a sample's cycle is ``⌊(φ − φ₀) / 2π⌋``, the whole cycles since the first finite
phase ``φ₀`` of its trial (batch element); a trial's ``n`` cycles ``0 … n − 1`` go to block
``⌊k · n_folds / n⌋``, so block ``f`` holds contiguous whole cycles of every trial, in time
order. Nothing is random: the same phase gives the same blocks. A NaN phase (a drop-out, or
a sample left out) belongs to no cycle and no block (``-1``).

Shapes: ``phase (..., N)`` is a trial's phase in radians (unwrapped, NaN where missing);
``...`` are the batch dims (trials). Pooled fits flatten the batch dims into the sample axis
(:func:`~torchconn.trajectory.pool_batch`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .trajectory import pool_batch

__all__ = ["FALLBACK_CYCLES", "cycle_number", "cycle_blocks", "cycle_index", "few_cycles"]

#: recordings that span at most this many cycles count as few (:func:`few_cycles`)
FALLBACK_CYCLES = 6


def cycle_number(phase: Tensor) -> Tensor:
    """``(..., N)`` whole cycles since each trial's first sample, ``⌊(φ − φ₀) / 2π⌋`` (float,
    NaN where the phase is NaN); ``phase (..., N)`` in radians."""
    start = torch.nan_to_num(phase, nan=float("inf")).amin(-1, keepdim=True)
    return torch.floor((phase - start) / (2 * math.pi))


def cycle_blocks(phase: Tensor, n_folds: int) -> Tensor:
    """``(..., N)`` int64 block in ``[0, n_folds)`` of every sample: each trial's whole cycles
    (:func:`cycle_number`) split into ``n_folds`` contiguous blocks of about equal numbers of
    cycles; -1 where the phase is NaN. A trial of fewer cycles than blocks leaves some empty."""
    cyc = cycle_number(phase)
    n_cyc = torch.nan_to_num(cyc, nan=-1.0).amax(-1, keepdim=True) + 1
    fold = torch.floor(cyc * n_folds / n_cyc)
    return torch.where(torch.isfinite(fold), fold, -1.0).long()


def cycle_index(phase: Tensor, pool: bool) -> Tensor:
    """int64 index of every sample's cycle (:func:`cycle_number`), -1 where the phase is NaN:
    ``(..., N)``, numbered from 0 per trial; pooled, ``(B·N,)`` (the batch dims flattened as
    :func:`~torchconn.trajectory.pool_batch` flattens them) and distinct across trials (trial
    ``b``'s cycles offset by ``b`` times the most cycles of any trial)."""
    cyc = cycle_number(phase)
    per_trial = int(torch.nan_to_num(cyc, nan=0.0).amax()) + 1
    trial = torch.arange(math.prod(phase.shape[:-1]), device=phase.device).reshape(
        phase.shape[:-1] + (1,))
    index = torch.where(torch.isfinite(cyc), cyc + trial * per_trial * pool, -1.0).long()
    return pool_batch(index, 0) if pool else index


def few_cycles(phase: Tensor, pool: bool) -> Tensor:
    """``(...)`` bool (pooled: ``()``) True where a trial (pooled: the trials together) spans
    at most :data:`FALLBACK_CYCLES` cycles of ``phase (..., N)``, rounded to whole cycles.

    The span ``(max φ − min φ) / 2π`` over the finite phases is counted, not the cycles seen:
    a recording of 6 cycles spans 5.9-6.1 cycles of its estimated phase while its samples
    touch 7 partial cycles. A trial without a finite phase spans 0 cycles."""
    finite = torch.isfinite(phase)
    span = (torch.where(finite, phase, -math.inf).amax(-1)
            - torch.where(finite, phase, math.inf).amin(-1)) / (2 * math.pi)
    span = span.clamp(min=0)
    if pool:
        span = span.sum()
    return torch.round(span) <= FALLBACK_CYCLES
