"""Batched Rauch–Tung–Striebel (Kalman) smoothing of sampled trajectories.

Each channel of ``y (..., T, C)`` is smoothed on its own with a linear Gaussian model: a
2-state (position, velocity) constant-velocity model driven by white acceleration
(``order=2``), or a 3-state (position, velocity, acceleration) model driven by white jerk
(``order=3``), observed in position with white noise. All batch elements and channels run
through one vectorised filter, over time in one of two ways that give the same result:

- a parallel scan (Särkkä & García-Fernández, "Temporal parallelization of Bayesian smoothers",
  IEEE TAC 2021): filter and smoother as associative scans of log depth in the number of
  samples (:mod:`torchconn.phase._scan`) -- a few large tensor operations per round, for GPUs
  and, on a CPU, for a few hundred rows or fewer;
- the sequential loop, one Python step per sample, kept as the reference and used on the CPU
  for many rows, where its per-step cost is shared by all of them.

Noise parameters, when not given, are estimated per channel (see :func:`rts_smooth`).
Missing samples (NaN) are predicted through, so outputs are finite everywhere.

The estimator's smoothing stage is an option object with one job, ``smoother.smooth(traj)``
(or ``smoother(traj)``): :class:`RTSSmoother` here; any :class:`Smoother` subclass slots in.
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass, fields
from typing import Literal, get_args

import torch
from torch import Tensor

from .. import _checks, _linalg
from .._options import Options
from ..trajectory import SmoothedState, Trajectory, over_spans
from . import _scan

__all__ = [
    "Smoother", "RTSSmoother", "ALGORITHMS",
    "rts_smooth", "unwrap", "body_velocity", "smooth_trajectory", "noise_parameters",
    "recorded_span",
]

Algorithm = Literal["auto", "scan", "loop"]
#: the ways :func:`rts_smooth` can run over time
ALGORITHMS: tuple[str, ...] = get_args(Algorithm)

# log10 grid of the dimensionless noise ratio q dt^(2 order - 1) / R searched by GCV
_MU_GRID = torch.linspace(-10.0, 6.0, 65).tolist()
# with DIFF_ORDER-th differences white noise of variance R has variance binom(2k, k) R,
# while a smooth signal sampled at >= ~30 samples per cycle is suppressed to (w dt)^k
_DIFF_ORDER = 4
_PRIOR_SCALE = 1e4
#: the least precision the noise estimates and the recursions run in: their covariance updates
#: cancel digits (``P − P²/(P + R)`` under the vague prior and on noise-free data), which in
#: float32 left only rounding -- NaN on a constant channel, a singular solve on a noise-free line,
#: derivatives 5-60 % off on simulated recordings; a capped float32 prior still put 66 % errors
#: on the first samples' derivatives. Results come back in the input's dtype.
_WORK_DTYPE = torch.float64
# the smallest noise variance, relative to the data's spread (noise-free data)
_NOISE_FLOOR = 1e-12
#: on a CPU the parallel scan is used for rows with drop-outs for at most this many rows (batch
#: elements × channels) per model order: the sequential loop's cost per sample is mostly
#: per-step overhead shared by all rows, the scan's is proportional to the rows
#: (benchmarks/bench_smoother.py, one thread: at 1,000-4,000 samples with 5 % drop-outs the
#: scan is 3-7x faster for 11 rows, even near 220 (order 2) and 44-110 (order 3), and slower
#: beyond). Rows without drop-outs share their covariance steps and take the scan at any size
#: (1,920 samples: 2.8-3x faster than the loop at 220-880 rows, order 2; 2.3x at 220, order 3)
_SCAN_MAX_ROWS_CPU = {2: 256, 3: 64}
#: samples (rows × time) per scan chunk: the scan keeps ~0.45 (order 2) to ~0.9 kB per sample
_SCAN_CHUNK_SAMPLES = 1 << 20


def unwrap(angle: Tensor, dim: int = -1) -> Tensor:
    """Unwrap angles (radians) along ``dim``, skipping NaNs.

    Each finite sample is shifted by a multiple of 2π so that it differs from the previous
    *finite* sample by less than π. NaNs stay NaN and do not break the unwrapping.
    """
    _checks.tensor(angle, "angle", "(..., T)")
    x = angle.movedim(dim, -1)
    n = x.shape[-1]
    if n == 0:
        return angle
    finite = torch.isfinite(x)
    idx = torch.arange(n, device=x.device).expand(x.shape)
    # forward-fill: index of the last finite sample at or before each position
    last = torch.cummax(torch.where(finite, idx, torch.zeros_like(idx)), dim=-1).values
    filled = torch.gather(x, -1, last)
    d = torch.diff(filled, dim=-1)
    step = torch.remainder(d + math.pi, 2 * math.pi) - math.pi - d  # multiple of 2π
    step = torch.nan_to_num(step, nan=0.0)
    shift = torch.cat([torch.zeros_like(step[..., :1]), torch.cumsum(step, dim=-1)], dim=-1)
    return (x + shift).movedim(-1, dim)


def _model(order: int, dt: float, dtype, device) -> tuple[Tensor, Tensor]:
    """Transition matrix ``F`` and unit-intensity process covariance ``Q1`` for one step."""
    if order == 2:
        F = [[1.0, dt], [0.0, 1.0]]
        Q = [[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]
    else:
        F = [[1.0, dt, dt**2 / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]]
        Q = [
            [dt**5 / 20, dt**4 / 8, dt**3 / 6],
            [dt**4 / 8, dt**3 / 3, dt**2 / 2],
            [dt**3 / 6, dt**2 / 2, dt],
        ]
    return (
        torch.tensor(F, dtype=dtype, device=device),
        torch.tensor(Q, dtype=dtype, device=device),
    )


def _nanvar(x: Tensor) -> Tensor:
    m = torch.nanmean(x, dim=-1, keepdim=True)
    return torch.nanmean((x - m) ** 2, dim=-1)


def _measurement_variance(y: Tensor) -> Tensor:
    """Robust white-noise variance from the spread of ``_DIFF_ORDER``-th differences.

    ``y (B, T)`` -> ``(B,)``. The median absolute deviation makes it insensitive to the odd
    outlier and to the few large differences a dropped sample's neighbours produce.
    """
    d = torch.diff(y, n=_DIFF_ORDER, dim=-1)
    med = torch.nanmedian(d, dim=-1, keepdim=True).values
    mad = torch.nanmedian((d - med).abs(), dim=-1).values
    return (1.4826 * mad) ** 2 / math.comb(2 * _DIFF_ORDER, _DIFF_ORDER)


def _spread(y: Tensor) -> Tensor:
    """A positive size per row of ``y (B, T)``: its variance, else (a constant row) its mean
    square, else (all zero) 1 -> ``(B,)``. Floors scaled by it never underflow in the
    covariance products, which gave NaN on constant channels."""
    v = _nanvar(y)
    v = torch.where(v > 0, v, torch.nanmean(y * y, dim=-1))
    return torch.where(v > 0, v, torch.ones_like(v))


def _prior(y: Tensor, finite: Tensor, order: int, dt: float) -> tuple[Tensor, Tensor]:
    """Vague initial state: first finite sample, zero rates, variances from the data's spread."""
    B, T = y.shape
    first = torch.argmax(finite.to(torch.int8), dim=-1)
    x0 = torch.zeros(B, order, dtype=y.dtype, device=y.device)
    x0[:, 0] = y.gather(-1, first[:, None])[:, 0]
    scales = [_nanvar(y)]
    for k in range(1, order):
        # mean square, not variance, of the differences: a steady drift must fit in the prior
        scales.append(torch.nanmean(torch.diff(y, n=k, dim=-1) ** 2, dim=-1) / dt ** (2 * k))
    scales = torch.nan_to_num(torch.stack(scales, -1), nan=1.0)
    # a rate (or spread) that is exactly zero gets the noise floor's size instead
    floor = _NOISE_FLOOR * _spread(y)[:, None] * torch.tensor(
        [dt ** (-2 * k) for k in range(order)], dtype=y.dtype, device=y.device)
    var = torch.where(scales > 0, scales, floor) + torch.finfo(y.dtype).tiny
    # vague: 1e4 times the data's own scale, so the prior's pull on the start is ~1e-4 of it
    return x0, torch.diag_embed(_PRIOR_SCALE * var)


def _filter_loop(y, finite, F, Q, R, x0, P0) -> tuple[Tensor, Tensor]:
    """Kalman filter over time, one Python step per sample (the reference implementation).

    ``y, finite (B, T)``, ``Q (B, n, n)``, ``R (B,)``, ``x0 (B, n)``, ``P0 (B, n, n)``.
    Returns the filtered means ``(B, T, n)`` and covariances ``(B, T, n, n)``.
    """
    T = y.shape[1]
    y = torch.where(finite, y, torch.zeros_like(y))
    m = finite.to(y.dtype)
    x, P = x0, P0
    xf, Pf = [], []
    for t in range(T):
        if t > 0:
            x = _mv(F, x)
            P = _mm(_mm(F, P), F.mT) + Q
        S = P[:, 0, 0] + R
        K = P[:, :, 0] * (m[:, t] / S)[:, None]  # zero gain at a drop-out: predict only
        x = x + K * (y[:, t] - x[:, 0])[:, None]
        # the prior's own update as the scan's first step makes it. The later updates keep the
        # plain form: the careful one made this loop more accurate than the scan after gaps
        # (a 300-sample gap: 3e-4 -> 2e-8 relative), beyond what the scan's tests hold it to
        if t == 0:
            P = _updated_covariance(P, K, m[:, t], R)
        else:
            P = P - K[:, :, None] * P[:, None, 0, :]
        xf.append(x)
        Pf.append(P)
    return torch.stack(xf, 1), torch.stack(Pf, 1)


def _updated_covariance(P: Tensor, K: Tensor, m: Tensor, R: Tensor) -> Tensor:
    """``P − K P[0]``: the covariance ``P (B, n, n)`` after measuring its first state with
    noise ``R (B,)`` (gain ``K (B, n)``, ``m (B,)`` 1, or 0 at a drop-out).

    The entries of row and column 0 are ``P₀ⱼ R / S`` (``S = P₀₀ + R``), not ``P₀ⱼ − K₀ P₀ⱼ``:
    under the vague prior ``P₀₀ ≫ R`` and the subtraction cancels all but ``R / P₀₀`` of the
    digits (~1e-8 relative on a 3-link recording), so that a last-bit change of the data moved
    the first samples' smoothed shapes by ~1e-10 relative, and with them the phase and the fit.
    """
    out = P - K[:, :, None] * P[:, None, 0, :]
    # 1 − m P₀₀ / S without the cancellation (exactly 1 at a drop-out: R + P₀₀ = S)
    keep = (R + (1 - m) * P[:, 0, 0]) / (P[:, 0, 0] + R)
    row = P[:, 0] * keep[:, None]
    out[:, 0] = row
    out[:, :, 0] = row
    return out


def _smooth_loop(F, Q, xf, Pf) -> Tensor:
    """RTS backward pass for the means, one Python step per sample (reference implementation)."""
    # the predictions and all gains at once: G_t = Pf_t Fᵀ Pp_{t+1}⁻¹, so Gᵀ = Pp⁻¹ F Pf_t
    Pp = F @ Pf[:, :-1] @ F.mT + Q[:, None]
    G = _linalg.solve(Pp, F @ Pf[:, :-1], "the smoother's predicted covariance").mT
    xp = xf[:, :-1] @ F.mT
    xs = [xf[:, -1]]
    for t in range(xf.shape[1] - 2, -1, -1):
        xs.append(xf[:, t] + _mv(G[:, t], xs[-1] - xp[:, t]))
    return torch.stack(xs[::-1], 1)


def _rts_loop(y, finite, F, Q1, q, R, x0, P0) -> Tensor:
    """Smoothed means ``(B, T, n)`` by the sequential filter and backward pass."""
    Q = q[:, None, None] * Q1
    xf, Pf = _filter_loop(y, finite, F, Q, R, x0, P0)
    return _smooth_loop(F, Q, xf, Pf)


def _eye(n: int, like: Tensor) -> Tensor:
    """Identity matrices broadcastable against ``like (T, n, n, *batch)``."""
    return torch.eye(n, dtype=like.dtype, device=like.device).reshape(
        (1, n, n) + (1,) * (like.ndim - 3))


def _posterior_covariance(C: Tensor, J: Tensor) -> Tensor:
    """``Σ = (C⁻¹ + J)⁻¹ = (I + C J)⁻¹ C``: covariance ``C`` updated with information ``J``.

    Formed as ``L (I + Lᵀ J L)⁻¹ Lᵀ`` with ``C = L Lᵀ``: the matrix solved is symmetric with
    eigenvalues >= 1, so a vague (huge) ``C`` costs no accuracy -- the plain ``(I + C J)⁻¹`` lost
    up to 6 digits on the prior's first steps. ``C`` may be singular (noise-free data).
    """
    L = _scan.cholesky(C)
    Lt = _scan.mT(L)
    N = _eye(C.shape[1], C) + _scan.mm(_scan.mm(Lt, J), L)
    return _scan.mm(L, _scan.solve_spd(N, Lt))


def _filter_combine(first, then):
    """Särkkä & García-Fernández's filtering operator: the element ``then ∘ first``.

    An element ``(A, b, C, η, J)`` of samples ``i..k`` stands for the conditional
    ``p(x_k | x_{i-1}, y_{i:k}) = N(A x_{i-1} + b, C)`` and the likelihood
    ``p(y_{i:k} | x_{i-1}) ∝ exp(-½ xᵀ J x + ηᵀ x)`` of the state before them.
    """
    Ai, bi, Ci, ei, Ji = first
    Aj, bj, Cj, ej, Jj = then
    # the plain inverse is accurate here: a composed element's C is process noise accumulated
    # over its samples, never the vague prior, which only enters through the state (_filter_apply)
    Minv = _scan.inv(_eye(Ai.shape[1], Ai) + _scan.mm(Ci, Jj))  # (I + C_i J_j)⁻¹
    S = _scan.mm(Minv, Ci)
    T1 = _scan.mm(Minv, Ai)
    T1t = _scan.mT(T1)
    w = ej - _scan.mv(Jj, bi)
    return (
        _scan.mm(Aj, T1),
        _scan.mv(Aj, bi + _scan.mv(S, w)) + bj,
        _scan.mm(_scan.mm(Aj, S), _scan.mT(Aj)) + Cj,
        _scan.mv(T1t, w) + ei,
        _scan.mm(_scan.mm(T1t, Jj), Ai) + Ji,
    )


def _filter_apply(state, element):
    """Filtered mean and covariance ``(b, C)`` after one more element (``state`` ends at ``i-1``)."""
    bi, Ci = state
    Aj, bj, Cj, ej, Jj = element
    S = _posterior_covariance(Ci, Jj)
    v = bi + _scan.mv(S, ej - _scan.mv(Jj, bi))
    return _scan.mv(Aj, v) + bj, _scan.mm(_scan.mm(Aj, S), _scan.mT(Aj)) + Cj


def _smooth_combine(first, then):
    """Composition ``then ∘ first`` of the backward maps ``x ↦ G x + g``."""
    Gi, gi = first
    Gj, gj = then
    return _scan.mm(Gj, Gi), _scan.mv(Gj, gi) + gj


def _smooth_apply(state, element):
    (x,) = state
    G, g = element
    return (_scan.mv(G, x) + g,)


def _rts_scan(y, finite, F, Q1, q, R, x0, P0) -> Tensor:
    """Smoothed means ``(B, T, n)`` by the parallel filter and smoother (two log-depth scans).

    The same model and prior as :func:`_rts_loop` (Särkkä & García-Fernández, "Temporal
    parallelization of Bayesian smoothers", IEEE TAC 2021): each sample ``t >= 1`` is an
    element ``p(x_t | x_{t-1}, y_t)`` with the likelihood of ``x_{t-1}`` (a drop-out has no
    measurement: ``A = F, C = Q`` and no information), and the filtered states are those
    elements applied in turn to the prior updated with ``y_0``. The smoother is the backward
    affine map ``x_t = G_t x_{t+1} + (x̂_t − G_t F x̂_t)`` applied from the end.
    """
    m = finite.to(y.dtype).mT  # (T, B)
    yt = torch.where(finite, y, torch.zeros_like(y)).mT
    Fb = F[None, :, :, None]  # (1, n, n, 1)
    f0 = F[0]  # y_t = x_t[0] + v = F[0] x_{t-1} + (noise of variance S)
    # samples 1..T-1: predict with (F, Q) then update with y_t
    S = q * Q1[0, 0] + R  # (B,)
    # without drop-outs after the first sample every step has the same gain, covariance and
    # information: those parts get time size 1 and are composed once per scan round, not once
    # per pair of samples (the means still are)
    mk = m[1:2] if bool(finite[:, 1:].all()) else m[1:]  # (1 or T-1, B)
    K = mk[:, None, :] * (q * Q1[:, 0, None] / S)[None]  # (1 or T-1, n, B) Kalman gains
    info = mk / S  # (1 or T-1, B)
    elements = (
        Fb - K[:, :, None, :] * f0[None, None, :, None],
        K * yt[1:, None, :],
        q * (Q1[None, :, :, None] - K[:, :, None, :] * Q1[0][None, None, :, None]),
        (info * yt[1:])[:, None, :] * f0[None, :, None],
        info[:, None, None, :] * (f0[:, None] * f0[None, :])[None, :, :, None],
    )
    # sample 0: the prior updated with y_0, as in the loop
    P0t = P0.permute(1, 2, 0)  # (n, n, B)
    x0t = x0.mT  # (n, B)
    K0 = P0t[:, 0] * (m[0] / (P0t[0, 0] + R))  # (n, B)
    P1 = _updated_covariance(P0, K0.mT, m[0], R).permute(1, 2, 0)
    first = (x0t + K0 * (yt[0] - x0t[0]), P1)
    xf, Pf = _scan.scan_states(_filter_combine, _filter_apply, first, elements)
    # backward: G_t = P_t Fᵀ (F P_t Fᵀ + Q)⁻¹, i.e. G_tᵀ = Pp⁻¹ F P_t as in the loop
    FP = _scan.mm(Fb, Pf[:-1])
    Pp = _scan.mm(FP, _scan.mT(Fb)) + q * Q1[None, :, :, None]
    G = _scan.mT(_scan.solve_spd(Pp, FP))
    g = xf[:-1] - _scan.mv(G, _scan.mv(Fb, xf[:-1]))
    (xs,) = _scan.scan_states(_smooth_combine, _smooth_apply, (xf[-1],), (G, g), reverse=True)
    return xs.permute(2, 0, 1)


# Tiny batched products written as broadcast-and-sum: inside the time loops these run on a
# few thousand numbers, where ATen's batched matmul spreads work over threads and, on a busy
# machine, spends far longer waiting for them than computing.
def _mv(A: Tensor, x: Tensor) -> Tensor:
    """``A (..., n, n) @ x (..., n)``."""
    return (A * x[..., None, :]).sum(-1)


def _mm(A: Tensor, B: Tensor) -> Tensor:
    """``A (..., n, k) @ B (..., k, m)``."""
    return (A[..., :, :, None] * B[..., None, :, :]).sum(-2)


def _fill_gaps(y: Tensor, finite: Tensor) -> Tensor:
    """Linear interpolation across NaNs (constant beyond the first/last finite sample)."""
    T = y.shape[-1]
    idx = torch.arange(T, device=y.device).expand(y.shape)
    prev = torch.cummax(torch.where(finite, idx, torch.zeros_like(idx)), -1).values
    big = torch.full_like(idx, T - 1)
    nxt = torch.cummin(torch.where(finite, idx, big).flip(-1), -1).values.flip(-1)
    # before the first finite sample `prev` points at a NaN: use `nxt` there (and vice versa)
    prev = torch.where(finite.gather(-1, prev), prev, nxt)
    nxt = torch.where(finite.gather(-1, nxt), nxt, prev)
    y0, y1 = y.gather(-1, prev), y.gather(-1, nxt)
    span = (nxt - prev).clamp_min(1).to(y.dtype)
    return y0 + (y1 - y0) * (idx - prev).to(y.dtype) / span


def _unit_spectrum(F: Tensor, Q1: Tensor, N: int) -> Tensor:
    """Power spectrum of the sampled position for unit process noise at ``2πk/N`` -> ``(N,)``.

    ``S(w) = e0ᵀ (e^{iw} I - F)^{-1} Q1 (e^{iw} I - F)^{-H} e0``; infinite at ``w = 0``.
    """
    n = F.shape[0]
    cdt = torch.complex128 if F.dtype == torch.float64 else torch.complex64
    w = 2 * math.pi * torch.arange(1, N, dtype=F.dtype, device=F.device) / N
    A = torch.exp(1j * w.to(cdt))[:, None, None] * torch.eye(n, dtype=cdt, device=F.device)
    Ainv_e0 = _linalg.inv(A - F.to(cdt), "the smoother's transfer matrix")[:, 0, :]  # row e0ᵀ (zI - F)^{-1}
    s = torch.einsum("fi,ij,fj->f", Ainv_e0, Q1.to(cdt), Ainv_e0.conj()).real
    return torch.cat([torch.full_like(s[:1], math.inf), s])


def _gcv_noise_ratio(y: Tensor, finite: Tensor, F: Tensor, Q1: Tensor, dt: float) -> Tensor:
    """Noise ratio ``q / R`` per row of ``y (B, T)`` by generalised cross-validation
    (:func:`_gcv_rows`), each row over its own span from its first to its last finite sample:
    missing samples before or after it (a shorter trial's padding on a shared grid) say
    nothing about the noise, and filled in they would make a row's ratio depend on the
    length of the others."""
    split = over_spans(finite, lambda rows, a, b: _gcv_rows(y[rows, a:b], finite[rows, a:b],
                                                            F, Q1, dt))
    return _gcv_rows(y, finite, F, Q1, dt) if split is None else split


def _gcv_rows(y: Tensor, finite: Tensor, F: Tensor, Q1: Tensor, dt: float) -> Tensor:
    """Noise ratio ``q / R`` per row of ``y (B, T)`` by generalised cross-validation.

    The steady-state RTS smoother is the Wiener filter ``H = λS/(λS + 1)`` with ``S`` the
    model's unit spectrum, so ``GCV(λ) = mean|(1 - H) Y|² / (1 - mean H)²`` is evaluated in
    the frequency domain for a whole log grid at once. Drop-outs are bridged linearly, and the
    signal is detrended and mirrored so that its periodic extension has no jump. The best grid
    point is refined by a parabola in log λ.
    """
    order, T = F.shape[0], y.shape[-1]
    z = _fill_gaps(y, finite)
    # remove the least-squares line first: a drift (a swimmer's x, y, heading) would otherwise
    # leave a kink at the mirror point whose spectrum looks like signal to GCV
    t = torch.linspace(-1.0, 1.0, T, dtype=y.dtype, device=y.device)
    z = z - z.mean(-1, keepdim=True)
    z = z - ((z * t).sum(-1) / (t @ t))[:, None] * t  # per row: z @ t rounds with the batch size
    z = torch.cat([z, z.flip(-1)], -1)
    power = torch.fft.fft(z).abs() ** 2  # (B, 2T)
    S = _unit_spectrum(F, Q1, 2 * T)
    g = torch.tensor(_MU_GRID, dtype=y.dtype, device=y.device)  # log10 of q dt^(2n-1) / R
    lam = 10.0**g / dt ** (2 * order - 1)
    H = torch.where(torch.isinf(S), torch.ones_like(S), lam[:, None] * S / (lam[:, None] * S + 1))
    # one product per row (batched), not one matrix product of all rows: with one row that is a
    # different BLAS path whose rounding differs
    weights = ((1 - H) ** 2).mT  # (2T, G)
    rss = torch.bmm(power[:, None, :], weights.expand(power.shape[0], -1, -1))[:, 0]  # (B, G)
    gcv = torch.log(rss) - 2 * torch.log1p(-H.mean(-1))
    G = g.numel()
    i = gcv.argmin(-1).clamp(1, G - 2)
    l0, l1, l2 = (gcv.gather(-1, (i + o)[:, None])[:, 0] for o in (-1, 0, 1))
    curv = l0 - 2 * l1 + l2
    off = torch.where(curv > 0, 0.5 * (l0 - l2) / curv, torch.zeros_like(curv)).clamp(-1, 1)
    # exp, not 10 ** x: torch's scalar-base power rounds the elements of a short tensor's tail
    # differently (a last-ulp change with the batch size), and a row's noise ratio -- hence
    # everything after it -- must not depend on the other rows of its batch
    log_ratio = (g[i] + off * (g[1] - g[0])) * math.log(10.0)
    return torch.exp(log_ratio) / dt ** (2 * order - 1)


def _default_noise(yb, fb, F, Q1, dt, q, R) -> tuple[Tensor, Tensor]:
    """Fill in the noise parameters ``q, R (B,)`` that were not given (None) for rows ``yb``."""
    tiny = _NOISE_FLOOR * _spread(yb) + torch.finfo(yb.dtype).tiny  # S > 0 for noise-free data
    if R is None:
        R = _measurement_variance(yb)
        R = torch.where(torch.isfinite(R), R, torch.zeros_like(R))
    R = torch.maximum(R, tiny)
    if q is None:
        # the smoothed means depend on q / R only, so R's scale does not bias them
        q = _gcv_noise_ratio(yb, fb, F, Q1, dt) * R
    return q.clamp_min(torch.finfo(yb.dtype).tiny), R


def noise_parameters(y: Tensor, dt: float, *, order: int = 2) -> tuple[Tensor, Tensor]:
    """The noise parameters :func:`rts_smooth` chooses by default, per channel.

    Passing them back as ``process_noise`` / ``measurement_noise`` reproduces the default
    smoothing exactly, so the same smoother can be applied to other signals (e.g. a model's
    prediction that must be compared with the smoothed measurement like with like).

    Args:
        y: samples ``(..., T, C)`` (NaN for missing samples); dt: sampling interval.
        order: smoother model order (2 or 3), as in :func:`rts_smooth`.

    Returns:
        ``(process_noise q, measurement_noise R)``, each ``(..., C)``.
    """
    _checks.tensor(y, "y", f"(..., T, C) with T >= {2 + _DIFF_ORDER}", fn="noise_parameters",
                   valid=lambda t: t.ndim >= 2 and t.shape[-2] >= 2 + _DIFF_ORDER)
    if order not in (2, 3):
        raise ValueError(f"noise_parameters: order must be 2 or 3, got {order!r}")
    if not y.is_floating_point():
        y = y.to(torch.get_default_dtype())
    out_dtype = y.dtype
    y = y.to(torch.promote_types(y.dtype, _WORK_DTYPE))
    T, C = y.shape[-2:]
    yb = y.movedim(-1, -2).reshape(-1, T)
    fb = torch.isfinite(yb)
    F, Q1 = _model(order, float(dt), y.dtype, y.device)
    q, R = _default_noise(yb, fb, F, Q1, float(dt), None, None)
    return (q.reshape(y.shape[:-2] + (C,)).to(out_dtype),
            R.reshape(y.shape[:-2] + (C,)).to(out_dtype))


def rts_smooth(
    y: Tensor,
    dt: float,
    *,
    order: int = 2,
    process_noise: float | Tensor | None = None,
    measurement_noise: float | Tensor | None = None,
    algorithm: Algorithm = "auto",
) -> tuple[Tensor, Tensor]:
    """Smooth each channel with a Kalman filter and Rauch–Tung–Striebel smoother.

    Args:
        y: samples ``(..., T, C)``; NaN marks a missing sample (the filter predicts through it).
        dt: sampling interval (> 0).
        order: 2 -- state (position, velocity), white-acceleration process noise;
            3 -- state (position, velocity, acceleration), white-jerk process noise.
        process_noise: spectral density ``q`` of the white acceleration (jerk), in units of
            ``y² / time³`` (``y² / time⁵``), scalar or broadcastable to ``(..., C)``. Default:
            per channel, ``q = λ R`` with the ratio ``λ`` minimising the generalised
            cross-validation score of the steady-state smoother (evaluated in the frequency
            domain over a 65-point log grid, refined by a parabola). GCV is used rather than
            the innovation likelihood because on smooth periodic signals -- which are not
            white-acceleration processes -- the likelihood prefers a 10-30x larger ``q`` and
            doubles the derivative error.
        measurement_noise: observation-noise *variance* ``R`` (units ``y²``), scalar or
            broadcastable to ``(..., C)``. Default: per channel, from the median absolute
            deviation of 4th differences, which for white noise have variance ``70 R`` while a
            smooth signal sampled at >= ~30 samples per cycle contributes little.
        algorithm: how the filter and smoother run over time -- ``"scan"``: two parallel
            (log-depth) associative scans, a few large tensor operations per round, for GPUs
            and for few rows; ``"loop"``: one Python step per sample (the reference); ``"auto"``
            (default): the scan off the CPU, and on the CPU for data without drop-outs (after
            the first sample) or for at most 256 rows (order 2) or 64 rows (order 3), rows
            being batch elements × channels -- where it is the faster.
            Both give the same result to rounding (≤ 1e-10 relative in float64 on
            well-conditioned data; the scan is the more accurate across long drop-outs).

    Returns:
        ``(values, derivatives)``, both ``(..., T, C)`` in ``y``'s dtype: smoothed positions and
        their time derivatives, finite everywhere. Lower precisions (float32) are computed in
        float64 and rounded back: the covariance recursions lose too many digits in float32.

    Raises:
        ValueError: bad shapes/arguments, or a channel that is NaN at every sample.
    """
    _checks.tensor(y, "y", "(..., T, C) with T >= 2 samples, C >= 1 channels and no empty "
                   "batch dimension", fn="rts_smooth",
                   valid=lambda t: t.ndim >= 2 and t.shape[-2] >= 2 and t.shape[-1] >= 1
                   and t.numel() > 0)
    if order not in (2, 3):
        raise ValueError(f"rts_smooth: order must be 2 or 3, got {order!r}")
    if algorithm not in ALGORITHMS:
        raise ValueError(f"rts_smooth: algorithm must be one of {', '.join(map(repr, ALGORITHMS))}, "
                         f"got {algorithm!r}")
    dt = float(dt)
    if not math.isfinite(dt) or dt <= 0:
        raise ValueError(f"rts_smooth: dt must be a positive sampling interval, got {dt}")
    if not y.is_floating_point():
        y = y.to(torch.get_default_dtype())
    out_dtype = y.dtype
    y = y.to(torch.promote_types(y.dtype, _WORK_DTYPE))
    T, C = y.shape[-2:]
    batch = y.shape[:-2]
    finite = torch.isfinite(y)
    empty = ~finite.any(-2)  # (..., C)
    if bool(empty.any()):
        where = torch.nonzero(empty)[0].tolist()
        raise ValueError(
            f"rts_smooth: channel {where[-1]} of y (batch index {tuple(where[:-1])}) has no "
            "finite sample; drop that channel or trial before smoothing"
        )
    if int(finite.sum(-2).min()) < 2 + _DIFF_ORDER and measurement_noise is None:
        raise ValueError(
            f"rts_smooth: a channel has fewer than {2 + _DIFF_ORDER} finite samples, too few to "
            "estimate measurement_noise; pass measurement_noise explicitly"
        )

    # channels become batch rows: (B, T) with B = prod(batch) * C
    yb = y.movedim(-1, -2).reshape(-1, T)
    fb = finite.movedim(-1, -2).reshape(-1, T)

    def per_row(v, name):
        v = torch.as_tensor(v, dtype=y.dtype, device=y.device)
        try:
            v = v.expand(batch + (C,))
        except RuntimeError as e:
            raise ValueError(
                f"rts_smooth: {name} must be a scalar or broadcast to (..., C) = "
                f"{tuple(batch) + (C,)}, got shape {tuple(v.shape)}"
            ) from e
        if not bool(torch.isfinite(v).all()) or bool((v < 0).any()):
            raise ValueError(f"rts_smooth: {name} must be finite and non-negative")
        return v.reshape(-1)

    F, Q1 = _model(order, dt, y.dtype, y.device)
    R = None if measurement_noise is None else per_row(measurement_noise, "measurement_noise")
    q = None if process_noise is None else per_row(process_noise, "process_noise")
    q, R = _default_noise(yb, fb, F, Q1, dt, q, R)
    x0, P0 = _prior(yb, fb, order, dt)

    if algorithm == "auto":
        scan = (yb.device.type != "cpu" or yb.shape[0] <= _SCAN_MAX_ROWS_CPU[order]
                or bool(fb[:, 1:].all()))
        algorithm = "scan" if scan else "loop"
    if algorithm == "loop":
        xs = _rts_loop(yb, fb, F, Q1, q, R, x0, P0)  # (B, T, n)
    else:
        step = max(1, _SCAN_CHUNK_SAMPLES // T)
        xs = torch.cat([
            _rts_scan(yb[i:i + step], fb[i:i + step], F, Q1, q[i:i + step], R[i:i + step],
                      x0[i:i + step], P0[i:i + step])
            for i in range(0, yb.shape[0], step)
        ])
    out = xs[..., :2].reshape(batch + (C, T, 2)).movedim(-3, -2).to(out_dtype)  # (..., T, C, 2)
    return out[..., 0], out[..., 1]


def body_velocity(pose: Tensor, pose_dot: Tensor) -> Tensor:
    """Body velocity ``xi = g⁻¹ ġ = (Rᵀ(θ) (ẋ, ẏ), θ̇)``.

    Args:
        pose: ``(..., T, 3)`` world poses ``(x, y, θ)``.
        pose_dot: ``(..., T, 3)`` their time derivatives.

    Returns:
        ``(..., T, 3)`` body velocities ``(v_x, v_y, ω)`` (conventions: ``ξ = g⁻¹ġ``).
    """
    _checks.last_dim(pose, 3, "pose", fn="body_velocity")
    _checks.last_dim(pose_dot, 3, "pose_dot", fn="body_velocity")
    th = pose[..., 2]
    c, s = torch.cos(th), torch.sin(th)
    xd, yd, thd = pose_dot.unbind(-1)
    return torch.stack([c * xd + s * yd, -s * xd + c * yd, thd], -1)


def smooth_trajectory(
    pose: Tensor,
    r: Tensor,
    dt: float,
    *,
    order: int = 2,
    process_noise: float | Tensor | None = None,
    measurement_noise: float | Tensor | None = None,
    shared_bandwidth: bool = False,
    algorithm: Algorithm = "auto",
) -> SmoothedState:
    """Smooth a recorded trajectory and derive its velocities.

    The heading is unwrapped (NaN-tolerant) before smoothing, so wrapped input is fine. The
    ``3 + d`` channels ``(x, y, θ, r_1..r_d)`` are smoothed by :func:`rts_smooth` (noise
    arguments broadcast to ``(..., 3 + d)``).

    Args:
        pose: ``(..., T, 3)`` world poses ``(x, y, θ)``; NaN for drop-outs.
        r: ``(..., T, d)`` shapes; NaN for drop-outs.
        dt: sampling interval.
        shared_bandwidth: when the noise is estimated (``process_noise`` None), give every
            channel of a trial the same noise ratio ``q/R`` -- the geometric mean of the
            channels' own GCV choices -- so that poses and shapes pass through one filter.
            Off by default: it biases the shape velocities, and raises the error under
            observation noise.
        algorithm: ``"auto"``, ``"scan"`` or ``"loop"``, as in :func:`rts_smooth`.

    Returns:
        :class:`~torchconn.trajectory.SmoothedState` with ``pose`` (heading unwrapped), ``pose_dot``,
        ``r``, ``r_dot`` and the body velocity ``xi = g⁻¹ġ``.
    """
    _checks.tensor(pose, "pose", "(..., T, 3)", fn="smooth_trajectory",
                   valid=lambda t: t.ndim >= 2 and t.shape[-1] == 3)
    _checks.tensor(r, "r", f"(..., T, d) with the same (..., T) as pose {tuple(pose.shape[:-1])}",
                   fn="smooth_trajectory", valid=lambda t: t.ndim >= 2 and t.shape[:-1] == pose.shape[:-1])
    pose = torch.cat([pose[..., :2], unwrap(pose[..., 2], dim=-1)[..., None]], -1)
    y = torch.cat([pose, r.to(pose.dtype)], -1)
    if shared_bandwidth and process_noise is None:
        q, R = noise_parameters(y, dt, order=order)
        if measurement_noise is not None:
            R = torch.as_tensor(measurement_noise, dtype=y.dtype, device=y.device).expand_as(R)
        ratio = torch.exp(torch.log(q / R).mean(-1, keepdim=True))
        process_noise, measurement_noise = ratio * R, R
    val, der = rts_smooth(y, dt, order=order, process_noise=process_noise,
                          measurement_noise=measurement_noise, algorithm=algorithm)
    p, pd = val[..., :3], der[..., :3]
    return SmoothedState(
        pose=p, pose_dot=pd, r=val[..., 3:], r_dot=der[..., 3:], xi=body_velocity(p, pd)
    )


class Smoother(Options, abc.ABC):
    """Base of the estimator's smoothing stage: ``smooth(traj) -> traj`` with ``smoothed`` set.

    A smoother fills :attr:`Trajectory.smoothed <torchconn.trajectory.Trajectory.smoothed>`
    (poses and shapes, their time derivatives, the body velocity) for every batch element,
    finite over each trial's recorded span and NaN on the padding after a shorter trial's end.
    """

    @abc.abstractmethod
    def smooth(self, traj: Trajectory) -> Trajectory:
        """``traj`` with ``smoothed`` set (every other field unchanged)."""

    def __call__(self, traj: Trajectory) -> Trajectory:
        return self.smooth(traj)


@dataclass(frozen=True, kw_only=True)
class RTSSmoother(Smoother):
    """Kalman/Rauch–Tung–Striebel smoothing of every channel (:func:`smooth_trajectory`).

    Attributes:
        order: 2 -- white-acceleration model (position, velocity); 3 -- white jerk.
        algorithm: ``"auto"`` (default), ``"scan"`` (parallel in time) or ``"loop"``
            (sequential): how the smoother runs over time, see :func:`rts_smooth`; the same
            result to rounding.
    """

    order: Literal[2, 3] = 2
    algorithm: Algorithm = "auto"

    def smooth(self, traj: Trajectory) -> Trajectory:
        """Smooth ``traj``'s poses ``(..., T, 3)`` and shapes ``(..., T, d)`` into ``smoothed``.

        Trials padded with NaN rows before their start or after their end (unequal lengths on
        one grid) are smoothed over their recorded span only, each as it would be alone (the
        filter starts at its first sample); the padding is NaN in ``smoothed``.
        """
        if not isinstance(traj, Trajectory):
            raise TypeError(f"RTSSmoother.smooth: traj must be a torchconn.Trajectory, "
                            f"got {type(traj).__name__}")

        def run(pose: Tensor, r: Tensor) -> SmoothedState:
            return smooth_trajectory(pose, r, traj.dt, order=self.order,
                                     algorithm=self.algorithm)

        T = traj.n_samples
        pose, r = traj.pose.reshape(-1, T, 3), traj.r.reshape(-1, T, traj.shape_dim)
        split = over_spans(recorded_span(traj).reshape(-1, T),
                           lambda rows, a, b: run(pose[rows, a:b], r[rows, a:b]), in_time=True)
        if split is None:
            return traj.with_fields(smoothed=run(traj.pose, traj.r))
        return traj.with_fields(smoothed=SmoothedState(**{
            f.name: getattr(split, f.name).reshape(traj.batch_shape + (T, -1))
            for f in fields(SmoothedState)}))


def recorded_span(traj: Trajectory) -> Tensor:
    """``(..., T)`` True from the first to the last sample with any finite value per trial.

    Trials of different lengths share one time grid, the shorter ones padded with NaN rows; the
    padding is not a drop-out to smooth through but time that was never recorded.
    """
    finite = torch.isfinite(torch.cat([traj.pose, traj.r], -1)).any(-1)  # (..., T)
    idx = torch.arange(finite.shape[-1], device=finite.device)
    first = torch.where(finite, idx, finite.shape[-1]).min(-1, keepdim=True).values
    last = torch.where(finite, idx, -1).max(-1, keepdim=True).values
    return (idx >= first) & (idx <= last)
