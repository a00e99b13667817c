"""One improvement step: the best nearby gait the local model can vouch for.

The proposal is ``γ'(φ) = γ̂(φ) + Δ(φ)``: the fitted cycle plus a change ``Δ``, a Fourier series
in the model's phase, bounded by a trust region ``max_φ |Δ(φ)| ≤ ρ``. ``ρ`` defaults to a multiple
of the tube radius the data covered (the first-order model is fitted there), so noisier data --
a wider tube -- allows longer steps, and the predicted gain comes with the interval the model's
standard errors give (:func:`torchconn.regression.gait_prediction.sample_models`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .._checks import check_value
from ..phase.fourier import FourierSeries
from ..physics.gaits.evaluate import gauss_phases
from ..physics.gaits.gait import FourierGait
from ..regression.gait_prediction import (
    GaitPrediction,
    normal_quantile,
    predict_cycle,
    predict_gait,
    sample_models,
    tube_radius,
)
from ..regression.model import LocalConnectionModel

__all__ = ["OBJECTIVES", "TrustRegion", "Proposal", "propose_gait", "objective_value",
           "penalised_objective", "check_trust_region"]

#: what a proposal maximises: |(x, y)| per cycle, |(x, y)| / cost, |θ| per cycle
OBJECTIVES = ("displacement", "efficiency", "turning")


@dataclass(frozen=True, kw_only=True)
class TrustRegion:
    """Where a proposal may go.

    Attributes:
        radius: largest change ``max_φ |Δ(φ)|`` (rad); None: ``scale`` tube radii.
        scale: the trust radius in tube radii when ``radius`` is None.
        order: Fourier order of the change ``Δ``.
        shape_bound: every shape of the proposal keeps ``|r| ≤ shape_bound`` (rad; joint limits,
            None: unbounded). π keeps a 3-link loop within the joint limits the gait optimiser
            uses, and a 9-link within its modal radius π/2 (``|r| = 2 × modal radius``).
        max_turn: for the displacement and efficiency objectives, the net rotation per cycle
            a proposal may have (rad, None: any). Without it ``|(x, y)|`` per cycle is maximised by
            gaits that also turn (the chord of a screw motion), which make no progress over
            many cycles; 0.05 rad (3°) per cycle keeps proposals going straight.
        steps, lr: projected Adam ascent (step ``lr × radius``).
    """

    radius: float | None = None
    scale: float = 2.0
    order: int = 3
    shape_bound: float | None = math.pi
    max_turn: float | None = 0.05
    steps: int = 200
    lr: float = 0.02

    def __post_init__(self) -> None:
        for name, tp, bounds in (("radius", float | None, {"gt": 0}), ("scale", float, {"gt": 0}),
                                 ("order", int, {"ge": 0}), ("shape_bound", float | None,
                                                             {"gt": 0}),
                                 ("max_turn", float | None, {"ge": 0}), ("steps", int, {"ge": 1}),
                                 ("lr", float, {"gt": 0})):
            check_value(f"TrustRegion.{name}", getattr(self, name), tp, bounds)

    def radius_for(self, model: LocalConnectionModel) -> float:
        """The trust radius (rad) for ``model``."""
        if self.radius is not None:
            return float(self.radius)
        tube = tube_radius(model)
        if tube is None:
            raise ValueError(
                "the model does not record its tube (meta['tube_rms']): pass "
                "TrustRegion(radius=...) in rad"
            )
        return self.scale * tube


@dataclass(frozen=True)
class Proposal:
    """The next gait to try, with what the model predicts for it.

    Attributes:
        gait: the proposed gait, a :class:`FourierGait` in the model's phase.
        objective: one of :data:`OBJECTIVES`.
        current: the objective of the fitted cycle (model).
        predicted: ``current + gain``.
        gain, gain_se: ``predicted − current`` and its standard error (model draws; the two
            predictions share the model, so their common errors cancel). The ascent also
            follows the model's errors, so the gain of its own optimum is biased high; no
            correction is applied here (the loop's intervals carry the over-prediction it
            observes, :class:`~torchconn.improve.loop.LoopSettings`).
        radius, step: the trust radius and the largest change ``max_φ |Δ|`` taken (rad).
        prediction: the model's :class:`GaitPrediction` of the proposal.
    """

    gait: FourierGait
    objective: str
    current: float
    predicted: float
    gain: float
    gain_se: float
    radius: float
    step: float
    prediction: GaitPrediction

    def gain_interval(self, level: float = 0.95) -> tuple[float, float]:
        z = normal_quantile(level)
        return self.gain - z * self.gain_se, self.gain + z * self.gain_se


def objective_value(objective: str, displacement: Tensor, cost: Tensor | None) -> Tensor:
    """The objective from a displacement ``(..., 3)`` and cost ``(...)``: ``(...)``."""
    planar = torch.linalg.vector_norm(displacement[..., :2], dim=-1)
    if objective == "displacement":
        return planar
    if objective == "turning":
        return displacement[..., 2].abs()
    if objective == "efficiency":
        if cost is None:
            raise ValueError("objective 'efficiency' needs a cost, i.e. the model's metric M̂")
        return planar / cost
    raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")


def penalised_objective(value: Tensor, displacement: Tensor, shapes: Tensor, objective: str,
                        trust_region: TrustRegion) -> Tensor:
    """``value (...)`` of a gait less the penalties of ``trust_region``'s constraints.

    ``displacement (..., 3)`` is the gait's displacement per cycle and ``shapes (..., n, d)`` its
    shapes at ``n`` phases. Turning more than ``max_turn`` rad per cycle costs
    ``10³ · (|θ| − max_turn)²`` (not for the ``"turning"`` objective), leaving ``|r| ≤ shape_bound``
    costs ``10³`` times the mean over the phases of the squared excess.
    """
    f = value
    if trust_region.max_turn is not None and objective != "turning":
        f = f - 1e3 * torch.relu(displacement[..., 2].abs() - trust_region.max_turn).pow(2)
    if trust_region.shape_bound is not None:
        excess = torch.relu(torch.linalg.vector_norm(shapes, dim=-1) - trust_region.shape_bound)
        f = f - 1e3 * excess.pow(2).mean(-1)
    return f


def propose_gait(
    model: LocalConnectionModel,
    objective: str = "displacement",
    trust_region: TrustRegion | None = None,
    *,
    n_steps: int = 128,
    n_draws: int = 64,
    seed: int = 0,
) -> Proposal:
    """Maximise the model's predicted ``objective`` over gaits within the trust region.

    Args:
        model: a fitted model without batch dims (fit with ``pool=True``, or pick one trial).
        objective: ``"displacement"`` (``|(x, y)|`` per cycle), ``"efficiency"`` (``|(x, y)| / cost``;
            needs the metric, i.e. recordings with a ``power`` column) or ``"turning"`` (``|θ|``).
        trust_region: a :class:`TrustRegion` (default: 2 tube radii, order-3 change, ``|r| ≤ π``).
        n_steps: Magnus steps per cycle; n_draws, seed: redrawn models for the gain's interval
            (batched).

    Raises:
        ValueError: an unknown objective; efficiency without a metric; a batched model; a model
            without ``∂Â/∂r``.
    """
    tr = _checked_trust_region(model, objective, trust_region)
    search = _ChangeSearch(model, objective, tr, n_steps, seed)
    u = search.ascend(model)
    delta = search.change(u)
    proposal = _shifted_gait(model, delta)
    step = float(torch.linalg.vector_norm(delta(search.grid), dim=-1).amax())

    current = float(search.predicted(model, None)[0])
    gain, gain_se = float(search.predicted(model, u)[0]) - current, float("nan")
    if n_draws > 0:
        sampled = sample_models(model, n_draws, seed=seed)
        gain_se = float((search.predicted(sampled, u)[0] - search.predicted(sampled, None)[0]).std())
    prediction = predict_gait(model, proposal, phase_offset=0.0, n_steps=n_steps,
                              n_draws=n_draws, seed=seed, warn_excursion=math.inf,
                              max_excursion=math.inf)
    return Proposal(
        gait=proposal, objective=objective, current=current, predicted=current + gain,
        gain=gain, gain_se=gain_se, radius=search.radius, step=step,
        prediction=prediction,
    )


def _checked_trust_region(model: LocalConnectionModel, objective: str,
                          trust_region: TrustRegion | None) -> TrustRegion:
    """The trust region (default :class:`TrustRegion()`), after checking that ``model`` and
    ``objective`` admit a proposal (a known objective, a metric for efficiency, one model, a
    finite ``∂Â/∂r``)."""
    tr = TrustRegion() if trust_region is None else trust_region
    if not isinstance(tr, TrustRegion):
        raise TypeError(f"trust_region must be a TrustRegion, got {type(tr).__name__}")
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    if objective == "efficiency" and model.M is None:
        raise ValueError(
            "objective 'efficiency' needs the metric M̂, and this model has none: record a "
            "'power' column (see the data format) and fit with metric=True"
        )
    if len(model.batch_shape):
        raise ValueError(
            f"propose_gait needs one model, got batch dims {tuple(model.batch_shape)}: fit with "
            "ConnectionEstimator(pool=True) or pick one trial, model[i]"
        )
    if model.dA is None or not bool(torch.isfinite(model.dA.coeffs).all()):
        raise ValueError("propose_gait needs the model's shape derivative ∂Â/∂r (model.dA), "
                         "but it is missing or non-finite")
    return tr


class _ChangeSearch:
    """The search over changes ``Δ`` of the fitted cycle ``γ̂`` of ``model``: the change's
    coefficients ``u (..., 2k+1, d)``, scaled into the trust radius, and the predicted,
    penalised objective of ``γ̂ + Δ(u)`` under any model of the same shape space.

    Attributes:
        radius: the trust radius (rad).
        grid: 256 phases on ``[0, 2π)`` where the change's peak is taken.
    """

    def __init__(self, model: LocalConnectionModel, objective: str, tr: TrustRegion,
                 n_steps: int, seed: int) -> None:
        self.objective, self.tr, self.n_steps = objective, tr, n_steps
        self.radius = tr.radius_for(model)
        self.with_cost = objective == "efficiency"
        h, theta = gauss_phases(n_steps, device=model.device)
        self.theta = theta.reshape(-1)
        base = FourierGait(model.gamma.coeffs.detach())
        self.base_r, self.base_v = base(self.theta), base.velocity(self.theta)
        kw = dict(dtype=torch.float64, device=model.device)
        self.grid = torch.arange(256, **kw) * (2 * math.pi / 256)
        gen = torch.Generator(device=model.device).manual_seed(seed)
        self.init = 1e-3 * torch.randn(2 * tr.order + 1, model.shape_dim, generator=gen, **kw)

    def change(self, u: Tensor) -> FourierSeries:
        """The change ``Δ`` of coefficients ``u (..., 2k+1, d)``, scaled into the trust region."""
        peak = torch.linalg.vector_norm(FourierSeries(u, value_ndim=1)(self.grid),
                                        dim=-1).amax(-1)
        return FourierSeries(u * torch.clamp(self.radius / peak, max=1.0)[..., None, None],
                             value_ndim=1)

    def predicted(self, m: LocalConnectionModel, u: Tensor | None) -> tuple[Tensor, Tensor]:
        """Objective ``(...)`` and displacement ``(..., 3)`` of ``γ̂ + Δ(u)`` under ``m``."""
        r, v = self.base_r, self.base_v
        if u is not None:
            delta = self.change(u)
            r, v = r + delta(self.theta), v + delta.derivative()(self.theta)
        disp, cost = predict_cycle(m, self.theta, r, v, self.n_steps, self.with_cost)
        return objective_value(self.objective, disp, cost), disp

    def penalised(self, m: LocalConnectionModel, u: Tensor) -> Tensor:
        """The predicted objective ``(...)`` less the turning and joint-limit penalties."""
        f, disp = self.predicted(m, u)
        return penalised_objective(f, disp, self.base_r + self.change(u)(self.theta),
                                   self.objective, self.tr)

    def ascend(self, m: LocalConnectionModel) -> Tensor:
        """Projected Adam ascent of ``m``'s objective over the change. The step length decays
        linearly to a tenth, and the best iterate is kept: the penalties (joint limits, turning)
        make the ascent oscillate, and the start (no change) is always a candidate."""
        tr = self.tr
        u = self.init.clone().requires_grad_(True)
        opt = torch.optim.Adam([u], lr=tr.lr * self.radius)
        sched = torch.optim.lr_scheduler.LambdaLR(
            opt, lambda i: 1 - 0.9 * i / max(tr.steps, 1))
        zero = torch.zeros_like(u)
        best_u, best_f = zero, self.penalised(m, zero).detach()
        for _ in range(tr.steps):
            opt.zero_grad()
            f = self.penalised(m, u)
            better = f.detach() > best_f
            best_f = torch.where(better, f.detach(), best_f)
            best_u = torch.where(better, u.detach(), best_u)
            (-f).backward()
            opt.step()
            sched.step()
        f = self.penalised(m, u).detach()
        return torch.where(f > best_f, u.detach(), best_u)


def _shifted_gait(model: LocalConnectionModel, delta: FourierSeries) -> FourierGait:
    """The gait ``γ̂ + Δ``: the model's cycle coefficients plus the change's, zero-padded to
    the higher of the two orders."""
    coeffs = model.gamma.coeffs.detach().clone()
    pad = delta.coeffs
    if pad.shape[0] > coeffs.shape[0]:
        coeffs = torch.cat([coeffs, coeffs.new_zeros(pad.shape[0] - coeffs.shape[0], coeffs.shape[1])])
    coeffs[: pad.shape[0]] += pad
    return FourierGait(coeffs)


def check_trust_region(model: LocalConnectionModel, gait, trust_region: TrustRegion,
                       *, phase_offset: float | None = 0.0) -> float:
    """The largest change ``max_φ |γ'(φ) − γ̂(φ + φ₀)|`` of ``gait`` from the model's cycle (rad);
    raises ``ValueError`` when it exceeds the trust radius (e.g. a hand-edited proposal).

    ``phase_offset``: ``φ₀`` (0 for gaits in the model's phase, None to align them).
    """
    pred = predict_gait(model, gait, phase_offset=phase_offset, n_draws=0,
                        warn_excursion=math.inf, max_excursion=math.inf)
    radius = trust_region.radius_for(model)
    step = float(pred.max_offset.max())
    if step > radius * (1 + 1e-6):
        raise ValueError(
            f"the gait leaves the trust region: it comes {step:.3g} rad from the fitted cycle, "
            f"the trust radius is {radius:.3g} rad; the model's prediction does not cover it. "
            "Take a shorter step, or record this gait first"
        )
    return step
