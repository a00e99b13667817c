"""The loop on a simulator: record a few cycles → model → propose → record the proposal → …

Every step records ``trials × cycles`` of one commanded gait with the paper's SDE (α, η) and the
observation model (ω), phased by the gait clock the loop commands. The model is one regression
over *every* recording so far, weighted by each recording's distance from the current gait
(:class:`~torchconn.improve.pooled.PooledConnection`): the tube widens as the loop moves and a
new recording of the current gait is an online update of the sums. After every recording the
loop proposes (:func:`~torchconn.improve.propose.propose_gait`) and moves to the proposal only
when the prediction interval of its gain excludes zero; otherwise it records the current gait
again, perturbed along the shape directions where ``∂Â/∂r`` is least known (deliberate
excitation, within the trust radius).

A proposal's predicted objective is the *observed* objective of the current gait plus the
model's gain, less the over-prediction learnt from the steps taken (it grows as the step²); the
interval holds both standard errors and that over-prediction's spread. The trust region adapts:
it grows when a step's observed gain is near the predicted one, shrinks when far below, and a
proposal whose recording scores worse than its start, or turns more than the turning limit, by
more than the noise is rejected -- the loop keeps the previous gait (the rejected recording
stays in the pooled data) and proposes again with a smaller radius. The simulator's exact
objective of every gait (:func:`torchconn.physics.gaits.evaluate`) is recorded for judging,
never used by the loop.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .._checks import check_value
from .._cli import resolve_device
from ..phase.fourier import fit_fourier
from ..physics.gaits.evaluate import evaluate
from ..physics.gaits.gait import FourierGait, as_gait
from ..physics.systems.base import LocomotionSystem
from ..regression.gait_prediction import normal_quantile
from ..regression.model import LocalConnectionModel
from ..simulation import observe, simulate
from ..trajectory import Trajectory
from .measure import measure_cycles
from .pooled import PooledConnection, gait_recording
from .propose import OBJECTIVES, TrustRegion, objective_value, penalised_objective, propose_gait

__all__ = ["LoopSettings", "Round", "LoopResult", "improve", "circle_gait", "true_objective",
           "gait_order", "excitation_gait", "true_score", "MIN_CYCLES", "LOOP_OBJECTIVES"]

#: the objectives the loop can improve (efficiency needs the metric, which its pooled model
#: does not estimate)
LOOP_OBJECTIVES = ("displacement", "turning")
#: the fewest cycles a recording may hold: two whole periods to measure its objective
MIN_CYCLES = 3
#: the trust radii a step is chosen from, as fractions of the current one
_STEP_FRACTIONS = (1.0, 0.5, 0.25)


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
        rounds: K recordings (each records one gait, then proposes).
        trials, cycles: one recording is ``trials × cycles`` cycles of one gait (``cycles ≥ 3``:
            two whole periods to measure).
        eta, alpha: the shape SDE (the paper's η = 0.025, α = 0.05).
        omega: observation noise on every recorded pose and joint sample.
        objective: see :data:`~torchconn.improve.propose.OBJECTIVES`.
        trust_region: the first proposal's trust region; ``scale`` then adapts.
        grow, shrink, good_ratio, poor_ratio, max_scale, min_scale: trust-radius adaptation
            (in tube radii): the radius grows when the observed gain of a step is more than
            ``good_ratio`` of the predicted one, shrinks below ``poor_ratio`` or when the
            recording scores worse than its start by more than the noise (rejected).
        truncation, truncation_spread: prior mean and spread of the model's over-prediction
            of a gain per rad² of step, in units of the first proposal's predicted gain (so the
            first step's prior is ``truncation × step² × gain``). The over-prediction grows
            with the step: as step² from the first-order model's truncation, and the ascent
            follows the model's errors in ``∂Â/∂r``. Every informative step (predicted gain
            above twice the noise of the observed gains, within the limits) adds its own
            ``(predicted − observed gain) / step²``, the prior counting as one step; the mean
            corrects the next predicted gain, the spread widens its interval.
        level: central level of the prediction intervals; the loop moves to a proposal when
            the interval of its gain lies above zero.
        pool_length: ``ℓ`` (rad) of the pooled model: a recording ``D`` rad (rms) from the
            current gait is weighted ``exp(−½ (D/ℓ)²)``
            (:class:`~torchconn.improve.pooled.PooledConnection`); None weights all alike.
        excitation: where a proposal's gain interval includes zero, the next recording of
            the current gait is perturbed by a first harmonic of peak ``excitation ×
            trust_region.scale`` tube radii (rad; the first trust radius, however far the
            radius has shrunk since) along the joints where ``∂Â/∂r`` is least known; 0: no
            perturbation.
        seed: root seed (per-recording seeds from ``numpy.random.SeedSequence``).
        device: where the recordings are simulated and the models fitted (``cpu``, ``cuda``,
            ``cuda:N``); CPU and CUDA draw different random numbers from the same seed.
    """

    rounds: int = 15
    trials: int = 1
    cycles: int = 3
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
    pool_length: float | None = 0.5
    excitation: float = 0.5
    seed: int = 0
    device: str = "cpu"

    def __post_init__(self) -> None:
        resolve_device(self.device, "LoopSettings.device")
        for name in ("rounds", "trials", "cycles"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"LoopSettings.{name} must be a positive integer, got {value!r}")
        if self.cycles < MIN_CYCLES:
            raise ValueError(f"LoopSettings.cycles must be at least {MIN_CYCLES} (two whole "
                             f"periods to measure a gait), got {self.cycles!r}")
        for name, bounds in (("eta", {"ge": 0}), ("alpha", {"gt": 0}), ("omega", {"ge": 0}),
                             ("grow", {"ge": 1}), ("shrink", {"gt": 0, "le": 1}),
                             ("good_ratio", {}), ("poor_ratio", {}), ("max_scale", {"gt": 0}),
                             ("min_scale", {"gt": 0}), ("truncation", {"ge": 0}),
                             ("truncation_spread", {"ge": 0}), ("level", {"gt": 0}),
                             ("excitation", {"ge": 0, "le": 1})):
            check_value(f"LoopSettings.{name}", getattr(self, name), float, bounds)
        check_value("LoopSettings.pool_length", self.pool_length, float | None, {"gt": 0})
        if not self.level < 1:
            raise ValueError(f"LoopSettings.level must be < 1, got {self.level!r}")
        if not self.poor_ratio <= self.good_ratio:
            raise ValueError(f"LoopSettings.poor_ratio ({self.poor_ratio}) must be <= good_ratio "
                             f"({self.good_ratio})")
        check_value("LoopSettings.seed", self.seed, int, {"ge": 0})
        if self.objective not in OBJECTIVES:
            raise ValueError(f"LoopSettings.objective must be one of {', '.join(OBJECTIVES)}, "
                             f"got {self.objective!r}")
        if self.objective not in LOOP_OBJECTIVES:
            raise ValueError("LoopSettings.objective 'efficiency' needs the metric, which the "
                             "loop's pooled model does not estimate: use 'displacement' or "
                             "'turning' (torchconn-improve propose fits the metric from "
                             "recordings with a power column)")
        if not isinstance(self.trust_region, TrustRegion):
            raise TypeError(f"LoopSettings.trust_region must be a TrustRegion, got "
                            f"{type(self.trust_region).__name__}")
        if not (0 < self.min_scale <= self.trust_region.scale <= self.max_scale):
            raise ValueError("need min_scale <= trust_region.scale <= max_scale")


def gait_order(settings: LoopSettings, start=None) -> int:
    """The Fourier order per joint of the loop's gaits under ``settings``: every proposal is
    the current gait plus a change of order ``trust_region.order``, so the start gait's order
    (``start``, a :class:`FourierGait`; None: a circle, order 1) or the change's, whichever is
    higher."""
    own = 1 if start is None else getattr(as_gait(start), "order", 1)
    return max(own, settings.trust_region.order)


@dataclass(frozen=True)
class Round:
    """One recording of the loop, and the proposal made after it.

    Attributes:
        index: recording number (0 records the start gait).
        kind: what was recorded: ``"start"``, ``"proposal"`` (the previous step's proposal),
            ``"repeat"`` (the current gait again) or ``"excited"`` (the current gait perturbed).
        cycles: cycles recorded in this step; cycles_used: recorded cycles so far, this
            step's included.
        gait: the gait recorded this step (perturbation included).
        excitation: the perturbation's peak ``max_φ |ε(φ)|`` (rad; 0: none).
        observed, observed_se: the recorded gait's objective estimated from this recording,
            and its standard error.
        true: the recorded gait's exact, penalised objective (:func:`true_score`; for
            judging only).
        accepted: for a proposal: False when its recording scored worse than the gait it was
            proposed from, or turns more than the trust region's ``max_turn`` per cycle as the
            model including the recording predicts it (by more than the noise); the loop then
            kept that gait.
        kept, kept_true: the gait the loop keeps after this step (its best so far: the
            start, an accepted proposal, or a perturbed recording that scored better than the
            kept gait by more than the noise) and its exact objective.
        scale: trust radius (tube radii) used for this step's proposal.
        step: the proposal's largest change ``max_φ |Δ|`` from the kept gait (rad).
        proposal: the gait proposed from the kept gait.
        predicted, predicted_low, predicted_high: the proposal's predicted objective (observed
            kept gait + corrected gain) and interval.
        model_predicted: the model's own prediction of the proposal's objective.
        gain, gain_se: the model's predicted gain (before the over-prediction correction) and
            its standard error; gain_low: the lower end of the corrected gain's interval.
        moved: the proposal is recorded next (its gain interval lies above zero).
        realised: the proposal's exact objective (simulator; what ``predicted`` predicts, no
            penalties).
    """

    index: int
    kind: str
    cycles: int
    cycles_used: int
    gait: FourierGait
    excitation: float
    observed: float
    observed_se: float
    true: float
    accepted: bool
    kept: FourierGait
    kept_true: float
    scale: float
    step: float
    proposal: FourierGait
    predicted: float
    predicted_low: float
    predicted_high: float
    model_predicted: float
    gain: float
    gain_se: float
    gain_low: float
    moved: bool
    realised: float

    @property
    def covered(self) -> bool:
        return self.predicted_low <= self.realised <= self.predicted_high

    def as_row(self) -> dict:
        """The JSON/CSV row (no gaits)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if f.name not in ("gait", "proposal", "kept")} | {"covered": self.covered}


@dataclass(frozen=True)
class LoopResult:
    """The recordings of one loop, the start gait's exact objective and the best kept gait."""

    rounds: tuple[Round, ...]
    start_true: float
    settings: LoopSettings

    @property
    def best(self) -> Round:
        """The last step: its kept gait is the loop's best."""
        return self.rounds[-1]

    @property
    def coverage(self) -> float:
        """The share of the proposals the loop moved to whose interval held the realised
        objective (NaN when it never moved)."""
        moved = [r.covered for r in self.rounds if r.moved]
        return float(np.mean(moved)) if moved else math.nan


def _record(system, gait, s: LoopSettings, seed: np.random.SeedSequence):
    seeds = seed.generate_state(2 * s.trials, dtype=np.uint32).astype(np.int64)
    eta = torch.tensor(s.eta, dtype=torch.float64, device=s.device)  # sets the device
    traj = simulate(system, gait, eta=eta, alpha=s.alpha, n_cycles=s.cycles,
                    seeds=seeds[: s.trials])
    if s.omega > 0:
        traj = observe(traj, s.omega, seeds=seeds[s.trials:])
    return traj


def excitation_gait(model: LocalConnectionModel, gait: FourierGait, peak: float,
                    seed: int, *, shape_bound: float | None = None) -> FourierGait:
    """``gait`` plus a first harmonic ``ε(φ) = u cos φ + v sin φ`` of peak ``max_φ |ε| = peak``
    (rad): ``u, v`` random, scaled per joint ``j`` by the standard error of ``∂Â/∂r`` along
    ``r_j`` (root-sum-square over bins and entries), so the joints whose derivative is least
    known move most. With ``shape_bound``, the perturbation is shrunk (halved up to 20 times)
    until every shape keeps ``|r| ≤ shape_bound``; ``gait`` itself when none does."""
    d = gait.shape_dim
    se = model.bins.dA_se.square().sum((-4, -3, -2)).sqrt()  # (d,): along r_j
    kw = dict(dtype=gait.coeffs.dtype, device=gait.coeffs.device)
    gen = torch.Generator(device=gait.coeffs.device).manual_seed(seed)
    uv = torch.randn(2, d, generator=gen, **kw) * torch.nan_to_num(se, nan=1.0).to(**kw)
    phi = torch.arange(256, **kw) * (2 * math.pi / 256)
    wave = torch.cos(phi)[:, None] * uv[0] + torch.sin(phi)[:, None] * uv[1]
    uv = uv * (peak / float(torch.linalg.vector_norm(wave, dim=-1).amax()))
    for _ in range(20):
        coeffs = gait.coeffs.detach().clone()
        coeffs[1:3] += uv
        out = FourierGait(coeffs)
        if shape_bound is None or _peak_shape(out) <= shape_bound:
            return out
        uv = uv / 2
    return gait


def _peak_shape(gait, base=None) -> float:
    """``max_φ |r(φ)|`` of ``gait`` at 256 phases (rad); with ``base``, of ``r(φ) − base(φ)``."""
    phi = torch.arange(256, dtype=torch.float64) * (2 * math.pi / 256)
    phi = phi.to(getattr(gait, "coeffs", phi).device)
    r = gait(phi) if base is None else gait(phi) - base(phi)
    return float(torch.linalg.vector_norm(r, dim=-1).amax())


def improve(system: LocomotionSystem, start, settings: LoopSettings | None = None,
            *, progress=None) -> LoopResult:
    """Run the improvement loop on a simulator from the ``start`` gait.

    Args:
        system: the simulator (e.g. ``NLinkSwimmer(3)``).
        start: the start gait (gait object or callable ``φ -> r``; a callable is sampled into a
            Fourier gait of the loop's order).
        settings: :class:`LoopSettings`.
        progress: optional callable ``(Round) -> None`` called after each recording.
    """
    s = LoopSettings() if settings is None else settings
    start = _as_fourier(start, gait_order(s))
    if start.shape_dim != system.shape_dim:
        raise ValueError(f"start gait has {start.shape_dim} joints, the system {system.shape_dim}")
    seeds = np.random.SeedSequence(s.seed).spawn(s.rounds)
    z = normal_quantile(s.level)
    scale = s.trust_region.scale
    pool = PooledConnection(length=s.pool_length)
    rounds, errors, first_gain = [], [], None
    kept = None  # the kept gait: gait, observed, observed_se, true, and its last proposal
    gait, kind, excitation = start, "start", 0.0
    for k in range(s.rounds):
        traj = _record(system, gait, s, seeds[k])
        pool.add(gait_recording(traj, gait, s.trials * s.cycles))
        recorded = measure_cycles(traj)
        meas, meas_se = recorded.objective(s.objective)
        true = true_score(system, gait, s)
        within = kind == "start" or _within_limits(gait, pool, s, z, seed=k)
        accepted = True
        if kind == "proposal":
            # the trust-region test: observed against predicted gain, both from data
            predicted_gain, observed_gain = kept["gain"], meas - kept["observed"]
            ratio = observed_gain / predicted_gain if predicted_gain > 0 else 0.0
            noise = math.hypot(meas_se, kept["observed_se"])
            accepted = within and meas >= kept["observed"] - z * noise
            if accepted and predicted_gain > 2 * noise and kept["step"] > 0:
                # an informative step (its gain stands out of the measurement noise, and
                # within the constraints): its over-prediction per rad² of step
                errors.append((predicted_gain - observed_gain) / kept["step"] ** 2)
            if not accepted or ratio < s.poor_ratio:
                scale = max(scale * s.shrink, s.min_scale)
            elif ratio > s.good_ratio:
                scale = min(scale * s.grow, s.max_scale)
        # an excited recording that scores better than the kept gait by more than the noise
        # is kept: the perturbation found a better gait
        better = kind == "excited" and within and meas > kept["observed"] + z * math.hypot(
            meas_se, kept["observed_se"])
        if (kind in ("start", "proposal") and accepted) or better:
            kept = {"gait": gait, "observed": meas, "observed_se": meas_se, "true": true,
                    "traj": [traj]}
        elif kind == "repeat":
            kept["traj"].append(traj)
            kept["observed"], kept["observed_se"] = measure_cycles(
                _stack_trials(kept["traj"])).objective(s.objective)
        try:
            model = pool.model(kept["gait"])
        except ValueError:  # too few samples near the kept gait for every phase bin yet
            model = None
        if model is None:
            rnd = _unfitted_round(k, kind, gait, excitation, meas, meas_se, true, accepted,
                                  kept, scale, pool.cycles, s)
        else:
            candidates = [propose_gait(model, s.objective, dataclasses.replace(
                s.trust_region, scale=scale * fraction), seed=k) for fraction in _STEP_FRACTIONS]
            if first_gain is None:
                first_gain = abs(candidates[0].gain)
            prop, gain, gain_half = _best_step(candidates, errors, first_gain, s, z)
            predicted = kept["observed"] + gain
            half = math.hypot(z * kept["observed_se"], gain_half)
            kept.update(gain=prop.gain, step=prop.step)
            rnd = Round(
                index=k, kind=kind, cycles=s.trials * s.cycles, cycles_used=pool.cycles,
                gait=gait, excitation=excitation, observed=meas, observed_se=meas_se, true=true,
                accepted=accepted, kept=kept["gait"], kept_true=kept["true"], scale=scale,
                step=prop.step, proposal=prop.gait, predicted=predicted,
                predicted_low=predicted - half, predicted_high=predicted + half,
                model_predicted=prop.predicted, gain=prop.gain, gain_se=prop.gain_se,
                gain_low=gain - gain_half, moved=gain - gain_half > 0,
                realised=true_objective(system, prop.gait, s.objective),
            )
        rounds.append(rnd)
        if progress is not None:
            progress(rnd)
        if rnd.moved:
            gait, kind, excitation = rnd.proposal, "proposal", 0.0
        elif s.excitation > 0 and model is not None:
            # the first trust radius of the current tube, however far the radius has shrunk
            tube = sum(model.meta["tube_rms"]) / len(model.meta["tube_rms"])
            peak = s.excitation * s.trust_region.scale * tube
            gait = excitation_gait(model, kept["gait"], peak, seed=k,
                                   shape_bound=s.trust_region.shape_bound)
            excitation, kind = _peak_shape(gait, kept["gait"]), "excited"
        else:
            gait, kind, excitation = kept["gait"], "repeat", 0.0
    return LoopResult(tuple(rounds), true_score(system, start, s), s)


def true_score(system: LocomotionSystem, gait, settings: LoopSettings,
               n_steps: int = 256) -> float:
    """The simulator's exact objective of ``gait`` less the trust region's penalties
    (:func:`~torchconn.improve.propose.penalised_objective`: turning beyond ``max_turn``,
    shapes beyond ``shape_bound``, at 256 phases), as the ceiling scores its gaits; for
    judging."""
    m = evaluate(system, gait, n_steps)
    value = objective_value(settings.objective, m.displacement, m.cost)
    phi = torch.arange(256, dtype=value.dtype, device=value.device) * (2 * math.pi / 256)
    return float(penalised_objective(value, m.displacement, as_gait(gait)(phi),
                                     settings.objective, settings.trust_region))


def _best_step(candidates: list, errors: list[float], first_gain: float, s: LoopSettings,
               z: float):
    """The proposal among ``candidates`` (one per trust radius) whose gain, corrected for the
    over-prediction, has the highest lower bound: ``(proposal, gain, half-width)``.

    The over-prediction grows as the step squared (the first-order model's truncation): it is
    learnt per rad² of step from ``errors``, the prior (scaled by the first proposal's gain,
    ``first_gain``) worth one step taken."""
    n = 1 + len(errors)
    bias = (s.truncation * first_gain + sum(errors)) / n
    spread = math.sqrt(((s.truncation_spread * first_gain) ** 2
                        + sum((e - bias) ** 2 for e in errors)) / n)
    best = None
    for prop in candidates:
        gain = prop.gain - bias * prop.step ** 2
        gain_half = z * math.sqrt(prop.gain_se ** 2 + (spread * prop.step ** 2) ** 2)
        if best is None or gain - gain_half > best[1] - best[2]:
            best = (prop, gain, gain_half)
    return best


def _unfitted_round(index, kind, gait, excitation, observed, observed_se, true, accepted, kept,
                    scale, cycles_used, s: LoopSettings) -> Round:
    """A step after which the pooled model cannot be fitted yet (too few samples near the
    kept gait in some phase bin): no proposal (NaN predictions), the kept gait recorded
    again."""
    nan = math.nan
    return Round(
        index=index, kind=kind, cycles=s.trials * s.cycles, cycles_used=cycles_used, gait=gait,
        excitation=excitation, observed=observed, observed_se=observed_se, true=true,
        accepted=accepted, kept=kept["gait"], kept_true=kept["true"], scale=scale, step=0.0,
        proposal=kept["gait"], predicted=nan, predicted_low=nan, predicted_high=nan,
        model_predicted=nan, gain=nan, gain_se=nan, gain_low=nan, moved=False, realised=nan)


def _within_limits(gait: FourierGait, pool: PooledConnection, s: LoopSettings, z: float, *,
                   seed: int) -> bool:
    """False when ``gait`` leaves the trust region's ``shape_bound``, or turns more than its
    ``max_turn`` per cycle by more than ``z`` standard errors as the pooled model centred on
    ``gait`` predicts it (the recordings' own turning per cycle varies too much from cycle to
    cycle to tell in a few cycles; the turning limit does not apply to the turning
    objective)."""
    bound, limit = s.trust_region.shape_bound, s.trust_region.max_turn
    if bound is not None and _peak_shape(gait) > bound * (1 + 1e-9):
        return False
    if limit is None or s.objective == "turning":
        return True
    try:
        model = pool.model(gait)
    except ValueError:  # too few samples near the gait to tell: not refused
        return True
    pred = model.evaluate_gait(gait, phase_offset=0.0, n_draws=32, seed=seed,
                               warn_excursion=math.inf, max_excursion=math.inf)
    return abs(float(pred.displacement[2])) - z * float(pred.displacement_se[2]) <= limit


def _as_fourier(gait, order: int) -> FourierGait:
    """``gait`` as a :class:`FourierGait` (a callable sampled and fitted at ``order``)."""
    gait = as_gait(gait)
    if isinstance(gait, FourierGait):
        return gait
    phi = torch.arange(256, dtype=torch.float64) * (2 * math.pi / 256)
    return FourierGait(fit_fourier(phi, gait(phi), order, value_ndim=1).coeffs)


def _stack_trials(trajs: list[Trajectory]) -> Trajectory:
    """Recordings of one length as the trials of one :class:`Trajectory` (poses, shapes,
    power)."""
    first = trajs[0]
    power = None if first.power is None else torch.cat([t.power for t in trajs])
    return Trajectory(t=first.t, pose=torch.cat([t.pose for t in trajs]),
                      r=torch.cat([t.r for t in trajs]), power=power)
