"""The tied metric model: one ``M(φ)`` (and ``∂M/∂r(φ)``) explains all of the recorded power.

On the sample intervals the power channel belongs to (docs/conventions.md: ``power`` at row ``k``
is the mean over ``[t_k, t_{k+1})``),

    P_k ≈ v_kᵀ [M(φ) + ∂M/∂r_k(φ) δ_k] v_k

with ``v_k = (r_{k+1} − r_k)/Δt`` the raw sample differences and ``M(φ)``, ``∂M/∂r(φ)`` Fourier
series in phase. The observation noise's known contribution to the normal equations is removed
(:mod:`~torchconn.regression.metric.normal`; :func:`~torchconn.regression.metric.noise.
power_noise_variance` estimates its level from the power residuals).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace
from typing import Literal

import torch
from torch import Tensor, nn

from ... import _linalg
from ...cycles import cycle_blocks, cycle_index
from ...phase.fourier import fourier_design
from .. import _wls
from .normal import (
    CorrectedNormal,
    held_out_orders,
    noise_terms,
    order_columns,
    principal,
    signal_floor,
)

#: the tied model's second-order offset term: None (none), ``"diagonal"`` (``δ_k²``) or
#: ``"full"`` (``δ_k δ_l``); see :func:`tied_metric_regression`
SecondOrder = Literal["diagonal", "full"] | None
_SECOND_ORDERS = (None, "diagonal", "full")

__all__ = ["MetricFit", "SecondOrder", "symmetric", "tied_metric_regression",
           "tied_metric_coefficients", "TiedMetricCoefficients", "tied_metric_n_coef",
           "tied_metric_predict"]


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
            excitation, see :class:`CorrectedNormal`); None for the paper's model.
        cov_M: ``(..., M, q, q)`` covariance of the ``q = d(d+1)/2`` metric coefficients (tied
            model only; with ``order_bias`` the outer product of ``bias_M``'s added, and so in
            ``se_M``, ``se_M_gamma_dot`` and ``se_power_on_cycle``).
        order: ``(...)`` Fourier order of ``M(φ)`` (tied model only).
        bias_M: ``(..., M, d, d)`` the bias allowed for in the bands (tied model with
            ``order_bias`` only): the change of ``M̂`` at two more harmonics of ``M(φ)``.
        se_bias_M: ``(..., M, d, d)`` that change's own standard error (its sampling noise,
            from the two fits' joint cluster-robust covariance; ``order_bias`` only). Where it
            is as large as ``bias_M`` the change does not resolve the bias; its variance is
            in ``se_M``.
        change_factor_M: ``(..., M, d, d, R)`` a factor of the part of the covariance of
            ``M̂`` that is that change's sampling covariance, across entries *and* phases
            (``Σ_r F[..., r] ⊗ F[..., r]``; its diagonal is the change's variance in ``se_M``):
            with ``order_bias``; None otherwise. ``R`` is at most the number of cycles;
            directions whose variance is below ``1e-14`` of the largest are left out.
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



def symmetric(upper: Tensor, d: int) -> Tensor:
    """``(..., q) -> (..., d, d)`` from the ``i ≤ j`` coefficients of ``δ̇_i δ̇_j``."""
    iu, ju = torch.triu_indices(d, d, device=upper.device)
    half = torch.where(iu == ju, 1.0, 0.5).to(upper)
    out = upper.new_zeros(upper.shape[:-1] + (d, d))
    out[..., iu, ju] = upper * half
    out[..., ju, iu] = upper * half
    return out


#: rows of the design built at once (bounds memory: rows × coefficients × 8 bytes)
_ROW_CHUNK = 2048
#: blocks of whole cycles held out in turn to choose the order of ``M(φ)``
_ORDER_FOLDS = 5
#: harmonics of ``M(φ)`` added to the chosen order for the bias allowance of the bands
#: (``order_bias``): the change of ``M̂`` from order ``K`` to ``K + 2`` is taken as ``M̂``'s bias
#: (the higher harmonics' leakage into the off-cycle directions).
_BIAS_ORDER_STEP = 2


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
    order_bias: bool = False,
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
    (docs/validation/metric.md).
    ``second_order`` fits that term too, constant in phase: ``"full"`` the products
    ``δ_k δ_l v_i v_j`` (``q·q`` coefficients), ``"diagonal"`` only ``δ_k² v_i v_j`` (``d·q``;
    removes the bias where the offsets of different joints are uncorrelated). It removes the
    bias but costs variance under noise (the products' mean is collinear with ``M(φ)``'s
    constant), so it is not the default.

    Noise: ``v`` comes from raw sample differences, so observation noise ``ε`` on ``r``
    enters as ``e = (ε_{k+1} − ε_k)/Δt``, Gaussian with covariance
    ``Σ = diag(noise_variance)`` (``= 2ω²/Δt²``) and independent of the noise on ``r̄``
    (a sum and a difference of i.i.d. Gaussians). The products of regressors are biased by
    ``Σ``; the known bias is removed from the normal equations (the Gaussian fourth-moment
    identity: an errors-in-variables correction). ``r̄``'s own noise, variance ``ω²/2`` against
    the offsets' ``η²/2α``, only biases ``∂M/∂r`` (by ~0.2 % at ω = 0.005) and is left alone.
    In the directions of the coefficients where the noise swamps the excitation (signal
    fraction of the corrected normal matrix below ``1.1 √(P/N)``) only part of the correction
    is applied, the other directions keep all of it (:class:`CorrectedNormal`;
    ``MetricFit.noise_correction`` < 1, with a warning).

    Standard errors: the sandwich ``G⁻¹ (Σ_c s_c s_cᵀ) G⁻¹`` over cycles ``c`` (whole turns of
    ``phase``), ``s_c`` the summed scores of the corrected regressors: they reflect the actual
    scatter, the serial correlation of differenced noise and how much excitation each direction
    of ``M`` gets (wide bands where the data do not excite a direction).

    Args:
        offset: ``(..., N, d)`` ``δ = r̄ − γ(φ)``, the interval's offset from the cycle at its
            own phase; velocity: ``(..., N, d)`` ``v``; power: ``(..., N)``; phase: ``(..., N)``
            unwrapped (one-sample intervals of
            :func:`~torchconn.noise.interval_samples`). Samples with any NaN
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
            ``0 … order`` by held-out blocks of whole cycles (:func:`held_out_orders`; the
            harmonics above it get zero coefficients, so ``coef`` keeps the layout of
            ``order``); False: ``order``.
        order_bias: widen the bands by the model's bias, estimated as the change of ``M̂`` when
            ``M(φ)`` gets two more harmonics (one more fit, at each element's order + 2): its
            outer product and its own sampling covariance (the mean squared bias given the
            change, under a flat prior on the bias) are added to the covariance of ``M̂``
            (``MetricFit.bias_M``, ``se_bias_M``; the estimates are unchanged). Without it,
            on clean data the bands see only the residuals' scatter, not the leakage of the
            truncated harmonics. Where that fit fails (too few samples), a warning and no
            widening. Default False; the estimator's metric stage uses True.
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
    order_bias: bool = False,
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
            the draws of nearby gaits. None: not
            estimated; where that fit fails, a warning and none.
    """
    for name, value in (("second_order", second_order), ("offset_bias", offset_bias)):
        if value not in _SECOND_ORDERS:
            raise ValueError(f"tied_metric_regression: {name} must be one of "
                             f"{_SECOND_ORDERS}, got {value!r}")
    if not isinstance(order_bias, bool):
        raise TypeError(f"tied_metric_regression: order_bias must be True or False, "
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
                   order_change_spread=spread)


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
    s = _tied_samples(offset, velocity, power, phase, order, derivative_order, second_order,
                      noise_variance, min_samples_per_coef, fn)
    if max_condition is None:
        max_condition = 1e12 if s.dtype == torch.float64 else 1e-2 / torch.finfo(s.dtype).eps
    # whole cycles of phase: the clusters of the standard errors and the held-out blocks
    # (cycles start at the multiples of 2π; a missing row is in cycle 0 and block 0)
    valid_ph = torch.where(s.valid, s.ph, torch.nan)
    cyc = cycle_index(valid_ph, False, origin="grid", missing="first")
    n_c = int(cyc.max()) + 1 if cyc.numel() else 1
    folds = _ORDER_FOLDS if held_out_order else 1
    fold = cycle_blocks(valid_ph, folds, origin="grid").clamp_min(0)
    gram, corr_g, rhs, corr_h = _block_normal_equations(s, fold, folds)
    diag = gram.sum(-3).diagonal(dim1=-2, dim2=-1)
    inv = torch.where(diag <= 0, 1.0, diag.rsqrt())
    chosen = torch.full(s.batch, order, dtype=torch.int64, device=s.device)
    if orders is not None:
        chosen = orders.to(chosen).expand(s.batch)
    elif held_out_order:
        n_fold = torch.stack([(s.valid & (fold == b)).sum(-1) for b in range(folds)], -1)
        chosen = held_out_orders(gram, corr_g, rhs, corr_h, inv, order, s.q, n_fold)
    # the harmonics above each element's order are dropped (zero coefficients): the fit is
    # solved at the size of the batch's largest chosen order (``cols``), and the elements with
    # a lower one keep their dropped columns as identity rows
    top = int(chosen.max()) if chosen.numel() else order
    cols = order_columns(s.p, s.q, top, order, s.device)  # (P',)
    feature = torch.arange(s.p, device=s.device)[cols] // s.q
    drop = (feature >= 2 * chosen[..., None] + 1) & (feature < 2 * order + 1)  # (..., P')
    keep = (~drop).to(s.dtype)
    both = keep.unsqueeze(-1) * keep.unsqueeze(-2)
    gram, corr_g = principal(gram.sum(-3), cols) * both, principal(corr_g.sum(-3), cols) * both
    rhs, corr_h = rhs.sum(-2)[..., cols] * keep, corr_h.sum(-2)[..., cols] * keep
    inv = inv[..., cols]
    normal, chol, condition = _checked_normal(s, gram, corr_g, inv, drop, max_condition, fn)
    applied = normal.applied
    h = rhs * inv - normal.correction_share(corr_h * inv)
    beta_r = torch.cholesky_solve(h.unsqueeze(-1), chol)[..., 0] * inv  # (..., P')
    beta = beta_r.new_zeros(s.batch + (s.p,)).index_copy_(-1, cols, beta_r)
    if bool((applied < 1).any()):
        warnings.warn(
            f"{fn}: in some directions of the metric's coefficients the noise swamps the "
            "off-cycle excitation (signal fraction of the corrected normal matrix below "
            f"{float(signal_floor(s.p, s.n_valid).max()):.2g}); the noise correction there "
            f"was limited to {float(applied.min()):.2g} of its size, so M̂'s weakly excited "
            "directions are biased towards smaller values", _wls.IllConditionedBinWarning,
            stacklevel=2)
    cov, influence, residual = _cluster_sandwich(s, cols, keep, beta_r, chol, inv, cyc, n_c)
    return TiedMetricCoefficients(
        coef=beta, cov=cov, order=chosen, condition=condition, noise_correction=applied,
        max_order=order, derivative_order=derivative_order, second_order=second_order,
        n_joints=s.d, phase=s.ph, weight=s.w, residual=residual, influence=influence)


@dataclass(frozen=True)
class _TiedSamples:
    """The checked samples of a tied fit (NaN samples zeroed, weight 0): offsets ``delta``
    and velocities ``v`` ``(..., N, d)``, power ``y`` and phase ``ph`` ``(..., N)``, which
    are ``valid`` (bool) and their weight ``w``, ``n_valid (...)``, the velocity noise's
    variance ``sig (..., d)`` and the model's layout (``p`` coefficients, ``q = d(d+1)/2``)."""

    delta: Tensor
    v: Tensor
    y: Tensor
    ph: Tensor
    valid: Tensor
    w: Tensor
    n_valid: Tensor
    sig: Tensor
    order: int
    derivative_order: int | None
    second_order: SecondOrder
    p: int

    @property
    def batch(self) -> tuple:
        return tuple(self.delta.shape[:-2])

    @property
    def d(self) -> int:
        return self.delta.shape[-1]

    @property
    def q(self) -> int:
        return self.d * (self.d + 1) // 2

    @property
    def dtype(self) -> torch.dtype:
        return self.delta.dtype

    @property
    def device(self) -> torch.device:
        return self.delta.device

    def features(self, rows: slice) -> Tensor:
        """The model's features ``(..., n, g)`` of rows ``rows`` (:func:`_features`)."""
        return _features(self.ph[..., rows], self.delta[..., rows, :], self.order,
                         self.derivative_order, self.second_order)

    def quad_indices(self) -> tuple[Tensor, Tensor, Tensor]:
        """``iu, ju`` (:func:`torch.triu_indices`) and whether each pair is on the diagonal."""
        iu, ju = torch.triu_indices(self.d, self.d, device=self.device)
        return iu, ju, (iu == ju).to(self.dtype)


def _tied_samples(offset: Tensor, velocity: Tensor, power: Tensor, phase: Tensor, order: int,
                  derivative_order: int | None, second_order: SecondOrder,
                  noise_variance: Tensor | None, min_samples_per_coef: float, fn: str
                  ) -> _TiedSamples:
    """The samples checked (shapes, orders, ``noise_variance``, enough usable samples for
    the coefficients: else a ValueError naming the input) as :class:`_TiedSamples`."""
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
            "lower the orders; or leave the metric out: metric__enabled=False (torchconn-fit --metric "
            "no) fits the connection alone from this recording"
        )
    zero = delta.new_zeros(())
    return _TiedSamples(
        delta=torch.where(valid.unsqueeze(-1), delta, zero),
        v=torch.where(valid.unsqueeze(-1), v, zero), y=torch.where(valid, y, zero),
        ph=torch.where(valid, ph, zero), valid=valid, w=valid.to(dtype), n_valid=n_valid,
        sig=sig, order=order, derivative_order=derivative_order, second_order=second_order,
        p=p)




def _block_normal_equations(s: _TiedSamples, fold: Tensor, folds: int
                            ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The normal matrix ``(..., B, P, P)``, the noise's contribution to it, the right-hand
    side ``(..., B, P)`` and the noise's contribution to that, per block ``fold (..., N)`` of
    ``folds`` blocks of cycles, summed over row chunks."""
    n, g_n, d = s.ph.shape[-1], s.p // s.q, s.d
    iu, ju, on_diag = s.quad_indices()
    gram = s.delta.new_zeros(s.batch + (folds, s.p, s.p))
    rhs = s.delta.new_zeros(s.batch + (folds, s.p))
    s2 = s.delta.new_zeros(s.batch + (folds, g_n, g_n * d * d))
    s0 = s.delta.new_zeros(s.batch + (folds, g_n, g_n))
    fy = s.delta.new_zeros(s.batch + (folds, g_n))
    for start in range(0, n, _ROW_CHUNK):
        rows = slice(start, min(start + _ROW_CHUNK, n))
        f = s.features(rows) * s.w[..., rows, None]  # zero rows for missing samples
        vr = s.v[..., rows, :]
        quad = vr[..., iu] * vr[..., ju]
        x = (f.unsqueeze(-1) * quad.unsqueeze(-2)).flatten(-2)
        vv = (vr.unsqueeze(-1) * vr.unsqueeze(-2)).flatten(-2)
        fvv = (f.unsqueeze(-1) * vv.unsqueeze(-2)).flatten(-2)
        for b in range(folds):
            sel = (fold[..., rows, None] == b).to(s.dtype) if folds > 1 else 1.0
            if folds > 1 and not bool(sel.any()):
                continue  # the block has no rows here: its products would be exact zeros
            xb, fb = x * sel, f * sel
            gram[..., b, :, :] += xb.mT @ x
            rhs[..., b, :] += (xb * s.y[..., rows, None]).sum(-2)
            s2[..., b, :, :] += fb.mT @ fvv
            s0[..., b, :, :] += fb.mT @ f
            fy[..., b, :] += (fb * s.y[..., rows, None]).sum(-2)
    corr_g, corr_h = noise_terms(s2.unflatten(-1, (g_n, d, d)), s0, fy, s.sig.unsqueeze(-2),
                                  iu, ju, on_diag)  # per block
    return gram, corr_g, rhs, corr_h


def _checked_normal(s: _TiedSamples, gram: Tensor, corr_g: Tensor, inv: Tensor, drop: Tensor,
                    max_condition: float, fn: str) -> tuple[CorrectedNormal, Tensor, Tensor]:
    """The equilibrated, noise-corrected normal matrix of the kept columns (scales ``inv
    (..., P')``; ``drop`` the columns left out per element), its Cholesky factor and its
    condition number ``(...)``; a ValueError where that exceeds ``max_condition`` (the data do not identify
    the metric)."""
    p_r = gram.shape[-1]
    dead = gram.diagonal(dim1=-2, dim2=-1) <= 0
    scale = inv.unsqueeze(-1) * inv.unsqueeze(-2)
    normal = CorrectedNormal.of(gram * scale + torch.diag_embed(dead.to(s.dtype)),
                                 corr_g * scale, signal_floor(s.p, s.n_valid))
    chol, ok = normal.cholesky(), normal.ok
    ev = _linalg.eigvalsh(chol @ chol.mT, "the metric's normal matrix")
    lo, hi = ev[..., 0], ev[..., -1]
    if p_r < s.p:  # the left-out columns' identity rows, as in the layout of ``order``
        lo, hi = lo.clamp(max=1.0), hi.clamp(min=1.0)
    condition = torch.where(~ok | (dead & ~drop).any(-1) | (lo <= 0), torch.inf,
                            hi / lo.clamp(min=torch.finfo(s.dtype).tiny))
    bad = ~(condition <= max_condition)
    if bool(bad.any()):
        where = [tuple(i) for i in torch.nonzero(bad).tolist()][:5] if s.batch else []
        raise ValueError(
            f"{fn}: the data do not identify the metric"
            + (f" (batch elements {where})" if where else "")
            + f": the normal matrix of its P = {s.p} coefficients has condition number "
              f"{float(condition.max()):.3g} > {max_condition:.3g}. The shape velocity must vary "
              "in every direction of shape space at every phase (noise on the gait over many "
              "cycles); a gait without noise, a joint held fixed or too few cycles leave M "
              "unidentified. Lower the Fourier orders, drop the derivative term "
              "(derivative_order=None), record more varied data, or fit the connection alone "
              "(metric__enabled=False; torchconn-fit: --metric no)"
        )
    return normal, chol, condition


def _cluster_sandwich(s: _TiedSamples, cols: Tensor, keep: Tensor, beta_r: Tensor,
                      chol: Tensor, inv: Tensor, cyc: Tensor, n_c: int
                      ) -> tuple[Tensor, Tensor, Tensor]:
    """The coefficients' cluster-robust covariance over whole cycles ``(..., P, P)`` (on the
    corrected regressors), each cycle's share of their error ``(..., C, P)`` (``cov =
    influenceᵀ influence``) and the samples' weighted power residuals ``(..., N)``, for the
    solution ``beta_r (..., P')`` of the columns ``cols``."""
    n, q, p_r = s.ph.shape[-1], s.q, cols.numel()
    iu, ju, on_diag = s.quad_indices()
    sums = s.delta.new_zeros(s.batch + (n_c, p_r))
    kept_features = cols[::q] // q  # the features of the columns solved for
    resids = []
    for start in range(0, n, _ROW_CHUNK):
        rows = slice(start, min(start + _ROW_CHUNK, n))
        f = s.features(rows)[..., kept_features] * s.w[..., rows, None]
        vr = s.v[..., rows, :]
        quad = vr[..., iu] * vr[..., ju] - s.sig[..., None, iu] * on_diag
        x = (f.unsqueeze(-1) * quad.unsqueeze(-2)).flatten(-2)  # (..., n, P')
        resid = (s.y[..., rows] - (x @ beta_r.unsqueeze(-1))[..., 0]) * s.w[..., rows]
        sums.scatter_add_(-2, cyc[..., rows, None].expand(x.shape), x * resid.unsqueeze(-1))
        resids.append(resid)
    sums = sums * keep.unsqueeze(-2)
    n_clusters = (sums.abs().sum(-1) > 0).sum(-1).to(s.dtype)
    meat = (sums.mT @ sums) * (n_clusters / (n_clusters - 1).clamp(min=1))[..., None, None]
    eye = torch.eye(p_r, dtype=s.dtype, device=s.device)
    l_inv = torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
    g_inv = (l_inv.mT @ l_inv) * inv.unsqueeze(-1) * inv.unsqueeze(-2)
    cov_r = g_inv @ meat @ g_inv
    cov = cov_r.new_zeros(s.batch + (s.p, s.p))
    cov[..., cols[:, None], cols] = cov_r
    # each cycle's share of the coefficients' error: cov = influenceᵀ influence
    influence_r = (sums @ g_inv) * (n_clusters / (n_clusters - 1).clamp(min=1)).sqrt()[
        ..., None, None]
    influence = influence_r.new_zeros(s.batch + (n_c, s.p)).index_copy_(-1, cols, influence_r)
    residual = torch.cat(resids, -1) if resids else s.ph.new_zeros(s.ph.shape)
    return cov, influence, residual


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
            sampling covariance).
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
    offset_m = None if fit.offset_change is None else symmetric(basis @ fit.offset_change, d)
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
        # and the change's own sampling covariance (the mean squared bias given the change)
        cov_m = cov_m + cov_change
        factor_m = _bin_factor(fit.order_change_spread, wide, d)
    se_m = cov_m.diagonal(dim1=-2, dim2=-1).clamp(min=0).sqrt()
    d_m = se_d = None
    if derivative_order is not None:
        bd = fourier_design(phase_m.to(ph), derivative_order)
        n_d = (2 * derivative_order + 1) * d * q
        blk = beta[..., n_m:n_m + n_d].unflatten(-1, (2 * derivative_order + 1, d, q))
        d_m = symmetric(torch.einsum("mh,...hkq->...mkq", bd, blk), d).movedim(-3, -1)
        var = cov[..., n_m:n_m + n_d, n_m:n_m + n_d].diagonal(dim1=-2, dim2=-1).unflatten(
            -1, (2 * derivative_order + 1, d, q))
        # standard errors of ∂M/∂r ignoring the covariance between its harmonics (a guide)
        se_d = symmetric(torch.einsum("mh,...hkq->...mkq", bd.square(), var).sqrt(),
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
        M=symmetric(coef_m, d), se_M=symmetric(se_m, d), dM=d_m, se_dM=se_d,
        power_on_cycle=p_cyc, n_samples=cnt.round().to(torch.int64),
        residual_rms=(sse / cnt.clamp(min=1)).sqrt(), condition=per_phase(condition),
        ridge=torch.zeros_like(per_phase(condition)), coef=beta, se_coef=se,
        se_power_on_cycle=se_p, M_gamma_dot=m_gd, se_M_gamma_dot=se_m_gd,
        noise_correction=per_phase(applied), cov_M=cov_m, order=chosen,
        bias_M=None if bias_m is None else symmetric(bias_m, d),
        se_bias_M=None if se_bias_m is None else symmetric(se_bias_m, d),
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
    return symmetric(factor, d).movedim(-4, -1)  # (..., M, d, d, R)


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
        m_v.append((symmetric(mq, d) @ vr.unsqueeze(-1)).squeeze(-1))
    return torch.cat(power, -1), torch.cat(m_v, -2)

