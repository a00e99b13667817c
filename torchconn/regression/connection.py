"""Phase-centred regression of the local connection (the paper's eq. ``advancedregression``).

Within the bin of centre ``γ_m`` every sample gives ``δ = r − γ_m``, ``δ̇ = ṙ − γ̇_m`` and

    ξᵏ ≈ cᵏ + bᵏ_j δʲ + Aᵏ_i δ̇ⁱ + (∂Aᵏ_i/∂r_j) δ̇ⁱ δʲ,

with ``c = A(γ_m) γ̇_m`` and ``b_j = ∂A/∂r_j(γ_m) γ̇_m``. For a connection affine in ``r`` the
model is exact (``ξ = A(γ_m + δ)(γ̇_m + δ̇)``), so noise-free data recover ``A`` and ``∂A/∂r``
to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from . import _wls
from .binning import BinIndex

__all__ = ["ConnectionFit", "connection_regression", "connection_design", "design_blocks",
           "fit_from_solution", "ridge_exemptions"]


@dataclass(frozen=True)
class ConnectionFit:
    """Per-bin estimates of the connection and its shape derivative (``M`` bins, ``d`` joints).

    Attributes:
        c: ``(..., M, 3)`` ``ĉ = A(γ_m) γ̇_m``, body velocity on the cycle.
        b: ``(..., M, 3, d)`` ``b̂[k, j] = (∂A/∂r_j γ̇_m)ᵏ``.
        A: ``(..., M, 3, d)`` ``Â(γ_m)``.
        dA: ``(..., M, 3, d, d)`` ``∂Aᵏ_i/∂r_j`` at ``[..., k, i, j]`` (as
            :meth:`~torchconn.physics.systems.LocomotionSystem.connection_jacobian`).
        se_c, se_b, se_A, se_dA: standard errors, same shapes.
        n_samples: ``(..., M)`` samples with positive weight in each bin.
        residual_rms: ``(..., M, 3)`` weighted RMS residual per body-velocity component.
        condition: ``(..., M)`` 1-norm condition number of the standardised normal matrix
            (ridge included).
        ridge: ``(..., M)`` ridge applied to each bin (relative to the standardised diagonal).
        coef, se_coef: ``(..., M, P, 3)`` raw coefficients in the column order of
            :func:`connection_design`, and their standard errors.
        eiv_scale: ``(..., M)`` fraction of the errors-in-variables noise correction applied
            (1: all of it, or no correction was asked for; below 1: the guard scaled it down
            because the full correction would have left a non-positive-definite normal matrix).
        dA_direct: ``(..., M, 3, d, d)`` where ``dA`` was tied
            (:func:`~torchconn.regression.tie_connection_derivative`), the direct ``δ̇⊗δ``
            estimate it replaced: the coefficient fitted beside ``c, b, A``, which predictions
            use; None otherwise.
        cov_b_dA: ``(..., M, 3, d + d², d + d²)`` where known, the joint covariance of each
            output row's ``(b̂[k, :], ∂Â/∂r[k] flattened (i, j))`` from the bin's one regression
            (:func:`~torchconn.regression.noise_aware.noise_aware_regression`), under which
            :func:`~torchconn.regression.tie_connection_derivative` takes its variance; None
            otherwise (the two taken as independent, with variances ``se_b², se_dA²``).
        offset_gain: ``(..., M, 1 + d, d)`` where known, how ``ĉ, b̂`` move when ``Â`` is
            moved and held, ``ĉ, b̂`` re-estimated in the bin's normal equations
            (:func:`~torchconn.regression.noise_aware.offset_gain`); None otherwise.
        influence_A: ``(..., M, 3, d, C)`` where asked for (``noise_aware_regression``'s
            ``cycles``), each of ``C`` cycles' share of the error of ``Â`` in every bin
            (``Σ_c`` of its outer products is the cluster-robust covariance of ``Â`` across
            entries *and* bins); None otherwise.
        sampling_factor_A: ``(..., M, 3, d, R)`` a factor of ``Â``'s sampling covariance
            across entries and bins whose diagonal is ``se_A²``
            (:func:`~torchconn.regression.noise_aware.sampling_factor`, from
            ``influence_A``): what nearby-gait draws use; None where not estimated.
        bias_allowance_A: ``(..., M, 3, d)`` an allowance for the bias of ``Â`` (the tube's
            second order and the sampling interval,
            :class:`~torchconn.regression.noise_aware.NoiseAwareRegression`'s
            ``bias_allowance``), not in ``se_A``; None where not estimated.
        corr_dA: ``(..., M, 3, d², d²)`` the correlation of each bin and row's tied
            ``∂Â/∂r`` entries (``vec`` row-major, as ``cov_b_dA``'s), where the tie was asked
            for it (:func:`~torchconn.regression.tie_connection_derivative`'s
            ``correlation``); None otherwise.
    """

    c: Tensor
    b: Tensor
    A: Tensor
    dA: Tensor
    se_c: Tensor
    se_b: Tensor
    se_A: Tensor
    se_dA: Tensor
    n_samples: Tensor
    residual_rms: Tensor
    condition: Tensor
    ridge: Tensor
    coef: Tensor
    se_coef: Tensor
    eiv_scale: Tensor | None = None
    dA_direct: Tensor | None = None
    cov_b_dA: Tensor | None = None
    offset_gain: Tensor | None = None
    influence_A: Tensor | None = None
    sampling_factor_A: Tensor | None = None
    bias_allowance_A: Tensor | None = None
    corr_dA: Tensor | None = None


def connection_design(delta: Tensor, delta_dot: Tensor) -> Tensor:
    """Regressors ``[1, δ, δ̇, δ̇ ⊗ δ]``: ``(..., d), (..., d) -> (..., 1 + 2d + d²)``.

    Column ``1 + 2d + i·d + j`` is ``δ̇_i δ_j``; its coefficient estimates ``∂Aᵏ_i/∂r_j``.
    """
    return torch.cat(design_blocks(delta, delta_dot, torch.ones_like(delta[..., :1])), -1)


def unpenalised_columns(d: int, device=None) -> Tensor:
    """``(1 + 2d + d²,)`` bool: the columns of :func:`connection_design` that a ridge leaves
    unpenalised besides the intercept, ``δ̇`` (``Â``'s). A ridge pulls coefficients towards 0;
    on ``Â`` that is the attenuation the noise correction removes (Â, not its offsets, is
    what the fit is for); it still regularises ``b̂`` and ``∂Â/∂r``
    (``TubeRegression(ridge_connection=False)``)."""
    mask = torch.zeros(1 + 2 * d + d * d, dtype=torch.bool, device=device)
    mask[1 + d:1 + 2 * d] = True
    return mask


def ridge_exemptions(d: int, ridge_connection: bool, device=None) -> Tensor | None:
    """The solver's ``unpenalised`` argument for a regression's ``ridge_connection`` setting:
    None (the ridge penalises every column but the intercept) where it is True, else
    :func:`unpenalised_columns` ``(1 + 2d + d²,)``."""
    return None if ridge_connection else unpenalised_columns(d, device)


def design_blocks(delta: Tensor, delta_dot: Tensor, row_scale: Tensor) -> list[Tensor]:
    """The column blocks of ``row_scale · [1, δ, δ̇, δ̇⊗δ]``, scaled through the small factors."""
    scaled_dot = row_scale * delta_dot
    cross = (scaled_dot.unsqueeze(-1) * delta.unsqueeze(-2)).flatten(-2)
    return [row_scale, row_scale * delta, scaled_dot, cross]


def connection_regression(
    r: Tensor,
    r_dot: Tensor,
    xi: Tensor,
    bins: BinIndex,
    gamma_m: Tensor,
    gamma_dot_m: Tensor,
    *,
    delta_max: float | None = None,
    ridge: float = 0.0,
    min_samples: int | None = None,
    max_condition: float | None = None,
    on_ill_conditioned: str = "raise",
    ridge_connection: bool = True,
    standard_errors: bool = True,
) -> ConnectionFit:
    """Estimate ``A(γ_m)`` and ``∂A/∂r(γ_m)`` in every phase bin, all batches at once.

    Args:
        r: ``(..., N, d)`` shapes (rad).
        r_dot: ``(..., N, d)`` shape velocities.
        xi: ``(..., N, 3)`` body velocities ``(v_x, v_y, ω)``. A sample with NaN in ``r``,
            ``r_dot`` or ``xi`` (a drop-out) is excluded automatically and not counted; ±inf
            raises.
        bins: :func:`~torchconn.regression.assign_bins` of the samples' ``(..., N)`` phase.
        gamma_m: ``(..., M, d)`` limit cycle at the bin centres (``...`` broadcastable).
        gamma_dot_m: ``(..., M, d)`` its phase derivative ``dγ/dφ`` there.
        delta_max: keep only samples with ``‖r − γ_m‖ < delta_max`` (the paper's tube); None
            keeps every sample of the bin.
        ridge: ridge ``λ ≥ 0`` added to the unit diagonal of the standardised normal matrix
            (all columns but the intercept); 0 is ordinary weighted least squares.
        ridge_connection: the ridge also penalises ``A``'s columns (default); False: not
            (:func:`unpenalised_columns`).
        min_samples: fewest samples a bin may have; default ``P + 5`` with ``P = 1 + 2d + d²``.
        max_condition: largest acceptable condition number of the standardised normal matrix;
            default ``1e12`` in float64.
        on_ill_conditioned: what to do with a bin that has fewer than ``min_samples`` samples or
            a numerically rank-deficient design: ``"raise"`` a ValueError naming the bins,
            ``"warn"`` and return NaN for them, or ``"ridge"``: add the smallest ridge bringing
            the condition number to ``1e8`` and warn (bins with too few samples stay NaN).
        standard_errors: False: the coefficients alone (the same bit for bit; the standard
            errors and ``residual_rms`` are NaN), about half the work (the bias correction
            of :func:`~torchconn.regression.noise_aware.bin_bias_correction` uses ``A``
            alone).

    Returns:
        :class:`ConnectionFit`; ``...`` = the batch dims of ``r``. All 3 body-velocity
        components share one design and one factorisation per bin.
    """
    fn = "connection_regression"
    s = _wls.prepare(fn, r, r_dot, xi, "xi", 3, bins, gamma_m, gamma_dot_m)
    d = s.r.shape[-1]
    p = 1 + 2 * d + d * d
    sol = _wls.solve(s, design_blocks, p, fn=fn, delta_max=delta_max, ridge=ridge,
                     min_samples=min_samples, max_condition=max_condition,
                     on_ill_conditioned=on_ill_conditioned, standard_errors=standard_errors,
                     unpenalised=ridge_exemptions(d, ridge_connection, s.r.device))
    return fit_from_solution(sol.unflatten(s.batch_shape, s.n_bins), d)


def split_coefficients(coef: Tensor, d: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Name the raw coefficients ``(..., P, 3)`` of the design ``[1, δ, δ̇, δ̇⊗δ]``
    (:func:`connection_design`): ``c (..., 3)``, ``b (..., 3, d)``, ``A (..., 3, d)``,
    ``∂A/∂r (..., 3, d, d)``."""
    c = coef[..., 0, :]
    b = coef[..., 1:1 + d, :].mT
    a = coef[..., 1 + d:1 + 2 * d, :].mT
    da = coef[..., 1 + 2 * d:, :].unflatten(-2, (d, d)).movedim(-1, -3)
    return c, b, a, da


def fit_from_solution(sol: _wls.Solution, d: int) -> ConnectionFit:
    """Name the coefficients of an unflattened solution ``(..., M, P, 3)`` of the design
    ``[1, δ, δ̇, δ̇⊗δ]``."""
    c, b, a, da = split_coefficients(sol.coef, d)
    se_c, se_b, se_a, se_da = split_coefficients(sol.se, d)
    return ConnectionFit(
        c=c, b=b, A=a, dA=da, se_c=se_c, se_b=se_b, se_A=se_a, se_dA=se_da,
        n_samples=sol.n_samples, residual_rms=sol.residual_rms, condition=sol.condition,
        ridge=sol.ridge, coef=sol.coef, se_coef=sol.se, eiv_scale=sol.eiv_scale,
    )
