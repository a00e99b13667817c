"""Batched real Fourier series in phase, for scalar-, vector- and matrix-valued functions.

A series of order ``K`` with values of shape ``value_shape`` stores its coefficients as
``coeffs (..., 2K+1, *value_shape)`` ordered ``[a0, a1, b1, a2, b2, ..., aK, bK]``::

    f(phi) = a0 + sum_k a_k cos(k phi) + b_k sin(k phi)

so a gait ``gamma`` is ``value_shape = (d,)``, a connection ``A`` is ``(3, d)``, its shape
derivative ``(3, d, d)`` and a metric ``M`` is ``(d, d)``. Leading dims ``...`` are batch dims
(noise levels, trials); every operation broadcasts over them.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .. import _checks, _linalg

__all__ = ["FourierSeries", "fit_fourier", "fourier_design", "fourier_on_grid"]

# Relative size below which a mean term counts as zero in FourierSeries.integral.
_MEAN_TOL = 1e-12
# Smallest allowed eigenvalue ratio of the normal matrix; below it the phases do not pin down
# the coefficients and the solve would return noise.
_RCOND = 1e-12


def fourier_design(phi: Tensor, order: int) -> Tensor:
    """Design matrix ``[1, cos phi, sin phi, ..., cos K phi, sin K phi]``.

    Args:
        phi: phases ``(..., T)`` in radians.
        order: ``K >= 0``.

    Returns:
        ``(..., T, 2K+1)``.
    """
    _checks.integer(order, "order")
    _checks.tensor(phi, "phi", "(..., T)")
    if not phi.is_floating_point():
        phi = phi.to(torch.get_default_dtype())
    k = torch.arange(1, order + 1, dtype=phi.dtype, device=phi.device)
    kphi = phi[..., None] * k  # (..., T, K)
    X = torch.empty(phi.shape + (2 * order + 1,), dtype=phi.dtype, device=phi.device)
    X[..., 0] = 1.0
    X[..., 1::2] = torch.cos(kphi)
    X[..., 2::2] = torch.sin(kphi)
    return X


@dataclass(frozen=True, eq=False)
class FourierSeries:
    """Real Fourier series in phase with batched coefficients.

    Attributes:
        coeffs: ``(..., 2K+1, *value_shape)``, ordered ``[a0, a1, b1, ..., aK, bK]``.
        value_ndim: number of trailing value dims (0 scalar, 1 vector, 2 matrix, ...).
    """

    coeffs: Tensor
    value_ndim: int = 0

    def __post_init__(self) -> None:
        c = self.coeffs
        _checks.tensor(c, "coeffs", "(..., 2K+1, *value_shape)")
        _checks.integer(self.value_ndim, "value_ndim")
        if c.ndim < self.value_ndim + 1:
            raise ValueError(
                f"coeffs must have shape (..., 2K+1, *value_shape) with {self.value_ndim} value "
                f"dims, got {tuple(c.shape)}"
            )
        if c.shape[self._axis] % 2 != 1:
            raise ValueError(
                f"coeffs axis {self._axis} holds [a0, a1, b1, ...] and must have odd length "
                f"2K+1, got {c.shape[self._axis]}"
            )

    # ------------------------------------------------------------------ shapes
    @property
    def _axis(self) -> int:
        """Axis of the harmonics in ``coeffs``."""
        return -(self.value_ndim + 1)

    @property
    def order(self) -> int:
        """Highest harmonic ``K``."""
        return (self.coeffs.shape[self._axis] - 1) // 2

    @property
    def value_shape(self) -> torch.Size:
        return self.coeffs.shape[self.coeffs.ndim - self.value_ndim :]

    @property
    def batch_shape(self) -> torch.Size:
        return self.coeffs.shape[: self.coeffs.ndim - self.value_ndim - 1]

    # ------------------------------------------------------------------ evaluation
    def __call__(self, phi: Tensor | float) -> Tensor:
        """Evaluate at phases ``phi (..., P)`` -> ``(..., P, *value_shape)``.

        The leading dims of ``phi`` broadcast against :attr:`batch_shape`. A 0-d ``phi`` gives
        ``(*batch_shape, *value_shape)``. A tensor ``phi`` sets the device of the result (the
        coefficients are moved to it); a float is evaluated on the coefficients' device.
        """
        c = self.coeffs
        if isinstance(phi, Tensor) and phi.device != c.device:
            c = c.to(phi.device)
        phi = torch.as_tensor(phi, dtype=c.dtype, device=c.device)
        scalar = phi.ndim == 0
        if scalar:
            phi = phi[None]
        X = fourier_design(phi, self.order)  # (..., P, n)
        flat = c.reshape(self.batch_shape + (2 * self.order + 1, -1))  # (*batch, n, V)
        out = X @ flat  # broadcasts batch dims -> (..., P, V)
        out = out.reshape(out.shape[:-1] + self.value_shape)
        return out.squeeze(-1 - self.value_ndim) if scalar else out

    def mean(self) -> Tensor:
        """Mean over one cycle, ``a0``: ``(*batch_shape, *value_shape)``."""
        return self.coeffs.select(self._axis, 0)

    def truncated(self, order: Tensor | int) -> FourierSeries:
        """This series with the harmonics above ``order`` set to zero: an integer, or ``(...)``
        integers broadcasting against :attr:`batch_shape` (one order per batch element); the
        coefficient array keeps its shape."""
        order = torch.as_tensor(order, device=self.coeffs.device)
        return self.truncated_values(order.reshape(order.shape + (1,) * self.value_ndim))

    def padded(self, order: int) -> FourierSeries:
        """This series with zero harmonics up to ``order`` (at least its own): the same function
        with ``coeffs (..., 2·order+1, *value_shape)``, so that series of different orders can be
        stacked. (Evaluated, it can differ from the unpadded series in the last bit.)"""
        c = self.coeffs
        extra = 2 * (order - self.order)
        if extra <= 0:
            return self
        pad = c.new_zeros(c.shape[:self._axis] + (extra,) + tuple(self.value_shape))
        return FourierSeries(torch.cat([c, pad], dim=self._axis), self.value_ndim)

    def truncated_values(self, order: Tensor) -> FourierSeries:
        """This series with the harmonics above ``order`` set to zero per value: ``order``
        ``(..., *value_shape)`` integers broadcasting against :attr:`batch_shape` and the value
        shape (one order per batch element and component); the coefficient array keeps its
        shape."""
        c = self.coeffs
        order = torch.as_tensor(order, device=c.device)
        # the harmonic of each coefficient [a0, a1, b1, ...]: 0, 1, 1, 2, ...
        harmonic = torch.div(torch.arange(c.shape[self._axis], device=c.device) + 1, 2,
                             rounding_mode="floor")
        keep = harmonic.reshape((-1,) + (1,) * self.value_ndim) <= order.unsqueeze(
            -1 - self.value_ndim)  # (..., 2K+1, *v)
        return FourierSeries(torch.where(keep, c, torch.zeros_like(c)), self.value_ndim)

    # ------------------------------------------------------------------ calculus
    def _harmonics(self) -> tuple[Tensor, Tensor, Tensor]:
        """``a (..., *v, K)``, ``b (..., *v, K)`` (harmonics moved last) and ``k (K,)``."""
        c = self.coeffs.movedim(self._axis, -1)  # (..., *v, 2K+1)
        a, b = c[..., 1::2], c[..., 2::2]
        k = torch.arange(1, self.order + 1, dtype=c.dtype, device=c.device)
        return a, b, k

    def _from_harmonics(self, a0: Tensor, a: Tensor, b: Tensor) -> FourierSeries:
        ab = torch.stack([a, b], dim=-1).flatten(-2)
        c = torch.cat([a0[..., None], ab], dim=-1).movedim(-1, self._axis)
        return FourierSeries(c, self.value_ndim)

    def derivative(self, n: int = 1) -> FourierSeries:
        """The ``n``-th derivative in phase (``n >= 0``); same order and shapes."""
        _checks.integer(n, "n")
        if n == 0:
            return self
        a, b, k = self._harmonics()
        kn = k**n
        # d/dphi maps (a, b) -> (k b, -k a): n derivatives rotate by n quarter turns.
        a, b = {0: (a, b), 1: (b, -a), 2: (-a, -b), 3: (-b, a)}[n % 4]
        a0 = torch.zeros_like(self.mean())
        return self._from_harmonics(a0, kn * a, kn * b)

    def integral(self, *, drop_mean: bool = False) -> FourierSeries:
        """Antiderivative in phase whose mean (``a0``) is zero.

        A series with a nonzero mean ``a0`` has antiderivative ``a0 * phi + periodic``, which is
        not a Fourier series, so by default this raises ``ValueError`` when any ``|a0|``
        exceeds ``1e-12 * max|coeffs|``. With ``drop_mean=True`` the mean is ignored and only
        the periodic part is integrated (what the limit-cycle fit wants for a fitted velocity).
        """
        if not drop_mean:
            a0 = self.mean().abs()
            scale = self.coeffs.abs().amax() if self.coeffs.numel() else 0.0
            if a0.numel() and bool((a0 > _MEAN_TOL * scale).any()):
                raise ValueError(
                    f"FourierSeries.integral: the series has a nonzero mean (max |a0| = "
                    f"{float(a0.max()):.3g}), so its antiderivative a0*phi + ... is not periodic. "
                    "Pass drop_mean=True to integrate only the periodic part, or subtract the mean."
                )
        a, b, k = self._harmonics()
        # integral maps (a, b) -> (-b / k, a / k)
        return self._from_harmonics(torch.zeros_like(self.mean()), -b / k, a / k)


def fit_fourier(
    phi: Tensor,
    values: Tensor,
    order: int,
    *,
    value_ndim: int | None = None,
    weights: Tensor | None = None,
    ridge: float = 0.0,
) -> FourierSeries:
    """Weighted least-squares Fourier series through scattered samples.

    Solves, per batch element and in one batched Cholesky solve for all value components,
    ``min_c  sum_t w_t |f_c(phi_t) - values_t|^2 / sum_t w_t  +  ridge * sum_{k>=1} (a_k^2+b_k^2)``
    (the mean ``a0`` is not shrunk).

    Args:
        phi: sample phases ``(..., T)`` (radians; wrapped or not).
        values: ``(..., T, *value_shape)``; leading dims broadcast against ``phi``'s.
        order: highest harmonic ``K >= 0``.
        value_ndim: number of value dims; default ``values.ndim - phi.ndim``.
        weights: optional non-negative ``(..., T)``; zero weight ignores a sample.
        ridge: non-negative Tikhonov penalty on the harmonics (relative to the mean square).

    Samples whose phase or any value component is NaN/inf are given zero weight, so drop-outs
    can be passed as they are.

    Returns:
        :class:`FourierSeries` with ``coeffs (..., 2K+1, *value_shape)``.

    Raises:
        ValueError: bad order or shapes; fewer than ``2K+1`` usable samples in a batch element;
            phases that do not cover the circle well enough to determine order ``K``.
    """
    _checks.integer(order, "order", fn="fit_fourier")
    _checks.tensor(phi, "phi", "(..., T)", fn="fit_fourier", valid=lambda t: t.ndim >= 1)
    _checks.tensor(values, "values", "(..., T, *value_shape)", fn="fit_fourier")
    if value_ndim is None:
        value_ndim = values.ndim - phi.ndim
    if not isinstance(value_ndim, int) or value_ndim < 0 or values.ndim < value_ndim + 1:
        raise ValueError(
            f"fit_fourier: values must have shape (..., T, *value_shape) matching phi (..., T) = "
            f"{tuple(phi.shape)}; got values {tuple(values.shape)} (value_ndim={value_ndim})"
        )
    T = phi.shape[-1]
    value_shape = values.shape[values.ndim - value_ndim :]
    if values.shape[values.ndim - value_ndim - 1] != T:
        raise ValueError(
            f"fit_fourier: values {tuple(values.shape)} must have T={T} samples (like phi "
            f"{tuple(phi.shape)}) at axis {-value_ndim - 1}, followed by {value_ndim} value dims"
        )
    if ridge < 0:
        raise ValueError(f"fit_fourier: ridge must be >= 0, got {ridge}")

    dtype = torch.promote_types(phi.dtype, values.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    phi, values = phi.to(dtype), values.to(dtype)
    Y = values.reshape(values.shape[: values.ndim - value_ndim] + (-1,))  # (..., T, V)

    try:
        batch = _checks.broadcast_shapes(phi.shape[:-1], Y.shape[:-2])
    except ValueError as e:
        raise ValueError(
            f"fit_fourier: batch dims of phi {tuple(phi.shape[:-1])} and values "
            f"{tuple(Y.shape[:-2])} do not broadcast"
        ) from e
    w = torch.ones((), dtype=dtype, device=phi.device) if weights is None else weights.to(dtype)
    if weights is not None:
        if weights.shape[-1:] != (T,):
            raise ValueError(
                f"fit_fourier: weights must have shape (..., T={T}), got {tuple(weights.shape)}"
            )
        if not bool(torch.isfinite(w).all()) or bool((w < 0).any()):
            raise ValueError("fit_fourier: weights must be finite and non-negative")
        batch = _checks.broadcast_shapes(batch, w.shape[:-1])
    phi = phi.expand(batch + (T,))
    Y = Y.expand(batch + Y.shape[-2:])
    w = w.expand(batch + (T,))

    # Drop-outs: zero weight and a harmless finite value so they cannot leak NaN into sums.
    bad = ~torch.isfinite(phi) | ~torch.isfinite(Y).all(-1)
    w = torch.where(bad, torch.zeros_like(w), w)
    phi = torch.where(bad, torch.zeros_like(phi), phi)
    Y = torch.where(bad[..., None], torch.zeros_like(Y), Y)

    n = 2 * order + 1
    used = (w > 0).sum(-1)
    if used.numel() and int(used.min()) < n:
        raise ValueError(
            f"fit_fourier: order {order} needs at least {n} samples with finite values and "
            f"nonzero weight per batch element, got {int(used.min())}; lower `order` or "
            "supply more data"
        )

    X = fourier_design(phi, order)  # (..., T, n)
    Xw = X * w[..., None]
    wsum = w.sum(-1)[..., None, None]
    G = Xw.mT @ X / wsum
    rhs = Xw.mT @ Y / wsum  # (..., n, V)
    if ridge > 0:
        pen = torch.full((n,), ridge, dtype=dtype, device=phi.device)
        pen[0] = 0.0
        G = G + torch.diag(pen)
    eig = _linalg.eigvalsh(G, "the Fourier fit's normal matrix")
    if bool((eig[..., 0] <= _RCOND * eig[..., -1]).any()):
        raise ValueError(
            f"fit_fourier: the sample phases do not cover the circle well enough to determine "
            f"a series of order {order} (singular normal equations); lower `order`, pass "
            "`ridge`, or supply data spread over the whole cycle"
        )
    L = _linalg.cholesky(G, "the Fourier fit's normal matrix")
    coef = torch.cholesky_solve(rhs, L)  # (..., n, V)
    return FourierSeries(coef.reshape(batch + (n,) + value_shape), value_ndim)


def fourier_on_grid(values: Tensor, order: int, *, value_ndim: int = 0) -> FourierSeries:
    """The least-squares Fourier series through samples on the equispaced grid ``2πj/N``.

    On that grid the design's columns up to harmonic ``K < N/2`` are orthogonal, so the fit of
    :func:`fit_fourier` (unweighted, no ridge) is the discrete Fourier transform -- the same
    coefficients to rounding, from one real FFT instead of a normal-matrix factorisation per
    batch element.

    Args:
        values: ``(..., N, *value_shape)`` at phases ``φ_j = 2πj/N``, ``j = 0 … N−1``; finite.
        order: highest harmonic ``K`` with ``2K < N``.
        value_ndim: number of trailing value dims.

    Returns:
        :class:`FourierSeries` with ``coeffs (..., 2K+1, *value_shape)``.
    """
    _checks.integer(order, "order", fn="fourier_on_grid")
    _checks.integer(value_ndim, "value_ndim", fn="fourier_on_grid")
    _checks.tensor(values, "values", "(..., N, *value_shape)", fn="fourier_on_grid",
                   valid=lambda t: t.ndim > value_ndim and t.is_floating_point())
    axis = values.ndim - value_ndim - 1
    n = values.shape[axis]
    if 2 * order >= n:
        raise ValueError(f"fourier_on_grid: order {order} needs more than {2 * order} grid "
                         f"samples (harmonics below N/2), got N = {n}")
    if not bool(torch.isfinite(values).all()):
        raise ValueError("fourier_on_grid: values must be finite")
    # f = a0 + Σ a_k cos kφ + b_k sin kφ has DFT coefficients N a0 and N (a_k − i b_k) / 2
    spec = torch.fft.rfft(values, dim=axis).narrow(axis, 0, order + 1) * (2.0 / n)
    a, b = spec.real, -spec.imag
    harmonics = torch.stack([a.narrow(axis, 1, order), b.narrow(axis, 1, order)], axis + 1)
    coeffs = torch.cat([a.narrow(axis, 0, 1) / 2, harmonics.flatten(axis, axis + 1)], axis)
    return FourierSeries(coeffs, value_ndim)
