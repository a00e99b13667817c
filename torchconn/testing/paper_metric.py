"""The paper's per-bin metric regression (eq. ``advancedmetricregression``), a reference.

Within the bin of centre ``γ_m``,

    P ≈ (γ̇_m + δ̇)ᵀ [M + ∂M/∂r_k δᵏ] (γ̇_m + δ̇),

expanded into regressors ``[1, δ̇, δ̇⊗̂δ̇, δ, δ⊗δ̇, δ⊗(δ̇⊗̂δ̇)]`` where ``δ̇⊗̂δ̇`` holds the unique
products ``δ̇_i δ̇_j``, ``i ≤ j`` (``M`` is symmetric, so the coefficient of ``δ̇_i δ̇_j`` is ``M_ii``
on the diagonal and ``2 M_ij`` off it). The last block carries ``∂M/∂r`` and is third order in
the offsets. Its linear and quadratic terms are separate coefficients, so the weakly identified
``M`` is not tied to the strongly identified ``2Mγ̇``. The estimator fits the tied model
(:mod:`torchconn.regression.metric`); this one is kept as the paper's reference for tests and
benchmarks.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..regression import _wls
from ..regression.binning import BinIndex
from ..regression.metric.tied import MetricFit, symmetric


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
    """Estimate ``M(γ_m)`` (and ``∂M/∂r(γ_m)``) in every phase bin from recorded power.

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
        return symmetric(x[..., 1 + d:1 + d + q], d)

    def derivative_of(x: Tensor) -> Tensor:
        start = 1 + 2 * d + q + d * d
        per_k = x[..., start:].unflatten(-1, (d, q))  # [..., k, q]
        return symmetric(per_k, d).movedim(-3, -1)  # [..., i, j, k]

    return MetricFit(
        M=metric_of(coef), se_M=metric_of(se),
        dM=derivative_of(coef) if deriv else None, se_dM=derivative_of(se) if deriv else None,
        power_on_cycle=coef[..., 0], n_samples=sol.n_samples,
        residual_rms=sol.residual_rms[..., 0], condition=sol.condition, ridge=sol.ridge,
        coef=coef, se_coef=se, se_power_on_cycle=se[..., 0],
        # the coefficient of δ̇ is 2 M γ̇
        M_gamma_dot=coef[..., 1:1 + d] / 2, se_M_gamma_dot=se[..., 1:1 + d] / 2,
    )
