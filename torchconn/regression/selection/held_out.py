"""Leave-blocks-out fits of the phase-bin regressions by downdating their normal equations.

Every bin's regression is a weighted least-squares fit ``G β = Xᵀ W y`` with ``G = Xᵀ W X``
(:mod:`~torchconn.regression._wls`). Leaving out the rows of one block ``f`` of whole cycles
changes only these sums::

    β₋f = (G − G_f)⁻¹ (Xᵀ W y − X_fᵀ W_f y_f),

so one pass over the data that forms each block's own sums ``G_f``, ``X_fᵀ W_f y_f`` gives the
fits without every block, for every bin, at the cost of one ``P x P`` solve per bin and block
-- instead of refitting the regression once per block. The errors-in-variables correction of
the noise-aware regression is linear in ``G`` and is applied to ``G − G_f`` (with its guard);
a ridge is applied to ``G − G_f`` as the solver applies it to ``G``. The coefficients equal a
refit on the remaining rows with the same bins, window and noise level.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from .. import _wls
from ..connection import design_blocks, ridge_exemptions

__all__ = ["leave_blocks_out"]


def leave_blocks_out(s: _wls.BinnedSamples, block: Tensor, n_blocks: int, *,
                     ridges: Sequence[float] = (0.0,), delta_max: float | None = None,
                     correction: _wls.Correction | None = None,
                     min_samples: int | None = None,
                     columns: Tensor | None = None,
                     ridge_connection: bool = True) -> Tensor:
    """Per-bin coefficients of the connection design fitted without each block in turn.

    Args:
        s: the bins' samples (:func:`~torchconn.regression._wls.prepare`), ``B·M`` bins.
        block: ``(B·N,)`` int64 block of every flattened sample, in ``[0, n_blocks)``, or -1
            for a sample in no block (it is in no fit: samples without a phase).
        n_blocks: ``F``.
        ridges: ridges ``λ`` to solve for (on the unit diagonal of the standardised normal
            matrix, the intercept unpenalised, and with ``ridge_connection=False`` ``Â``'s
            columns too, as :func:`~torchconn.regression.connection_regression` solves them).
        delta_max: the regression's tube radius (None: every sample of the bin).
        correction: the regression's errors-in-variables correction, ``(gram (b, P, P), bins
            (b,) index into B·M) -> (b, P, P)``, linear in ``gram``.
        min_samples: fewest remaining samples a bin needs (default ``P + 5``, the solver's,
            with ``P`` the columns kept).
        columns: ``(P',)`` index of the design's columns to fit (None: all); the others get
            coefficient 0 (a simpler local model, e.g. without ``∂A/∂r``).

    Returns:
        ``(R, B·M, F, P, K)`` coefficients for the ``R`` ridges; NaN where a bin cannot be
        fitted without a block (too few samples left, a column without data, or a normal
        matrix that is not positive definite).
    """
    d = s.r.shape[-1]
    p = 1 + 2 * d + d * d
    keep = torch.arange(p, device=s.r.device) if columns is None else columns.to(s.r.device)
    if min_samples is None:
        min_samples = keep.numel() + 5
    total, n_max = s.rows.shape
    width = p + s.y.shape[-1]
    n_ridges = len(ridges)
    lams = torch.tensor([float(lam) for lam in ridges], dtype=s.r.dtype, device=s.r.device)
    out = s.r.new_zeros((n_ridges, total, n_blocks, p, s.y.shape[-1]))  # columns not kept: 0
    free = ridge_exemptions(d, ridge_connection, s.r.device)
    free = None if free is None else free[keep]
    # chunks of bins bound the memory of the per-block sums (F of them per bin); they do not
    # depend on the ridges asked for, so neither do a bin's sums (their padding, and so their
    # rounding, is the chunk's)
    item = s.r.dtype.itemsize
    for sel in _wls._chunks(total, n_max * width * item * 4, s.r.device):
        sums, counts = _block_sums(s, sel, block, n_blocks, delta_max)  # (b, F, C, C), (b, F)
        full = sums.sum(1, keepdim=True) - sums  # every block but f
        gram, rhs = full[..., :p, :p], full[..., :p, p:]
        few = (counts.sum(1, keepdim=True) - counts) < min_samples
        b = gram.shape[0]
        flat = gram.reshape(b * n_blocks, p, p)
        if correction is not None:
            bins = torch.arange(total, device=gram.device)[sel].repeat_interleave(n_blocks)
            flat, _ = _wls._guarded_correction(flat, correction(flat, bins))
        flat = flat[:, keep][:, :, keep]
        rhs = rhs.reshape(b * n_blocks, p, -1)[:, keep]
        # as many ridges in one batch (g·b·F, P', P') as the chunk budget holds (the solver
        # makes about three copies of its normal matrices)
        group = max(1, _wls.chunk_budget(s.r.device) // (3 * flat.numel() * item))
        for first in range(0, n_ridges, group):
            lam = lams[first:first + group]
            beta = _solve(flat.repeat(len(lam), 1, 1), rhs.repeat(len(lam), 1, 1),
                          lam.repeat_interleave(flat.shape[0]), free)
            beta = beta.reshape(len(lam), b, n_blocks, keep.numel(), -1)
            out[first:first + len(lam), sel, :, keep] = beta.masked_fill(
                few[..., None, None], math.nan)
    return out


def _block_sums(s: _wls.BinnedSamples, sel: slice, block: Tensor, n_blocks: int, delta_max):
    """``[X | y]ᵀ W [X | y]`` of each block's rows in the bins ``sel`` ``(b, F, P+K, P+K)``
    and the rows with positive weight per block ``(b, F)``.

    The rows are sorted by block, so every block's sum is one batched product over its own
    rows (padded to the largest block): about one pass over the data, not ``F``."""
    n_max = s.rows.shape[1]
    xy, w = _wls._chunk_design(s, sel, design_blocks, delta_max)
    width = xy.shape[-1]
    lab = block[s.rows[sel]]
    lab = torch.where((w > 0) & (lab >= 0), lab, n_blocks)  # n_blocks: in no sum
    count = (lab.unsqueeze(-1) == torch.arange(n_blocks, device=lab.device)).sum(-2)  # (b, F)
    order = torch.argsort(lab, dim=-1, stable=True)
    start = torch.cumsum(count, -1) - count
    longest = max(int(count.max()) if count.numel() else 0, 1)
    slot = torch.arange(longest, device=lab.device)
    pos = (start.unsqueeze(-1) + slot).clamp(max=n_max - 1)  # (b, F, L)
    row = torch.gather(order, 1, pos.flatten(1))
    part = torch.gather(xy, 1, row.unsqueeze(-1).expand(-1, -1, width))
    part = part * (slot < count.unsqueeze(-1)).flatten(1).unsqueeze(-1).to(part)
    part = part.unflatten(1, (n_blocks, longest))  # (b, F, L, C)
    return part.mT @ part, count


def _solve(gram: Tensor, rhs: Tensor, lam: Tensor, unpenalised: Tensor | None) -> Tensor:
    """``β`` of the normal equations ``(b, P, P) β = (b, P, K)`` with the solver's ridges
    ``lam (b,)``, not on the columns ``unpenalised (P,)`` (None: on every column but the
    intercept) (:func:`~torchconn.regression._wls.ridge_cholesky`); NaN where a column has no
    data (without a ridge) or the matrix is not positive definite. ``gram`` is overwritten."""
    chol, failed, dead, _ = _wls.ridge_cholesky(gram, lam, unpenalised)
    bad = failed | (dead.any(-1) & (lam == 0))
    beta = torch.cholesky_solve(rhs, chol)
    beta = beta.masked_fill(bad[:, None, None], math.nan)
    return beta.masked_fill(dead.unsqueeze(-1), math.nan)
