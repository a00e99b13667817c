"""The one batched weighted least-squares solver behind every phase-bin regression.

Both :func:`~torchconn.regression.connection_regression` and
:func:`~torchconn.testing.paper_metric.metric_regression` reduce to: for every (batch element, bin), fit
``y ≈ X β`` on that bin's weighted rows, where ``X`` is a polynomial design in the offsets
``δ = r − γ_m`` and ``δ̇ = ṙ − γ̇_m``. This module gathers the rows, builds the design chunk by
chunk, forms the weighted normal equations with one batched matmul, equilibrates them, solves
by Cholesky and reports standard errors, conditioning and sample counts -- and decides what to do
with bins that cannot be fitted reliably.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from .. import _checks, _linalg
from .binning import BinIndex

__all__ = ["IllConditionedBinWarning"]

#: a design callable: (delta (b, n, d), delta_dot (b, n, d), row_scale (b, n, 1)) -> the column
#: blocks of row_scale · X, X (b, n, P) (scaling the small factors saves a pass over X)
Design = Callable[[Tensor, Tensor, Tensor], list[Tensor]]

#: bytes of design matrix built at once on a CPU; bounds memory and keeps each chunk's design
#: hot in cache between forming XᵀWX and the residuals.
_CHUNK_BYTES = 8 * 2**20
#: the same budget on an accelerator (CUDA): there a chunk is a few kernel launches, and a
#: chunk of a few bins leaves the device idle between launches, so chunks are as large as
#: memory allows (a 9-link fit of 40 trials x 30 cycles made ~4,000 chunks of 8 MiB, each
#: ~40 launches and host syncs). Per-bin results do not depend on the chunking.
_DEVICE_CHUNK_BYTES = 1 * 2**30
#: the "ridge" policy regularises ill-conditioned bins down to this condition number
_RIDGE_TARGET_CONDITION = 1e8
#: errors-in-variables guard: the subtracted noise part may remove at most this fraction of the
#: observed Gram matrix in any direction (beyond it the corrected matrix is near-singular or
#: indefinite and the correction is scaled down)
_MAX_CORRECTION = 0.9

#: an errors-in-variables correction: (Gram matrix XᵀWX of the observed regressors (b, P, P),
#: the bins it belongs to (a slice or index tensor into B·M)) -> its expected noise part (b, P, P)
Correction = Callable[[Tensor, object], Tensor]
_MODES = ("raise", "warn", "ridge")


class IllConditionedBinWarning(RuntimeWarning):
    """Some phase bins had too few samples or a rank-deficient design (see the message)."""


@dataclass(frozen=True)
class BinnedSamples:
    """Validated samples, flattened for gathering: ``B`` batch elements, ``M`` bins, ``N`` samples.

    Attributes:
        batch_shape: the leading dims ``...`` of the inputs (``B`` = their product).
        n_bins: ``M``.
        rows: ``(B·M, Nmax)`` indices into the flattened ``(B·N, ·)`` sample arrays.
        weight: ``(B·M, Nmax)`` kernel weight times sample validity (0 for NaN samples).
        r, r_dot: ``(B·N, d)`` samples, NaN replaced by 0; ``y``: ``(B·N, K)`` responses.
        gamma, gamma_dot: ``(B·M, d)`` the bin centre points ``γ_m`` and ``γ̇_m``.
    """

    batch_shape: torch.Size
    n_bins: int
    rows: Tensor
    weight: Tensor
    r: Tensor
    r_dot: Tensor
    y: Tensor
    gamma: Tensor
    gamma_dot: Tensor


@dataclass(frozen=True)
class Solution:
    """Per-bin least-squares results, flattened over ``B·M`` bins (``P`` coefs, ``K`` outputs)."""

    coef: Tensor  # (B·M, P, K)
    se: Tensor  # (B·M, P, K)
    n_samples: Tensor  # (B·M,) int64
    residual_rms: Tensor  # (B·M, K)
    condition: Tensor  # (B·M,)
    ridge: Tensor  # (B·M,)
    eiv_scale: Tensor  # (B·M,) fraction of the errors-in-variables correction applied (1: all)

    def unflatten(self, batch_shape: torch.Size, n_bins: int) -> "Solution":
        def f(t: Tensor) -> Tensor:
            return t.reshape(batch_shape + (n_bins,) + t.shape[1:])

        return Solution(*(f(getattr(self, k)) for k in self.__dataclass_fields__))


# ---------------------------------------------------------------------------------- inputs
def _check_samples(x, name: str, batch_n: tuple | None, width: int | None, fn: str) -> Tensor:
    what = "(..., N" + (")" if width == 0 else f", {width if width else 'd'})")
    if batch_n is not None:
        what = str(batch_n + ((width,) if width else ()))
    ndim = 1 if width == 0 else 2

    def ok(t: Tensor) -> bool:
        good = t.ndim >= ndim and (width in (None, 0) or t.shape[-1] == width)
        return good and (batch_n is None or tuple(t.shape[: t.ndim - ndim + 1]) == batch_n)

    _checks.tensor(x, name, what, fn=fn, valid=ok, floating=True)
    return _checks.finite(x, name, fn=fn, nan_ok=True,
                          hint="only NaN marks a missing sample (it is then excluded)")


def _check_cycle(x, name: str, batch: tuple, m: int, d: int, fn: str, like: Tensor) -> Tensor:
    _checks.tensor(
        x, name, f"(..., M, d) = (..., {m}, {d}) (one point per phase bin of the limit "
        f"cycle, in the d = {d} shape coordinates of r)", fn=fn,
        valid=lambda t: t.ndim >= 2 and tuple(t.shape[-2:]) == (m, d),
    )
    try:
        x = x.to(like).expand(batch + (m, d))
    except RuntimeError:
        raise ValueError(
            f"{fn}: {name} of shape {tuple(x.shape)} does not broadcast to the batch "
            f"{batch} of r: expected (..., {m}, {d}) with ... broadcastable to {batch}"
        ) from None
    return _checks.finite(x, name, fn=fn, hint="the limit cycle must be finite")


def prepare(fn: str, r, r_dot, y, y_name: str, y_width: int, bins: BinIndex,
            gamma_m, gamma_dot_m) -> BinnedSamples:
    """Validate the inputs of a bin regression and flatten them for gathering.

    ``r, r_dot: (..., N, d)``, ``y: (..., N, K)`` (or ``(..., N)`` when ``y_width == 0``),
    ``gamma_m, gamma_dot_m: (..., M, d)`` broadcastable to the batch, ``bins`` from
    :func:`assign_bins` on the same ``(..., N)`` phase. NaN samples get weight 0.
    """
    if not isinstance(bins, BinIndex):
        raise TypeError(
            f"{fn}: bins must be a BinIndex from assign_bins, got {type(bins).__name__}"
        )
    r = _check_samples(r, "r", None, None, fn)
    batch, n, d = tuple(r.shape[:-2]), r.shape[-2], r.shape[-1]
    r_dot = _check_samples(r_dot, "r_dot", batch + (n,), d, fn)
    y = _check_samples(y, y_name, batch + (n,), y_width, fn)
    if y_width == 0:
        y = y.unsqueeze(-1)
    if tuple(bins.batch_shape) != batch or bins.n_points != n:
        raise ValueError(
            f"{fn}: bins were built for a phase of shape "
            f"{tuple(bins.batch_shape) + (bins.n_points,)} but r has (..., N) = {batch + (n,)}; "
            f"call assign_bins on the phase of these samples"
        )
    m = bins.n_bins
    gamma_m = _check_cycle(gamma_m, "gamma_m", batch, m, d, fn, r)
    gamma_dot_m = _check_cycle(gamma_dot_m, "gamma_dot_m", batch, m, d, fn, r)
    r_dot, y = r_dot.to(r), y.to(r)

    valid = ~(r.isnan().any(-1) | r_dot.isnan().any(-1) | y.isnan().any(-1))  # (..., N)
    b = math.prod(batch)
    offsets = torch.arange(b, device=r.device).reshape(batch + (1, 1)) * n
    rows = (bins.index.to(r.device) + offsets).reshape(b * m, -1)
    flat_valid = valid.reshape(b * n)
    weight = bins.weight.to(r).reshape(b * m, -1) * flat_valid[rows]
    zero = r.new_zeros(())
    return BinnedSamples(
        batch_shape=torch.Size(batch), n_bins=m, rows=rows, weight=weight,
        r=torch.where(valid.unsqueeze(-1), r, zero).reshape(b * n, d),
        r_dot=torch.where(valid.unsqueeze(-1), r_dot, zero).reshape(b * n, d),
        y=torch.where(valid.unsqueeze(-1), y, zero).reshape(b * n, -1),
        gamma=gamma_m.reshape(b * m, d), gamma_dot=gamma_dot_m.reshape(b * m, d),
    )


# ---------------------------------------------------------------------------------- solver
def _chunk_design(s: BinnedSamples, sel, design: Design, delta_max: float | None):
    """``[X | y]`` of the bins ``sel`` (a slice or index tensor into ``B·M``), rows scaled by √w.

    Returns ``xy (b, n, P + K)`` and the weights ``w (b, n)`` (0 on padding, NaN samples and,
    with ``delta_max``, samples outside the tube).
    """
    rows = s.rows[sel]
    delta = s.r[rows] - s.gamma[sel].unsqueeze(-2)
    delta_dot = s.r_dot[rows] - s.gamma_dot[sel].unsqueeze(-2)
    w = s.weight[sel]
    if delta_max is not None:
        w = w * (delta.norm(dim=-1) < delta_max)
    sqrt_w = w.sqrt().unsqueeze(-1)
    return torch.cat(design(delta, delta_dot, sqrt_w) + [s.y[rows] * sqrt_w], -1), w


def _guarded_correction(gram: Tensor, corr: Tensor) -> tuple[Tensor, Tensor]:
    """``gram − κ·corr`` with the largest ``κ ≤ 1`` that removes at most :data:`_MAX_CORRECTION`
    of ``gram`` in any direction; returns it and ``κ (b,)``.

    ``κ = 1`` unless the noise part reaches the observed matrix's own size in some direction
    (few samples, or more noise than signal there), where the full correction would leave an
    indefinite matrix: the largest generalised eigenvalue ``λ`` of ``(corr, gram)`` gives
    ``κ = min(1, _MAX_CORRECTION / λ)``.

    ``λ < _MAX_CORRECTION`` exactly when ``_MAX_CORRECTION · gram − corr`` is positive definite,
    so one Cholesky factorisation per bin settles the usual case (``κ = 1``); ``λ`` itself (a
    triangular inverse, two products and a symmetric eigensolver, ~10x the cost) is computed
    only for the bins that fail it.
    """
    diag = gram.diagonal(dim1=-2, dim2=-1)
    # equilibrate and decouple all-zero columns so that the factorisation exists
    scale = torch.where(diag > 0, diag.sqrt(), 1.0)
    outer = scale.unsqueeze(-1) * scale.unsqueeze(-2)
    g_s = gram / outer + torch.diag_embed((diag <= 0).to(gram))
    c_s = corr / outer
    chol, info = torch.linalg.cholesky_ex(g_s)
    _, info_rest = torch.linalg.cholesky_ex(_MAX_CORRECTION * g_s - c_s)
    kappa = gram.new_ones(gram.shape[0])
    check = ((info == 0) & (info_rest != 0)).nonzero().flatten()
    if check.numel():
        l_inv = _triangular_inverse(chol[check])
        rel = l_inv @ c_s[check] @ l_inv.mT
        lam_max = _linalg.eigvalsh(0.5 * (rel + rel.mT), "the regression's noise-to-signal matrix")[..., -1]
        kappa[check] = torch.where(lam_max > _MAX_CORRECTION, _MAX_CORRECTION / lam_max, 1.0)
    kappa = torch.where(info != 0, 0.0, kappa)  # already singular: left to the rank checks
    return gram - kappa[:, None, None] * corr, kappa


def ridge_cholesky(gram: Tensor, lam: Tensor | float, unpenalised: Tensor | None = None
                   ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Cholesky factor of normal matrices ``gram (b, P, P)`` with the solver's ridge convention;
    ``gram`` is changed in place into the factorised matrix.

    The ridge ``lam`` (``(b,)`` or one number) sits on the unit diagonal of the equilibrated
    matrix, i.e. ``λ (XᵀWX)ⱼⱼ`` is added to every column but the intercept and the columns
    ``unpenalised`` (``(P,)`` bool, None: none; the connection's ``Â``,
    :func:`~torchconn.regression.connection.unpenalised_columns`); a dead (all-zero)
    column is decoupled with a unit pivot (its coefficient comes out 0; callers report NaN).

    Returns:
        ``(chol (b, P, P), failed (b,), dead (b, P), d2 (b, P))``: the factor (the identity
        where the factorisation failed), the failures, the dead columns and the diagonal of
        ``gram`` before the ridge.
    """
    d2 = gram.diagonal(dim1=-2, dim2=-1).clone()
    dead = d2 <= 0  # an all-zero column: its coefficient is not identified
    penalty = torch.as_tensor(lam, dtype=gram.dtype, device=gram.device).reshape(-1, 1) * d2
    penalty[..., 0] = 0  # the intercept is not penalised
    if unpenalised is not None:
        penalty = penalty.masked_fill(unpenalised.to(penalty.device), 0.0)
    gram.diagonal(dim1=-2, dim2=-1).add_(torch.where(dead, 1.0, penalty))
    chol, info = torch.linalg.cholesky_ex(gram)
    failed = info != 0
    # unconditionally (asking whether any failed would stop a GPU for a host sync); the
    # factor's column-major layout is kept (the triangular solves' rounding depends on it):
    # the selection runs on its transpose (row-major, one contiguous pass)
    eye = torch.eye(gram.shape[-1], dtype=gram.dtype, device=gram.device)
    chol = torch.where(failed[..., None, None], eye, chol.mT).mT
    return chol, failed, dead, d2


def condition_bound(matrix: Tensor, l_inv: Tensor, scale: Tensor) -> Tensor:
    """Upper bound ``(b,)`` of the 1-norm condition number of the equilibrated normal matrix
    ``A_s = D⁻¹AD⁻¹`` from ``A = matrix (b, P, P)`` (ridge included), the inverse ``l_inv`` of
    its Cholesky factor and the column scales ``scale = diag(D) (b, P)``:
    ``κ₁(A_s) ≤ ‖A_s‖₁ ‖L_s⁻¹‖₁ ‖L_s⁻¹‖∞`` with ``L_s⁻¹ = L⁻¹D``, exact for an orthogonal
    design."""
    # matrix-vector products as multiply-sum, norms as abs + sum: cheaper on CPU for small
    # matrices than a bmm or torch.linalg.vector_norm
    inv_scale = 1 / scale
    a_norm = (matrix.abs().mul_(inv_scale.unsqueeze(-2)).sum(-1) * inv_scale).amax(-1)
    l_abs = l_inv.abs()
    l_norm1 = (l_abs.sum(-2) * scale).amax(-1)
    l_norm_inf = l_abs.mul_(scale.unsqueeze(-2)).sum(-1).amax(-1)
    return a_norm * l_norm1 * l_norm_inf


def sandwich(a_inv: Tensor, g2: Tensor, gram: Tensor | None, sum_w: Tensor
             ) -> tuple[Tensor, Tensor]:
    """The effective residual dof ``(b,)`` and ``diag(A⁻¹G₂A⁻¹) (b, P)`` of weighted least
    squares with normal matrix ``A`` (``a_inv = A⁻¹ (b, P, P)``, ridge and correction
    included), ``G₂ = XᵀW²X`` (``g2``), the observed ``G = XᵀWX`` (``gram``; None where
    ``G₂ = G``, 0/1 weights) and ``Σw`` (``sum_w``): ``dof = Σw − 2 tr(A⁻¹G₂) +
    tr(A⁻¹G A⁻¹G₂)``, which makes ``σ̂² = RSS / dof`` unbiased, and the sandwich's diagonal,
    so that ``Cov β = σ² A⁻¹G₂A⁻¹``."""
    s_mat = a_inv @ g2
    trace = s_mat.diagonal(dim1=-2, dim2=-1).sum(-1)
    a_g = s_mat if gram is None else a_inv @ gram  # G₂ = G for 0/1 weights
    dof = sum_w - 2 * trace + (a_g * s_mat.mT).sum((-2, -1))
    return dof, (s_mat * a_inv.mT).sum(-1)


def _fit_chunk(xy: Tensor, w: Tensor, lam: Tensor, binary: bool, n_out: int,
               tolerate_dead: bool, correction: Correction | None = None, sel=None,
               standard_errors: bool = True, unpenalised: Tensor | None = None):
    """Solve one chunk of bins from ``xy = √w [X | y]`` ``(b, n, P + K)``; ``lam (b,)`` ridge.

    ``correction``, when given, maps this chunk's ``XᵀWX (b, P, P)`` (the bins ``sel``) to its
    expected noise part (errors in the regressors), which is subtracted under the guard of
    :func:`_guarded_correction`; it gets the ``XᵀWX`` block of the one ``[X|y]ᵀW[X|y]``
    product (no second product of the design).

    One batched matmul forms ``[X|y]ᵀW[X|y]``; Cholesky is invariant to diagonal scaling (van der
    Sluis), so the unscaled normal matrix is factorised and the equilibrated quantities --
    ridge ``λ`` on the unit diagonal of every column but the intercept, condition number -- are
    expressed through the column scales ``dⱼ = √(XᵀWX)ⱼⱼ`` (each column's weighted RMS ·
    √Σw), so the condition number measures collinearity, not units.

    ``standard_errors=False`` stops after the coefficients and the condition number (the
    standard errors and residual RMS come back NaN): the residuals and the sandwich's
    ``n·P²`` product are skipped, and the coefficients are the same bit for bit.
    """
    p = xy.shape[-1] - n_out
    xw, yw = xy[..., :p], xy[..., p:]
    full = xy.mT @ xy
    gram, rhs = full[..., :p, :p], full[..., :p, p:]
    no_ridge = not bool((lam > 0).any())
    plain = correction is None and no_ridge  # A = XᵀWX (+ unit pivots of dead columns)
    general = not (binary and no_ridge) and not plain
    # the general sandwich needs the observed XᵀWX; the normal matrix is changed in place
    unpen = gram.clone() if general else None
    if correction is None:
        kappa = gram.new_ones(gram.shape[0])
    else:
        gram, kappa = _guarded_correction(gram, correction(gram, sel))
    # unless tolerated (a ridge was asked for) a dead column makes the bin rank-deficient:
    # infinite condition number
    chol, failed, dead, d2 = ridge_cholesky(gram, lam, unpenalised)
    scale = torch.where(dead, 1.0, d2.sqrt())
    beta = torch.cholesky_solve(rhs, chol)
    # L⁻¹ gives diag(A⁻¹) for the standard errors and the condition bound
    l_inv = _triangular_inverse(chol)

    # condition of the equilibrated A_s = D⁻¹AD⁻¹
    bound = condition_bound(gram, l_inv, scale)
    rank_deficient = failed | (dead.any(-1) & (not tolerate_dead))
    condition = torch.where(rank_deficient, torch.inf, bound)
    if not standard_errors:
        beta = beta.masked_fill(dead.unsqueeze(-1), torch.nan)
        nan = torch.full_like(beta, torch.nan)
        return beta, nan, nan[:, 0], condition, (w > 0).sum(-1), kappa

    rss = _row_sum_((yw - xw @ beta).square_(), -2)  # (b, K)
    sum_w = _row_sum(w, -1)
    if binary and no_ridge:
        dof = sum_w - p
        cov_diag = l_inv.square_().sum(-2)  # diag(A⁻¹); L⁻¹ is not used after this
    elif plain:
        # kernel weights, no ridge, no correction: A = G = XᵀWX (dead columns aside, where
        # G₂ is 0 too), so the sandwich Cov = σ² A⁻¹G₂A⁻¹ with G₂ = XᵀW²X and the dof
        # Σw − 2 tr(A⁻¹G₂) + tr(A⁻¹G A⁻¹G₂) = Σw − tr(A⁻¹G₂) come from Q = (W X) A⁻¹ (n × P)
        # alone: diag(A⁻¹G₂A⁻¹) = Σ_rows Q², tr(A⁻¹G₂) = Σ Q ∘ (W X) -- one n·P² product
        # instead of forming G₂ and two P³ products with it
        xww = xw * w.sqrt().unsqueeze(-1)  # rows scaled by w
        q = xww @ (l_inv.mT @ l_inv)
        cov_diag = _row_sum_(q.square(), -2)
        dof = sum_w - _row_sum(q.mul_(xww).sum(-1), -1)
    else:
        # sandwich for kernel weights / ridge: Cov = σ² A⁻¹ (XᵀW²X) A⁻¹, and the effective
        # residual dof  Σw − 2 tr(A⁻¹G₂) + tr(A⁻¹G A⁻¹G₂)  that makes σ̂² unbiased
        a_inv = l_inv.mT @ l_inv
        if binary:
            g2 = unpen
        else:
            xww = xw * w.sqrt().unsqueeze(-1)  # rows scaled by w: XᵀW²X
            g2 = xww.mT @ xww
        dof, cov_diag = sandwich(a_inv, g2, None if binary else unpen, sum_w)
    sigma2 = torch.where(dof.unsqueeze(-1) > 0, rss / dof.unsqueeze(-1), torch.nan)
    se = (cov_diag.clamp(min=0).unsqueeze(-1) * sigma2.unsqueeze(-2)).sqrt()
    beta = beta.masked_fill(dead.unsqueeze(-1), torch.nan)
    se = se.masked_fill(dead.unsqueeze(-1), torch.nan)
    rms = (rss / sum_w.unsqueeze(-1)).sqrt()
    return beta, se, rms, condition, (w > 0).sum(-1), kappa


#: a per-row errors-in-variables correction: (the rows √w·x̃ (b, n, P), the coefficients
#: (b, P, K), the bins (a slice or index tensor into B·M)) -> each row's expected noise part of
#: its score, C(w x̃x̃ᵀ) β (b, n, K, P) (linear in the row's Gram matrix, summing to the
#: :data:`Correction` of the bin times β)
RowCorrection = Callable[[Tensor, Tensor, object], Tensor]


def _inverse_normal_columns(xw: Tensor, ridge: Tensor, columns: Tensor,
                            correction: Correction | None, sel,
                            unpenalised: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The columns ``columns (c,)`` of ``A⁻¹ (b, P, c)``, ``A`` the normal matrix of the rows
    ``xw = √w x̃ (b, n, P)`` as :func:`solve` makes it (corrected by ``correction`` of the bins
    ``sel`` under the guard, with the ridge ``ridge (b,)``), and the guard's scale ``κ (b,)``
    (1 without a correction)."""
    gram = xw.mT @ xw
    kappa = gram.new_ones(gram.shape[0])
    if correction is not None:
        gram, kappa = _guarded_correction(gram, correction(gram, sel))
    chol, _, _, _ = ridge_cholesky(gram, ridge, unpenalised)
    return torch.cholesky_inverse(chol)[..., columns], kappa


def score_covariance(s: BinnedSamples, design: Design, sol: Solution, columns: Tensor, *,
                     lags: int, delta_max=None, correction: Correction | None = None,
                     row_correction: RowCorrection | None = None,
                     unpenalised: Tensor | None = None) -> Tensor:
    """Robust covariance ``(B·M, K, c, c)`` of the coefficients ``columns (c,)`` of every bin
    of a :func:`solve` result ``sol``, from the rows' own scores instead of a common residual
    variance.

    The estimate solves ``Σ_t ψ_t = 0`` with the score ``ψ_t = w_t x̃_t (y_t − x̃_tᵀβ) +
    κ C_t β`` (``C_t`` the row's share of the errors-in-variables correction, ``κ`` the
    guard's scale), so ``Cov β = A⁻¹ (Σ_t Σ_|l|≤lags ψ_t ψ_{t+l}ᵀ) A⁻¹`` (``A`` the corrected
    normal matrix): the sandwich with the scores' own heteroscedasticity (the regressors'
    noise times the coefficients, which a common residual variance spreads evenly over the
    rows), the correction's own variance, and the correlation of rows ``l ≤ lags`` samples
    apart that share recorded samples (pairs within one bin, by sample index), times
    ``n/(n − P)`` (``n`` the bin's rows with ``w > 0``). NaN where the bin's coefficients are
    NaN.

    What it estimates (tests/test_joint_covariance.py): for fixed regressors its expectation
    is ``A⁻¹ (Σ_{|i−j| ≤ lags} w_i w_j x_i x_jᵀ E[ê_i ê_j]) A⁻¹ · n/(n − P)`` with the
    residuals ``ê = (I − H)(Xβ + e)`` (with a ridge they carry its bias), an HC1 estimate:
    the covariance of the estimates where every row has the same leverage (with the
    correction too), but biased low where leverages differ (docs/validation/ gives its
    coverage). Rows more than ``lags`` samples apart are taken as uncorrelated.
    """
    p = sol.coef.shape[-2]
    out = []
    for sel, proj, w in _projected_scores(s, design, sol, columns, delta_max=delta_max,
                                          correction=correction,
                                          row_correction=row_correction,
                                          unpenalised=unpenalised):
        # rows in sample order, padding last: a pair of rows at most `lags` samples apart is
        # at most that many slots apart
        index = torch.where(w > 0, s.rows[sel], torch.iinfo(s.rows.dtype).max)
        index, order = index.sort(-1)
        proj = proj.gather(1, order[..., None, None].expand_as(proj))
        cov = torch.einsum("bnkc,bnke->bkce", proj, proj)
        for step in range(1, min(lags, index.shape[-1] - 1) + 1):
            pair = ((index[:, step:] - index[:, :-step]) <= lags).to(proj)
            cross = torch.einsum("bnkc,bn,bnke->bkce", proj[:, :-step], pair, proj[:, step:])
            cov = cov + cross + cross.mT
        n = (w > 0).sum(-1).to(cov)
        cov = cov * torch.where(n > p, n / (n - p), torch.nan)[:, None, None, None]
        bad = ~torch.isfinite(sol.coef[sel]).all(-2).all(-1)
        out.append(torch.where(bad[:, None, None, None], torch.nan, cov))
    return torch.cat(out)


def cluster_scores(s: BinnedSamples, design: Design, sol: Solution, columns: Tensor,
                   clusters: Tensor, n_clusters: int, *, delta_max=None,
                   correction: Correction | None = None,
                   row_correction: RowCorrection | None = None,
                   unpenalised: Tensor | None = None) -> Tensor:
    """Each cluster's share ``(B·M, C, K, c)`` of the error of the coefficients ``columns
    (c,)`` of every bin of a :func:`solve` result ``sol``: ``A⁻¹ Σ_{t ∈ cluster} ψ_t`` with
    the rows' scores ``ψ_t`` of :func:`score_covariance` (the errors-in-variables row
    correction included). Over the clusters the shares sum to zero (the estimating
    equations), and ``Σ_c share_c share_cᵀ`` is the cluster-robust sandwich
    ``A⁻¹ (Σ_c s_c s_cᵀ) A⁻¹`` (``s_c`` the cluster's summed score; no small-sample factor).
    Rows of one cluster may fall in several bins (overlapping windows): the shares of
    different bins are then correlated through them, as their errors are.

    Args:
        clusters: ``(B·N,)`` int64 cluster of every flattened sample (``s.r``'s rows), in
            ``[0, n_clusters)`` (numbered within each batch element: a bin's rows are all its
            element's).

    NaN where the bin's coefficients are NaN."""
    k = sol.coef.shape[-1]
    out = []
    for sel, proj, w in _projected_scores(s, design, sol, columns, delta_max=delta_max,
                                          correction=correction,
                                          row_correction=row_correction,
                                          unpenalised=unpenalised):
        label = clusters[s.rows[sel]]  # (b, n)
        proj = proj * (w > 0)[..., None, None].to(proj)  # padding and excluded rows: none
        sums = proj.new_zeros((proj.shape[0], n_clusters, k, proj.shape[-1]))
        sums.scatter_add_(1, label[..., None, None].expand_as(proj), proj)
        bad = ~torch.isfinite(sol.coef[sel]).all(-2).all(-1)
        out.append(torch.where(bad[:, None, None, None], torch.nan, sums))
    return torch.cat(out)


def _projected_scores(s: BinnedSamples, design: Design, sol: Solution, columns: Tensor, *,
                      delta_max, correction: Correction | None,
                      row_correction: RowCorrection | None, unpenalised: Tensor | None):
    """Per chunk of bins ``sel`` (:func:`_design_chunks`): every row's score times the columns
    ``columns (c,)`` of ``A⁻¹``, ``(b, n, K, c)`` (the rows as :func:`_chunk_design` gathers
    them), and the rows' weights ``(b, n)`` (what :func:`score_covariance` and
    :func:`cluster_scores` sum)."""
    p = sol.coef.shape[-2]
    for sel, xy, w in _design_chunks(s, design, p, delta_max, copies=8):
        xw, yw = xy[..., :p], xy[..., p:]
        a_inv, kappa = _inverse_normal_columns(xw, sol.ridge[sel], columns, correction, sel,
                                               unpenalised)
        beta = torch.nan_to_num(sol.coef[sel])
        score = xw.unsqueeze(-2) * (yw - xw @ beta).unsqueeze(-1)  # (b, n, K, P)
        if row_correction is not None:
            score = score + kappa[:, None, None, None] * row_correction(xw, beta, sel)
        yield sel, score @ a_inv.unsqueeze(1), w


def sandwich_correlation(s: BinnedSamples, design: Design, sol: Solution, columns: Tensor, *,
                         delta_max=None, correction: Correction | None = None,
                         unpenalised: Tensor | None = None) -> Tensor:
    """Correlation ``(B·M, c, c)`` of the coefficients ``columns (c,)`` of every bin of a
    :func:`solve` result ``sol``, from the sandwich whose diagonal gives its standard errors:
    ``A⁻¹ (XᵀW²X) A⁻¹`` (``A`` the normal matrix, corrected and with the ridge as :func:`solve`
    makes it; its residual variance, common to the coefficients, cancels). NaN where the bin's
    coefficients are NaN. (With 0/1 weights and no ridge the solver's standard errors take
    ``diag(A⁻¹)`` instead, which equals this sandwich's diagonal only without a correction;
    the correlation is this sandwich's either way.)

    It is the estimates' correlation exactly for fixed regressors and independent response
    errors of one variance, whatever the weights and ridge (tests/test_joint_covariance.py,
    against a Monte Carlo). It does not model errors whose variance varies over the rows,
    rows that share samples, or, with a correction, the correction's own variance (the
    regressors' noise times the coefficients, largest on the largest regressors): with
    regressor noise 0.4 of their spread, its covariance (times the standard errors) had
    variances 1.2-1.9 times too small and correlations off; :func:`score_covariance` models
    those."""
    p = sol.coef.shape[-2]
    out = []
    for sel, xy, w in _design_chunks(s, design, p, delta_max):
        xw = xy[..., :p]
        a_inv, _ = _inverse_normal_columns(xw, sol.ridge[sel], columns, correction, sel,
                                           unpenalised)
        xww = xw * w.sqrt().unsqueeze(-1)  # rows scaled by w: XᵀW²X
        half = xww @ a_inv  # (b, n, c)
        cov = half.mT @ half
        sd = cov.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()
        corr = cov / (sd.unsqueeze(-1) * sd.unsqueeze(-2))
        bad = ~torch.isfinite(sol.coef[sel]).all(-2).all(-1)
        out.append(torch.where(bad[:, None, None], torch.nan, corr))
    return torch.cat(out)


def held_gain(s: BinnedSamples, design: Design, sol: Solution, free: int, held: slice, *,
              delta_max=None, correction: Correction | None = None,
              unpenalised: Tensor | None = None) -> Tensor:
    """How the first ``free`` coefficients of every bin of a :func:`solve` result ``sol`` move
    when the coefficients ``held`` are set to other values and held there, the rest
    re-estimated: ``G = −N_ff⁻¹ N_fh`` ``(B·M, free, len(held))``, so that the least-squares
    solution with ``β_h`` held at ``β̂_h + Δ`` is ``β̂_f + G Δ`` (each output alike; the
    columns neither free nor held stay at their estimates).

    ``N`` is the bin's normal matrix as :func:`solve` made it: ``XᵀWX`` less the fit's share
    ``κ`` (``sol.eiv_scale``) of ``correction``, with its ridge (``sol.ridge``, the
    convention of :func:`ridge_cholesky`). The free columns come first, so the leading block
    of ``N``'s Cholesky factor ``L`` is that of ``N_ff`` and ``G = −L_ffᵀ⁻¹ L_hfᵀ``. One pass
    over the design, no solve of the full system. NaN where the bin's coefficients are NaN."""
    p = sol.coef.shape[-2]
    out = []
    for sel, xy, _ in _design_chunks(s, design, p, delta_max):
        xw = xy[..., :p]
        gram = xw.mT @ xw
        if correction is not None:
            gram = gram - sol.eiv_scale[sel][:, None, None] * correction(gram, sel)
        chol, _, _, _ = ridge_cholesky(gram, sol.ridge[sel], unpenalised)
        gain = -torch.linalg.solve_triangular(chol[:, :free, :free].mT,
                                              chol[:, held, :free].mT, upper=True)
        bad = ~torch.isfinite(sol.coef[sel]).all(-2).all(-1)
        out.append(torch.where(bad[:, None, None], torch.nan, gain))
    return torch.cat(out)


def _design_chunks(s: BinnedSamples, design: Design, p: int, delta_max, copies: int = 2):
    """``(sel, xy, w)`` for the chunks of bins of ``s`` that the post-fit passes over a
    ``P = p`` design (:func:`score_covariance`, :func:`cluster_scores`,
    :func:`sandwich_correlation`, :func:`held_gain`) take at once: ``sel`` a slice into
    ``B·M``, ``xy = √w [X | y]`` and ``w`` (:func:`_chunk_design`), sized for
    ``copies`` working copies of the design."""
    total, n_max = s.rows.shape
    for sel in _chunks(total, n_max * (p + s.r.shape[-1]) * s.r.dtype.itemsize * copies,
                       s.r.device):
        xy, w = _chunk_design(s, sel, design, delta_max)
        yield sel, xy, w


def _row_sum(x: Tensor, dim: int) -> Tensor:
    """Sum over the bins' padded rows in sample order (a running sum): trailing zero rows leave
    it unchanged, so a bin's sum does not depend on how far the batch pads its rows (torch's
    cascade ``sum`` rounds with the padded length)."""
    return x.cumsum(dim).select(dim, -1)


def _row_sum_(x: Tensor, dim: int) -> Tensor:
    """:func:`_row_sum` of a temporary ``x``, overwritten with its running sum (the same sum;
    in place saves allocating a second array the size of the design)."""
    return x.cumsum_(dim).select(dim, -1)


def _triangular_inverse(chol: Tensor) -> Tensor:
    """``L⁻¹`` of lower-triangular ``L (b, P, P)`` by one 2 × 2 block split::

        [L₁₁ 0; L₂₁ L₂₂]⁻¹ = [L₁₁⁻¹ 0; −L₂₂⁻¹ L₂₁ L₁₁⁻¹ L₂₂⁻¹]

    torch's triangular solve against the identity costs ``P³`` (it does not know that the
    right side is triangular) and runs one matrix at a time; the split halves that work and
    moves the rest into two batched matmuls (used from ``P = 48``; below it, one solve). A
    triangular inverse is cheaper on CPU than cholesky_inverse.
    """
    p = chol.shape[-1]
    eye = torch.eye(p, dtype=chol.dtype, device=chol.device)
    if p < 48:
        return torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
    h = p // 2
    batch = chol.shape[:-2]
    top = torch.linalg.solve_triangular(chol[..., :h, :h], eye[:h, :h].expand(batch + (h, h)),
                                        upper=False)
    bottom = torch.linalg.solve_triangular(
        chol[..., h:, h:], eye[h:, h:].expand(batch + (p - h, p - h)), upper=False)
    out = torch.zeros_like(chol)
    out[..., :h, :h] = top
    out[..., h:, h:] = bottom
    out[..., h:, :h] = -(bottom @ (chol[..., h:, :h] @ top))
    return out


def _solve_bins(s: BinnedSamples, sel_list, design: Design, lam: Tensor, delta_max, binary,
                tolerate_dead: bool, correction: Correction | None = None,
                standard_errors: bool = True, unpenalised: Tensor | None = None):
    outs = []
    for sel in sel_list:
        xy, w = _chunk_design(s, sel, design, delta_max)
        outs.append(_fit_chunk(xy, w, lam[sel], binary, s.y.shape[-1], tolerate_dead,
                               correction, sel, standard_errors, unpenalised))
    return [torch.cat(parts) for parts in zip(*outs, strict=True)]


def chunk_budget(device: torch.device) -> int:
    """Bytes of working memory one batched pass over bins may take on ``device``:
    :data:`_CHUNK_BYTES` on the CPU, :data:`_DEVICE_CHUNK_BYTES` elsewhere."""
    return _CHUNK_BYTES if torch.device(device).type == "cpu" else _DEVICE_CHUNK_BYTES


def _chunks(n_bins_total: int, bytes_per_bin: int, device: torch.device) -> list[slice]:
    """Slices of ``n_bins_total`` bins of ``bytes_per_bin`` working memory each, at most
    :data:`_CHUNK_BYTES` per slice on the CPU and :data:`_DEVICE_CHUNK_BYTES` elsewhere."""
    step = max(1, chunk_budget(device) // max(bytes_per_bin, 1))
    return [slice(i, min(i + step, n_bins_total)) for i in range(0, n_bins_total, step)]


def fit_limits(p: int, dtype: torch.dtype, min_samples: int | None = None,
               max_condition: float | None = None) -> tuple[int, float]:
    """The fewest samples and the largest condition number with which :func:`solve` fits a
    bin of ``p`` coefficients (None: the defaults, ``p + 5`` and ``1e12`` in float64)."""
    if min_samples is None:
        min_samples = p + 5
    if max_condition is None:
        max_condition = 1e12 if dtype == torch.float64 else 1e-2 / torch.finfo(dtype).eps
    return min_samples, max_condition


def unfittable(count: Tensor, condition: Tensor, p: int, dtype: torch.dtype,
               min_samples: int | None = None, max_condition: float | None = None) -> Tensor:
    """The bins :func:`solve` cannot fit reliably (too few samples or ill-conditioned; what
    ``on_ill_conditioned`` acts on), from their sample counts and condition numbers (same
    shape)."""
    min_samples, max_condition = fit_limits(p, dtype, min_samples, max_condition)
    return (count < min_samples) | ~(condition <= max_condition)


def solve(s: BinnedSamples, design: Design, n_coef: int, *, fn: str, delta_max, ridge: float,
          min_samples: int | None, max_condition: float | None,
          on_ill_conditioned: str, correction: Correction | None = None,
          standard_errors: bool = True, unpenalised: Tensor | None = None) -> Solution:
    """Fit every bin of ``s`` with ``design`` (``n_coef`` columns, column 0 the intercept).

    Returns a flat :class:`Solution` over ``B·M`` bins. Standard errors are
    ``σ̂ √diag(Cov)``: for box weights and no ridge the OLS ``(XᵀWX)⁻¹`` with ``n − P`` dof; for
    kernel weights or a ridge the sandwich ``A⁻¹(XᵀW²X)A⁻¹`` with the effective dof, so they are
    calibrated for homoscedastic noise whatever the weights. Ill-conditioned bins are handled per
    ``on_ill_conditioned``. ``correction`` (errors in variables) subtracts the regressors' expected
    noise part from every bin's ``XᵀWX`` (see :func:`_guarded_correction`).
    ``standard_errors=False``: the coefficients alone (bit for bit the same; ``se`` and
    ``residual_rms`` NaN), for callers that use nothing else (:func:`_fit_chunk`).
    ``unpenalised``: ``(n_coef,)`` bool, columns the ridge (given or added for ill-conditioned
    bins) leaves alone besides the intercept (:func:`ridge_cholesky`).
    """
    if on_ill_conditioned not in _MODES:
        raise ValueError(f"{fn}: on_ill_conditioned must be one of {_MODES}, "
                         f"got {on_ill_conditioned!r}")
    if ridge < 0 or not math.isfinite(ridge):
        raise ValueError(f"{fn}: ridge must be a finite number ≥ 0, got {ridge!r}")
    if delta_max is not None and not delta_max > 0:
        raise ValueError(f"{fn}: delta_max must be positive or None, got {delta_max!r}")
    p = n_coef
    min_samples, max_condition = fit_limits(p, s.r.dtype, min_samples, max_condition)
    total, n_max = s.rows.shape
    dtype, dev = s.r.dtype, s.r.device
    lam = torch.full((total,), float(ridge), dtype=dtype, device=dev)
    binary = bool(((s.weight == 0) | (s.weight == 1)).all())
    chunks = _chunks(total, n_max * (p + s.r.shape[-1]) * dtype.itemsize * 2, dev)

    if total == 0 or n_max == 0:
        beta = torch.full((total, p, s.y.shape[-1]), torch.nan, dtype=dtype, device=dev)
        zeros = torch.zeros(total, dtype=torch.int64, device=dev)
        nan = torch.full((total,), torch.nan, dtype=dtype, device=dev)
        sol = [beta, beta.clone(), beta[:, 0].clone(), nan.clone().fill_(torch.inf), zeros,
               nan.clone().fill_(1.0)]
    else:
        sol = _solve_bins(s, chunks, design, lam, delta_max, binary, tolerate_dead=ridge > 0,
                          correction=correction, standard_errors=standard_errors,
                          unpenalised=unpenalised)
    beta, se, rms, cond, count, kappa = sol
    few = count < min_samples
    ill = unfittable(count, cond, p, dtype, min_samples, max_condition)
    if bool(ill.any()):
        if on_ill_conditioned == "raise":
            raise ValueError(_ill_message(fn, s, ill, few, count, cond, p, min_samples,
                                          max_condition, ending=_ADVICE))
        if on_ill_conditioned == "ridge":
            report = _ill_message(fn, s, ill, few, count, cond, p, min_samples, max_condition,
                                  ending="")
            fix = (ill & ~few).nonzero().flatten()
            if fix.numel():
                lam, beta, se, rms, cond = _add_ridge(s, design, fix, lam, beta, se, rms, cond,
                                                      delta_max, binary, max_condition,
                                                      correction, standard_errors, unpenalised)
            ill = unfittable(count, cond, p, dtype, min_samples, max_condition)
            report += (f"Added a ridge to {fix.numel()} ill-conditioned bin(s) (largest "
                       f"{float(lam.max()):.3g}, relative to the unit diagonal of the "
                       f"standardised normal matrix; see the fit's .ridge)")
            if bool(few.any()):
                report += "; bins with too few samples are returned as NaN"
            warnings.warn(report, IllConditionedBinWarning, stacklevel=3)
        else:
            warnings.warn(_ill_message(fn, s, ill, few, count, cond, p, min_samples,
                                       max_condition, ending="these bins are returned as NaN"),
                          IllConditionedBinWarning, stacklevel=3)
        bad = ill.view(-1, 1, 1)
        beta = torch.where(bad, torch.nan, beta)
        se = torch.where(bad, torch.nan, se)
        rms = torch.where(ill.view(-1, 1), torch.nan, rms)
    return Solution(beta, se, count, rms, cond, lam, kappa)


def _add_ridge(s, design, fix, lam, beta, se, rms, cond, delta_max, binary, max_condition,
               correction=None, standard_errors=True, unpenalised=None):
    """Smallest ridge bringing each bin in ``fix`` to the target condition (a few tries)."""
    target = min(_RIDGE_TARGET_CONDITION, max_condition)
    xy, _ = _chunk_design(s, fix, design, delta_max)
    xw = xy[..., : xy.shape[-1] - s.y.shape[-1]]
    gram = xw.mT @ xw
    diag = gram.diagonal(dim1=-2, dim2=-1)
    dead = diag <= 0  # decoupled in the re-solve: they need no ridge
    scale = torch.where(dead, 1.0, diag.sqrt())
    gram_s = gram / (scale.unsqueeze(-1) * scale.unsqueeze(-2))
    gram_s.diagonal(dim1=-2, dim2=-1).add_(dead.to(gram_s))
    eig = _linalg.eigvalsh(gram_s, "the regression's normal matrix")
    need = (eig[:, -1] - target * eig[:, 0].clamp(min=0)) / (target - 1)
    lam = lam.clone()
    lam[fix] = torch.maximum(lam[fix], need * 1.01)
    for _ in range(6):  # the intercept is unpenalised, so the prediction can fall short
        chunks = [fix[i:i + 256] for i in range(0, fix.numel(), 256)]
        b, e, r, c, _, _ = _solve_bins(s, chunks, design, lam, delta_max, binary, True,
                                       correction, standard_errors, unpenalised)
        beta, se, rms, cond = beta.clone(), se.clone(), rms.clone(), cond.clone()
        beta[fix], se[fix], rms[fix], cond[fix] = b, e, r, c
        still = ~(cond[fix] <= max_condition)
        if not bool(still.any()):
            break
        lam[fix[still]] *= 10
    return lam, beta, se, rms, cond


_ADVICE = (
    "Fix: use fewer phase bins (n_bins) or a wider window (assign_bins(..., window=...)), record "
    "more cycles, pass ridge=... , or on_ill_conditioned='warn' (NaN for these bins) / 'ridge' "
    "(regularise them). A shape coordinate that never varies within a bin (a joint held fixed) "
    "makes the design rank-deficient whatever the sample count."
)


def _ill_message(fn, s, ill, few, count, cond, p, min_samples, max_condition, ending) -> str:
    idx = ill.nonzero().flatten().tolist()
    batch, m = s.batch_shape, s.n_bins
    items = []
    for flat in idx[:8]:
        b, bin_m = divmod(flat, m)
        where = f"batch {_unravel(b, batch)} bin {bin_m}" if len(batch) else f"bin {bin_m}"
        c = float(cond[flat])
        if few[flat]:
            why = f"{int(count[flat])} samples < min_samples={min_samples}"
        elif math.isinf(c):
            why = (f"{int(count[flat])} samples, rank-deficient design (an all-zero column or "
                   f"a failed Cholesky factorisation: numerically singular)")
        else:
            why = (f"{int(count[flat])} samples, rank-deficient design (scaled condition number "
                   f"{c:.3g} > {max_condition:.3g})")
        items.append(f"{where}: {why}")
    more = f" ... and {len(idx) - 8} more" if len(idx) > 8 else ""
    return (f"{fn}: {len(idx)} of {ill.numel()} phase bins cannot be fitted reliably with "
            f"P = {p} regressors per bin: " + "; ".join(items) + more + ". " + ending)


def _unravel(flat: int, shape: torch.Size) -> tuple[int, ...]:
    out = []
    for size in reversed(shape):
        flat, rem = divmod(flat, size)
        out.append(rem)
    return tuple(reversed(out))
