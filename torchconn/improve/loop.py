"""The loop on a simulator: record → fit → propose → record the proposal → …

Every round records ``trials × cycles`` of the current gait with the paper's SDE (α, η) and the
observation model (ω), estimates its objective from the recordings alone, fits a pooled local
model and proposes the next gait (:func:`~torchconn.improve.propose.propose_gait`). The
proposal's predicted objective is the *observed* objective of the current gait plus the model's
predicted gain (the model's errors common to both gaits cancel in the gain), less the model's
over-prediction, which grows with the step and is learned from the steps taken; the interval
holds both standard errors and that over-prediction's spread. The trust region
adapts: it grows when a step's observed gain is near the predicted one, shrinks when far below,
and a proposal whose recording scores worse than its start by more than the noise is
rejected -- the loop returns to the previous gait and proposes again with half the radius.
The simulator's exact objective of every gait (:func:`torchconn.physics.gaits.evaluate`) is
recorded for judging, never used by the loop.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from .._checks import check_value
from .._cli import resolve_device
from ..physics.gaits.evaluate import evaluate
from ..physics.gaits.gait import FourierGait, as_gait
from ..physics.systems.base import LocomotionSystem
from ..regression.defaults import POOLED
from ..regression.estimator import estimator_from_settings
from ..regression.gait_prediction import normal_quantile
from ..simulation import observe, simulate
from .measure import measure_cycles
from .propose import OBJECTIVES, TrustRegion, objective_value, propose_gait

__all__ = ["LoopSettings", "Round", "LoopResult", "improve", "circle_gait", "true_objective",
           "gait_order"]


def circle_gait(shape_dim: int, radius: float = 0.5, direction: int = -1) -> FourierGait:
    """A start gait: a circle of ``radius`` about the straight shape.

    For 2 joints ``r = radius (cos φ, direction · sin φ)``; for ``d > 2`` joints the travelling
    wave ``r_k = radius · sin(φ + direction · 2πk/d)``, k = 1..d (for 8 joints the circle of that
    radius in the 9-link's two-mode plane). ``direction = −1`` swims towards +x for the swimmers
    of docs/conventions.md.
    """
    if direction not in (1, -1):
        raise ValueError(f"direction must be +1 or -1, got {direction!r}")
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius!r}")
    coeffs = torch.zeros(3, shape_dim, dtype=torch.float64)
    if shape_dim == 2:
        coeffs[1, 0], coeffs[2, 1] = radius, direction * radius
    else:
        k = torch.arange(1, shape_dim + 1, dtype=torch.float64)
        lag = -direction * 2 * math.pi * k / shape_dim
        # sin(φ − lag) = cos(lag) sin φ − sin(lag) cos φ
        coeffs[1], coeffs[2] = -radius * torch.sin(lag), radius * torch.cos(lag)
    return FourierGait(coeffs)


def true_objective(system: LocomotionSystem, gait, objective: str, n_steps: int = 256) -> float:
    """The simulator's exact objective of ``gait`` (:func:`gaits.evaluate`), for judging."""
    m = evaluate(system, gait, n_steps)
    return float(objective_value(objective, m.displacement, m.cost))


@dataclass(frozen=True, kw_only=True)
class LoopSettings:
    """Settings of :func:`improve`.

    Attributes:
        rounds: K rounds (each records one gait, then proposes the next).
        trials, cycles: recordings per round (``trials × cycles`` recorded cycles).
        eta, alpha: the shape SDE (the paper's η = 0.025, α = 0.05).
        omega: observation noise on every recorded pose and joint sample.
        objective: see :data:`~torchconn.improve.propose.OBJECTIVES`.
        trust_region: the first round's trust region; ``scale`` then adapts.
        grow, shrink, good_ratio, poor_ratio, max_scale, min_scale: trust-radius adaptation
            (in tube radii): the radius grows when the observed gain of a step is more than
            ``good_ratio`` of the predicted one, shrinks below ``poor_ratio`` or when the
            recording scores worse than its start by more than the noise (rejected).
        truncation, truncation_spread: prior mean and spread of the model's over-prediction
            of a gain per rad of step, in units of the first proposal's predicted gain (so the
            first step's prior is ``truncation × step × gain``; default 0.5 per rad). The
            over-prediction grows with the step: as step² from the
            first-order model's truncation, as the step from its errors in ``∂Â/∂r``, which
            the ascent follows (the optimiser's curse: largest near an optimum, where the true
            gain vanishes and the predicted one does not). Every informative step
            (predicted gain above twice the noise of the observed gains) adds its own
            ``(predicted − observed gain) / step``, each prior counting as one step; the mean
            corrects the next predicted gain, the spread widens its interval.
        level: central level of the prediction intervals.
        estimator: the estimator's settings table (:func:`estimator_from_settings`) for the
            pooled fit each round (default: the noise-aware regression).
        seed: root seed (per-round seeds from ``numpy.random.SeedSequence``).
        device: where the recordings are simulated and the models fitted (``cpu``, ``cuda``,
            ``cuda:N``); CPU and CUDA draw different random numbers from the same seed.
    """

    rounds: int = 8
    trials: int = 4
    cycles: int = 20
    eta: float = 0.025
    alpha: float = 0.05
    omega: float = 0.0
    objective: str = "displacement"
    trust_region: TrustRegion = field(default_factory=lambda: TrustRegion(scale=3.0))
    grow: float = 1.5
    shrink: float = 0.5
    good_ratio: float = 0.75
    poor_ratio: float = 0.25
    max_scale: float = 4.5
    min_scale: float = 0.5
    truncation: float = 0.5
    truncation_spread: float = 1.0
    level: float = 0.95
    estimator: dict = field(default_factory=lambda: {**POOLED,
                                                      "regression": {"method": "noise_aware"}})
    seed: int = 0
    device: str = "cpu"

    def __post_init__(self) -> None:
        resolve_device(self.device, "LoopSettings.device")
        for name in ("rounds", "trials", "cycles"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"LoopSettings.{name} must be a positive integer, got {value!r}")
        for name, bounds in (("eta", {"ge": 0}), ("alpha", {"gt": 0}), ("omega", {"ge": 0}),
                             ("grow", {"ge": 1}), ("shrink", {"gt": 0, "le": 1}),
                             ("good_ratio", {}), ("poor_ratio", {}), ("max_scale", {"gt": 0}),
                             ("min_scale", {"gt": 0}), ("truncation", {"ge": 0}),
                             ("truncation_spread", {"ge": 0}), ("level", {"gt": 0})):
            check_value(f"LoopSettings.{name}", getattr(self, name), float, bounds)
        if not self.level < 1:
            raise ValueError(f"LoopSettings.level must be < 1, got {self.level!r}")
        if not self.poor_ratio <= self.good_ratio:
            raise ValueError(f"LoopSettings.poor_ratio ({self.poor_ratio}) must be <= good_ratio "
                             f"({self.good_ratio})")
        check_value("LoopSettings.seed", self.seed, int, {"ge": 0})
        if self.objective not in OBJECTIVES:
            raise ValueError(f"LoopSettings.objective must be one of {', '.join(OBJECTIVES)}, "
                             f"got {self.objective!r}")
        if not isinstance(self.trust_region, TrustRegion):
            raise TypeError(f"LoopSettings.trust_region must be a TrustRegion, got "
                            f"{type(self.trust_region).__name__}")
        if not estimator_from_settings(self.estimator, where="LoopSettings.estimator").pool:
            raise ValueError("LoopSettings.estimator must pool the trials (pool=True): a "
                             "proposal needs one model")
        if not (0 < self.min_scale <= self.trust_region.scale <= self.max_scale):
            raise ValueError("need min_scale <= trust_region.scale <= max_scale")


def gait_order(settings: LoopSettings) -> int:
    """The Fourier order per joint of the loop's proposals under ``settings``: the fitted
    cycle's order (the estimator's ``cycle.order``) or the change's (``trust_region.order``),
    whichever is higher -- a proposal is the fitted cycle plus the change."""
    cycle = estimator_from_settings(settings.estimator, where="LoopSettings.estimator").cycle
    return max(int(cycle.order), settings.trust_region.order)


@dataclass(frozen=True)
class Round:
    """One round of the loop.

    Attributes:
        index: round number (0 records the start gait).
        cycles_used: recorded cycles so far, this round's included.
        gait: the gait recorded this round.
        observed, observed_se: its objective estimated from the recordings, and its standard
            error.
        true: its exact objective (simulator, for judging only).
        accepted: False when the recording scored worse than the gait it was proposed from
            (by more than the noise); the loop then proposed again from that gait.
        scale: trust radius (tube radii) used for this round's proposal.
        step: the proposal's largest change ``max_φ |Δ|`` from the fitted cycle (rad).
        proposal: the gait proposed from this round's base gait.
        predicted, predicted_low, predicted_high: the proposal's predicted objective (observed
            base + model gain) and interval.
        model_predicted: the model's own prediction of the proposal's objective.
        gain, gain_se: the model's predicted gain (selection-bias corrected, before the
            truncation correction) and its standard error.
        realised: the proposal's exact objective (simulator).
    """

    index: int
    cycles_used: int
    gait: FourierGait
    observed: float
    observed_se: float
    true: float
    accepted: bool
    scale: float
    step: float
    proposal: FourierGait
    predicted: float
    predicted_low: float
    predicted_high: float
    model_predicted: float
    gain: float
    gain_se: float
    realised: float

    @property
    def covered(self) -> bool:
        return self.predicted_low <= self.realised <= self.predicted_high

    def as_row(self) -> dict:
        """The JSON/CSV row (no gaits)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if f.name not in ("gait", "proposal")} | {"covered": self.covered}


@dataclass(frozen=True)
class LoopResult:
    """The rounds of one loop, the start gait's exact objective and the best accepted gait."""

    rounds: tuple[Round, ...]
    start_true: float
    settings: LoopSettings

    @property
    def best(self) -> Round:
        return max((r for r in self.rounds if r.accepted), key=lambda r: r.observed)

    @property
    def coverage(self) -> float:
        return float(np.mean([r.covered for r in self.rounds]))


def _record(system, gait, s: LoopSettings, seed: np.random.SeedSequence):
    seeds = seed.generate_state(2 * s.trials, dtype=np.uint32).astype(np.int64)
    eta = torch.tensor(s.eta, dtype=torch.float64, device=s.device)  # sets the device
    traj = simulate(system, gait, eta=eta, alpha=s.alpha, n_cycles=s.cycles,
                    seeds=seeds[: s.trials])
    if s.omega > 0:
        traj = observe(traj, s.omega, seeds=seeds[s.trials:])
    return traj


def improve(system: LocomotionSystem, start, settings: LoopSettings | None = None,
            *, progress=None) -> LoopResult:
    """Run the improvement loop on a simulator from the ``start`` gait.

    Args:
        system: the simulator (e.g. ``NLinkSwimmer(3)``).
        start: the start gait (gait object or callable ``φ -> r``).
        settings: :class:`LoopSettings`.
        progress: optional callable ``(Round) -> None`` called after each round.
    """
    s = LoopSettings() if settings is None else settings
    start = as_gait(start)
    if start.shape_dim != system.shape_dim:
        raise ValueError(f"start gait has {start.shape_dim} joints, the system {system.shape_dim}")
    seeds = np.random.SeedSequence(s.seed).spawn(s.rounds)
    z = normal_quantile(s.level)
    scale = s.trust_region.scale
    gait, rounds, base, errors, first_gain = start, [], None, [], None
    for k in range(s.rounds):
        traj = _record(system, gait, s, seeds[k])
        meas, meas_se = measure_cycles(traj).objective(s.objective)
        accepted = True
        if base is not None:
            # the trust-region test: observed against predicted gain, both from data
            predicted_gain, observed_gain = base["gain"], meas - base["observed"]
            ratio = observed_gain / predicted_gain if predicted_gain > 0 else 0.0
            if meas < base["observed"] - z * math.hypot(meas_se, base["observed_se"]):
                accepted = False
            noise = math.hypot(meas_se, base["observed_se"])
            if predicted_gain > 2 * noise and base["step"] > 0:
                # an informative step (its gain stands out of the measurement noise): its
                # over-prediction per rad of step
                errors.append((predicted_gain - observed_gain) / base["step"])
            if not accepted or ratio < s.poor_ratio:
                scale = max(scale * s.shrink, s.min_scale)
            elif ratio > s.good_ratio:
                scale = min(scale * s.grow, s.max_scale)
        if accepted:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # e.g. no power channel: metric not estimated
                model = estimator_from_settings(s.estimator).fit(traj).model_
            base = {"model": model, "observed": meas, "observed_se": meas_se, "gait": gait}
        tr = dataclasses.replace(s.trust_region, scale=scale)
        prop = propose_gait(base["model"], s.objective, tr, seed=k)
        # The over-prediction grows with the step: learned per rad of step, each prior
        # (scaled by the first proposal's gain) worth one step taken.
        if first_gain is None:
            first_gain = abs(prop.gain)
        n = 1 + len(errors)
        bias = (s.truncation * first_gain + sum(errors)) / n
        spread = math.sqrt(((s.truncation_spread * first_gain) ** 2
                            + sum((e - bias) ** 2 for e in errors)) / n)
        gain = prop.gain - bias * prop.step
        predicted = base["observed"] + gain
        half = z * math.sqrt(base["observed_se"] ** 2 + prop.gain_se ** 2
                             + (spread * prop.step) ** 2)
        base.update(gain=prop.gain, step=prop.step)
        rnd = Round(
            index=k, cycles_used=(k + 1) * s.trials * s.cycles, gait=gait, observed=meas,
            observed_se=meas_se, true=true_objective(system, gait, s.objective),
            accepted=accepted, scale=scale, step=prop.step, proposal=prop.gait,
            predicted=predicted,
            predicted_low=predicted - half, predicted_high=predicted + half,
            model_predicted=prop.predicted, gain=prop.gain, gain_se=prop.gain_se,
            realised=true_objective(system, prop.gait, s.objective),
        )
        rounds.append(rnd)
        if progress is not None:
            progress(rnd)
        gait = prop.gait
    return LoopResult(tuple(rounds), true_objective(system, start, s.objective), s)
