"""Noise-corrected normal equations of the tied metric model, and its held-out orders.

The shapes' observation noise adds a known matrix ``C`` to the raw normal matrix ``G`` of the
tied model. In the generalized eigenvectors of ``(G, C)`` the correction divides each direction
by its signal fraction ``1 − ν``; below a floor (:func:`signal_floor`) that fraction is mostly
sampling error and only part of the correction is applied (:class:`CorrectedNormal`). The
order of ``M(φ)`` is chosen on held-out blocks of whole cycles (:func:`held_out_orders`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ... import _linalg

#: the floor on the signal fraction kept in any direction of the noise-corrected normal
#: matrix is this many times ``√(P/N)`` (``P`` coefficients of the largest model, ``N``
#: samples), the scale on which sampling error spreads a Gram matrix's eigenvalues. In the
#: generalized eigenvectors of (G, C) (raw normal matrix G, the noise's contribution C) the
#: correction divides each direction by its signal fraction 1 − ν; below the floor it is
#: mostly sampling error and only part of the correction is applied (:class:`CorrectedNormal`).
#: The 3-link gets a floor of about 0.1, the 5-link 0.2, the 9-link 0.45-0.55.
_FLOOR_SCALE = 1.1
#: the floor's largest value
_MAX_FLOOR = 0.9
#: standard errors by which a lower order must beat the largest on the held-out blocks
_ORDER_Z = 1.0


def signal_floor(n_coef: int, n_samples: Tensor) -> Tensor:
    """The floor on the signal fraction, ``(...)``: :data:`_FLOOR_SCALE` ``√(P/N)`` for ``P =
    n_coef`` coefficients and ``N = n_samples (...)`` samples, at most :data:`_MAX_FLOOR`."""
    ratio = n_coef / n_samples.to(torch.float64).clamp(min=1)
    return (_FLOOR_SCALE * ratio.sqrt()).clamp(max=_MAX_FLOOR)


@dataclass(frozen=True)
class CorrectedNormal:
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
    direction, including the well-excited ones that carry ``M̂γ̇``. One Cholesky of
    ``(1 − floor) G − C`` finds the elements that need no floor (``A = G − C``); only the
    others get the eigenvalue solve.

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
           nested: _LeadingFactors | None = None) -> CorrectedNormal:
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
        return CorrectedNormal(full=full, floored=floored, lower=lower, rotation=u,
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


def held_out_orders(gram: Tensor, corr: Tensor, rhs: Tensor, corr_h: Tensor, inv: Tensor,
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
    final fit is (:class:`CorrectedNormal`); an order whose raw normal matrix there is not
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
    gram, corr = principal(gram, perm), principal(corr, perm)
    rhs, corr_h, inv = rhs[..., perm], corr_h[..., perm], inv[..., perm]
    train_g = gram.sum(-3, keepdim=True) - gram
    train_c = corr.sum(-3, keepdim=True) - corr
    gram = gram - corr  # the blocks' corrected normal matrices, for the held-out loss
    train_h = rhs.sum(-2, keepdim=True) - rhs
    train_ch = corr_h.sum(-2, keepdim=True) - corr_h
    rhs = rhs - corr_h
    dead = train_g.diagonal(dim1=-2, dim2=-1) <= 0
    # the floor of the whole fit, so that it does not favour one order or block over another
    floor = signal_floor(p, n_fold.sum(-1, keepdim=True)).expand(n_fold.shape)
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
        normal = CorrectedNormal.of(train_g[..., :c, :c], train_c[..., :c, :c], floor, nested)
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


def order_columns(p: int, q: int, k: int, order: int, device) -> Tensor:
    """``(P_k,)`` int64 columns of the tied model at Fourier order ``k ≤ order`` of ``M(φ)``,
    in the layout of ``order`` (``P`` columns, feature ``column // q``; the first
    ``2·order+1`` features those of ``M(φ)``, the rest those of ``∂M/∂r(φ)``)."""
    feature = torch.arange(p, device=device) // q
    return torch.nonzero((feature < 2 * k + 1) | (feature >= 2 * order + 1))[:, 0]


def principal(x: Tensor, cols: Tensor) -> Tensor:
    """``(..., P_k, P_k)`` the principal submatrix of ``x (..., P, P)`` on ``cols (P_k,)``."""
    return x.index_select(-1, cols).index_select(-2, cols)


def noise_terms(s2: Tensor, s0: Tensor, fy: Tensor, sig: Tensor, iu: Tensor, ju: Tensor,
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

