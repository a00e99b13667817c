"""Regression of the dissipation metric ``M`` from a recorded power channel.

Two models:

- :func:`tied_metric_regression` (the estimator's default): on the sample intervals the power
  channel belongs to (docs/conventions.md: ``power`` at row ``k`` is the mean over
  ``[t_k, t_{k+1})``), one metric explains all of the power,
  ``P_k ≈ v_kᵀ [M(φ) + ∂M/∂r_k(φ) δ_k] v_k`` with
  ``v_k = (r_{k+1} − r_k)/Δt`` the raw sample differences and ``M(φ)``, ``∂M/∂r(φ)`` Fourier
  series in phase; the observation noise's known contribution to the normal equations is
  removed (:func:`power_noise_variance` estimates its level from the power residuals).
- :func:`metric_regression` (the paper's eq. ``advancedmetricregression``, torchconn 0.1):
  within the bin of centre ``γ_m``,

      P ≈ (γ̇_m + δ̇)ᵀ [M + ∂M/∂r_k δᵏ] (γ̇_m + δ̇),

  expanded into regressors ``[1, δ̇, δ̇⊗̂δ̇, δ, δ⊗δ̇, δ⊗(δ̇⊗̂δ̇)]`` where ``δ̇⊗̂δ̇`` holds the
  unique products ``δ̇_i δ̇_j``, ``i ≤ j`` (``M`` is symmetric, so the coefficient of
  ``δ̇_i δ̇_j`` is ``M_ii`` on the diagonal and ``2 M_ij`` off it). The last block carries
  ``∂M/∂r`` and is third order in the offsets; it is fitted only when requested or when every
  bin has samples enough. Its linear and quadratic terms are separate coefficients, so the
  weakly identified ``M`` is not tied to the strongly identified ``2Mγ̇``; measured 100–250 %
  off on the swimmer (README, "Known limits").
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace
from typing import Literal

import torch
from torch import Tensor, nn

from .. import _linalg
from ..phase.fourier import fourier_design
from . import _wls
from .binning import BinIndex

#: the tied model's second-order offset term: None (none), ``"diagonal"`` (``δ_k²``) or
#: ``"full"`` (``δ_k δ_l``); see :func:`tied_metric_regression`
SecondOrder = Literal["diagonal", "full"] | None
_SECOND_ORDERS = (None, "diagonal", "full")

__all__ = ["MetricFit", "metric_regression", "metric_design", "metric_n_coef",
           "tied_metric_regression", "tied_metric_coefficients", "TiedMetricCoefficients",
           "tied_metric_n_coef", "tied_metric_predict",
           "power_noise_variance"]


@dataclass(frozen=True)
class MetricFit:
    """Per-bin estimates of the metric and its shape derivative (``M`` bins, ``d`` joints).

    Attributes:
        M: ``(..., M, d, d)`` symmetric ``M̂(γ_m)``.
        dM: ``(..., M, d, d, d)`` ``∂M_ij/∂r_k`` at ``[..., i, j, k]`` (as
            :meth:`~torchconn.physics.systems.LocomotionSystem.metric_jacobian`), symmetric in ``i, j``;
            None when the derivative block was not fitted.
        se_M, se_dM: standard errors, same shapes (``se_dM`` None with ``dM``).
        power_on_cycle: ``(..., M)`` the intercept, ``γ̇_mᵀ M γ̇_m``.
        n_samples: ``(..., M)`` samples with positive weight in each bin.
        residual_rms: ``(..., M)`` weighted RMS residual of the power.
        condition: ``(..., M)`` 1-norm condition number of the standardised normal matrix.
        ridge: ``(..., M)`` ridge applied to each bin.
        coef, se_coef: ``(..., M, P)`` raw coefficients in the column order of
            :func:`metric_design` (or of :func:`tied_metric_regression`), and their standard
            errors.
        se_power_on_cycle: ``(..., M)`` standard error of ``power_on_cycle``.
        M_gamma_dot, se_M_gamma_dot: ``(..., M, d)`` ``M̂γ̇_m``, strongly identified by the gait
            itself (the full ``M̂`` needs off-cycle excitation), and its standard error.
        noise_correction: ``(..., M)`` the least fraction of the noise correction applied in
            any direction of the coefficients (1 unless the noise swamps some direction's
            excitation, see :class:`_CorrectedNormal`); None for the paper's model.
        cov_M: ``(..., M, q, q)`` covariance of the ``q = d(d+1)/2`` metric coefficients (tied
            model only; with ``order_bias`` the outer product of ``bias_M``'s added, and so in
            ``se_M``, ``se_M_gamma_dot`` and ``se_power_on_cycle``).
        order: ``(...)`` Fourier order of ``M(φ)`` (tied model only).
        bias_M: ``(..., M, d, d)`` the bias allowed for in the bands (tied model with
            ``order_bias`` only): the change of ``M̂`` at two more harmonics of ``M(φ)``.
        se_bias_M: ``(..., M, d, d)`` that change's own standard error (its sampling noise,
            from the two fits' joint cluster-robust covariance; ``order_bias`` only). Where it
            is as large as ``bias_M`` the change does not resolve the bias; with
            ``order_bias="posterior"`` its variance is in ``se_M`` (with ``"dropped"`` only
            where the held-out order is below the order given).
        change_factor_M: ``(..., M, d, d, R)`` a factor of the part of the covariance of
            ``M̂`` that is that change's sampling covariance, across entries *and* phases
            (``Σ_r F[..., r] ⊗ F[..., r]``; its diagonal is the change's variance in ``se_M``):
            with ``order_bias="posterior"`` (``"dropped"``: zero where nothing was dropped);
            None otherwise. ``R`` is at most the number of cycles; directions whose variance
            is below ``1e-14`` of the largest are left out.
        sampling_factor_M: ``(..., M, d, d, R)`` a factor of ``M̂``'s own sampling covariance
            (the cluster-robust sandwich's, before any bias allowance) across entries *and*
            phases, from each cycle's share of the error (``TiedMetricCoefficients.influence``)
            at the phases; compressed like ``change_factor_M``. Tied model only, else None.
        offset_bias_M: ``(..., M, d, d)`` the tube's second-order bias of ``M̂`` as estimated
            by ``offset_bias`` (the change of ``M̂`` when that term is fitted too), or None;
            not in ``se_M``.
    """

    M: Tensor
    dM: Tensor | None
    se_M: Tensor
    se_dM: Tensor | None
    power_on_cycle: Tensor
    n_samples: Tensor
    residual_rms: Tensor
    condition: Tensor
    ridge: Tensor
    coef: Tensor
    se_coef: Tensor
    se_power_on_cycle: Tensor | None = None
    M_gamma_dot: Tensor | None = None
    se_M_gamma_dot: Tensor | None = None
    noise_correction: Tensor | None = None
    cov_M: Tensor | None = None
    order: Tensor | None = None
    bias_M: Tensor | None = None
    se_bias_M: Tensor | None = None
    change_factor_M: Tensor | None = None
    sampling_factor_M: Tensor | None = None
    offset_bias_M: Tensor | None = None


def metric_n_coef(d: int, with_metric_derivative: bool) -> int:
    """Number of regressors ``P``: ``1 + d + q + d + d²`` (+ ``d·q``), ``q = d(d+1)/2``."""
    q = d * (d + 1) // 2
    return 1 + 2 * d + q + d * d + (d * q if with_metric_derivative else 0)


def metric_design(delta: Tensor, delta_dot: Tensor, with_metric_derivative: bool = True) -> Tensor:
    """Regressors ``[1, δ̇, δ̇⊗̂δ̇, δ, δ⊗δ̇, δ⊗(δ̇⊗̂δ̇)]``: ``(..., d), (..., d) -> (..., P)``.

    ``δ̇⊗̂δ̇`` lists the ``n_q = d(d+1)/2`` products ``δ̇_i δ̇_j``, ``i ≤ j``, in
    ``torch.triu_indices`` order (index ``q``); within its block ``δ⊗δ̇`` holds ``δ_k δ̇_j`` at
    ``k·d + j`` and ``δ⊗(δ̇⊗̂δ̇)`` holds ``δ_k (δ̇⊗̂δ̇)_q`` at ``k·n_q + q``.
    """
    ones = torch.ones_like(delta[..., :1])
    return torch.cat(_blocks(delta, delta_dot, ones, with_metric_derivative), -1)


def _blocks(delta: Tensor, delta_dot: Tensor, row_scale: Tensor, deriv: bool) -> list[Tensor]:
    """The column blocks of ``row_scale · metric_design(...)``, scaled through small factors."""
    d = delta.shape[-1]
    iu, ju = torch.triu_indices(d, d, device=delta.device)
    scaled_dot = row_scale * delta_dot
    quad = scaled_dot[..., iu] * delta_dot[..., ju]
    blocks = [row_scale, scaled_dot, quad, row_scale * delta,
              (delta.unsqueeze(-1) * scaled_dot.unsqueeze(-2)).flatten(-2)]
    if deriv:
        blocks.append((delta.unsqueeze(-1) * quad.unsqueeze(-2)).flatten(-2))
    return blocks


def _symmetric(upper: Tensor, d: int) -> Tensor:
    """``(..., q) -> (..., d, d)`` from the ``i ≤ j`` coefficients of ``δ̇_i δ̇_j``."""
    iu, ju = torch.triu_indices(d, d, device=upper.device)
    half = torch.where(iu == ju, 1.0, 0.5).to(upper)
    out = upper.new_zeros(upper.shape[:-1] + (d, d))
    out[..., iu, ju] = upper * half
    out[..., ju, iu] = upper * half
    return out


def metric_regression(
    r: Tensor,
    r_dot: Tensor,
    power: Tensor,
    bins: BinIndex,
    gamma_m: Tensor,
    gamma_dot_m: Tensor,
    *,
    with_metric_derivative: bool | None = None,
    delta_max: float | None = None,
    ridge: float = 0.0,
    min_samples: int | None = None,
    max_condition: float | None = None,
    on_ill_conditioned: str = "raise",
) -> MetricFit:
    """Estimate ``M(γ_m)`` (and ``∂M/∂r(γ_m)``) in every phase bin from measured power.

    Args:
        r, r_dot: ``(..., N, d)`` shapes and shape velocities.
        power: ``(..., N)`` dissipated power ``P = ṙᵀ M(r) ṙ`` (the paper's ``ṡ²``). NaN samples
            (in ``r``, ``r_dot`` or ``power``) are excluded automatically.
        bins, gamma_m, gamma_dot_m: as in :func:`connection_regression`.
        with_metric_derivative: fit the third-order ``δ⊗(δ̇⊗̂δ̇)`` block that yields ``∂M/∂r``.
            It has ``d²(d+1)/2`` columns (288 for ``d = 8``, ``P = 405``), so it needs many
            samples per bin. ``None`` (default) fits it only when every bin of every batch
            element has at least ``P_full + 5`` samples (``min_samples`` if given), else
            leaves it out and returns ``dM = None``; True/False force the choice.
        delta_max, ridge, min_samples, max_condition, on_ill_conditioned: as in
            :func:`connection_regression` (``min_samples`` defaults to ``P + 5``).

    Returns:
        :class:`MetricFit` with ``...`` the batch dims of ``r``.
    """
    fn = "metric_regression"
    s = _wls.prepare(fn, r, r_dot, power, "power", 0, bins, gamma_m, gamma_dot_m)
    d = s.r.shape[-1]
    if with_metric_derivative is None:
        p_full = metric_n_coef(d, True)
        need = p_full + 5 if min_samples is None else min_samples
        fewest = int(bins.count.min()) if bins.count.numel() else 0
        with_metric_derivative = fewest >= need
    deriv = bool(with_metric_derivative)
    p = metric_n_coef(d, deriv)
    q = d * (d + 1) // 2

    def design(delta: Tensor, delta_dot: Tensor, row_scale: Tensor) -> list[Tensor]:
        return _blocks(delta, delta_dot, row_scale, deriv)

    sol = _wls.solve(s, design, p, fn=fn, delta_max=delta_max, ridge=ridge,
                     min_samples=min_samples, max_condition=max_condition,
                     on_ill_conditioned=on_ill_conditioned)
    sol = sol.unflatten(s.batch_shape, s.n_bins)
    coef, se = sol.coef[..., 0], sol.se[..., 0]  # (..., M, P)

    def metric_of(x: Tensor) -> Tensor:
        return _symmetric(x[..., 1 + d:1 + d + q], d)

    def derivative_of(x: Tensor) -> Tensor:
        start = 1 + 2 * d + q + d * d
        per_k = x[..., start:].unflatten(-1, (d, q))  # [..., k, q]
        return _symmetric(per_k, d).movedim(-3, -1)  # [..., i, j, k]

    return MetricFit(
        M=metric_of(coef), se_M=metric_of(se),
        dM=derivative_of(coef) if deriv else None, se_dM=derivative_of(se) if deriv else None,
        power_on_cycle=coef[..., 0], n_samples=sol.n_samples,
        residual_rms=sol.residual_rms[..., 0], condition=sol.condition, ridge=sol.ridge,
        coef=coef, se_coef=se, se_power_on_cycle=se[..., 0],
        # the coefficient of δ̇ is 2 M γ̇
        M_gamma_dot=coef[..., 1:1 + d] / 2, se_M_gamma_dot=se[..., 1:1 + d] / 2,
    )


# ================================================================================ tied model
#: the floor on the signal fraction kept in any direction of the noise-corrected normal
#: matrix is this many times ``√(P/N)`` (``P`` coefficients of the largest model, ``N``
#: samples), the scale on which sampling error spreads a Gram matrix's eigenvalues. In the
#: generalized eigenvectors of (G, C) (raw normal matrix G, the noise's contribution C) the
#: correction divides each direction by its signal fraction 1 − ν; below the floor it is
#: mostly sampling error and only part of the correction is applied (:class:`_CorrectedNormal`).
#: Tuned on the pooled 5-link wave at ω = 0.005 (seeds 1000 and 3000, four noise draws each;
#: floor 0.2 there): M̂γ̇ RMS error 6.0 / 5.7 / 6.6 / 7.8 % at floors 0.1 / 0.2 / 0.3 / 0.5.
#: The 3-link gets about 0.1, the 9-link 0.45-0.55 (where 0.2 left M̂γ̇ 40 % off at order 6)
_FLOOR_SCALE = 1.1
#: the floor's largest value
_MAX_FLOOR = 0.9
#: blocks of consecutive samples over which the residual noise level's standard error is taken
_NOISE_BLOCKS = 24
#: rows of the design built at once (bounds memory: rows × coefficients × 8 bytes)
_ROW_CHUNK = 2048
#: blocks of whole cycles held out in turn to choose the order of ``M(φ)``
_ORDER_FOLDS = 5
#: standard errors by which a lower order must beat the largest on the held-out blocks
_ORDER_Z = 1.0
#: harmonics of ``M(φ)`` added to the chosen order for the bias allowance of the bands
#: (``order_bias``): the change of ``M̂`` from order ``K`` to ``K + 2`` is taken as ``M̂``'s bias
#: (the higher harmonics' leakage into the off-cycle directions, README "The metric").
#: Tuned on seeds 2000 and 5000 (3-/5-link, ω = 0-0.005): its square added in full, cover 80 →
#: 96 % (mean of 12 cells); half of it 92 %; less its own sampling variance 93 %
_BIAS_ORDER_STEP = 2
#: ``order_bias`` values: none, the change's square, the change's square and its own variance
#: everywhere, or that variance only where the held-out order dropped harmonics
_ORDER_BIAS = (False, True, "posterior", "dropped")


def tied_metric_n_coef(d: int, order: int, derivative_order: int | None,
                       second_order: SecondOrder = None) -> int:
    """Coefficients of the tied model: ``(2K+1)·q`` for ``M(φ)`` plus ``(2K_d+1)·d·q`` for
    ``∂M/∂r(φ)`` plus ``½∂²M/∂r²``'s ``d·q`` (``second_order="diagonal"``) or ``q·q``
    (``"full"``), ``q = d(d+1)/2``."""
    q = d * (d + 1) // 2
    return _n_features(d, order, derivative_order, second_order) * q


def _n_features(d: int, order: int, derivative_order: int | None,
                second_order: SecondOrder) -> int:
    """Features of the tied model (each multiplies the ``q`` products ``v_i v_j``): ``M(φ)``'s
    ``2K+1``, then ``∂M/∂r(φ)``'s ``(2K_d+1)·d``, then ``½∂²M/∂r²``'s ``d`` or ``d(d+1)/2``."""
    n_second = {None: 0, "diagonal": d, "full": d * (d + 1) // 2}[second_order]
    return 2 * order + 1 + (0 if derivative_order is None else (2 * derivative_order + 1) * d) \
        + n_second


def _cycles_needed(phase: Tensor, valid: Tensor, samples: int) -> str:
    """`` (about k cycles at n usable samples per cycle)``: ``samples`` usable samples in
    cycles of this recording (its median phase step), or "" when that cannot be told."""
    step = phase.diff(dim=-1).abs()
    step = step[valid[..., 1:] & valid[..., :-1] & (step > 0) & (step < math.pi)]
    if step.numel() == 0:
        return ""
    per_cycle = 2 * math.pi / float(step.median())
    return (f" (about {math.ceil(10 * samples / per_cycle) / 10:g} cycles at the "
            f"{per_cycle:.0f} samples per cycle of this recording)")


def tied_metric_regression(
    offset: Tensor,
    velocity: Tensor,
    power: Tensor,
    phase: Tensor,
    phase_m: Tensor,
    gamma_dot_m: Tensor,
    *,
    order: int = 6,
    derivative_order: int | None = 2,
    second_order: SecondOrder = None,
    noise_variance: Tensor | None = None,
    held_out_order: bool = False,
    order_bias: bool | Literal["posterior", "dropped"] = False,
    min_samples_per_coef: float = 3.0,
    max_condition: float | None = None,
) -> MetricFit:
    """Fit ``P ≈ vᵀ [M(φ) + ∂M/∂r_k(φ) δ_k] v`` over the whole cycle, noise-corrected.

    One metric explains the whole power of every sample interval: the term linear in the offset
    velocity (``2 M γ̇ · δ̇``, strongly identified by the gait) and the quadratic one
    (``δ̇ᵀ M δ̇``, identified only by off-cycle excitation) share their coefficients instead of
    being fitted apart. ``M(φ)`` is a Fourier series of order ``order`` in phase and
    ``∂M/∂r(φ)`` one of order ``derivative_order`` (None: not fitted); each coefficient is
    estimated from all samples, not one bin's. Regressors: ``b_h(φ) v_i v_j`` and
    ``b_h(φ) δ_k v_i v_j`` (``i ≤ j`` in :func:`torch.triu_indices` order, ``b`` the
    :func:`~torchconn.phase.fourier.fourier_design` columns).

    The tube's second order: the power is ``vᵀ M(γ + δ) v``, and the first-order model leaves
    ``½ δᵀ∂²M/∂r²δ`` out. Its mean over the offsets, ``½ ∂²M/∂r² : E[δδᵀ]``, goes into
    ``M(φ)``: ``M̂`` is then the metric averaged over the tube, not the metric on the cycle
    (measured on the swimmer, paper SDE: the on-cycle power +0.1 % (3-link) and +0.3 %
    (5-link) at ω = 0, scaling as ``η²``; README "Is the cost standard error honest?").
    ``second_order`` fits that term too, constant in phase: ``"full"`` the products
    ``δ_k δ_l v_i v_j`` (``q·q`` coefficients), ``"diagonal"`` only ``δ_k² v_i v_j`` (``d·q``;
    removes the bias where the offsets of different joints are uncorrelated). It removes the
    bias but costs variance under noise (the products' mean is collinear with ``M(φ)``'s
    constant), so it is not the default (README).

    Noise: ``v`` comes from raw sample differences, so observation noise ``ε`` on ``r``
    enters as ``e = (ε_{k+1} − ε_k)/Δt``, Gaussian with covariance
    ``Σ = diag(noise_variance)`` (``= 2ω²/Δt²``) and independent of the noise on ``r̄``
    (a sum and a difference of i.i.d. Gaussians). The products of regressors are biased by
    ``Σ``; the known bias is removed from the normal equations (the Gaussian fourth-moment
    identity: an errors-in-variables correction). ``r̄``'s own noise, variance ``ω²/2`` against
    the offsets' ``η²/2α``, only biases ``∂M/∂r`` (by ~0.2 % at ω = 0.005) and is left alone.
    In the directions of the coefficients where the noise swamps the excitation (signal
    fraction of the corrected normal matrix below ``1.1 √(P/N)``) only part of the correction
    is applied, the other directions keep all of it (:class:`_CorrectedNormal`;
    ``MetricFit.noise_correction`` < 1, with a warning).

    Standard errors: the sandwich ``G⁻¹ (Σ_c s_c s_cᵀ) G⁻¹`` over cycles ``c`` (whole turns of
    ``phase``), ``s_c`` the summed scores of the corrected regressors: they reflect the actual
    scatter, the serial correlation of differenced noise and how much excitation each direction
    of ``M`` gets (wide bands where the data do not excite a direction).

    Args:
        offset: ``(..., N, d)`` ``δ = r̄ − γ(φ)``, the interval's offset from the cycle at its
            own phase; velocity: ``(..., N, d)`` ``v``; power: ``(..., N)``; phase: ``(..., N)``
            unwrapped (one-sample intervals of
            :func:`~torchconn.regression.noise_aware.interval_samples`). Samples with any NaN
            are excluded.
        phase_m: ``(M,)`` phases at which to report (bin centres).
        gamma_dot_m: ``(..., M, d)`` ``γ̇`` there, for ``M̂γ̇`` and the on-cycle power.
        order, derivative_order: Fourier orders of ``M(φ)`` and ``∂M/∂r(φ)``.
        second_order: the second-order offset term (above): None (default), ``"diagonal"``
            or ``"full"``; its columns follow ``∂M/∂r``'s in ``coef``. The offsets' own
            observation noise (variance ``ω²/2`` beside ``E[δ²] = η²/2α``) is not corrected.
        noise_variance: ``(..., d)`` or ``(d,)`` variance of the noise on ``velocity``;
            None: no correction.
        held_out_order: choose the Fourier order of ``M(φ)`` per batch element in
            ``0 … order`` by held-out blocks of whole cycles (:func:`_held_out_orders`; the
            harmonics above it get zero coefficients, so ``coef`` keeps the layout of
            ``order``); False: ``order``.
        order_bias: widen the bands by the model's bias, estimated as the change of ``M̂`` when
            ``M(φ)`` gets two more harmonics (one more fit, at each element's order + 2): its
            outer product is added to the covariance of ``M̂`` (``MetricFit.bias_M``; the
            estimates are unchanged). Without it, on clean data the bands see only the
            residuals' scatter, not the leakage of the truncated harmonics (README, "The
            metric"). Where that fit fails (too few samples), a warning and no widening.
            ``"posterior"``: the change's own sampling covariance is added as well (the mean
            squared bias given the change, under a flat prior on the bias), for where the
            change is as noisy as the bias it estimates: where the held-out order drops
            harmonics under noise, the change is measured on the harmonics the choice found
            indistinguishable from noise, and comes out small when the noise cancelled them
            (README, "The metric": the bands then hold the truth, at 1.3-2.3 times the width
            where they already did). ``"dropped"``: that variance added only to the batch
            elements whose held-out order is below ``order`` (the selection effect), the
            change's square alone elsewhere (bit for bit ``True``'s bands there). Measured
            (README): the 5-link's held-out order is below 6 on every recording, so there it
            is ``"posterior"``; it is not the default.
        min_samples_per_coef: fewest valid samples per coefficient.
        max_condition: largest condition number of the equilibrated normal matrix (default
            1e12 in float64).

    Returns:
        :class:`MetricFit` at ``phase_m``: ``coef``/``se_coef`` are the ``(..., P)``
        coefficients; ``n_samples`` and ``residual_rms`` count the samples nearest each
        ``phase_m``; ``condition`` and ``noise_correction`` are the fit's, repeated per phase;
        ``order`` ``(...)`` the order of ``M(φ)`` used.

    Raises:
        ValueError: too few samples, or a metric the data do not identify (the shape velocity
            does not vary in every direction: a gait without noise, a joint held fixed).
    """
    fn = "tied_metric_regression"
    delta = _wls._check_samples(offset, "offset", None, None, fn)
    _check_phases(fn, phase_m, gamma_dot_m, tuple(delta.shape[:-2]), delta)
    return tied_metric_coefficients(
        offset, velocity, power, phase, order=order, derivative_order=derivative_order,
        second_order=second_order, noise_variance=noise_variance,
        held_out_order=held_out_order, order_bias=order_bias,
        min_samples_per_coef=min_samples_per_coef, max_condition=max_condition,
    ).at(phase_m, gamma_dot_m)


def _check_phases(fn: str, phase_m, gamma_dot_m, batch: tuple, like: Tensor) -> Tensor:
    """``gamma_dot_m (..., M, d)`` checked against ``phase_m (M,)``, the batch and ``like``'s
    ``d``, broadcast to the batch."""
    if not isinstance(phase_m, Tensor) or phase_m.ndim != 1:
        raise ValueError(f"{fn}: phase_m must be a 1-D tensor of phases (M,)")
    return _wls._check_cycle(gamma_dot_m, "gamma_dot_m", batch, phase_m.shape[0],
                             like.shape[-1], fn, like)


def tied_metric_coefficients(
    offset: Tensor,
    velocity: Tensor,
    power: Tensor,
    phase: Tensor,
    *,
    order: int = 6,
    derivative_order: int | None = 2,
    second_order: SecondOrder = None,
    noise_variance: Tensor | None = None,
    held_out_order: bool = False,
    order_bias: bool | Literal["posterior", "dropped"] = False,
    offset_bias: SecondOrder = None,
    min_samples_per_coef: float = 3.0,
    max_condition: float | None = None,
) -> TiedMetricCoefficients:
    """:func:`tied_metric_regression`'s fit without the phases to report at: its coefficients,
    their covariance and residuals (:class:`TiedMetricCoefficients`), which do not depend on
    those phases; ``.at(phase_m, gamma_dot_m)`` gives the :class:`MetricFit` (the same bit for
    bit). Arguments and errors as :func:`tied_metric_regression`'s, and:

    Args:
        offset_bias: also fit the second-order offset term of this form (``second_order``'s
            choices) at each element's order of ``M(φ)``, and keep the change of ``M(φ)``'s
            coefficients it makes (``TiedMetricCoefficients.offset_change``): an estimate of
            the tube's second-order bias of ``M̂`` (``M̂`` absorbs ``½∂²M/∂r² : E[δδᵀ]``), for
            the draws of nearby gaits (README, "Is the cost standard error honest?"). None: not
            estimated; where that fit fails, a warning and none.
    """
    for name, value in (("second_order", second_order), ("offset_bias", offset_bias)):
        if value not in _SECOND_ORDERS:
            raise ValueError(f"tied_metric_regression: {name} must be one of "
                             f"{_SECOND_ORDERS}, got {value!r}")
    if not (isinstance(order_bias, bool) or order_bias in _ORDER_BIAS):
        raise ValueError(f"tied_metric_regression: order_bias must be one of {_ORDER_BIAS}, "
                         f"got {order_bias!r}")
    opts = dict(derivative_order=derivative_order, second_order=second_order,
                noise_variance=noise_variance,
                min_samples_per_coef=min_samples_per_coef, max_condition=max_condition)
    fit = _tied_fit(offset, velocity, power, phase, order=order, held_out_order=held_out_order,
                    **opts)
    if offset_bias is not None and second_order is None:
        fit = _with_offset_change(fit, offset, velocity, power, phase, offset_bias, opts)
    if not order_bias:
        return fit
    # the same data at two more harmonics of M(φ) than each element's order (the layout of
    # the largest of those orders); its floor's warning would repeat the fit's
    top = int(fit.order.max()) + _BIAS_ORDER_STEP if fit.order.numel() else order
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", _wls.IllConditionedBinWarning)
            richer = _tied_fit(offset, velocity, power, phase, order=top,
                               orders=fit.order + _BIAS_ORDER_STEP, **opts)
    except ValueError as err:
        warnings.warn(f"tied_metric_regression: the metric's bands are not widened for the "
                      f"model's bias (its fit at {_BIAS_ORDER_STEP} more harmonics of M(φ) "
                      f"failed: {err})", stacklevel=2)
        return fit
    q = fit.n_joints * (fit.n_joints + 1) // 2
    wide = 2 * (order + _BIAS_ORDER_STEP) + 1

    def m_series(x: Tensor, max_order: int) -> Tensor:  # (..., [C,] (2(order+step)+1) q)
        h = (2 * max_order + 1) * q
        return nn.functional.pad(x[..., :h], (0, (wide - h // q) * q))

    # the change's own noise: the two fits share their samples, so its covariance comes from
    # each cycle's share of the difference (not the difference of the two covariances)
    spread = (m_series(richer.influence, richer.max_order)
              - m_series(fit.influence, fit.max_order))  # (..., C, W q)
    change = m_series(richer.coef, richer.max_order) - m_series(fit.coef, fit.max_order)
    return replace(fit, order_change=change.unflatten(-1, (wide, q)),
                   order_change_spread=spread, order_bias=order_bias)


def _with_offset_change(fit: TiedMetricCoefficients, offset: Tensor, velocity: Tensor,
                        power: Tensor, phase: Tensor, form: SecondOrder, opts: dict
                        ) -> TiedMetricCoefficients:
    """``fit`` with ``offset_change``: the change of ``M(φ)``'s coefficients when the
    second-order offset term ``form`` is fitted beside them (at ``fit``'s orders)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", _wls.IllConditionedBinWarning)
            second = _tied_fit(offset, velocity, power, phase, order=fit.max_order,
                               orders=fit.order, **{**opts, "second_order": form})
    except ValueError as err:
        warnings.warn(f"tied_metric_regression: the metric's second-order offset bias is not "
                      f"estimated (its fit failed: {err})", stacklevel=3)
        return fit
    q = fit.n_joints * (fit.n_joints + 1) // 2
    n_m = (2 * fit.max_order + 1) * q
    change = (second.coef[..., :n_m] - fit.coef[..., :n_m]).unflatten(-1, (-1, q))
    return replace(fit, offset_change=change)


def _features(phase: Tensor, delta: Tensor, order: int, derivative_order: int | None,
              second_order: SecondOrder) -> Tensor:
    """The tied model's features ``(..., n, g)`` (:func:`_n_features`'s layout) of samples at
    ``phase (..., n)`` with offsets ``delta (..., n, d)``: ``M(φ)``'s Fourier columns, then
    ``∂M/∂r(φ)``'s (``b_h(φ) δ_k`` at ``h·d + k``), then ``½∂²M/∂r²``'s
    (:func:`_second_order_features`)."""
    f = [fourier_design(phase, order)]
    if derivative_order is not None:
        fd = fourier_design(phase, derivative_order)
        f.append((fd.unsqueeze(-1) * delta.unsqueeze(-2)).flatten(-2))
    if second_order is not None:
        f.append(_second_order_features(delta, second_order))
    return torch.cat(f, -1) if len(f) > 1 else f[0]


def _second_order_features(delta: Tensor, second_order: SecondOrder) -> Tensor:
    """The second-order term's features of offsets ``delta (..., n, d)``, constant in phase:
    ``"diagonal"``: ``δ_k²`` ``(..., n, d)``; ``"full"``: ``δ_k δ_l``, ``k ≤ l``
    (:func:`torch.triu_indices` order) ``(..., n, d(d+1)/2)``."""
    if second_order == "diagonal":
        return delta.square()
    d = delta.shape[-1]
    ku, lu = torch.triu_indices(d, d, device=delta.device)
    return delta[..., ku] * delta[..., lu]


def _tied_fit(
    offset: Tensor,
    velocity: Tensor,
    power: Tensor,
    phase: Tensor,
    *,
    order: int,
    derivative_order: int | None,
    second_order: SecondOrder = None,
    noise_variance: Tensor | None,
    held_out_order: bool = False,
    orders: Tensor | None = None,
    min_samples_per_coef: float,
    max_condition: float | None,
) -> TiedMetricCoefficients:
    """:func:`tied_metric_coefficients` without the bias allowance; ``orders``: ``(...)``
    int64 orders of ``M(φ)`` per batch element (at most ``order``, the layout's) instead of
    ``order`` or the held-out choice."""
    fn = "tied_metric_regression"
    delta = _wls._check_samples(offset, "offset", None, None, fn)
    batch_n, d = tuple(delta.shape[:-1]), delta.shape[-1]
    v = _wls._check_samples(velocity, "velocity", batch_n, d, fn).to(delta)
    y = _wls._check_samples(power, "power", batch_n, 0, fn).to(delta)
    ph = _wls._check_samples(phase, "phase", batch_n, 0, fn).to(delta)
    batch = batch_n[:-1]
    for name, k in (("order", order), ("derivative_order", derivative_order)):
        if k is not None and (isinstance(k, bool) or not isinstance(k, int) or k < 0):
            raise ValueError(f"{fn}: {name} must be a non-negative int, got {k!r}")
    dtype, dev = delta.dtype, delta.device
    if max_condition is None:
        max_condition = 1e12 if dtype == torch.float64 else 1e-2 / torch.finfo(dtype).eps
    q = d * (d + 1) // 2
    p = tied_metric_n_coef(d, order, derivative_order, second_order)
    sig = delta.new_zeros(batch + (d,))
    if noise_variance is not None:
        nv = torch.as_tensor(noise_variance, dtype=dtype, device=dev)
        try:
            sig = nv.expand(batch + (d,))
        except RuntimeError:
            raise ValueError(f"{fn}: noise_variance must have shape (..., d) broadcastable to "
                             f"{batch + (d,)}, got {tuple(nv.shape)}") from None
        if not bool(torch.isfinite(sig).all()) or bool((sig < 0).any()):
            raise ValueError(f"{fn}: noise_variance must be finite and >= 0")

    valid = ~(delta.isnan().any(-1) | v.isnan().any(-1) | y.isnan() | ph.isnan())
    w = valid.to(dtype)
    n_valid = valid.sum(-1)
    fewest = int(n_valid.min()) if n_valid.numel() else 0
    if fewest < min_samples_per_coef * p:
        raise ValueError(
            f"{fn}: {fewest} usable power samples (finite power, shapes at both ends of the "
            f"interval) for P = {p} coefficients of the metric (Fourier order {order}"
            + ("" if derivative_order is None else f", derivative order {derivative_order}")
            + f", d = {d}); need at least {min_samples_per_coef:g}·P = "
              f"{math.ceil(min_samples_per_coef * p)}" + _cycles_needed(
                ph, valid, math.ceil(min_samples_per_coef * p)) + ". Record more cycles, or "
            "lower the orders; or leave the metric out: metric=False (torchconn-fit --metric "
            "no) fits the connection alone from this recording"
        )
    zero = delta.new_zeros(())
    delta = torch.where(valid.unsqueeze(-1), delta, zero)
    v = torch.where(valid.unsqueeze(-1), v, zero)
    y = torch.where(valid, y, zero)
    ph = torch.where(valid, ph, zero)
    iu, ju = torch.triu_indices(d, d, device=dev)
    on_diag = (iu == ju).to(dtype)

    def features(rows: slice) -> Tensor:  # (..., n, g)
        return _features(ph[..., rows], delta[..., rows, :], order, derivative_order,
                         second_order)

    # whole cycles of phase: the clusters of the standard errors and the held-out blocks
    cyc = torch.floor(ph / (2 * math.pi))
    cyc = torch.where(valid, cyc, torch.inf)
    cyc = cyc - cyc.amin(-1, keepdim=True)
    cyc = torch.where(valid, cyc, 0.0).to(torch.int64)
    n_c = int(cyc.max()) + 1 if cyc.numel() else 1
    folds = _ORDER_FOLDS if held_out_order else 1
    fold = torch.div(cyc * folds, cyc.amax(-1, keepdim=True) + 1, rounding_mode="floor")

    # normal equations and the noise's contributions per block of cycles, over row chunks
    n = ph.shape[-1]
    g_n = p // q
    gram = delta.new_zeros(batch + (folds, p, p))
    rhs = delta.new_zeros(batch + (folds, p))
    s2 = delta.new_zeros(batch + (folds, g_n, g_n * d * d))
    s0 = delta.new_zeros(batch + (folds, g_n, g_n))
    fy = delta.new_zeros(batch + (folds, g_n))
    for start in range(0, n, _ROW_CHUNK):
        rows = slice(start, min(start + _ROW_CHUNK, n))
        f = features(rows) * w[..., rows, None]  # zero rows for missing samples
        vr = v[..., rows, :]
        quad = vr[..., iu] * vr[..., ju]
        x = (f.unsqueeze(-1) * quad.unsqueeze(-2)).flatten(-2)
        vv = (vr.unsqueeze(-1) * vr.unsqueeze(-2)).flatten(-2)
        fvv = (f.unsqueeze(-1) * vv.unsqueeze(-2)).flatten(-2)
        for b in range(folds):
            sel = (fold[..., rows, None] == b).to(dtype) if folds > 1 else 1.0
            if folds > 1 and not bool(sel.any()):
                continue  # the block has no rows here: its products would be exact zeros
            xb, fb = x * sel, f * sel
            gram[..., b, :, :] += xb.mT @ x
            rhs[..., b, :] += (xb * y[..., rows, None]).sum(-2)
            s2[..., b, :, :] += fb.mT @ fvv
            s0[..., b, :, :] += fb.mT @ f
            fy[..., b, :] += (fb * y[..., rows, None]).sum(-2)
    corr_g, corr_h = _noise_terms(s2.unflatten(-1, (g_n, d, d)), s0, fy, sig.unsqueeze(-2), iu,
                                  ju, on_diag)  # per block
    diag = gram.sum(-3).diagonal(dim1=-2, dim2=-1)
    inv = torch.where(diag <= 0, 1.0, diag.rsqrt())
    chosen = torch.full(batch, order, dtype=torch.int64, device=dev)
    if orders is not None:
        chosen = orders.to(chosen).expand(batch)
    elif held_out_order:
        n_fold = torch.stack([(valid & (fold == b)).sum(-1) for b in range(folds)], -1)
        chosen = _held_out_orders(gram, corr_g, rhs, corr_h, inv, order, q, n_fold)
    # the harmonics above each element's order are dropped (zero coefficients): the fit is
    # solved at the size of the batch's largest chosen order (``cols``), and the elements with
    # a lower one keep their dropped columns as identity rows
    top = int(chosen.max()) if chosen.numel() else order
    cols = _order_columns(p, q, top, order, dev)  # (P',)
    p_r = cols.numel()
    feature = torch.arange(p, device=dev)[cols] // q
    drop = (feature >= 2 * chosen[..., None] + 1) & (feature < 2 * order + 1)  # (..., P')
    keep = (~drop).to(dtype)
    both = keep.unsqueeze(-1) * keep.unsqueeze(-2)
    gram, corr_g = _principal(gram.sum(-3), cols) * both, _principal(corr_g.sum(-3), cols) * both
    rhs, corr_h = rhs.sum(-2)[..., cols] * keep, corr_h.sum(-2)[..., cols] * keep
    inv = inv[..., cols]

    dead = gram.diagonal(dim1=-2, dim2=-1) <= 0
    eye = torch.eye(p_r, dtype=dtype, device=dev)
    scale = inv.unsqueeze(-1) * inv.unsqueeze(-2)
    floor = _signal_floor(p, n_valid)
    normal = _CorrectedNormal.of(gram * scale + torch.diag_embed(dead.to(dtype)),
                                 corr_g * scale, floor)
    chol, applied, ok = normal.cholesky(), normal.applied, normal.ok
    ev = _linalg.eigvalsh(chol @ chol.mT, "the metric's normal matrix")
    lo, hi = ev[..., 0], ev[..., -1]
    if p_r < p:  # the left-out columns' identity rows, as in the layout of ``order``
        lo, hi = lo.clamp(max=1.0), hi.clamp(min=1.0)
    condition = torch.where(~ok | (dead & ~drop).any(-1) | (lo <= 0), torch.inf,
                            hi / lo.clamp(min=torch.finfo(dtype).tiny))
    bad = ~(condition <= max_condition)
    if bool(bad.any()):
        where = [tuple(i) for i in torch.nonzero(bad).tolist()][:5] if batch else []
        raise ValueError(
            f"{fn}: the data do not identify the metric"
            + (f" (batch elements {where})" if where else "")
            + f": the normal matrix of its P = {p} coefficients has condition number "
              f"{float(condition.max()):.3g} > {max_condition:.3g}. The shape velocity must vary "
              "in every direction of shape space at every phase (noise on the gait over many "
              "cycles); a gait without noise, a joint held fixed or too few cycles leave M "
              "unidentified. Lower the Fourier orders, drop the derivative term "
              "(derivative_order=None), record more varied data, or fit the connection alone "
              "(TubeRegression(metric=False); torchconn-fit: --metric no)"
        )
    h = rhs * inv - normal.correction_share(corr_h * inv)
    beta_r = torch.cholesky_solve(h.unsqueeze(-1), chol)[..., 0] * inv  # (..., P')
    beta = beta_r.new_zeros(batch + (p,)).index_copy_(-1, cols, beta_r)
    if bool((applied < 1).any()):
        warnings.warn(
            f"{fn}: in some directions of the metric's coefficients the noise swamps the "
            "off-cycle excitation (signal fraction of the corrected normal matrix below "
            f"{float(floor.max()):.2g}); the noise correction there was limited to "
            f"{float(applied.min()):.2g} of its size, so M̂'s weakly excited directions are "
            "biased towards smaller values", _wls.IllConditionedBinWarning, stacklevel=2)

    # cluster-robust sandwich over whole cycles, on the corrected regressors
    sums = delta.new_zeros(batch + (n_c, p_r))
    kept_features = cols[::q] // q  # the features of the columns solved for
    resids = []
    for start in range(0, n, _ROW_CHUNK):
        rows = slice(start, min(start + _ROW_CHUNK, n))
        f = features(rows)[..., kept_features] * w[..., rows, None]
        vr = v[..., rows, :]
        quad = vr[..., iu] * vr[..., ju] - sig[..., None, iu] * on_diag
        x = (f.unsqueeze(-1) * quad.unsqueeze(-2)).flatten(-2)  # (..., n, P')
        resid = (y[..., rows] - (x @ beta_r.unsqueeze(-1))[..., 0]) * w[..., rows]
        sums.scatter_add_(-2, cyc[..., rows, None].expand(x.shape), x * resid.unsqueeze(-1))
        resids.append(resid)
    sums = sums * keep.unsqueeze(-2)
    n_clusters = (sums.abs().sum(-1) > 0).sum(-1).to(dtype)
    meat = (sums.mT @ sums) * (n_clusters / (n_clusters - 1).clamp(min=1))[..., None, None]
    l_inv = torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
    g_inv = (l_inv.mT @ l_inv) * inv.unsqueeze(-1) * inv.unsqueeze(-2)
    cov_r = g_inv @ meat @ g_inv
    cov = cov_r.new_zeros(batch + (p, p))
    cov[..., cols[:, None], cols] = cov_r
    # each cycle's share of the coefficients' error: cov = influenceᵀ influence
    influence_r = (sums @ g_inv) * (n_clusters / (n_clusters - 1).clamp(min=1)).sqrt()[
        ..., None, None]
    influence = influence_r.new_zeros(batch + (n_c, p)).index_copy_(-1, cols, influence_r)
    return TiedMetricCoefficients(
        coef=beta, cov=cov, order=chosen, condition=condition, noise_correction=applied,
        max_order=order, derivative_order=derivative_order, second_order=second_order,
        n_joints=d, phase=ph, weight=w,
        residual=torch.cat(resids, -1) if resids else ph.new_zeros(ph.shape),
        influence=influence)


@dataclass(frozen=True)
class TiedMetricCoefficients:
    """The fit of :func:`tied_metric_coefficients` (``...`` batch dims, ``P`` coefficients,
    ``N`` samples): everything of :func:`tied_metric_regression` that does not depend on the
    phases it reports at, so that one fit serves any bins (:meth:`at`).

    Attributes:
        coef: ``(..., P)`` coefficients (the layout of ``max_order``); cov: ``(..., P, P)``
            their cluster-robust covariance.
        order: ``(...)`` the order of ``M(φ)`` used; max_order, derivative_order,
            second_order: the orders of the layout; n_joints: ``d``.
        condition, noise_correction: ``(...)`` the fit's condition number and least share
            of the noise correction applied.
        phase, weight, residual: ``(..., N)`` the samples' phase (0 where excluded), weight
            (0/1) and weighted power residual.
        influence: ``(..., C, P)`` each of the ``C`` cycles' share of the coefficients'
            error (``cov = influenceᵀ influence``; cycles without samples give zero rows).
        order_change: ``(..., 2(max_order+2)+1, q)`` the change of ``M(φ)``'s series
            coefficients from each element's order to two more harmonics (``order_bias``),
            taken as its bias; None without the allowance. order_change_spread: ``(..., C, W
            q)`` (``W = 2(max_order+2)+1``) each cycle's share of that change's error, from the
            two fits' joint influence (``order_change_cov = spreadᵀ spread``, the change's own
            sampling covariance). order_bias: the rule of the allowance (``order_bias``).
        offset_change: ``(..., 2·max_order+1, q)`` the change of ``M(φ)``'s series
            coefficients when the second-order offset term is fitted too (``offset_bias``),
            taken as the tube's second-order bias; None without it.
    """

    coef: Tensor
    cov: Tensor
    order: Tensor
    condition: Tensor
    noise_correction: Tensor
    max_order: int
    derivative_order: int | None
    second_order: SecondOrder
    n_joints: int
    phase: Tensor
    weight: Tensor
    residual: Tensor
    influence: Tensor
    order_change: Tensor | None = None
    order_change_spread: Tensor | None = None
    order_bias: bool | str = False
    offset_change: Tensor | None = None

    @property
    def order_change_cov(self) -> Tensor | None:
        """``(..., W q, W q)`` the order change's own sampling covariance, or None."""
        spread = self.order_change_spread
        return None if spread is None else spread.mT @ spread

    def at(self, phase_m: Tensor, gamma_dot_m: Tensor) -> MetricFit:
        """The :class:`MetricFit` at phases ``phase_m (M,)`` with ``γ̇`` there
        ``gamma_dot_m (..., M, d)`` (see :func:`tied_metric_regression`)."""
        batch, d = tuple(self.phase.shape[:-1]), self.n_joints
        gd = _check_phases("tied_metric_regression", phase_m, gamma_dot_m, batch,
                           self.phase.new_zeros(batch + (1, d)))
        return _tied_at(self, phase_m, gd)


def _tied_at(fit: TiedMetricCoefficients, phase_m: Tensor, gd: Tensor) -> MetricFit:
    """:meth:`TiedMetricCoefficients.at` on checked inputs (``gd (..., M, d)`` broadcast)."""
    ph, w, residual, beta, cov = fit.phase, fit.weight, fit.residual, fit.coef, fit.cov
    order, derivative_order, d = fit.max_order, fit.derivative_order, fit.n_joints
    chosen, condition, applied = fit.order, fit.condition, fit.noise_correction
    batch = tuple(ph.shape[:-1])
    n, m = ph.shape[-1], phase_m.shape[0]
    dtype, dev = ph.dtype, ph.device
    q = d * (d + 1) // 2
    iu, ju = torch.triu_indices(d, d, device=dev)
    se = cov.diagonal(dim1=-2, dim2=-1).clamp(min=0).sqrt()
    # the residuals of the samples nearest each phase, summed in the fit's row chunks
    sse = ph.new_zeros(batch + (m,))
    cnt = ph.new_zeros(batch + (m,))
    near = torch.remainder(torch.round(ph * (m / (2 * math.pi))), m).to(torch.int64)
    for start in range(0, n, _ROW_CHUNK):
        rows = slice(start, min(start + _ROW_CHUNK, n))
        sse.scatter_add_(-1, near[..., rows], residual[..., rows].square())
        cnt.scatter_add_(-1, near[..., rows], w[..., rows])

    # evaluate at phase_m
    basis = fourier_design(phase_m.to(ph), order)  # (M, 2K+1)
    n_m = (2 * order + 1) * q
    coef_m = basis @ beta[..., :n_m].unflatten(-1, (2 * order + 1, q))  # (..., M, q)
    cov_blk = cov[..., :n_m, :n_m].unflatten(-1, (2 * order + 1, q)).unflatten(-3, (
        2 * order + 1, q))  # (..., h, q, h', q')
    cov_m = torch.einsum("mh,...hapb,mp->...mab", basis, cov_blk, basis)
    sampling_m = _bin_factor(fit.influence[..., :n_m], basis, d)
    offset_m = None if fit.offset_change is None else _symmetric(basis @ fit.offset_change, d)
    bias_m = se_bias_m = factor_m = None
    if fit.order_change is not None:
        # the bias allowed for: its outer product added to the covariance (a mean squared error)
        n_w = fit.order_change.shape[-2]
        wide = fourier_design(phase_m.to(ph), (n_w - 1) // 2)
        bias_m = wide @ fit.order_change  # (..., M, q)
        cov_change = torch.einsum("mh,...hapb,mp->...mab", wide, fit.order_change_cov.unflatten(
            -1, (n_w, q)).unflatten(-3, (n_w, q)), wide)  # (..., M, q, q)
        se_bias_m = cov_change.diagonal(dim1=-2, dim2=-1).clamp(min=0).sqrt()
        cov_m = cov_m + bias_m.unsqueeze(-1) * bias_m.unsqueeze(-2)
        if fit.order_bias == "posterior":
            cov_m = cov_m + cov_change
            factor_m = _bin_factor(fit.order_change_spread, wide, d)
        elif fit.order_bias == "dropped":  # where the choice fell below the order given
            dropped = (chosen < order)[..., None, None, None]
            cov_m = torch.where(dropped, cov_m + cov_change, cov_m)
            factor_m = _bin_factor(fit.order_change_spread, wide, d)
            factor_m = torch.where(dropped[..., None], factor_m, 0.0)
    se_m = cov_m.diagonal(dim1=-2, dim2=-1).clamp(min=0).sqrt()
    d_m = se_d = None
    if derivative_order is not None:
        bd = fourier_design(phase_m.to(ph), derivative_order)
        n_d = (2 * derivative_order + 1) * d * q
        blk = beta[..., n_m:n_m + n_d].unflatten(-1, (2 * derivative_order + 1, d, q))
        d_m = _symmetric(torch.einsum("mh,...hkq->...mkq", bd, blk), d).movedim(-3, -1)
        var = cov[..., n_m:n_m + n_d, n_m:n_m + n_d].diagonal(dim1=-2, dim2=-1).unflatten(
            -1, (2 * derivative_order + 1, d, q))
        # standard errors of ∂M/∂r ignoring the covariance between its harmonics (a guide)
        se_d = _symmetric(torch.einsum("mh,...hkq->...mkq", bd.square(), var).sqrt(),
                          d).movedim(-3, -1)

    # ∂(Mγ̇)_i/∂c_kl = ½([i=k] γ̇_l + [i=l] γ̇_k): c_kl is M_kk on the diagonal, 2 M_kl off it
    eye_d = torch.eye(d, dtype=dtype, device=dev)
    jac = 0.5 * (eye_d[:, iu] * gd[..., None, ju] + eye_d[:, ju] * gd[..., None, iu])
    grad = gd[..., iu] * gd[..., ju]
    m_gd = (jac @ coef_m.unsqueeze(-1))[..., 0]
    se_m_gd = ((jac @ cov_m) * jac).sum(-1).clamp(min=0).sqrt()
    p_cyc = (grad * coef_m).sum(-1)
    se_p = (grad.unsqueeze(-2) @ cov_m @ grad.unsqueeze(-1))[..., 0, 0].clamp(min=0).sqrt()

    def per_phase(x: Tensor) -> Tensor:
        return x.unsqueeze(-1).expand(batch + (m,))

    return MetricFit(
        M=_symmetric(coef_m, d), se_M=_symmetric(se_m, d), dM=d_m, se_dM=se_d,
        power_on_cycle=p_cyc, n_samples=cnt.round().to(torch.int64),
        residual_rms=(sse / cnt.clamp(min=1)).sqrt(), condition=per_phase(condition),
        ridge=torch.zeros_like(per_phase(condition)), coef=beta, se_coef=se,
        se_power_on_cycle=se_p, M_gamma_dot=m_gd, se_M_gamma_dot=se_m_gd,
        noise_correction=per_phase(applied), cov_M=cov_m, order=chosen,
        bias_M=None if bias_m is None else _symmetric(bias_m, d),
        se_bias_M=None if se_bias_m is None else _symmetric(se_bias_m, d),
        change_factor_M=factor_m, sampling_factor_M=sampling_m, offset_bias_M=offset_m,
    )


def _bin_factor(spread: Tensor, wide: Tensor, d: int) -> Tensor:
    """A factor ``(..., M, d, d, R)`` of a sampling covariance of series coefficients across
    the entries and phases of ``M̂`` (the order change's, or the fit's own): each cycle's share
    ``spread (..., C, W q)`` evaluated at the phases (``wide (M, W)``, the series' design
    there), compressed by an SVD to the ``R`` directions whose variance exceeds ``1e-14`` of
    the largest (``R ≤ min(C, W q)``)."""
    n_w, q = wide.shape[-1], d * (d + 1) // 2
    at = torch.einsum("mh,...chq->...cmq", wide, spread.unflatten(-1, (n_w, q)))
    _, sv, vh = _linalg.svd(at.flatten(-2), "the metric's error factor")  # (..., k), (..., k, M q)
    kept = sv > 1e-7 * sv[..., :1]
    rank = max(int(kept.sum(-1).max()), 1) if kept.numel() else 1
    factor = (sv[..., :rank, None] * vh[..., :rank, :]).unflatten(-1, at.shape[-2:])
    return _symmetric(factor, d).movedim(-4, -1)  # (..., M, d, d, R)


def _signal_floor(n_coef: int, n_samples: Tensor) -> Tensor:
    """The floor on the signal fraction, ``(...)``: :data:`_FLOOR_SCALE` ``√(P/N)`` for ``P =
    n_coef`` coefficients and ``N = n_samples (...)`` samples, at most :data:`_MAX_FLOOR`."""
    ratio = n_coef / n_samples.to(torch.float64).clamp(min=1)
    return (_FLOOR_SCALE * ratio.sqrt()).clamp(max=_MAX_FLOOR)


@dataclass(frozen=True)
class _CorrectedNormal:
    """The noise-corrected normal matrix ``A`` of a batch of fits, with a floor on the signal
    fraction of every direction.

    With ``G = L Lᵀ`` and ``L⁻¹ C L⁻ᵀ = U diag(ν) Uᵀ``, i.e. ``T = LU``, ``G = T Tᵀ`` and
    ``C = T diag(ν) Tᵀ``: direction ``j`` keeps the fraction ``1 − ν_j`` of its raw excitation
    once the noise's share ``ν_j`` is removed, and the full correction divides by it. Where the
    noise swamps a direction (``1 − ν_j`` below ``floor``, mostly sampling error there) only the
    share ``κ_j = (1 − floor)/ν_j`` of the correction is applied, to both sides of the normal
    equations: ``A = T diag(1 − κν) Tᵀ`` and the right-hand side's correction ``c`` becomes
    ``T diag(κ) T⁻¹ c``. Each such direction thus lies between the uncorrected fit (``κ = 0``)
    and the corrected one, as a uniform shrink of the whole correction would put every
    direction (the previous guard, which also attenuated the well-excited directions that
    carry ``M̂γ̇``); pulling those directions towards zero instead (a ridge) was measured far
    worse on the 9-link. One Cholesky of ``(1 − floor) G − C`` finds the elements that need no
    floor (``A = G − C``); only the others get the eigenvalue solve.

    Attributes (``B`` batch elements, flattened; ``P`` coefficients):
        full: ``(B, P, P)`` Cholesky factor of ``G − C`` where not ``floored``.
        floored: ``(B,)`` bool, elements with a floored direction.
        lower, rotation: ``(n, P, P)`` ``L`` and ``U`` of the ``n`` floored elements;
            scale, share: ``(n, P)`` their ``1 − κν`` and ``κ``.
        applied: ``(B,)`` least ``κ`` (1 where nothing was floored).
        ok: ``(B,)`` False where ``G`` itself is not positive definite (unusable).
        shape: the batch shape to restore.
    """

    full: Tensor
    floored: Tensor
    lower: Tensor
    rotation: Tensor
    scale: Tensor
    share: Tensor
    applied: Tensor
    ok: Tensor
    shape: tuple

    @staticmethod
    def of(gram: Tensor, corr: Tensor, floor: Tensor,
           nested: _LeadingFactors | None = None) -> _CorrectedNormal:
        """From ``gram, corr (..., P, P)`` (equilibrated, ``gram`` positive definite) and the
        floor ``(...)`` of each element; ``nested``: the factors of larger matrices whose
        leading ``P × P`` blocks ``gram`` and ``corr`` are (computed there once for all sizes)."""
        shape, p = gram.shape[:-2], gram.shape[-1]
        g, c = gram.reshape(-1, p, p), corr.reshape(-1, p, p)
        floor = torch.as_tensor(floor, dtype=g.dtype, device=g.device).expand(shape).reshape(-1)
        _, info = torch.linalg.cholesky_ex((1 - floor)[:, None, None] * g - c)
        # G − C's factor only where the floor is not reached (the others are solved through
        # the eigenvalues and keep an identity here)
        easy = torch.nonzero(info == 0)[:, 0]
        full = torch.eye(p, dtype=g.dtype, device=g.device).repeat(g.shape[0], 1, 1)
        info_full = torch.zeros_like(info)
        if easy.numel():
            full[easy], info_full[easy] = torch.linalg.cholesky_ex(g[easy] - c[easy])
        floored = (info != 0) | (info_full != 0)
        ok = torch.ones_like(floored)
        applied = g.new_ones(g.shape[0])
        need = torch.nonzero(floored)[:, 0]
        factors = None if nested is None or not need.numel() else nested.leading(need, p)
        if factors is None:
            lower, info_g = torch.linalg.cholesky_ex(g[need])
            n = _LeadingFactors.whitened(lower, c[need])
        else:
            lower, n, info_g = factors
        # an element whose G is not positive definite has no whitened matrix (its factor is
        # partial): it is marked unusable below and gets no correction
        good = (info_g == 0)[:, None, None]
        nu, u = _linalg.eigh(torch.where(good, (n + n.mT) / 2, torch.zeros_like(n)),
                             "the metric's noise-corrected normal matrix")
        top = (1 - floor[need]).unsqueeze(-1)
        share = torch.where(nu > top, top / nu, 1.0)
        applied[need] = share.amin(-1)
        ok[need] = info_g == 0
        return _CorrectedNormal(full=full, floored=floored, lower=lower, rotation=u,
                                scale=1 - share * nu, share=share, applied=applied.reshape(shape),
                                ok=ok.reshape(shape), shape=tuple(shape))

    def _t_inv(self, x: Tensor) -> Tensor:
        """``T⁻¹ x = Uᵀ L⁻¹ x`` for ``x (n, P)`` of the floored elements."""
        y = torch.linalg.solve_triangular(self.lower, x.unsqueeze(-1), upper=False)
        return (self.rotation.mT @ y)[..., 0]

    def correction_share(self, c: Tensor) -> Tensor:
        """The right-hand side's correction ``c (..., P)`` in the shares applied."""
        out = c.reshape(-1, c.shape[-1]).clone()
        if bool(self.floored.any()):
            z = self._t_inv(out[self.floored]) * self.share
            out[self.floored] = (self.lower @ (self.rotation @ z.unsqueeze(-1)))[..., 0]
        return out.reshape(c.shape)

    def solve(self, h: Tensor) -> Tensor:
        """``A⁻¹ h`` for ``h (..., P)``."""
        flat = h.reshape(-1, h.shape[-1])
        out = torch.cholesky_solve(flat.unsqueeze(-1), self.full)[..., 0]
        if bool(self.floored.any()):
            z = self._t_inv(flat[self.floored]) / self.scale
            # T⁻ᵀ z = L⁻ᵀ U z
            w = torch.linalg.solve_triangular(self.lower.mT, self.rotation @ z.unsqueeze(-1),
                                              upper=True)
            out[self.floored] = w[..., 0]
        return out.reshape(h.shape)

    def cholesky(self) -> Tensor:
        """``(..., P, P)`` the Cholesky factor of ``A`` (forms ``A`` for floored elements)."""
        chol = self.full.clone()
        if bool(self.floored.any()):
            t = self.lower @ self.rotation
            a = (t * self.scale.unsqueeze(-2)) @ t.mT
            chol[self.floored] = torch.linalg.cholesky_ex((a + a.mT) / 2)[0]
        return chol.reshape(self.shape + chol.shape[-2:])


class _LeadingFactors:
    """The Cholesky factor ``L`` of ``G`` and ``L⁻¹ C L⁻ᵀ`` of the largest of nested normal
    matrices, computed once, on first use: for ``L`` lower triangular, those of a leading
    block ``G[:P, :P], C[:P, :P]`` are the leading blocks of the largest's.

    Args (of the constructor): gram, corr: ``(B, P', P')`` the largest matrices.
    """

    def __init__(self, gram: Tensor, corr: Tensor):
        self._gram, self._corr = gram, corr
        self._factors: tuple[Tensor, Tensor, Tensor] | None = None

    @staticmethod
    def whitened(lower: Tensor, corr: Tensor) -> Tensor:
        """``L⁻¹ C L⁻ᵀ (..., P, P)`` from ``lower, corr (..., P, P)``."""
        half = torch.linalg.solve_triangular(lower, corr, upper=False)  # L⁻¹ C
        return torch.linalg.solve_triangular(lower, half.mT, upper=False)

    def leading(self, idx: Tensor, p: int) -> tuple[Tensor, Tensor, Tensor] | None:
        """``L, L⁻¹CL⁻ᵀ (n, P, P)`` and ``info (n,)`` (zeros) of the elements ``idx (n,)`` at
        the leading size ``p``, or None where the largest ``G`` of one of them is not positive
        definite (its factor is then computed at size ``p``)."""
        if self._factors is None:
            lower, info = torch.linalg.cholesky_ex(self._gram)
            good = torch.nonzero(info == 0)[:, 0]
            n = torch.zeros_like(lower)
            n[good] = self.whitened(lower[good], self._corr[good])
            self._factors = (lower, n, info)
        lower, n, info = self._factors
        if bool((info[idx] != 0).any()):
            return None
        return lower[idx, :p, :p], n[idx, :p, :p], info[idx]


def _held_out_orders(gram: Tensor, corr: Tensor, rhs: Tensor, corr_h: Tensor, inv: Tensor,
                     order: int, q: int, n_fold: Tensor) -> Tensor:
    """The Fourier order of ``M(φ)`` in ``0 … order`` with the least held-out error over
    blocks of whole cycles, per batch element.

    Each block's noise-corrected normal equations ``G_b β = h_b`` (``G_b = X̂_bᵀX̂_b − C_b``,
    ``h_b = X̂_bᵀy_b − c_b``) make ``β ᵀG_b β − 2βᵀh_b`` an unbiased estimate of the block's
    noise-free squared prediction error of ``β`` up to a constant (the noise's contributions
    ``C_b, c_b`` are removed as in the fit), so the coefficients fitted on the other blocks are
    scored on it without the noisy regressors favouring attenuated models. Among ``order``
    and the lower orders whose summed loss beats ``order``'s by more than :data:`_ORDER_Z`
    standard errors of the difference (from its spread over the blocks), the one with the least
    summed loss is chosen (the lowest on ties). The fits on the other blocks are floored as the
    final fit is (:class:`_CorrectedNormal`); an order whose raw normal matrix there is not
    positive definite scores infinity (``order`` when every order does). Each order is solved
    at its own size, on the factors of the largest order's fits (:class:`_LeadingFactors`).

    Args:
        gram: ``(..., F, P, P)`` raw normal matrices ``X̂_bᵀX̂_b`` per block (``P`` in the
            layout of ``order``: feature ``a = column // q``, the first ``2·order+1`` those of
            ``M(φ)``); corr: ``(..., F, P, P)`` the noise's contributions ``C_b``; rhs, corr_h:
            ``(..., F, P)`` raw right-hand sides ``X̂_bᵀy_b`` and the noise's contributions
            ``c_b``; inv: ``(..., P)`` equilibration of the whole fit.
        order: largest order; q: metric coefficients per feature.
        n_fold: ``(..., F)`` usable samples per block.

    Returns:
        ``(...)`` int64 orders.
    """
    p = gram.shape[-1]
    # columns reordered once, those of ∂M/∂r(φ) first and M(φ)'s by harmonic: each order's
    # columns are then a leading block (the order's own size, not kept as identity rows: the
    # eigenvalue solve of the floor costs P³)
    n_m = (2 * order + 1) * q
    dev = gram.device
    perm = torch.cat([torch.arange(n_m, p, device=dev), torch.arange(n_m, device=dev)])
    gram, corr = _principal(gram, perm), _principal(corr, perm)
    rhs, corr_h, inv = rhs[..., perm], corr_h[..., perm], inv[..., perm]
    train_g = gram.sum(-3, keepdim=True) - gram
    train_c = corr.sum(-3, keepdim=True) - corr
    gram = gram - corr  # the blocks' corrected normal matrices, for the held-out loss
    train_h = rhs.sum(-2, keepdim=True) - rhs
    train_ch = corr_h.sum(-2, keepdim=True) - corr_h
    rhs = rhs - corr_h
    dead = train_g.diagonal(dim1=-2, dim2=-1) <= 0
    # the floor of the whole fit, so that it does not favour one order or block over another
    floor = _signal_floor(p, n_fold.sum(-1, keepdim=True)).expand(n_fold.shape)
    # the largest order's equilibrated fits on the other blocks (dead columns as identity
    # rows); each order's are their leading blocks
    scale, keep = inv.unsqueeze(-2), (~dead).to(gram)  # (..., 1, P), (..., F, P)
    both = (scale * keep).unsqueeze(-1) * (scale * keep).unsqueeze(-2)
    train_g = train_g * both + torch.diag_embed(dead.to(gram))
    train_c = train_c * both
    nested = _LeadingFactors(train_g.reshape(-1, p, p), train_c.reshape(-1, p, p))
    losses = []
    for k in range(order + 1):
        c = p - n_m + (2 * k + 1) * q  # the order's columns: [:c], P_k = c
        normal = _CorrectedNormal.of(train_g[..., :c, :c], train_c[..., :c, :c], floor, nested)
        h = (train_h[..., :c] * scale[..., :c]
             - normal.correction_share(train_ch[..., :c] * scale[..., :c])) * keep[..., :c]
        beta = normal.solve(h) * scale[..., :c]
        loss = ((beta.unsqueeze(-2) @ gram[..., :c, :c] @ beta.unsqueeze(-1))[..., 0, 0]
                - 2 * (beta * rhs[..., :c]).sum(-1))
        losses.append(torch.where(normal.ok, loss, torch.inf))
    losses = torch.stack(losses, -1)  # (..., F, order + 1)
    # a lower order than ``order`` only where it predicts the held-out blocks better by more
    # than _ORDER_Z standard errors of the difference (over the blocks): a harmonic dropped
    # by chance biases M̂ beyond its bands
    diff = losses - losses[..., -1:]
    n_f = diff.shape[-2]
    spread = (n_f / max(n_f - 1, 1) * (diff - diff.mean(-2, keepdim=True)).square().sum(-2)).sqrt()
    total = losses.sum(-2)
    allowed = (diff.sum(-2) + _ORDER_Z * spread < 0) | ~torch.isfinite(total[..., -1:])
    allowed[..., -1] = True
    best = torch.where(allowed & torch.isfinite(total), total, torch.inf).argmin(-1)
    return torch.where(torch.isfinite(total).any(-1), best, order)


def _order_columns(p: int, q: int, k: int, order: int, device) -> Tensor:
    """``(P_k,)`` int64 columns of the tied model at Fourier order ``k ≤ order`` of ``M(φ)``,
    in the layout of ``order`` (``P`` columns, feature ``column // q``; the first
    ``2·order+1`` features those of ``M(φ)``, the rest those of ``∂M/∂r(φ)``)."""
    feature = torch.arange(p, device=device) // q
    return torch.nonzero((feature < 2 * k + 1) | (feature >= 2 * order + 1))[:, 0]


def _principal(x: Tensor, cols: Tensor) -> Tensor:
    """``(..., P_k, P_k)`` the principal submatrix of ``x (..., P, P)`` on ``cols (P_k,)``."""
    return x.index_select(-1, cols).index_select(-2, cols)


def _noise_terms(s2: Tensor, s0: Tensor, fy: Tensor, sig: Tensor, iu: Tensor, ju: Tensor,
                 on_diag: Tensor) -> tuple[Tensor, Tensor]:
    """The noise's expected contribution to the normal equations of the tied model.

    With ``v̂ = v + e``, ``e ~ N(0, diag(σ))`` independent of the (noise-free) features ``F``,
    the Gaussian moment identity gives the bias of ``Σ w F_a F_c v̂_i v̂_j v̂_k v̂_l`` as the six
    terms ``(v̂v̂)σ`` minus the three ``σσ`` pairings, and of ``Σ w F_a y v̂_i v̂_j`` as
    ``σ_i [i=j] Σ w F_a y``.

    Args:
        s2: ``(..., g, g, d, d)`` ``Σ w F_a F_c v̂_i v̂_j``; s0: ``(..., g, g)`` ``Σ w F_a F_c``;
        fy: ``(..., g)`` ``Σ w F_a y``; sig: ``(..., d)`` noise variances.

    Returns:
        corrections ``(..., g·q, g·q)`` and ``(..., g·q)`` to subtract (layout ``a·q + pair``).
    """
    g = s0.shape[-1]
    qn = iu.numel()
    i, j = iu[:, None].expand(qn, qn), ju[:, None].expand(qn, qn)
    k, l_ = iu[None, :].expand(qn, qn), ju[None, :].expand(qn, qn)
    sg = sig[..., None, None, :]  # (..., 1, 1, d)

    def eq(a: Tensor, b: Tensor) -> Tensor:
        return (a == b).to(s2)

    def s(a: Tensor, b: Tensor) -> Tensor:  # (..., g, g, q, q)
        return s2[..., a, b]

    def z(a: Tensor) -> Tensor:  # σ_a as (..., 1, 1, q, q)
        return sg[..., a]

    corr = (s(i, j) * z(k) * eq(k, l_) + s(k, l_) * z(i) * eq(i, j)
            + s(i, k) * z(j) * eq(j, l_) + s(i, l_) * z(j) * eq(j, k)
            + s(j, k) * z(i) * eq(i, l_) + s(j, l_) * z(i) * eq(i, k))
    corr = corr - s0[..., None, None] * (z(i) * z(k) * eq(i, j) * eq(k, l_)
                                         + z(i) * z(j) * (eq(i, k) * eq(j, l_)
                                                          + eq(i, l_) * eq(j, k)))
    corr_g = corr.transpose(-3, -2).reshape(corr.shape[:-4] + (g * qn, g * qn))
    corr_h = (fy.unsqueeze(-1) * (sig[..., None, iu] * on_diag)).flatten(-2)
    return corr_g, corr_h


def tied_metric_predict(coef: Tensor, offset: Tensor, velocity: Tensor, phase: Tensor, *,
                        order: int, derivative_order: int | None,
                        second_order: SecondOrder = None) -> tuple[Tensor, Tensor]:
    """Power and ``M̂(φ) v`` the tied model predicts for samples.

    Args:
        coef: ``(..., P)`` coefficients from :func:`tied_metric_regression` (its ``coef``).
        offset, velocity: ``(..., N, d)``; phase: ``(..., N)``.
        order, derivative_order, second_order: the model the coefficients were fitted with.

    Returns:
        ``(power (..., N), M̂v (..., N, d))`` (``M̂`` on the cycle, without the offset term).
    """
    d = velocity.shape[-1]
    q = d * (d + 1) // 2
    iu, ju = torch.triu_indices(d, d, device=velocity.device)
    n_m = (2 * order + 1) * q
    n_d = 0 if derivative_order is None else (2 * derivative_order + 1) * d * q
    m_coef = coef[..., :n_m].unflatten(-1, (2 * order + 1, q))  # (..., h, q)
    power, m_v = [], []
    for start in range(0, phase.shape[-1], _ROW_CHUNK):
        rows = slice(start, min(start + _ROW_CHUNK, phase.shape[-1]))
        b = fourier_design(phase[..., rows], order)
        mq = b @ m_coef  # (..., n, q)
        mq_full = mq
        if derivative_order is not None:
            bd = fourier_design(phase[..., rows], derivative_order)
            dq = coef[..., n_m:n_m + n_d].unflatten(-1, (2 * derivative_order + 1, d * q))
            dq = (bd @ dq).unflatten(-1, (d, q))  # (..., n, d, q)
            mq_full = mq + (offset[..., rows, :, None] * dq).sum(-2)
        if second_order is not None:  # ½ δᵀ∂²M/∂r²δ
            mq_full = mq_full + _second_order_features(offset[..., rows, :], second_order) @ coef[
                ..., n_m + n_d:].unflatten(-1, (-1, q))
        vr = velocity[..., rows, :]
        power.append((mq_full * vr[..., iu] * vr[..., ju]).sum(-1))
        m_v.append((_symmetric(mq, d) @ vr.unsqueeze(-1)).squeeze(-1))
    return torch.cat(power, -1), torch.cat(m_v, -2)


def power_noise_variance(residual: Tensor, m_v: Tensor, dt: float, *, with_se: bool = False
                         ) -> Tensor | tuple[Tensor, Tensor]:
    """Observation-noise variance of the shape channels, from the power residuals' lag structure.

    The power channel is noise-free, while the model's velocity ``v̂ = v + e`` carries the
    differenced noise ``e_k = (ε_{k+1} − ε_k)/Δt``. To first order the residual of a fit
    without noise correction is ``−2 (M̂v)ᵀ e_k``, and adjacent intervals share ``ε_{k+1}``, so
    ``E[res_k res_{k+1}] = −(4/Δt²) Σ_i (M̂v)_{k,i} (M̂v)_{k+1,i} ω_i²``, while a smooth model
    error contributes the same to lags 1 and 2. Regressing ``res_k (res_{k+1} − res_{k+2})`` on
    that feature gives ``ω²``. One level is fitted for all joints (the motion-capture noise of
    every joint angle, as in docs/conventions.md): per-joint levels were measured too noisy to separate
    on the 5-link (0 to 1.5× the truth at ω = 0.002).

    Args:
        residual: ``(..., N)`` ``P − P̂`` of an uncorrected fit, in time order (NaN: skipped;
            pooled trials may be concatenated when a NaN separates them).
        m_v: ``(..., N, d)`` ``M̂v`` of the same samples.
        dt: sampling interval.
        with_se: also return the standard error of ``ω²``, from the spread of the regression's
            sums over :data:`_NOISE_BLOCKS` blocks of consecutive samples (the products of
            residuals are serially correlated, so samples are not independent).

    Returns:
        ``(..., d)`` ``ω²`` (≥ 0, the same for every joint), the noise on the recorded shapes;
        with ``with_se`` also its ``(..., d)`` standard error (before clamping).
    """
    z = residual[..., :-2] * (residual[..., 1:-1] - residual[..., 2:])  # (..., N-2)
    f = -(4 / dt**2) * (m_v[..., :-2, :] * m_v[..., 1:-1, :]).sum(-1)
    ok = torch.isfinite(z) & torch.isfinite(f)
    z, f = torch.where(ok, z, 0.0), torch.where(ok, f, 0.0)
    tiny = torch.finfo(f.dtype).tiny
    omega2 = (f * z).sum(-1) / (f * f).sum(-1).clamp(min=tiny)
    shape = m_v.shape[:-2] + m_v.shape[-1:]
    out = omega2.clamp(min=0).unsqueeze(-1).expand(shape)
    if not with_se:
        return out
    # the ratio estimator's linearised spread over blocks of consecutive samples
    n_b = _NOISE_BLOCKS
    pad = (-z.shape[-1]) % n_b
    fz = _pad_last(f * z, pad).unflatten(-1, (n_b, -1)).sum(-1)
    ff = _pad_last(f * f, pad).unflatten(-1, (n_b, -1)).sum(-1)
    u = fz - omega2.unsqueeze(-1) * ff
    se = (u.square().sum(-1) * n_b / (n_b - 1)).sqrt() / ff.sum(-1).clamp(min=tiny)
    return out, se.unsqueeze(-1).expand(shape)


def _pad_last(x: Tensor, n: int) -> Tensor:
    """``x (..., N)`` with ``n`` zeros appended along the last dim."""
    return torch.cat([x, x.new_zeros(x.shape[:-1] + (n,))], -1)
