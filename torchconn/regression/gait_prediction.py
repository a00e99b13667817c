"""What a fitted local model predicts for a *nearby* gait: displacement, cost, efficiency.

A :class:`~torchconn.regression.model.LocalConnectionModel` knows ``Â(φ)``, ``∂Â/∂r(φ)`` and
``M̂(φ)`` along its cycle ``γ(φ)``. For a gait ``γ'(θ)`` near the cycle, with ``φ = θ + φ₀`` (the
phase offset aligning the two loops) and ``δ = γ'(θ) − γ(φ)``, the first-order model of the
connection is

    A(γ') ≈ Â(φ) + ∂Â/∂r(φ) · δ,

and the body velocity ``ξ = A(γ') dγ'/dθ`` is integrated over one cycle with the same
fourth-order Magnus scheme as :func:`torchconn.physics.gaits.evaluate` (the reference on a
known system). The cost ``∫ √(γ'_θᵀ M̂(φ) γ'_θ) dθ`` uses the metric on the cycle (zeroth order
in ``δ``); the first-order term ``∂M̂/∂r(φ) · δ`` (``model.dM``) enters its standard error only
(:func:`_off_cycle_cost`).

Uncertainty comes from the model's per-bin standard errors: the bin estimates are redrawn with
their standard errors -- correlated between neighbouring bins as much as their phase windows
overlap -- the Fourier series refitted, and the prediction repeated per draw
(:func:`sample_models`). How far ``γ'`` leaves the data is given in radii of the tube the data
covered (``meta["tube_rms"]``, the per-joint RMS of the recorded offsets ``δ``).

The displacement's standard error: ``Â`` is drawn from its sampling factor across entries and
bins (each whole cycle's share of its error, ``bins.A_sampling_factor``), so the draws are as
narrow along the cycle's tangent as the error there, and, without detected noise, with an
allowance for the bias of ``Â`` (the tube's second order and the sampling interval,
``bins.A_bias_allowance``) drawn as one shared error. docs/validation/ gives how well these
standard errors cover the held-out errors.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .. import _linalg
from ..phase.fourier import fit_fourier
from ..physics.gaits.evaluate import gauss_cost, gauss_phases, magnus_displacement
from ..physics.gaits.gait import as_gait
from .binning import assign_bins

if TYPE_CHECKING:
    from .model import LocalConnectionModel

__all__ = ["GaitPrediction", "ExcursionWarning", "predict_gait", "predict_cycle", "sample_models",
           "align_phase", "best_shift", "tube_radius", "normal_quantile"]


class ExcursionWarning(UserWarning):
    """A gait leaves the tube the data covered: the local model extrapolates there."""


@dataclass(frozen=True)
class GaitPrediction:
    """One cycle of a gait as the local model predicts it (batch dims ``...`` of the model).

    Attributes:
        displacement: ``(..., 3)`` net displacement ``(x, y, θ)`` per cycle.
        displacement_se: ``(..., 3)`` its standard error from the model's standard errors.
        cost, cost_se: ``(...)`` cost ``∫√(ṙᵀM̂ṙ)dφ`` per cycle and its standard error, or None
            (a model without a metric).
        efficiency, efficiency_se: ``(...)`` ``|(x, y)| / cost`` and its standard error, or None.
        excursion: ``(...)`` largest ``|δ|`` along the gait in tube radii (NaN when the model
            does not know its tube).
        max_offset: ``(...)`` largest ``|δ| = |γ'(θ) − γ(θ + φ₀)|`` (rad).
        phase_offset: ``φ₀``, the model phase at the gait's ``θ = 0``.
        draws: ``(S, ..., 3)`` displacement under each redrawn model (``S = 0``: none).
    """

    displacement: Tensor
    displacement_se: Tensor
    cost: Tensor | None
    cost_se: Tensor | None
    efficiency: Tensor | None
    efficiency_se: Tensor | None
    excursion: Tensor
    max_offset: Tensor
    phase_offset: float
    draws: Tensor

    def interval(self, name: str = "displacement", level: float = 0.95) -> tuple[Tensor, Tensor]:
        """Normal ``level`` interval ``(low, high)`` of ``name`` (displacement, cost, efficiency)."""
        value, se = getattr(self, name), getattr(self, f"{name}_se")
        if value is None:
            raise ValueError(f"this prediction has no {name}: the model has no metric")
        z = normal_quantile(level)
        return value - z * se, value + z * se


def normal_quantile(level: float) -> float:
    """Two-sided standard normal quantile for a central ``level`` interval (0.95 -> 1.96)."""
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level!r}")
    return statistics.NormalDist().inv_cdf(0.5 + level / 2)


def tube_radius(model: "LocalConnectionModel") -> float | None:
    """RMS radius ``√Σⱼ rmsⱼ²`` of the tube of offsets the model was fitted to (rad), or None."""
    rms = (model.meta or {}).get("tube_rms")
    if rms is None:
        return None
    return float(math.sqrt(sum(v * v for v in rms)))


def align_phase(model: "LocalConnectionModel", gait, n_grid: int = 512) -> float:
    """The phase offset ``φ₀`` that best lays ``gait(θ)`` onto the model's cycle ``γ(θ + φ₀)``.

    Least squares over ``n_grid`` equispaced phases (all batch elements together), to within
    ``π / n_grid``.
    """
    gait = as_gait(gait)
    theta = torch.arange(n_grid, dtype=torch.float64, device=model.device) * (2 * math.pi / n_grid)
    cycle = model.gamma_at(theta.expand(model.batch_shape + (n_grid,)))  # (..., G, d)
    cycle = cycle.reshape(-1, n_grid, cycle.shape[-1]).mean(0)
    return float(theta[best_shift(cycle, gait(theta))])


def best_shift(cycle: Tensor, target: Tensor) -> int:
    """The shift ``s`` (in grid steps) that minimises ``Σ_j |target_j − cycle_(j+s mod G)|²`` for
    two closed curves sampled at the same ``G`` equispaced phases, ``(G, d)`` each: ``target(θ)``
    lies best on ``cycle(θ + 2πs/G)``."""
    # a circular cross-correlation, by FFT (the squared norms do not depend on the shift)
    cross = torch.fft.irfft(
        (torch.fft.rfft(cycle, dim=0) * torch.fft.rfft(target, dim=0).conj()).sum(-1),
        n=cycle.shape[0])
    return int(torch.argmax(cross))


def sample_models(
    model: "LocalConnectionModel", n_draws: int, *, seed: int = 0
) -> "LocalConnectionModel":
    """``n_draws`` models redrawn from the per-bin estimates and standard errors.

    Every bin estimate of ``Â``, ``∂Â/∂r`` (and ``M̂``) is perturbed by Gaussian noise with its
    standard error; bins whose phase windows overlap share samples, so their noise is correlated
    with the overlap of their kernel weights. Where the model keeps ``Â``'s sampling factor
    (``bins.A_sampling_factor``, a pooled noise-aware fit) ``Â``'s noise is drawn from it
    instead (``F z``, ``z`` standard normal of length ``R`` per draw): correlated across
    entries and bins as each whole cycle's share of the error is, so that ``Âγ̇``, which the
    displacement integrates and the data know better than the entries one by one, is drawn
    with its own spread; its bias allowance (``bins.A_bias_allowance``, not in ``A_se``) is
    added as one error shared by all entries and bins. These come from a stream of their own
    (``seed + 2``): ``∂Â/∂r``'s and ``M̂``'s draws are those of a model without them. The
    part of ``M̂``'s standard error that is its bias allowance (``bins.M_bias``) is drawn as
    one error shared by all entries and bins (``s · M_bias``, ``s`` standard normal per draw):
    drawn entry by entry, it would spread the on-cycle power that the gait pins down. Likewise
    the sampling noise of that bias estimate, where ``M_se`` holds it
    (``bins.M_change_factor``), is drawn from its
    covariance across entries and bins, and so is the fit's own sampling noise where the
    model keeps its factor (``bins.M_sampling_factor``): drawn entry by entry it would spread
    the on-cycle power that the gait pins down. The tube's second-order bias
    (``bins.M_offset_bias``, not in ``M_se``) is added as one more shared error. ``∂M̂/∂r``
    (``model.dM``) is not redrawn (:func:`predict_gait` adds its first-order change of the
    cost whole). The Fourier series are refitted at the model's order. The result has batch
    dims ``(n_draws, ...)``.
    """
    if not isinstance(n_draws, int) or n_draws < 1:
        raise ValueError(f"n_draws must be a positive integer, got {n_draws!r}")
    meta, bins = model.meta or {}, model.bins
    settings = meta.get("settings", {})
    kernel = settings.get("regression", settings).get("kernel", "box")
    # drawn on the model's device: CPU and CUDA draw different numbers from the same seed
    gen = torch.Generator(device=model.device).manual_seed(seed)
    centres = bins.phase

    def redraw(series, values, se, window, bias=None, factors=(), allowances=(), shared=gen,
               within=None):
        """``values`` drawn: the scatter ``se`` entry by entry (bins correlated by their
        windows' overlap; with ``within`` ``(..., M, *v[:-2], E, E)``, ``E`` the last two
        value dims' entries, those entries correlated by it in each bin) less what ``bias``
        and ``factors`` hold, which are drawn whole, and the ``allowances`` beyond ``se``; the
        shared draws come from ``shared``."""
        m = values.shape[len(model.batch_shape)]
        chol = _bin_noise_factor(m, window, kernel, values)
        factors = [f for f in factors if f is not None]
        if bias is not None or factors:
            # the scatter apart from the bias and the noise drawn whole below
            var = se.square()
            if bias is not None:
                var = var - bias.square()
            for factor in factors:
                var = var - torch.nan_to_num(factor).square().sum(-1)
            se = var.clamp(min=0).sqrt()
        moved = values.movedim(len(model.batch_shape), -1)  # (..., *v, M)
        z = torch.randn((n_draws,) + moved.shape, generator=gen, dtype=values.dtype,
                        device=values.device)
        u = (z @ chol.mT).movedim(-1, len(model.batch_shape) + 1)  # (S, ..., M, *v)
        if within is not None:
            # the same standard normals, correlated within each bin by the Cholesky factor of
            # ``within`` (the diagonal, and so each entry's spread, is unchanged)
            low, info = torch.linalg.cholesky_ex(torch.nan_to_num(within))
            eye = torch.eye(low.shape[-1], dtype=low.dtype, device=low.device)
            low = torch.where((info == 0)[..., None, None], low, eye)  # (not PD: entrywise)
            flat = u.flatten(-2)  # (S, ..., M, *v[:-2], E)
            u = (low @ flat.unsqueeze(-1)).squeeze(-1).unflatten(-1, u.shape[-2:])
        noisy = values + torch.nan_to_num(se) * u  # (S, ..., M, *v)
        # the bias, and allowances beyond se (the tube's second-order bias, the sampling
        # interval's): each one systematic error, shared by every entry and bin (its
        # covariance is the outer product of the error, not a diagonal), scaled by one
        # Gaussian per draw
        for one in (bias, *allowances):
            if one is not None:
                s = torch.randn((n_draws,) + (1,) * one.ndim, generator=shared,
                                dtype=values.dtype, device=values.device)
                noisy = noisy + s * torch.nan_to_num(one)
        for factor in factors:
            # noise correlated across entries and bins (the fit's, the bias estimate's): F z
            batch = factor.shape[:len(model.batch_shape)]
            z = torch.randn((n_draws,) + batch + (factor.shape[-1],), generator=shared,
                            dtype=values.dtype, device=values.device)
            z = z.reshape(z.shape[:-1] + (1,) * (factor.ndim - len(batch) - 1) + z.shape[-1:])
            noisy = noisy + (torch.nan_to_num(factor) * z).sum(-1)
        return fit_fourier(centres, noisy, series.order, value_ndim=series.value_ndim)

    window = meta.get("window") or 0.5
    # Â's drawn-whole parts from a stream of their own: ∂Â/∂r's and M̂'s draws stay those
    # of models without them
    gen_a = torch.Generator(device=model.device).manual_seed(seed + 2)
    A = redraw(model.A, bins.A, bins.A_se, window, factors=(bins.A_sampling_factor,),
               allowances=(bins.A_bias_allowance,), shared=gen_a)
    dA = redraw(model.dA, bins.dA, bins.dA_se, window, within=bins.dA_correlation)
    M = None
    if model.M is not None and bins.M is not None and bins.M_se is not None:
        M = redraw(model.M, bins.M, bins.M_se, meta.get("metric_window") or window,
                   bins.M_bias, (bins.M_change_factor, bins.M_sampling_factor),
                   (bins.M_offset_bias,))
    # draws of the Jacobian only (dA_fit, the prediction coefficient, is not drawn)
    return dataclasses.replace(model, A=A, dA=dA, M=M, dA_fit=None)


def _bin_noise_factor(n_bins: int, window: float, kernel: str, like: Tensor) -> Tensor:
    """Cholesky factor ``(M, M)`` of the correlation between bin estimates whose kernel windows
    overlap: ``C_mm' = Σ w_m w_m' / √(Σ w_m² Σ w_m'²)`` over uniformly spread phases (the
    correlation of two weighted means of the same i.i.d. samples); computed in float64 on
    ``like``'s device, returned in its dtype."""
    per_bin = 64
    kw = dict(dtype=torch.float64, device=like.device)
    grid = torch.arange(n_bins * per_bin, **kw) * (2 * math.pi / (n_bins * per_bin))
    idx = assign_bins(grid, n_bins, window=min(window, n_bins / 2 - 1e-9), kernel=kernel)
    dense = torch.zeros(n_bins, grid.shape[0], **kw)
    dense.scatter_add_(1, idx.index, idx.weight)
    gram = dense @ dense.T
    norm = gram.diagonal().sqrt()
    corr = gram / (norm[:, None] * norm[None, :])
    return _linalg.cholesky(corr + 1e-10 * torch.eye(n_bins, **kw), "the phase bins' overlap").to(like.dtype)


def predict_gait(
    model: "LocalConnectionModel",
    gait,
    *,
    phase_offset: float | None = None,
    n_steps: int = 128,
    n_draws: int = 64,
    seed: int = 0,
    warn_excursion: float = 2.0,
    max_excursion: float = 4.0,
) -> GaitPrediction:
    """Displacement, cost and efficiency per cycle of ``gait`` from the local model alone.

    Args:
        model: a fitted :class:`~torchconn.regression.model.LocalConnectionModel`.
        gait: a gait object or callable ``θ -> r`` over ``[0, 2π)`` with the model's joints.
        phase_offset: ``φ₀`` with ``φ = θ + φ₀``; None aligns the gait to the cycle
            (:func:`align_phase`). A gait built on the model's own phase (``γ + Δ``) has 0.
        n_steps: Magnus steps per cycle.
        n_draws: redrawn models for the standard errors (0: no uncertainty, se = NaN).
        seed: seed of the redraws.
        warn_excursion, max_excursion: in tube radii; past the first an
            :class:`ExcursionWarning`, past the second a ``ValueError``.
    """
    gait = as_gait(gait)
    d = model.shape_dim
    if gait.shape_dim != d:
        raise ValueError(f"gait has {gait.shape_dim} joints but the model has {d}")
    if model.dA is None or not bool(torch.isfinite(model.dA.coeffs).all()):
        raise ValueError(
            "predicting a nearby gait needs the model's shape derivative ∂Â/∂r (model.dA), but "
            "this model has none or a non-finite one; refit with the full connection regression"
        )
    if not 0 < warn_excursion <= max_excursion:
        raise ValueError(f"need 0 < warn_excursion <= max_excursion, got {warn_excursion!r}, "
                         f"{max_excursion!r}")
    if phase_offset is None:
        phase_offset = align_phase(model, gait)
    h, theta = gauss_phases(n_steps, device=model.device)
    theta = theta.reshape(-1)  # (2n,): series take (..., P) phases
    r, r_theta = gait(theta), gait.velocity(theta)  # (2n, d)
    phi = theta + phase_offset

    delta = r - model.gamma_at(phi.expand(model.batch_shape + phi.shape))
    offset = torch.linalg.vector_norm(delta, dim=-1).amax(-1)
    radius = tube_radius(model)
    excursion = offset / radius if radius else torch.full_like(offset, float("nan"))
    _check_excursion(excursion, offset, radius, warn_excursion, max_excursion)

    disp, cost = _integrate(model, phi, r_theta, delta, h, n_steps)
    draws = disp.new_zeros((0,) + disp.shape)
    nan = torch.full_like(disp, float("nan"))
    disp_se, cost_se, eff_se = nan, None, None
    if n_draws > 0:
        sampled = sample_models(model, n_draws, seed=seed)
        draws, cost_draws = _integrate(sampled, phi, r_theta, delta, h, n_steps)
        disp_se = draws.std(0)
        if cost_draws is not None and model.dM is not None:
            # the metric off the cycle: the first-order change of the cost, drawn whole
            cost_draws = cost_draws + _off_cycle_cost(model, phi, r_theta, delta, h, n_steps,
                                                      cost, n_draws, seed)
        if cost_draws is not None:
            cost_se = cost_draws.std(0)
            eff_se = _efficiency(draws, cost_draws).std(0)
    eff = None if cost is None else _efficiency(disp, cost)
    if cost is not None and cost_se is None:
        cost_se, eff_se = torch.full_like(cost, float("nan")), torch.full_like(cost, float("nan"))
    return GaitPrediction(
        displacement=disp, displacement_se=disp_se, cost=cost, cost_se=cost_se,
        efficiency=eff, efficiency_se=eff_se, excursion=excursion, max_offset=offset,
        phase_offset=float(phase_offset), draws=draws,
    )


def predict_cycle(
    model: "LocalConnectionModel", phi: Tensor, r: Tensor, r_theta: Tensor, n_steps: int,
    with_cost: bool = False,
) -> tuple[Tensor, Tensor | None]:
    """Differentiable core for gait optimisation: displacement ``(..., 3)`` and cost ``(...)``
    (None without ``with_cost`` or a metric) of shapes ``r`` and ``dr/dθ`` ``(2n, d)`` given at
    the model phases ``phi (2n,)`` -- :func:`gauss_phases` for ``n_steps``, flattened."""
    h = 2 * math.pi / n_steps
    delta = r - model.gamma_at(phi.expand(model.batch_shape + phi.shape))
    return _integrate(model, phi, r_theta, delta, h, n_steps, with_cost=with_cost)


def _integrate(model, phi, r_theta, delta, h, n_steps, with_cost: bool = True):
    a = model.connection(phi) + torch.einsum(
        "...kij,...j->...ki", model.connection_jacobian(phi), delta
    )
    xi = (a @ r_theta.unsqueeze(-1)).squeeze(-1)  # (..., 2n, 3)
    disp = magnus_displacement(xi.reshape(xi.shape[:-2] + (n_steps, 2, 3)), h)
    if not with_cost or model.M is None:
        return disp, None
    power = torch.einsum("...i,...ij,...j->...", r_theta, model.metric(phi), r_theta)
    return disp, gauss_cost(power.reshape(power.shape[:-1] + (n_steps, 2)), h)


def _off_cycle_cost(model, phi, r_theta, delta, h, n_steps, cost, n_draws, seed) -> Tensor:
    """``(S, ...)`` the cost's allowance for the metric off the cycle: ``s · Δ`` with ``Δ`` the
    change of the cost when ``M̂(φ)`` gets its first-order term ``∂M̂/∂r(φ) δ`` and ``s``
    standard normal per draw (from ``seed``, apart from :func:`sample_models`' stream).

    The prediction keeps ``M̂(φ)`` on the cycle; the first-order term's size enters only as
    an error."""
    power = torch.einsum("...i,...ij,...j->...", r_theta, model.metric_at(phi, delta), r_theta)
    change = gauss_cost(power.reshape(power.shape[:-1] + (n_steps, 2)), h) - cost
    gen = torch.Generator(device=model.device).manual_seed(seed + 1)
    s = torch.randn((n_draws,) + (1,) * change.ndim, generator=gen, dtype=change.dtype,
                    device=change.device)
    return s * change


def _efficiency(disp: Tensor, cost: Tensor) -> Tensor:
    return torch.linalg.vector_norm(disp[..., :2], dim=-1) / cost


def _check_excursion(excursion, offset, radius, warn_at, max_at) -> None:
    if radius is None:
        warnings.warn(
            "the model does not record the tube its data covered (meta['tube_rms']; models "
            "fitted by older versions): the gait's distance from the data is not checked",
            ExcursionWarning, stacklevel=3,
        )
        return
    worst = float(excursion.max())
    where = (f"the gait comes up to {float(offset.max()):.3g} rad from the fitted cycle, "
             f"{worst:.2f} tube radii (the data's RMS offset is {radius:.3g} rad)")
    if worst > max_at:
        raise ValueError(
            f"{where}: past max_excursion={max_at:g} the first-order local model is not "
            "trustworthy. Record a gait closer to this one, or raise max_excursion knowingly"
        )
    if worst > warn_at:
        warnings.warn(f"{where}: the local model extrapolates beyond the data",
                      ExcursionWarning, stacklevel=3)
