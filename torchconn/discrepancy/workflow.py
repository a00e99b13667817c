"""The discrepancy workflow: where do simulation and measurement disagree, and why?

:func:`diagnose` runs the investigation in named stages, each returning a typed result
(:mod:`.report`):

1. **Where** (:mod:`.forward`): the recorded body velocity minus the nominal simulator's, driven
   by the recorded shapes and passed through the same smoother as the measurement.
2. **Screen** (:mod:`~torchconn.physics.effects`, :mod:`.fitting`): every registered effect
   not yet in the model is fitted jointly with the accepted ones by differentiating the
   augmented simulator, and scored by its held-out gain (cross-validation over blocks of whole
   cycles).
3. **Select**: the best candidate is accepted when its gain clears a statistical bar (one-sided
   paired t-test over held-out cycles, ``p < alpha`` Bonferroni-corrected over the candidates
   left) *and* a practical one (at least ``min_gain`` of the noise variance, and
   ``excess_fraction`` of the excess of the RMS gap over the noise floor) *and* its physical
   values are inside the effect's range (a negative lag or length is a look-alike of something
   else, never the effect: :class:`~.report.Implausible`). Screen and select repeat until no
   candidate clears the bars (:class:`~.report.SelectionStep`).
4. **Check backward**: each accepted effect must still earn its place next to the others.
5. **Refit** the accepted effects jointly to full precision, correct them for the estimator's
   own bias (estimated by refitting simulated twins with the fitted values and the recording's
   estimated observation noise, in antithetic pairs), with intervals that account for the
   noise (cluster-robust over cycles), the bias correction and the lack of fit
   (:class:`~.report.EffectEstimate`).
6. **Confounding** (:mod:`.confounding`): a runner-up that clears the bars, is not significantly
   worse on held-out cycles and whose signature is collinear with the winner's on the actual
   data is reported as confounded with it, with the simulated experiment that would separate
   them best (:class:`~.report.Confound`).
7. **Flexible residual test**: a flexible residual model (Fourier series in phase per
   component, plus heading and per-trial terms) against the final physical model on held-out
   cycles, pooled and per component (:class:`~.report.FlexibleTest`).
8. **Verdict**: ``none`` -- the nominal model is within noise; ``effect`` -- named effects with
   parameters and intervals, leaving residuals that look like noise in every component;
   ``unexplained`` -- a structured residual remains (the flexible model still predicts held-out
   cycles better in some component, the held-out gap stays far above the noise floor, or only a
   physically impossible fit would explain it), reported with where it lives
   (:class:`~.report.Unexplained`) beside any effects that explain part of it.

The noise floor is the residual a correct model would leave: the white-noise variance of the
recorded-minus-predicted poses (from their fourth differences, which cancel any smooth model
error) pushed through the smoothing kernels (:meth:`ForwardModel.noise_floor`). Gaps are RMS
held-out residuals per component (each cycle predicted by parameters fitted without its fold).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import torch
from scipy import stats
from torch import Tensor

from .._options import Options, option
from ..noise import estimate_noise
from ..phase.smoothing import smooth_trajectory, unwrap
from ..physics.effects import REGISTRY, Effect, get_effect
from ..physics.systems.base import LocomotionSystem
from ..physics.systems.swimmer import NLinkSwimmer
from ..trajectory import Trajectory
from .confounding import principal_cosine, separating_experiments, signature_collinearity
from .fitting import EffectFit, Problem, cycle_stats, fit_effects, fourier_columns, paired_gain
from .forward import (
    MIN_CYCLES,
    ForwardModel,
    Measurement,
    measurement_from_clean,
    prepare_measurement,
)
from .model import AugmentedModel
from .report import (
    VERDICTS,
    CandidateTest,
    Confound,
    DiscrepancyReport,
    EffectEstimate,
    FlexibleTest,
    Implausible,
    LookAlike,
    SelectionStep,
    Unexplained,
    Where,
)
from .residuals import COMPONENTS, compare_terms, phase_profile

__all__ = ["DiscrepancySettings", "DiscrepancyReport", "diagnose", "VERDICTS"]

#: fine integration steps per gait cycle the forward model aims for when ``upsample`` is None
FINE_STEPS_PER_CYCLE = 256
#: antithetic pairs of noisy simulated twins behind the intervals' bias term
TWIN_PAIRS = 1


@dataclass(frozen=True, kw_only=True)
class DiscrepancySettings(Options):
    """Every knob of :func:`diagnose`.

    Attributes:
        candidates: effect names to screen (default: every registered effect the nominal model
            supports).
        n_folds: cross-validation folds (blocks of whole, contiguous cycles of every trial).
        alpha: family-wise significance level of each selection step (Bonferroni over the
            candidates left) and of the unexplained-discrepancy test.
        min_gain: practical bar, held-out mean-square gain in units of the noise variance
            (averaged over the three components).
        excess_fraction: practical bar, fraction of the current excess of the held-out RMS gap
            over the noise floor that a candidate must remove.
        unexplained_min_gain: practical bar of the flexible residual model (pooled over the
            three components).
        component_min_gain: practical bar of the flexible residual model in one component (in
            that component's noise-variance units; its test is Bonferroni over components).
        max_unexplained_excess: a held-out mean square (noise units) above ``1 +`` this after
            the final model counts as unexplained even when not phase-locked.
        flex_order: harmonics per component of the flexible residual model.
        confound_collinearity: signature collinearity above which two candidates that the data
            cannot tell apart are reported as confounded.
        confound_alpha: a collinear runner-up is "not significantly worse" (confounded) above
            this p-value of the paired held-out comparison, a look-alike the data rule out
            below it.
        ci_level: confidence level of the parameter intervals, simultaneous over each effect's
            parameters (Bonferroni: all of an effect's intervals cover its values together).
        twin_intervals: correct the estimates for the estimator's own bias, estimated on
            simulated twins with the fitted values and the recording's observation noise, and
            widen the intervals by it.
        max_effects: most effects accepted.
        max_iter: Levenberg–Marquardt iterations per screening fit.
        n_bins, n_boot: phase bins and bootstrap resamples of the residual profiles.
        upsample: fine integration steps per sample in the forward model (None: enough for
            about ``FINE_STEPS_PER_CYCLE`` steps per gait cycle).
        min_relative_floor: smallest noise floor, relative to the RMS body velocity.
        compare_terms: also fit Stage 4's local model and compare it term by term.
        experiments: simulate alternative experiments for confounded pairs.
        min_cycles: fewest whole cycles in the recording.
        seed: bootstrap seed.
    """

    candidates: tuple[str, ...] | None = None
    n_folds: int = option(5, ge=2)
    alpha: float = option(0.01, gt=0, lt=1)
    min_gain: float = option(0.02, ge=0)
    excess_fraction: float = option(0.15, ge=0, le=1)
    unexplained_min_gain: float = option(0.05, ge=0)
    component_min_gain: float = option(0.05, ge=0)
    max_unexplained_excess: float = option(1.0, ge=0)
    flex_order: int = option(6, ge=1)
    confound_collinearity: float = option(0.9, ge=0, le=1)
    confound_alpha: float = option(0.01, gt=0, lt=1)
    ci_level: float = option(0.95, gt=0, lt=1)
    twin_intervals: bool = True
    max_effects: int = option(3, ge=1)
    max_iter: int = option(10, ge=1)
    n_bins: int = option(16, ge=2)
    n_boot: int = option(300, ge=1)
    upsample: int | None = option(None, ge=1)
    min_relative_floor: float = option(1e-3, ge=0)
    compare_terms: bool = True
    experiments: bool = True
    min_cycles: float = option(MIN_CYCLES, ge=0)
    seed: int = option(0, ge=0)

    def __post_init__(self) -> None:
        super().__post_init__()  # every field's type and range
        if self.candidates is not None:
            if not isinstance(self.candidates, (tuple, list)) or not all(
                    isinstance(c, (str, Effect)) for c in self.candidates):
                raise ValueError("DiscrepancySettings.candidates must be a list of effect names "
                                 f"({', '.join(REGISTRY)}) or None, got {self.candidates!r}")
            for c in self.candidates:
                get_effect(c)


# ============================================================================ diagnose
def diagnose(
    traj: Trajectory,
    system: LocomotionSystem,
    settings: DiscrepancySettings | None = None,
    *,
    phase: Tensor | None = None,
    log=None,
) -> DiscrepancyReport:
    """Find, name and add the effect behind a disagreement between a simulator and a recording.

    Args:
        traj: recorded trials (:func:`torchconn.io.trajectory_files.read_csv` or simulated),
            any batch shape.
        system: the nominal simulator (an :class:`~torchconn.physics.systems.NLinkSwimmer`).
        settings: :class:`DiscrepancySettings` (defaults if None).
        phase: optional ``(..., T)`` gait phase (else Phaser's estimate).
        log: optional callable receiving progress lines.

    Returns:
        a :class:`~torchconn.discrepancy.report.DiscrepancyReport`.

    Raises:
        ValueError: wrong number of joints, too few cycles, unknown candidates.
    """
    s = settings or DiscrepancySettings()
    say = log or (lambda *_: None)
    job = _Job.start(traj, system, s, phase)
    say(f"{job.m.n_trials} trial(s), {job.m.n_cycles} cycles, noise floor "
        + ", ".join(f"{c}={float(v):.3g}" for c, v in zip(COMPONENTS, job.fm.floor, strict=True)))

    base = job.fit([])                                    # 1. where
    sel = _screen_and_select(job, _candidates(s, system), base, say)   # 2.-3.
    sel = _check_backward(job, sel, say)                  # 4.
    final = _refit(job, sel)                              # 5.
    flex = _flexible_residual_test(job, final)            # 7.
    gaps = _gaps(job, base, final)
    bias = _bias(job, sel, final)                         # 5. (the estimator's bias)
    estimates = _estimates(job, sel, final, bias)         # 5. (intervals)
    confounds = _confounding(job, sel)                    # 6.
    unexplained = _unexplained(job, sel, flex, gaps)      # 8.
    say(f"flexible residual model: gain {flex.gain:.3g} (p={flex.p:.2g}); per component "
        + ", ".join(f"{c} {flex.component_gain[c]:.3g}" for c in COMPONENTS))
    verdict = "unexplained" if unexplained else ("effect" if sel.accepted else "none")

    estimates = [replace(e, confounded_with=[c.effects[1] for c in confounds
                                             if c.effects[0] == e.name])
                 for e in estimates]
    effects = ({n: (final.p[sl] - bias[sl]).detach() for n, sl in final.slices.items()}
               if verdict == "effect" else {})
    model = AugmentedModel(nominal=system, effects=effects,
                           meta={"verdict": verdict, "source": traj.meta.get("source")})
    return DiscrepancyReport(
        verdict=verdict,
        effects=estimates if verdict == "effect" else [],
        partial_effects=estimates if verdict == "unexplained" else [],
        confounded_with=confounds, implausible=list(sel.implausible),
        gap_before=gaps.before, gap_after=gaps.after, noise_floor=gaps.floor,
        unexplained=unexplained, selection=list(sel.steps),
        terms=_terms(job, say), profiles=gaps.profiles,
        data=_data_summary(job, base, final, flex), settings=_settings_dict(s, system),
        model=model,
        fits={"base": base, "final": final, "problem": job.pb, "measurement": job.m},
    )


# ============================================================================ the job
@dataclass(eq=False)
class _Job:
    """One diagnosis: the prepared measurement, forward model, problem and a cache of fits."""

    s: DiscrepancySettings
    m: Measurement
    fm: ForwardModel
    pb: Problem
    fits: dict

    @classmethod
    def start(cls, traj, system, s: DiscrepancySettings, phase) -> _Job:
        m = prepare_measurement(traj, system, phase=phase, min_cycles=s.min_cycles)
        fm = ForwardModel(m, system, upsample=_upsample(s, m),
                          min_relative_floor=s.min_relative_floor)
        return cls(s=s, m=m, fm=fm, pb=Problem(fm, n_folds=s.n_folds), fits={})

    @property
    def n_entries(self) -> int:
        return int(self.pb.cycle.numel())

    def fit(self, names: list[str], start: EffectFit | None = None) -> EffectFit:
        """The joint fit of ``names`` to screening precision (cached), started from ``start``'s
        values of the effects they share."""
        key = tuple(names)
        if key not in self.fits:
            p0 = None
            if start is not None:
                slices, scale = self.pb.specs(list(names))
                p0 = torch.zeros_like(scale)
                for n, sl in slices.items():
                    if n in start.slices:
                        p0[sl] = start.p[start.slices[n]]
            # screening precision: a held-out gain to ~1e-4 of the noise variance
            self.fits[key] = fit_effects(self.pb, list(names), p0,
                                         abs_tol=1e-4 * self.n_entries,
                                         max_iter=self.s.max_iter)
        return self.fits[key]


def _upsample(s: DiscrepancySettings, m: Measurement) -> int:
    """Fine steps per sample: the setting, or enough for ~FINE_STEPS_PER_CYCLE per cycle."""
    if s.upsample is not None:
        return s.upsample
    dphi = torch.diff(m.phase, dim=-1)[m.mask[:, 1:] & m.mask[:, :-1]]
    per_cycle = 2 * math.pi / max(float(dphi.mean()), 1e-12)
    return max(1, math.ceil(FINE_STEPS_PER_CYCLE / per_cycle - 1e-9))


def _candidates(s: DiscrepancySettings, system: LocomotionSystem) -> list[str]:
    names = list(s.candidates) if s.candidates is not None else list(REGISTRY)
    return [n for n in names if _applicable(n, system)]


def _applicable(name: str, system: LocomotionSystem) -> bool:
    e = get_effect(name)
    if type(e).system_kwargs is not Effect.system_kwargs:
        return isinstance(system, NLinkSwimmer)
    return True


# ============================================================================ 2.-3. screen, select
@dataclass(frozen=True, eq=False)
class _Selection:
    """What forward selection found: the accepted effects and their fit, the steps, collinear
    runners-up (confounded or ruled out) and candidates with impossible values."""

    accepted: tuple[str, ...]
    current: EffectFit
    steps: tuple[SelectionStep, ...]
    groups: tuple[dict, ...]  # confounded runners-up per accepted effect (raw, see _confounding)
    look_alikes: dict[str, tuple[LookAlike, ...]]
    gains: dict[str, tuple[float, float]]  # effect -> (gain, p) that earned its place
    implausible: tuple[Implausible, ...]
    last_implausible: tuple[Implausible, ...]  # passing look-alikes against the final model


def _screen(job: _Job, accepted: list[str], current: EffectFit, remaining: list[str]
            ) -> tuple[dict[str, EffectFit], dict[str, dict], dict[str, dict[str, float]]]:
    """Fit every remaining candidate beside the accepted ones: fits, held-out tests, and the
    physical values outside range of each."""
    fits = {c: job.fit(accepted + [c], current) for c in remaining}
    every = paired_gain(current.sse_cv, torch.stack([fits[c].sse_cv for c in remaining]),
                        job.n_entries)  # all candidates' tests at once
    tests = {c: {k: float(v[i]) for k, v in every.items()} for i, c in enumerate(remaining)}
    bad = {c: get_effect(c).out_of_range(fits[c].p[fits[c].slices[c]], job.fm.system)
           for c in remaining}
    return fits, tests, bad


def _screen_and_select(job: _Job, candidates: list[str], base: EffectFit, say) -> _Selection:
    s, system = job.s, job.fm.system
    current, accepted, remaining = base, [], list(candidates)
    steps, groups, implausible, last_implausible = [], [], [], []
    look_alikes: dict[str, list[LookAlike]] = {}
    gains: dict[str, tuple[float, float]] = {}
    while remaining and len(accepted) < s.max_effects:
        fits, tests, bad = _screen(job, accepted, current, remaining)
        order = sorted(remaining, key=lambda c: -tests[c]["gain"])
        need = _required_gain(current.mse_cv, s)
        alpha_b = s.alpha / len(remaining)
        clears = {c for c in remaining if tests[c]["p"] < alpha_b and tests[c]["gain"] >= need}
        passing = {c for c in clears if not bad[c]}
        last_implausible = [_implausible(c, fits[c], tests[c], bad[c], system)
                            for c in order if c in clears and bad[c]]
        implausible += [x for x in last_implausible
                        if x.name not in {y.name for y in implausible}]
        in_range = [c for c in order if not bad[c]]
        best = in_range[0] if in_range else None
        ok = best is not None and best in passing
        steps.append(SelectionStep(
            step=len(steps) + 1, model=tuple(accepted), held_out_mse=current.mse_cv,
            required_gain=need, alpha=alpha_b,
            candidates=tuple(CandidateTest(name=c, gain=tests[c]["gain"], t=tests[c]["t"],
                                           p=tests[c]["p"], passes=c in passing,
                                           parameters=tuple(fits[c].p[fits[c].slices[c]]
                                                            .tolist()),
                                           out_of_range=bad[c]) for c in order),
            accepted=best if ok else None))
        for x in last_implausible:
            say(f"step {len(steps)}: {x.message}")
        if best is None:
            break
        say(f"step {len(steps)}: best {best} gain {tests[best]['gain']:.3g} "
            f"(p={tests[best]['p']:.2g}, needs {need:.3g}) -> " + ("accepted" if ok else "stop"))
        if not ok:
            break
        group, ruled_out = _runners_up(job, accepted, best, order, passing, fits, tests)
        if group:
            groups.append({"best": best, "others": group, "accepted_before": list(accepted),
                           "gain": tests[best]["gain"]})
        if ruled_out:
            look_alikes[best] = tuple(ruled_out)
        gains[best] = (tests[best]["gain"], tests[best]["p"])
        accepted.append(best)
        current = fits[best]
        remaining.remove(best)
        last_implausible = []  # the model changed: they were scored against the old one
    return _Selection(accepted=tuple(accepted), current=current, steps=tuple(steps),
                      groups=tuple(groups), look_alikes=look_alikes, gains=gains,
                      implausible=tuple(implausible), last_implausible=tuple(last_implausible))


def _implausible(name: str, fit: EffectFit, test: dict, bad: dict, system) -> Implausible:
    e = get_effect(name)
    values = {k: float(v) for k, v in e.physical(fit.p[fit.slices[name]].detach(),
                                                 system).items()}
    return Implausible(name=name, gain=test["gain"], p=test["p"], values=values,
                       out_of_range=bad, ranges=e.physical_range(system))


def _runners_up(job: _Job, accepted, best, order, passing, fits, tests):
    """Runners-up whose signatures are collinear with the winner's: confounded (not
    significantly worse on held-out cycles) or look-alikes the data rule out."""
    s = job.s
    fb = fits[best]
    base_cols = fb.J[:, [i for n in accepted for i in range(fb.slices[n].start,
                                                              fb.slices[n].stop)]]
    Jb, pbest = fb.J[:, fb.slices[best]], fb.p[fb.slices[best]]
    group, ruled_out = [], []
    for c in order:
        if c == best or c not in passing:
            continue
        fc = fits[c]
        Jc, pc = fc.J[:, fc.slices[c]], fc.p[fc.slices[c]]
        col = max(signature_collinearity(Jb, pbest, Jc, base_cols),
                  signature_collinearity(Jc, pc, Jb, base_cols))
        if col < s.confound_collinearity:
            continue
        diff = paired_gain(fc.sse_cv, fb.sse_cv, job.n_entries)  # H1: best predicts better
        # indistinguishable: the winner's edge on held-out cycles is not significant (a
        # significant edge makes the runner-up a look-alike the data rule out)
        if diff["p"] >= s.confound_alpha:
            group.append({"name": c, "collinearity": col, "gain": tests[c]["gain"],
                          "p_worse": diff["p"], "gain_difference": diff["gain"],
                          "principal_cosine": principal_cosine(Jb, Jc, base_cols),
                          "parameters": tuple(pc.tolist())})
        else:
            ruled_out.append(LookAlike(name=c, collinearity=col, gain=tests[c]["gain"],
                                       gain_difference=diff["gain"], p_worse=diff["p"]))
    return group, ruled_out


def _required_gain(mse: float, s: DiscrepancySettings) -> float:
    """The practical bar, as a held-out mean-square gain (noise-variance units).

    A candidate must gain at least ``min_gain``, and shrink the held-out RMS gap by at least
    ``excess_fraction`` of its excess over the noise floor (RMS units: ``√mse − 1``).
    """
    rms = math.sqrt(max(mse, 0.0))
    target = rms - s.excess_fraction * max(rms - 1.0, 0.0)
    return max(s.min_gain, mse - target * target)


# ============================================================================ 4. check backward
def _check_backward(job: _Job, sel: _Selection, say) -> _Selection:
    """Drop accepted effects that no longer earn their place next to the others (or whose
    values left their physical range in the joint fit), one at a time."""
    s, system = job.s, job.fm.system
    accepted, current = list(sel.accepted), sel.current
    gains, groups = dict(sel.gains), list(sel.groups)
    changed = True
    while changed and len(accepted) > 1:
        changed = False
        for e in list(accepted):
            reduced = job.fit([n for n in accepted if n != e], current)
            t = paired_gain(reduced.sse_cv, current.sse_cv, job.n_entries)
            bad = get_effect(e).out_of_range(current.p[current.slices[e]], system)
            if not (t["p"] < s.alpha and t["gain"] >= s.min_gain) or bad:
                why = f"values out of range {bad}" if bad else f"gain {t['gain']:.3g}"
                say(f"backward check: {e} no longer earns its place ({why}); dropped")
                accepted.remove(e)
                current = reduced
                groups = [g for g in groups if g["best"] != e]
                changed = True
                break
            gains[e] = (t["gain"], t["p"])
    return _Selection(accepted=tuple(accepted), current=current, steps=sel.steps,
                      groups=tuple(groups), look_alikes=sel.look_alikes, gains=gains,
                      implausible=sel.implausible, last_implausible=sel.last_implausible)


# ============================================================================ 5. refit
def _refit(job: _Job, sel: _Selection) -> EffectFit:
    """The final joint fit, to a small fraction of the parameters' standard errors."""
    if not sel.accepted:
        return sel.current
    final = fit_effects(job.pb, list(sel.current.names), sel.current.p, abs_tol=1e-3,
                        max_iter=4 * job.s.max_iter)
    job.fits[tuple(final.names)] = final
    return final


def _twin_bias(job: _Job, fit: EffectFit, max_cycles: float = 8.0,
               n_pairs: int = TWIN_PAIRS) -> Tensor:
    """The estimator's own error at the fitted values: ``(P,)`` refit minus fit on simulated
    twin recordings.

    A twin is the augmented simulator with the fitted effects, driven by the smoothed recorded
    shapes of the first trial (up to ``max_cycles`` cycles), integrated on SE(2) with four times
    finer steps than the forward model and observed through the recording's own smoother, with
    white observation noise at the level estimated in the recording
    (:func:`~torchconn.noise.estimate_noise`, per pose and shape channel) on
    its poses and on the shapes that drive its forward model. The refit shows what the time
    stepping, the smoothing and the errors in variables (noisy shapes drive the forward model,
    which attenuates a fitted joint bias) do to the estimate. The noise comes in ``n_pairs``
    antithetic pairs ``(ε, −ε)`` refitted jointly: the noise's first-order effect on the refit
    cancels exactly, leaving its bias, with no sampling error of the order of the standard error.
    """
    m, fm = job.m, job.fm
    params = {n: v.detach() for n, v in fit.params().items()}
    usable = torch.nonzero(m.mask[0]).flatten()
    dphi = torch.diff(m.phase[0, usable[0]: usable[-1] + 1]).mean()
    margin = m.half_width + 16
    T = min(m.n_samples, int(usable[0]) + margin
            + int(math.ceil(max_cycles * 2 * math.pi / float(dphi))))
    kernel, t, phase = m.kernel[0], m.t[:T], m.phase[:1, :T]
    shapes = smooth_trajectory(m.pose[:1, :T], m.r[:1, :T], m.dt).r  # what the sensors read
    placeholder = measurement_from_clean(t, m.pose[:1, :T], shapes, phase, kernel, m.dt)
    fine = ForwardModel(placeholder, fm.system, upsample=4 * fm.upsample)
    pose = fine.integrate_poses(params)
    for name, p in params.items():
        effect = get_effect(name)
        if type(effect).observe is not Effect.observe:
            pose = effect.observe(p, pose)
    noise = estimate_noise(torch.cat([m.pose, m.r], -1)).measurement.square().mean(0).sqrt()
    gen = torch.Generator(device=pose.device).manual_seed(int(job.s.seed))
    eps = torch.randn((n_pairs, T, noise.shape[0]), generator=gen, dtype=pose.dtype,
                      device=pose.device) * noise.to(pose)
    eps = torch.cat([eps, -eps])  # antithetic pairs
    R = 2 * n_pairs
    twin = measurement_from_clean(t, pose + eps[..., :3], shapes + eps[..., 3:],
                                  phase.expand(R, T), kernel, m.dt,
                                  heading=unwrap(pose[..., 2], dim=-1))
    pb = Problem(ForwardModel(twin, fm.system, upsample=fm.upsample), n_folds=2,
                 weight=job.pb.weight)
    refit = fit_effects(pb, list(fit.names), fit.p, abs_tol=1e-6, max_iter=2 * job.s.max_iter)
    return (refit.p - fit.p).detach()


def _bias(job: _Job, sel: _Selection, fit: EffectFit) -> Tensor:
    """``(P,)`` the estimator's bias at the final fit (zeros without effects or twins)."""
    if not sel.accepted or not job.s.twin_intervals:
        return torch.zeros_like(fit.p)
    return _twin_bias(job, fit)


def _estimates(job: _Job, sel: _Selection, fit: EffectFit, bias_all: Tensor
               ) -> list[EffectEstimate]:
    """Physical values of the accepted effects, corrected for the estimator's bias
    ``bias_all (P,)``, with calibrated intervals (delta method).

    The half-width is ``q·√(se² + bias²)·√max(1, held-out MSE)``: the noise, an allowance for
    the bias correction's own error (at most the bias itself), and the lack of fit. The
    intervals of one effect are simultaneous (Bonferroni over its ``k`` values: ``q`` the
    Student-t quantile at ``1 − (1 − ci_level)/(2k)`` over the cycles), so that all of them
    cover the truth together at ``ci_level``."""
    if not sel.accepted:
        return []
    s, system = job.s, job.fm.system
    lack = math.sqrt(max(1.0, fit.mse_cv))
    out = []
    for name, sl in fit.slices.items():
        e = get_effect(name)
        p, cov, bias = (fit.p[sl] - bias_all[sl]).detach(), fit.cov[sl, sl], bias_all[sl]
        k = len(e.physical(p, system))
        q = float(stats.t.ppf(1 - (1 - s.ci_level) / (2 * k), df=max(job.m.n_cycles - 1, 1)))

        def phys(x, e=e):
            return torch.stack([torch.as_tensor(v, dtype=x.dtype, device=x.device) for v in
                                e.physical(x, system).values()])

        values = phys(p)
        jac = torch.autograd.functional.jacobian(phys, p)
        se = torch.sqrt(torch.clamp(torch.diagonal(jac @ cov @ jac.T), min=0.0))
        b = (jac @ bias).abs()
        half = q * torch.sqrt(se ** 2 + b ** 2) * lack
        keys = list(e.physical(p, system).keys())
        specs = e.param_specs(system)
        p_se = torch.sqrt(torch.clamp(torch.diagonal(cov), min=0.0))
        gain, pval = sel.gains.get(name, (float("nan"), float("nan")))
        out.append(EffectEstimate(
            name=name, description=e.description,
            parameters={k: float(v) for k, v in zip(keys, values, strict=True)},
            ci={k: (float(v - h), float(v + h)) for k, v, h in zip(keys, values, half,
                                                                   strict=True)},
            se={k: float(x) for k, x in zip(keys, se, strict=True)},
            bias={k: float(x) for k, x in zip(keys, b, strict=True)},
            lack_of_fit=lack, units=e.physical_units(system),
            fitted={sp.name: float(v) for sp, v in zip(specs, p, strict=True)},
            fitted_se={sp.name: float(v) for sp, v in zip(specs, p_se, strict=True)},
            ci_level=s.ci_level, gain=gain, p_value=pval,
            look_alikes=list(sel.look_alikes.get(name, ()))))
    return out


# ============================================================================ 6. confounding
def _confounding(job: _Job, sel: _Selection) -> list[Confound]:
    out = []
    for g in sel.groups:
        if g["best"] not in sel.accepted:
            continue
        for other in g["others"]:
            experiments = separating = None
            if job.s.experiments:
                experiments = tuple(_experiments_for(job, g, other))
                good = [x for x in experiments if x["collinearity"] is not None
                        and x["name"] != "as_recorded"]
                separating = good[0]["name"] if good else None
            out.append(Confound(
                effects=(g["best"], other["name"]), accepted_before=tuple(g["accepted_before"]),
                collinearity=other["collinearity"], principal_cosine=other["principal_cosine"],
                gains={g["best"]: g["gain"], other["name"]: other["gain"]},
                p_value_difference=other["p_worse"], gain_difference=other["gain_difference"],
                parameters={other["name"]: other["parameters"]},
                experiments=experiments, separating_experiment=separating))
    return out


def _experiments_for(job: _Job, g: dict, other: dict) -> list[dict]:
    acc = g["accepted_before"]
    fa = job.fits[tuple(acc + [g["best"]])]
    fo = job.fits[tuple(acc + [other["name"]])]

    def evaluate_columns(fm_exp: ForwardModel, weight: Tensor):
        pe = Problem(fm_exp, weight=weight)
        _, Ja = pe.evaluate(fa.names, fa.p)
        _, Jo = pe.evaluate(fo.names, fo.p)
        base_idx = [i for n in acc for i in range(fa.slices[n].start, fa.slices[n].stop)]
        return (Ja[:, base_idx], Ja[:, fa.slices[g["best"]]], fa.p[fa.slices[g["best"]]],
                Jo[:, fo.slices[other["name"]]], fo.p[fo.slices[other["name"]]])

    return separating_experiments(job.fm.system, job.m, job.pb.weight, evaluate_columns,
                                  g["best"], other["name"])


# ============================================================================ 7. flexible test
def _flexible_columns(problem: Problem, order: int) -> Tensor:
    """Whitened design of the flexible residual model: per component a Fourier series in phase,
    ``cos θ, sin θ`` of the heading and one constant per trial (beyond the first)."""
    m = problem.fm.m
    F = fourier_columns(problem, order)  # (n, 3(2K+1))
    th = m.heading[m.mask]
    trial = torch.nonzero(m.mask)[:, 0]
    extra = [torch.cos(th), torch.sin(th)]
    extra += [(trial == b).to(th.dtype) for b in range(1, m.n_trials)]
    E = torch.stack(extra, -1)  # (N, e)
    N, ne = E.shape
    out = th.new_zeros(N, 3, 3 * ne)
    for c in range(3):
        out[:, c, c * ne:(c + 1) * ne] = E
    cols = torch.cat([F, out.reshape(N * 3, 3 * ne)], 1)
    # drop columns that carry nothing (e.g. a heading that never changes)
    keep = cols.abs().amax(0) > 0
    return cols[:, keep]


def _component_sse(rows: Tensor, pb: Problem) -> Tensor:
    """Held-out squared error per cycle and component: whitened rows ``(n,)`` -> ``(C, 3)``."""
    r2 = (rows * rows).reshape(-1, 3)
    return rows.new_zeros(pb.n_cycles, 3).index_add_(0, pb.cycle[::3], r2)


def _flexible_residual_test(job: _Job, fit: EffectFit) -> FlexibleTest:
    """Does a flexible residual model predict held-out cycles better than the physics?"""
    pb = job.pb
    row_fold = pb.fold[pb.cycle]
    J = torch.cat([fit.J, _flexible_columns(pb, job.s.flex_order)], 1)
    st = cycle_stats(fit.rho, J, pb.cycle, pb.n_cycles, pb.fold)
    flex_cv, _ = st.held_out()
    pooled = paired_gain(fit.sse_cv, flex_cv, job.n_entries)
    before = _component_sse(fit.stats.held_out_rows(fit.rho, fit.J, row_fold), pb)
    after = _component_sse(st.held_out_rows(fit.rho, J, row_fold), pb)
    per = [paired_gain(before[:, k], after[:, k], job.n_entries / 3) for k in range(3)]
    return FlexibleTest(gain=pooled["gain"], t=pooled["t"], p=pooled["p"],
                        component_gain={c: t["gain"] for c, t in zip(COMPONENTS, per,
                                                                      strict=True)},
                        component_p={c: t["p"] for c, t in zip(COMPONENTS, per, strict=True)})


# ============================================================================ gaps, verdict
@dataclass(frozen=True, eq=False)
class _Gaps:
    before: dict[str, float]
    after: dict[str, float]
    floor: dict[str, float]
    profiles: dict

    @property
    def excess_after(self) -> float:
        """Held-out mean square after the final model, in noise units, minus 1."""
        return float(sum(self.after[c] ** 2 / self.floor[c] ** 2 for c in COMPONENTS) / 3 - 1)


def _gaps(job: _Job, base: EffectFit, final: EffectFit) -> _Gaps:
    """Held-out RMS gaps before and after, the final model's noise floor and the residual
    profiles over phase."""
    s, m, pb = job.s, job.m, job.pb
    row_fold = pb.fold[pb.cycle]

    def held_out(fit: EffectFit) -> Tensor:  # (N, 3) in physical units
        return fit.stats.held_out_rows(fit.rho, fit.J, row_fold).reshape(-1, 3) / pb.weight

    _, floor_after = job.fm.noise_floor({n: v.detach() for n, v in final.params().items()})
    res = {"before": held_out(base), "after": held_out(final)}
    rms = {k: dict(zip(COMPONENTS, torch.sqrt((v ** 2).mean(0)).tolist(), strict=True))
           for k, v in res.items()}
    profiles = {k: phase_profile(_scatter(v, m), m, n_bins=s.n_bins, n_boot=s.n_boot,
                                 seed=s.seed) for k, v in res.items()}
    return _Gaps(before=rms["before"], after=rms["after"],
                 floor=dict(zip(COMPONENTS, floor_after.tolist(), strict=True)),
                 profiles=profiles)


def _scatter(values: Tensor, m: Measurement) -> Tensor:
    out = values.new_zeros(m.n_trials, m.n_samples, 3)
    out[m.mask] = values
    return out


def _unexplained(job: _Job, sel: _Selection, flex: FlexibleTest, gaps: _Gaps
                 ) -> Unexplained | None:
    """A structured residual that the accepted effects leave, or None when they leave noise."""
    s = job.s
    phase_locked = flex.p < s.alpha and flex.gain >= s.unexplained_min_gain
    components = tuple(c for c in COMPONENTS if flex.component_p[c] < s.alpha / 3
                       and flex.component_gain[c] >= s.component_min_gain)
    too_big = gaps.excess_after > s.max_unexplained_excess
    look_alike = sel.last_implausible
    if not (phase_locked or components or too_big or look_alike):
        return None
    why = []
    if phase_locked or components:
        where = ", ".join(f"{c} (gain {flex.component_gain[c]:.3g}, "
                          f"p = {flex.component_p[c]:.2g})" for c in components)
        why.append(f"a flexible residual model still predicts held-out cycles better "
                   f"(gain {flex.gain:.3g} of the noise variance, p = {flex.p:.2g}"
                   + (f"; in {where}" if where else "") + ")")
    if too_big:
        why.append(f"the held-out gap stays {math.sqrt(1 + gaps.excess_after):.2f}x the noise "
                   "floor")
    for x in look_alike:
        why.append(x.message)
    after = f" after {', '.join(sel.accepted)}" if sel.accepted else ""
    flagged = set(components)
    return Unexplained(
        message=f"a significant discrepancy that no candidate explains{after}: "
                + "; ".join(why),
        flexible_gain=flex.gain, flexible_p=flex.p, excess_over_floor=gaps.excess_after,
        components=components,
        where=_where(gaps.profiles["after"], gaps.after, gaps.floor, flagged))


def _where(profile: dict, gap: dict, floor: dict, flagged: set[str]) -> tuple[Where, ...]:
    out = []
    for k, comp in enumerate(COMPONENTS):
        bad = profile["disagrees"][:, k]
        if not bad.any() and gap[comp] <= 1.1 * floor[comp] and comp not in flagged:
            continue
        phases = profile["centres"][bad]
        peak_i = int(abs(profile["mean"][:, k]).argmax())
        text = (f"held-out gap {gap[comp]:.3g} vs noise floor {floor[comp]:.3g}; "
                f"the phase-averaged residual disagrees with zero in {int(bad.sum())} of "
                f"{bad.size} phase bins, largest {profile['mean'][peak_i, k]:.3g} at phase "
                f"{profile['centres'][peak_i]:.2f} rad")
        out.append(Where(component=comp, phase_bins=tuple(float(x) for x in phases),
                         peak=float(profile["mean"][peak_i, k]),
                         peak_phase=float(profile["centres"][peak_i]),
                         gap=gap[comp], noise_floor=floor[comp], text=text))
    return tuple(out)


# ============================================================================ report details
def _terms(job: _Job, say) -> dict | None:
    """Stage 4's fitted terms of the data against those of a simulated twin recording."""
    if not job.s.compare_terms:
        return None
    m = job.m
    try:
        return compare_terms(Trajectory(t=m.t, pose=m.pose, r=m.r, phase=m.phase),
                             job.fm.system, twin=_twin(job.fm, job.s.seed), phase=m.phase,
                             n_bins=job.s.n_bins)
    except (ValueError, RuntimeError) as err:  # the local model needs enough data per bin
        say(f"term-by-term comparison skipped: {err}")
        return None


def _twin(fm: ForwardModel, seed: int) -> Trajectory:
    """The nominal simulator's own recording of the recording's shapes: poses integrated from
    them, plus white noise of the level estimated in the recording's poses."""
    m = fm.m
    # drawn on the recording's device: CPU and CUDA give different (equally valid) twins
    gen = torch.Generator(device=m.device).manual_seed(int(seed))
    noise = torch.randn(m.pose.shape, generator=gen, dtype=torch.float64, device=m.device)
    pose = fm.integrate_poses() + noise * fm.noise_variance.sqrt()[:, None, :]
    return Trajectory(t=m.t, pose=pose, r=m.r, phase=m.phase)


def _data_summary(job: _Job, base: EffectFit, final: EffectFit, flex: FlexibleTest) -> dict:
    m, fm = job.m, job.fm
    return {
        "n_trials": m.n_trials, "n_cycles": m.n_cycles, "n_samples": m.n_samples, "dt": m.dt,
        "usable_samples": int(m.mask.sum()), "smoothing_half_width": m.half_width,
        "upsample": fm.upsample, "device": str(m.device),
        "noise_std": {ch: float(v) for ch, v in zip(
            ("x", "y", "theta"), fm.noise_variance.mean(0).sqrt().tolist(), strict=True)},
        "noise_floor_nominal": dict(zip(COMPONENTS, fm.floor.tolist(), strict=True)),
        "held_out_mse_before": base.mse_cv, "held_out_mse_after": final.mse_cv,
        "flexible_model": flex.to_dict(),
    }


def _settings_dict(s: DiscrepancySettings, system) -> dict:
    d = asdict(s)
    d["system"] = repr(system)
    return d
