"""Fitting candidate effects by autograd, cross-validating over whole cycles, selecting them.

Least squares in noise units
    The residual of every usable sample and body-velocity component is divided by that
    component's noise floor (:class:`~torchconn.discrepancy.forward.ForwardModel`), so the mean
    square of a correct model's residual is about 1 and the three components weigh alike.

Fitting (:func:`fit_effects`)
    Levenberg–Marquardt on the effects' parameters (scaled by their typical magnitudes), with
    the Jacobian of the residual from forward-mode automatic differentiation of the augmented
    simulator (one dual pass per parameter; no finite differences). Effects that do not change
    the body twist of a fine step (flow, drift, marker offset) reuse its primal value, so their
    columns cost only the cheap integration and smoothing.

Statistics over cycles
    All statistics are built from per-cycle sums -- ``ρ_cᵀρ_c``, ``J_cᵀρ_c``, ``J_cᵀJ_c`` at the
    fit -- so that cross-validation over blocks of whole cycles costs no refits: the fit
    without fold ``k`` is one Gauss–Newton step from the full fit using the other folds' sums,
    and a held-out cycle's squared error after that step follows from its own sums. Parameter
    covariances are cluster-robust (sandwich) over cycles, which accounts for the smoothed
    residual's autocorrelation within a cycle and for heteroscedasticity.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.autograd.forward_ad as fwAD
from scipy import stats
from torch import Tensor

from .. import _linalg
from ..cycles import rank_blocks
from ..physics.effects import Effect, get_effect
from .forward import ForwardModel

__all__ = ["CycleStats", "EffectFit", "fit_effects", "cycle_stats", "fourier_columns",
           "paired_gain"]

#: the name of the least-squares normal matrix in error messages
_NORMAL = "the effect fit's normal matrix"


# ============================================================================ per-cycle sums
@dataclass(frozen=True, eq=False)
class CycleStats:
    """Per-cycle sufficient statistics of a linearised least-squares problem.

    Attributes:
        sse: ``(C,)`` ``ρ_cᵀρ_c``; g: ``(C, P)`` ``J_cᵀρ_c``; G: ``(C, P, P)`` ``J_cᵀJ_c``.
        n: ``(C,)`` residual entries per cycle; fold: ``(C,)`` fold of each cycle.
    """

    sse: Tensor
    g: Tensor
    G: Tensor
    n: Tensor
    fold: Tensor

    @property
    def n_params(self) -> int:
        return self.g.shape[1]

    def held_out(self, ridge: float = 1e-9) -> tuple[Tensor, Tensor]:
        """Held-out squared error per cycle after refitting without its fold.

        Returns:
            ``(sse_cv (C,), steps (K, P))``: each cycle's ``‖ρ_c + J_c δ_k‖²`` with
            ``δ_k = −(Σ_{c∉k} G_c)⁻¹ Σ_{c∉k} g_c`` the Gauss–Newton step fitted without its fold.
        """
        P = self.n_params
        if P == 0:
            return self.sse.clone(), self.g.new_zeros(0, 0)
        K = int(self.fold.max()) + 1
        G_all, g_all = self.G.sum(0), self.g.sum(0)
        out = self.sse.clone()
        steps = []
        eye = torch.eye(P, dtype=self.G.dtype, device=self.G.device)
        for k in range(K):
            sel = self.fold == k
            G = G_all - self.G[sel].sum(0)
            g = g_all - self.g[sel].sum(0)
            reg = ridge * (torch.diagonal(G).mean() + 1e-300) * eye
            delta = -_linalg.solve(G + reg, g, "the fold fit's normal matrix")
            steps.append(delta)
            out[sel] = (self.sse[sel] + 2 * self.g[sel] @ delta
                        + torch.einsum("i,cij,j->c", delta, self.G[sel], delta))
        return out, torch.stack(steps)


    def held_out_rows(self, rho: Tensor, J: Tensor, row_fold: Tensor) -> Tensor:
        """Held-out residual of every row: ``ρ + J δ_k`` with ``δ_k`` the step fitted without
        the row's fold. ``rho (n,)``, ``J (n, P)``, ``row_fold (n,)`` -> ``(n,)``."""
        if self.n_params == 0:
            return rho.clone()
        _, steps = self.held_out()
        return rho + (J * steps[row_fold]).sum(-1)


def cycle_stats(rho: Tensor, J: Tensor, cycle: Tensor, n_cycles: int, fold: Tensor) -> CycleStats:
    """Per-cycle sums of a whitened residual ``rho (n,)`` and Jacobian ``J (n, P)``."""
    P = J.shape[1]
    idx = cycle
    sse = rho.new_zeros(n_cycles).index_add_(0, idx, rho * rho)
    g = rho.new_zeros(n_cycles, P).index_add_(0, idx, J * rho[:, None])
    G = rho.new_zeros(n_cycles, P, P).index_add_(0, idx, J[:, :, None] * J[:, None, :])
    n = rho.new_zeros(n_cycles).index_add_(0, idx, torch.ones_like(rho))
    return CycleStats(sse=sse, g=g, G=G, n=n, fold=fold)


def concat_stats(a: CycleStats, J_extra: Tensor, rho: Tensor, J: Tensor, cycle: Tensor) -> CycleStats:
    """Stats of ``[J, J_extra]`` (recomputed from the rows; ``a`` supplies folds and counts)."""
    return cycle_stats(rho, torch.cat([J, J_extra], 1), cycle, a.sse.shape[0], a.fold)


def paired_gain(sse_base: Tensor, sse_new: Tensor, n_entries: float) -> dict:
    """Held-out gain of a model over a base, and its one-sided paired test over cycles.

    Args:
        sse_base, sse_new: ``(..., C)`` held-out squared errors per cycle (noise units),
            broadcast against each other (e.g. one base against ``(K, C)`` candidates).
        n_entries: number of residual entries over all cycles (normalises the gain).

    Returns:
        dict with ``gain`` (drop of the held-out mean square, noise-variance units),
        ``t`` and ``p`` (one-sided paired t-test, :func:`scipy.stats.ttest_1samp` on the
        per-cycle differences; H1: the new model predicts held-out cycles better): floats for
        ``(C,)`` inputs, arrays of the batch shape otherwise. Differences without spread give
        ``t = ±inf, p = 0 | 1`` by the sign of the gain, and ``t = 0, p = 0.5`` when it is 0.
    """
    d = (sse_base - sse_new).double()
    diff = d.cpu().numpy()
    gain = diff.sum(-1) / n_entries
    flat = (d.std(-1) == 0).cpu().numpy() if d.shape[-1] > 1 else np.ones(diff.shape[:-1], bool)
    with warnings.catch_warnings(), np.errstate(divide="ignore", invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)  # degenerate rows are replaced below
        res = stats.ttest_1samp(diff, 0.0, axis=-1, alternative="greater")
    sign = np.sign(gain)
    t = np.where(flat, np.where(sign == 0, 0.0, np.copysign(np.inf, gain)), res.statistic)
    p = np.where(flat, np.where(sign > 0, 0.0, np.where(sign < 0, 1.0, 0.5)), res.pvalue)
    if diff.ndim == 1:
        return {"gain": float(gain), "t": float(t), "p": float(p)}
    return {"gain": gain, "t": t, "p": p}


# ============================================================================ fitting
@dataclass(eq=False)
class EffectFit:
    """A joint fit of a set of effects.

    Attributes:
        names: the effects, in parameter order; slices: their parameter ranges.
        p: ``(P,)`` fitted parameters (physical units, 0 = absent).
        cov: ``(P, P)`` cluster-robust covariance of ``p``.
        rho: ``(n,)`` whitened residual at the fit; J: ``(n, P)`` its Jacobian in ``p``.
        stats: per-cycle sums at the fit; sse_cv: ``(C,)`` held-out squared error per cycle.
        cost_history: the Levenberg–Marquardt costs.
    """

    names: list[str]
    slices: dict[str, slice]
    p: Tensor
    cov: Tensor
    rho: Tensor
    J: Tensor
    stats: CycleStats
    sse_cv: Tensor
    cost_history: list[float] = field(default_factory=list)

    def params(self) -> dict[str, Tensor]:
        return {n: self.p[s] for n, s in self.slices.items()}

    def se(self) -> Tensor:
        return torch.sqrt(torch.clamp(torch.diagonal(self.cov), min=0.0))

    @property
    def n_entries(self) -> int:
        return self.rho.numel()

    @property
    def mse_cv(self) -> float:
        return float(self.sse_cv.sum()) / self.n_entries

    @property
    def mse(self) -> float:
        return float(self.stats.sse.sum()) / self.n_entries


class Problem:
    """The whitened least-squares problem of one measurement and forward model."""

    def __init__(self, fm: ForwardModel, n_folds: int = 5, weight: Tensor | None = None):
        m = fm.m
        self.fm = fm
        self.mask = m.mask
        self.weight = 1.0 / fm.floor if weight is None else weight  # (3,)
        cyc = m.cycle[m.mask]  # (N,)
        self.cycle = cyc.repeat_interleave(3)  # rows ordered sample-major, component-minor
        self.n_cycles = m.n_cycles
        n_folds = max(2, min(n_folds, int(torch.bincount(m.cycle_trial).min())))
        self.fold = rank_blocks(m.cycle_trial, m.cycle_index, n_folds)
        self.n_folds = n_folds
        self._twist_cache = None  # (key, primal twist) of the last evaluation

    def flat(self, res: Tensor) -> Tensor:
        """``(B, T, 3)`` residual -> whitened ``(n,)`` over usable samples."""
        return (res[self.mask] * self.weight.to(res.dtype)).reshape(-1)

    def specs(self, names: list[str]) -> tuple[dict[str, slice], Tensor]:
        slices, scales, i = {}, [], 0
        for n in names:
            sp = get_effect(n).param_specs(self.fm.system)
            slices[n] = slice(i, i + len(sp))
            scales.extend(s.scale for s in sp)
            i += len(sp)
        return slices, torch.tensor(scales, dtype=torch.float64, device=self.fm.m.device)

    def evaluate(self, names: list[str], p: Tensor, jacobian: bool = True
                 ) -> tuple[Tensor, Tensor | None]:
        """Whitened residual ``(n,)`` and its Jacobian ``(n, P)`` (forward-mode AD)."""
        slices, _ = self.specs(names)
        params = {n: p[s] for n, s in slices.items()}
        fm = self.fm
        twist_names = [n for n in names if _changes_twist(get_effect(n))]
        key = (tuple(twist_names), p[[i for n in twist_names
                                      for i in range(slices[n].start, slices[n].stop)]].tolist())
        if self._twist_cache is not None and self._twist_cache[0] == key:
            twist = self._twist_cache[1]
        else:
            with torch.no_grad():
                twist = fm._twist({n: params[n] for n in twist_names})
            self._twist_cache = (key, twist)
        with torch.no_grad():
            rho = self.flat(fm.residual_from_twist(twist, params))
        if not jacobian:
            return rho, None
        cols = []
        for n in names:
            s = slices[n]
            for j in range(s.start, s.stop):
                tangent = torch.zeros_like(p)
                tangent[j] = 1.0
                with fwAD.dual_level():
                    dual = fwAD.make_dual(p, tangent)
                    dparams = {k: dual[sl] for k, sl in slices.items()}
                    if n in twist_names:
                        tw = fm._twist({k: dparams[k] for k in twist_names})
                    else:
                        tw = twist
                    out = fm.residual_from_twist(tw, dparams)
                    cols.append(self.flat(fwAD.unpack_dual(out).tangent))
        return rho, torch.stack(cols, 1)


def _changes_twist(effect: Effect) -> bool:
    return (type(effect).true_shapes is not Effect.true_shapes
            or type(effect).system_kwargs is not Effect.system_kwargs)


def fit_effects(
    problem: Problem,
    names: list[str],
    p0: Tensor | None = None,
    *,
    max_iter: int = 30,
    tol: float = 1e-10,
    abs_tol: float = 1e-3,
) -> EffectFit:
    """Jointly fit ``names`` by Levenberg–Marquardt with autograd Jacobians.

    Args:
        problem: the whitened problem (:class:`Problem`).
        names: effect names (may be empty: the nominal model).
        p0: starting parameters (default absent, 0).
    """
    slices, scale = problem.specs(names)
    P = int(scale.numel())
    p = torch.zeros_like(scale) if p0 is None else p0.to(scale, copy=True)
    rho, J = problem.evaluate(names, p, jacobian=P > 0)
    costs = [float(rho @ rho)]
    fresh = True  # J is the exact Jacobian at p (not a Broyden update)
    if P > 0:
        mu = 1e-6
        for _ in range(max_iter):
            Js = J * scale  # columns in units of the typical magnitude
            H = Js.T @ Js
            g = Js.T @ rho
            damp = torch.diagonal(H).clamp_min(1e-12 * float(torch.diagonal(H).max()) + 1e-300)
            if fresh and float(g @ _linalg.solve(H + mu * torch.diag(damp), g, _NORMAL)) <= abs_tol:
                # converged where the exact Jacobian was just taken: the step it predicts would
                # lower the cost by less than abs_tol and need another Jacobian at its end
                break
            accepted = False
            for _ in range(12):
                step = -_linalg.solve(H + mu * torch.diag(damp), g, _NORMAL) * scale
                rho_new, _ = problem.evaluate(names, p + step, jacobian=False)
                cost_new = float(rho_new @ rho_new)
                if cost_new <= costs[-1]:
                    accepted = True
                    break
                if not fresh:  # a stale Jacobian failed: get the exact one before damping more
                    rho, J = problem.evaluate(names, p, jacobian=True)
                    fresh = True
                    Js = J * scale
                    H, g = Js.T @ Js, Js.T @ rho
                    continue
                mu *= 10.0
            if not accepted:
                break
            exact = fresh  # the step came from the exact Jacobian, not a Broyden update
            pred = float(-(g @ (step / scale)))  # first-order predicted decrease / 2
            decrease = costs[-1] - cost_new
            costs.append(cost_new)
            mu = max(mu / 10.0, 1e-12)
            # Broyden's rank-one update instead of a new autograd Jacobian at every step: the
            # exact one costs a dual pass per parameter, the update nothing
            J = J + torch.outer(rho_new - rho - J @ step, step) / float(step @ step)
            rho, p, fresh = rho_new, p + step, False
            # the cost is a sum of squares in noise units: a change far below 1 moves the
            # parameters by a tiny fraction of their standard errors
            if decrease <= tol * costs[-2] + abs_tol or abs(pred) <= abs_tol:
                if exact:
                    break
                # a stalled Broyden Jacobian also takes small steps, far from the minimum;
                # only a step
                # from the exact Jacobian may declare convergence
                rho, J = problem.evaluate(names, p, jacobian=True)
                fresh = True
        if not fresh:  # statistics need the exact Jacobian at the fit
            rho, J = problem.evaluate(names, p, jacobian=True)
    st = cycle_stats(rho, J if P > 0 else rho.new_zeros(rho.numel(), 0), problem.cycle,
                     problem.n_cycles, problem.fold)
    sse_cv, _ = st.held_out()
    cov = _sandwich(st) if P > 0 else rho.new_zeros(0, 0)
    return EffectFit(names=list(names), slices=slices, p=p, cov=cov, rho=rho,
                     J=J if P > 0 else rho.new_zeros(rho.numel(), 0), stats=st, sse_cv=sse_cv,
                     cost_history=costs)


def _sandwich(st: CycleStats) -> Tensor:
    """Cluster-robust covariance ``H⁻¹ (Σ_c g_c g_cᵀ) H⁻¹ · C/(C−1)`` over cycles.

    At the least-squares fit ``Σ g_c = 0``; each cycle's score ``g_c = J_cᵀρ_c`` then carries its
    own noise, whatever its autocorrelation within the cycle.
    """
    H = st.G.sum(0)
    C = st.g.shape[0]
    meat = st.g.T @ st.g * (C / max(C - 1, 1))
    Hinv = _linalg.pinv(H, _NORMAL)
    return Hinv @ meat @ Hinv


def fourier_columns(problem: Problem, order: int) -> Tensor:
    """Whitened design of a phase-locked residual model: per component, ``[1, cos kφ, sin kφ]``.

    Returns ``(n, 3 (2K+1))`` rows aligned with :meth:`Problem.flat`.
    """
    m = problem.fm.m
    phi = m.phase[m.mask]  # (N,)
    k = torch.arange(1, order + 1, dtype=phi.dtype, device=phi.device)
    basis = torch.cat([torch.ones_like(phi)[:, None], torch.cos(phi[:, None] * k),
                       torch.sin(phi[:, None] * k)], 1)  # (N, 2K+1)
    N, F = basis.shape
    out = phi.new_zeros(N, 3, 3 * F)
    for c in range(3):
        out[:, c, c * F:(c + 1) * F] = basis
    return out.reshape(N * 3, 3 * F)
