"""Phase bins as a padded gather: which samples each phase-centred regression sees.

The paper partitions phase into ``M`` evenly spaced centres ``φ_m = 2π m / M`` and fits one
local model per centre from the samples near it. :func:`assign_bins` turns a phase series into
an index ``(..., M, Nmax)`` of the samples in each bin plus kernel weights (0 on padding), so
every downstream regression is one dense batched matmul over ``(..., M, Nmax, P)`` designs:
memory ``O(N · P · overlap)``, never ``O(M · N · P)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .. import _checks

__all__ = ["BinIndex", "assign_bins", "KERNELS", "auto_window", "auto_windows"]

#: weight kernels on the scaled distance ``s = |φ − φ_m| / (window · 2π/M)`` in ``[0, 1]``
KERNELS = ("box", "tricube", "epanechnikov")


@dataclass(frozen=True)
class BinIndex:
    """Samples of each phase bin, padded to a common length ``Nmax``.

    Attributes:
        index: ``(..., M, Nmax)`` int64 sample indices into the time axis ``N`` of the data the
            phase came from; padding slots hold a valid index with weight 0.
        weight: ``(..., M, Nmax)`` kernel weights, 0 on padding (phase dtype).
        count: ``(..., M)`` int64 number of samples inside each bin's window.
        n_bins: ``M``.
        n_points: ``N``, the length of the time axis that was binned.
        window: half-width of each bin in units of the bin spacing ``2π/M``.
        kernel: one of :data:`KERNELS`.
    """

    index: Tensor
    weight: Tensor
    count: Tensor
    n_bins: int
    n_points: int
    window: float
    kernel: str

    @property
    def batch_shape(self) -> torch.Size:
        """Leading batch dimensions ``...`` of the binned phase."""
        return self.index.shape[:-2]

    @property
    def max_count(self) -> int:
        """``Nmax``, the padded bin length (the largest bin count across the batch)."""
        return self.index.shape[-1]

    def centres(self, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
        """Bin centres ``φ_m = 2π m / M``: ``(M,)`` (rad)."""
        m = torch.arange(self.n_bins, dtype=dtype, device=device)
        return m * (2 * math.pi / self.n_bins)

    def gather(self, x: Tensor) -> Tensor:
        """The samples of every bin: ``(..., N, C) -> (..., M, Nmax, C)``.

        Padding slots repeat a real sample; multiply by :attr:`weight` (or mask with it).
        """
        batch, n = self.batch_shape, self.n_points
        if x.ndim < 2 or x.shape[:-1] != batch + (n,):
            raise ValueError(
                f"x must have shape {tuple(batch) + (n, 'C')} to match the binned phase "
                f"(..., N) = {tuple(batch) + (n,)}, got {tuple(x.shape)}"
            )
        flat = self.index.reshape(batch + (-1, 1)).expand(batch + (-1, x.shape[-1]))
        out = torch.gather(x, -2, flat)
        return out.reshape(self.index.shape + x.shape[-1:])


def kernel_weight(s: Tensor, kernel: str) -> Tensor:
    """A bin's weight at scaled distance ``s = |φ − φ_m| / window`` (``0 ≤ s ≤ 1``) from its
    centre: ``"box"`` 1, ``"tricube"`` ``(1 − s³)³``, ``"epanechnikov"`` ``1 − s²``."""
    if kernel == "box":
        return torch.ones_like(s)
    if kernel == "tricube":
        return (1 - s**3) ** 3
    return 1 - s**2


def assign_bins(
    phase: Tensor, n_bins: int, *, window: float = 0.5, kernel: str = "box"
) -> BinIndex:
    """Assign samples to ``n_bins`` phase bins centred on ``φ_m = 2π m / M``.

    A sample with phase ``φ`` belongs to bin ``m`` when its signed circular offset
    ``φ − φ_m`` lies in ``[−window · 2π/M, +window · 2π/M)``. The interval is half-open so that
    ``window = 0.5`` puts every sample in exactly one bin (a sample on a boundary goes to the
    later bin); larger windows give overlapping bins. Weights come from ``kernel`` evaluated on
    the scaled distance ``s = |φ − φ_m| / (window · 2π/M) ∈ [0, 1]``: ``"box"`` 1,
    ``"tricube"`` ``(1 − s³)³``, ``"epanechnikov"`` ``1 − s²``.

    Samples are sorted by phase once per batch element; each bin is then a contiguous (possibly
    wrapping) run of the sorted order, located with ``searchsorted``. No loop over bins or trials.

    Args:
        phase: ``(..., N)`` phase in radians, any real value (wrapped mod 2π). NaN phases (missing
            samples) belong to no bin.
        n_bins: ``M ≥ 1``.
        window: bin half-width in units of the bin spacing ``2π/M``; ``0 < window < M/2``.
        kernel: one of :data:`KERNELS`.

    Returns:
        :class:`BinIndex` with ``index``/``weight`` ``(..., M, Nmax)``, ``Nmax`` the largest bin
        count across the batch.
    """
    _checks.tensor(phase, "phase", "(..., N)", floating=True, valid=lambda t: t.ndim >= 1)
    _checks.integer(n_bins, "n_bins", minimum=1)
    if not (0 < window < n_bins / 2):
        raise ValueError(
            f"window must lie in (0, n_bins/2) = (0, {n_bins / 2}) bin spacings, so that a bin "
            f"is shorter than the whole cycle; got {window!r}"
        )
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
    if torch.isinf(phase).any():
        raise ValueError("phase contains ±inf; mark missing samples with NaN instead")

    m_bins, n = n_bins, phase.shape[-1]
    # phase in units of the bin spacing, wrapped to [0, M); remainder can round up to M exactly
    x = torch.remainder(phase * (m_bins / (2 * math.pi)), m_bins)
    x = torch.where(x >= m_bins, x - m_bins, x)
    finite = torch.isfinite(x)
    # missing samples sort after every bin edge (all edges are < M), so no bin reaches them
    xs, order = torch.sort(torch.where(finite, x, x.new_full((), m_bins + 1.0)), dim=-1)
    n_valid = finite.sum(-1, keepdim=True)  # (..., 1)

    centre = torch.arange(m_bins, dtype=x.dtype, device=x.device)
    lo = torch.remainder(centre - window, m_bins)
    hi = torch.remainder(centre + window, m_bins)
    batch = phase.shape[:-1]
    start = torch.searchsorted(xs, lo.expand(batch + (m_bins,)).contiguous(), side="left")
    end = torch.searchsorted(xs, hi.expand(batch + (m_bins,)).contiguous(), side="left")
    wraps = lo > hi  # the bin straddles phase 0
    count = torch.where(wraps, n_valid - start + end, end - start)  # (..., M)

    n_max = int(count.max()) if count.numel() else 0
    slot = torch.arange(n_max, device=x.device)
    pos = start.unsqueeze(-1) + slot  # (..., M, Nmax) positions in the sorted order
    pos = torch.where(pos >= n_valid.unsqueeze(-1), pos - n_valid.unsqueeze(-1), pos)
    filled = slot < count.unsqueeze(-1)
    pos = torch.where(filled, pos, 0).clamp_(0, max(n - 1, 0))
    flat_pos = pos.reshape(batch + (-1,))
    index = torch.gather(order, -1, flat_pos).reshape(pos.shape)

    # scaled circular distance from the bin centre
    offset = torch.gather(xs, -1, flat_pos).reshape(pos.shape) - centre.unsqueeze(-1)
    offset = torch.remainder(offset + m_bins / 2, m_bins) - m_bins / 2
    s = (offset.abs() / window).clamp_(max=1.0)
    weight = torch.where(filled, kernel_weight(s, kernel), 0.0)
    return BinIndex(index=index, weight=weight, count=count, n_bins=m_bins, n_points=n,
                    window=float(window), kernel=kernel)


def auto_window(phase: Tensor, n_bins: int, n_regressors: int, per_regressor: float) -> float:
    """Half-width (in bin spacings) holding ``per_regressor`` samples per regressor on average
    in the batch element with the fewest finite samples (the widest of
    :func:`auto_windows`)."""
    return float(auto_windows(phase, n_bins, n_regressors, per_regressor).max())


def auto_windows(phase: Tensor, n_bins: int, n_regressors: int, per_regressor: float
                 ) -> Tensor:
    """Per batch element of ``phase (..., N)``: the half-width ``(...)`` (in bin spacings,
    float64) holding ``per_regressor`` samples per regressor on average in its windows; at
    least 1, at most a quarter cycle (a window must stay local for the first-order model to
    hold). Each element's width depends on its own samples only."""
    per_spacing = torch.isfinite(phase).sum(-1).to(torch.float64) / n_bins
    # a tricube window of half-width w spacings carries the weight of ~1.2 w spacings
    window = per_regressor * n_regressors / (1.2 * per_spacing)
    return window.clamp(1.0, n_bins / 4)
