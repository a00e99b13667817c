"""The discrepancy workflow: where do simulation and measurement disagree, and why?

:func:`diagnose` runs the whole investigation on a recording and a nominal swimmer:

1. **Residuals** (:mod:`.forward`): the measured body velocity minus the nominal simulator's,
   driven by the measured shapes and passed through the same smoother as the measurement.
2. **Candidates** (:mod:`.effects`): every registered effect is fitted to the data by
   differentiating the augmented simulator (:mod:`.fitting`).
3. **Forward selection** by held-out gain: cross-validation over blocks of whole cycles; the
   best candidate is accepted when its gain clears a statistical bar (one-sided paired t-test
   over held-out cycles, ``p < alpha`` Bonferroni-corrected over the candidates left) *and* a
   practical one (at least ``min_gain`` of the noise variance, and ``excess_fraction`` of the
   excess of the RMS gap over the noise floor). All accepted effects are refitted jointly and the rest
   re-screened; at the end each accepted effect must still earn its place (backward check).
4. **Confounding** (:mod:`.confounding`): a runner-up that clears the bars, is not
   significantly worse on held-out cycles and whose signature is collinear with the winner's on
   the actual data is reported as confounded with it, with the simulated experiment that would
   separate them best.
5. **Verdict**: ``none`` -- the nominal model is within noise; ``effect`` -- named effects with
   parameters and confidence intervals; ``unexplained`` -- a flexible residual model (Fourier
   series in phase per component, plus heading and per-trial terms) still has a significant,
   practical held-out gain over the best physical model, or the held-out gap stays far above
   the noise floor: a discrepancy no candidate explains, reported with where it lives.

The noise floor is the residual a correct model would leave: the white-noise variance of the
recorded-minus-predicted poses (from their fourth differences, which cancel any smooth model
error) pushed through the smoothing kernels (:meth:`ForwardModel.noise_floor`). Gaps are RMS
held-out residuals per component (each cycle predicted by parameters fitted without its fold).
"""

from __future__ import annotations

import csv
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from scipy import stats
from torch import Tensor

from .._provenance import write_sidecar
from ..physics.systems.base import LocomotionSystem
from ..physics.systems.swimmer import NLinkSwimmer
from ..trajectory import Trajectory
from .confounding import principal_cosine, separating_experiments, signature_collinearity
from .effects import REGISTRY, Effect, get_effect
from .fitting import EffectFit, Problem, cycle_stats, fit_effects, fourier_columns, paired_gain
from .forward import MIN_CYCLES, ForwardModel, Measurement, prepare_measurement
from .model import AugmentedModel
from .residuals import COMPONENTS, compare_terms, phase_profile

__all__ = ["DiscrepancySettings", "DiscrepancyReport", "diagnose", "VERDICTS"]

VERDICTS = ("none", "effect", "unexplained")


@dataclass(frozen=True, kw_only=True)
class DiscrepancySettings:
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
        unexplained_min_gain: practical bar of the flexible residual model.
        max_unexplained_excess: a held-out mean square (noise units) above ``1 +`` this after
            the final model counts as unexplained even when not phase-locked.
        flex_order: harmonics per component of the flexible residual model.
        confound_collinearity: signature collinearity above which two candidates that the data
            cannot tell apart are reported as confounded.
        confound_alpha: a collinear runner-up is "not significantly worse" (confounded) above
            this p-value of the paired held-out comparison, a look-alike the data rule out
            below it.
        ci_level: confidence level of the parameter intervals.
        max_effects: most effects accepted.
        max_iter: Levenberg–Marquardt iterations per screening fit.
        n_bins, n_boot: phase bins and bootstrap resamples of the residual profiles.
        upsample: fine integration steps per sample in the forward model.
        min_relative_floor: smallest noise floor, relative to the RMS body velocity.
        compare_terms: also fit Stage 4's local model and compare it term by term.
        experiments: simulate alternative experiments for confounded pairs.
        min_cycles: fewest whole cycles in the recording.
        seed: bootstrap seed.
    """

    candidates: tuple[str, ...] | None = None
    n_folds: int = 5
    alpha: float = 0.01
    min_gain: float = 0.02
    excess_fraction: float = 0.15
    unexplained_min_gain: float = 0.05
    max_unexplained_excess: float = 1.0
    flex_order: int = 6
    confound_collinearity: float = 0.9
    confound_alpha: float = 0.01
    ci_level: float = 0.95
    max_effects: int = 3
    max_iter: int = 10
    n_bins: int = 16
    n_boot: int = 300
    upsample: int = 4
    min_relative_floor: float = 1e-3
    compare_terms: bool = True
    experiments: bool = True
    min_cycles: float = MIN_CYCLES
    seed: int = 0

    def __post_init__(self) -> None:
        if self.candidates is not None:
            for c in self.candidates:
                get_effect(c)
        if not 0 < self.alpha < 1 or not 0 < self.ci_level < 1:
            raise ValueError("alpha and ci_level must be in (0, 1)")
        if self.n_folds < 2:
            raise ValueError(f"n_folds must be >= 2, got {self.n_folds}")


# ============================================================================ report
@dataclass(eq=False)
class DiscrepancyReport:
    """The outcome of :func:`diagnose` (see :meth:`to_dict` for the JSON layout)."""

    verdict: str
    effects: list[dict]
    partial_effects: list[dict]
    confounded_with: list[dict]
    gap_before: dict[str, float]
    gap_after: dict[str, float]
    noise_floor: dict[str, float]
    unexplained: dict | None
    selection: list[dict]
    terms: dict | None
    profiles: dict
    data: dict
    settings: dict
    model: AugmentedModel
    fits: dict = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        """JSON-ready report: ``verdict``, ``effects`` (name, parameters, ci, ...),
        ``confounded_with``, ``gap_before``, ``gap_after``, ``noise_floor`` and the details."""
        return {
            "verdict": self.verdict,
            "effects": self.effects,
            "partial_effects": self.partial_effects,
            "confounded_with": self.confounded_with,
            "gap_before": self.gap_before,
            "gap_after": self.gap_after,
            "noise_floor": self.noise_floor,
            "unexplained": self.unexplained,
            "selection": self.selection,
            "terms": _terms_summary(self.terms),
            "profiles": _profiles_json(self.profiles),
            "data": self.data,
            "settings": self.settings,
            "model": self.model.to_dict() if isinstance(self.model.nominal, NLinkSwimmer)
            else repr(self.model),
        }

    def summary(self) -> str:
        """A readable account of the verdict, the effects and the gaps."""
        lines = [f"verdict: {self.verdict.upper()}"]
        if self.verdict == "none":
            lines.append("  the nominal model agrees with the data within the noise")
        for e in self.effects:
            lines.append(f"  effect {e['name']}: {e['description']}")
            for k, v in e["parameters"].items():
                lo, hi = e["ci"][k]
                lines.append(f"      {k} = {v:.5g}  [{lo:.5g}, {hi:.5g}]  {e['units'][k]}")
            lines.append(f"      held-out gain {e['gain']:.3g} (noise-variance units), "
                         f"p = {e['p_value']:.2g}")
        for e in self.partial_effects:
            pars = ", ".join(f"{k}={v:.4g}" for k, v in e["parameters"].items())
            lines.append(f"  partly explained by {e['name']} ({pars}), but not within noise")
        if self.unexplained:
            lines.append(f"  unexplained discrepancy: {self.unexplained['message']}")
            for w in self.unexplained.get("where", []):
                lines.append(f"      {w['component']}: {w['text']}")
        for c in self.confounded_with:
            lines.append(f"  CONFOUNDED: {c['message']}")
        lines.append("  held-out gap (RMS residual)      before       after   noise floor")
        for k in COMPONENTS:
            lines.append(f"      {k:6s} {self.gap_before[k]:23.4g} {self.gap_after[k]:11.4g} "
                         f"{self.noise_floor[k]:13.4g}")
        return "\n".join(lines)

    def save(self, out: str | Path, *, figures: bool = True) -> dict[str, Path]:
        """Write ``report.json``, ``augmented_model.json``, ``residual_profile.csv`` and the
        figures into ``out``; returns the paths."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        paths = {}
        paths["report"] = out / "report.json"
        write_sidecar(paths["report"], self.to_dict())
        if isinstance(self.model.nominal, NLinkSwimmer):
            paths["model"] = self.model.save(out / "augmented_model.json")
        paths["profile_csv"] = out / "residual_profile.csv"
        with paths["profile_csv"].open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["model", "component", "phase", "mean", "lo", "hi", "disagrees",
                        "noise_floor"])
            for label, prof in self.profiles.items():
                for i, ph in enumerate(prof["centres"]):
                    for k, comp in enumerate(COMPONENTS):
                        w.writerow([label, comp, f"{ph:.6g}", f"{prof['mean'][i, k]:.6g}",
                                    f"{prof['lo'][i, k]:.6g}", f"{prof['hi'][i, k]:.6g}",
                                    int(prof["disagrees"][i, k]), f"{self.noise_floor[comp]:.6g}"])
        if figures:
            from .figures import plot_residual_profiles, plot_terms

            paths["figure"] = plot_residual_profiles(self, out / "residual_vs_phase.png")
            if self.terms is not None:
                paths["terms_figure"] = plot_terms(self.terms, out / "terms_vs_simulator.png")
        return paths


def _profiles_json(profiles: dict) -> dict:
    return {k: {kk: vv.tolist() for kk, vv in v.items()} for k, v in profiles.items()}


def _terms_summary(terms: dict | None) -> dict | None:
    if terms is None:
        return None
    return {"phase": terms["phase"], "reference": terms["reference"],
            "summary": {k: v["summary"] for k, v in terms["terms"].items()},
            "z": {k: v["z"] for k, v in terms["terms"].items()}}


# ============================================================================ helpers
def _applicable(name: str, system: LocomotionSystem) -> bool:
    e = get_effect(name)
    if type(e).system_kwargs is not Effect.system_kwargs:
        return isinstance(system, NLinkSwimmer)
    return True


def _flexible_columns(problem: Problem, order: int) -> Tensor:
    """Whitened design of the flexible residual model: per component a Fourier series in phase,
    ``cos θ, sin θ`` of the heading and one constant per trial (beyond the first)."""
    m = problem.fm.m
    F = fourier_columns(problem, order)  # (n, 3(2K+1))
    th = m.heading[m.mask]
    trial = torch.nonzero(m.mask)[:, 0]
    extra = [torch.cos(th), torch.sin(th)]
    for b in range(1, m.n_trials):
        extra.append((trial == b).to(th.dtype))
    E = torch.stack(extra, -1)  # (N, e)
    N, ne = E.shape
    out = torch.zeros(N, 3, 3 * ne, dtype=th.dtype)
    for c in range(3):
        out[:, c, c * ne:(c + 1) * ne] = E
    cols = torch.cat([F, out.reshape(N * 3, 3 * ne)], 1)
    # drop columns that carry nothing (e.g. a heading that never changes)
    keep = cols.abs().amax(0) > 0
    return cols[:, keep]


def _held_out_residual(fit: EffectFit, problem: Problem) -> Tensor:
    """Held-out residual per usable sample and component, in physical units: ``(N, 3)``."""
    rho = fit.rho.clone()
    if fit.p.numel():
        _, steps = fit.stats.held_out()
        fold_row = problem.fold[problem.cycle]
        for k in range(steps.shape[0]):
            sel = fold_row == k
            rho[sel] = fit.rho[sel] + fit.J[sel] @ steps[k]
    return rho.reshape(-1, 3) / problem.weight


def _scatter(values: Tensor, m: Measurement) -> Tensor:
    out = torch.zeros(m.n_trials, m.n_samples, 3, dtype=values.dtype)
    out[m.mask] = values
    return out


def _effect_entries(fit: EffectFit, system, level: float, df: int, gains: dict) -> list[dict]:
    """Parameters and confidence intervals (delta method) in physical units per effect."""
    q = float(stats.t.ppf(0.5 + level / 2, df=max(df, 1)))
    entries = []
    for name, sl in fit.slices.items():
        e = get_effect(name)
        p = fit.p[sl].detach()
        cov = fit.cov[sl, sl]

        def phys(x, e=e):
            return torch.stack([torch.as_tensor(v, dtype=x.dtype) for v in
                                e.physical(x, system).values()])

        values = phys(p)
        jac = torch.autograd.functional.jacobian(phys, p)
        se = torch.sqrt(torch.clamp(torch.diagonal(jac @ cov @ jac.T), min=0.0))
        keys = list(e.physical(p, system).keys())
        units = e.physical_units(system)
        specs = e.param_specs(system)
        p_se = torch.sqrt(torch.clamp(torch.diagonal(cov), min=0.0))
        g = gains.get(name, {})
        entries.append({
            "name": name,
            "description": e.description,
            "parameters": {k: float(v) for k, v in zip(keys, values, strict=True)},
            "ci": {k: [float(v - q * s), float(v + q * s)]
                   for k, v, s in zip(keys, values, se, strict=True)},
            "se": {k: float(s) for k, s in zip(keys, se, strict=True)},
            "units": units,
            "fitted": {s.name: float(v) for s, v in zip(specs, p, strict=True)},
            "fitted_se": {s.name: float(v) for s, v in zip(specs, p_se, strict=True)},
            "ci_level": level,
            "gain": g.get("gain", float("nan")),
            "p_value": g.get("p", float("nan")),
            "confounded_with": [],
        })
    return entries


def _where(profile: dict, gap: dict, floor: dict) -> list[dict]:
    out = []
    for k, comp in enumerate(COMPONENTS):
        bad = profile["disagrees"][:, k]
        if not bad.any() and gap[comp] <= 1.1 * floor[comp]:
            continue
        phases = profile["centres"][bad]
        peak_i = int(abs(profile["mean"][:, k]).argmax())
        text = (f"held-out gap {gap[comp]:.3g} vs noise floor {floor[comp]:.3g}; "
                f"the phase-averaged residual disagrees with zero in {int(bad.sum())} of "
                f"{bad.size} phase bins, largest {profile['mean'][peak_i, k]:.3g} at phase "
                f"{profile['centres'][peak_i]:.2f} rad")
        out.append({"component": comp, "phase_bins": [float(x) for x in phases],
                    "peak": float(profile["mean"][peak_i, k]),
                    "peak_phase": float(profile["centres"][peak_i]),
                    "gap": gap[comp], "noise_floor": floor[comp], "text": text})
    return out


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
        traj: recorded trials (:func:`torchconn.io.trajectory_files.read_csv` or simulated), any batch shape.
        system: the nominal simulator (an :class:`~torchconn.physics.systems.NLinkSwimmer`).
        settings: :class:`DiscrepancySettings` (defaults if None).
        phase: optional ``(..., T)`` gait phase (else Phaser's estimate).
        log: optional callable receiving progress lines.

    Returns:
        a :class:`DiscrepancyReport`.

    Raises:
        ValueError: wrong number of joints, too few cycles, unknown candidates.
    """
    s = settings or DiscrepancySettings()
    say = log or (lambda *_: None)
    m = prepare_measurement(traj, system, phase=phase, min_cycles=s.min_cycles)
    fm = ForwardModel(m, system, upsample=s.upsample, min_relative_floor=s.min_relative_floor)
    pb = Problem(fm, n_folds=s.n_folds)
    names = list(s.candidates) if s.candidates is not None else list(REGISTRY)
    candidates = [n for n in names if _applicable(n, system)]
    say(f"{m.n_trials} trial(s), {m.n_cycles} cycles, noise floor "
        + ", ".join(f"{c}={float(v):.3g}" for c, v in zip(COMPONENTS, fm.floor, strict=True)))

    base = fit_effects(pb, [])
    n_entries = base.n_entries
    current, accepted = base, []
    remaining = list(candidates)
    selection, confounded, gains_at_accept = [], [], {}
    look_alikes: dict[str, list[dict]] = {}  # collinear runners-up the data did rule out
    all_fits: dict[tuple, EffectFit] = {(): base}

    def fit(names_: list[str], start: EffectFit | None) -> EffectFit:
        key = tuple(names_)
        if key not in all_fits:
            p0 = None
            if start is not None:
                _, scale = pb.specs(names_)
                p0 = torch.zeros_like(scale)
                for n, sl in pb.specs(names_)[0].items():
                    if n in start.slices:
                        p0[sl] = start.p[start.slices[n]]
            # screening precision: a held-out gain to ~1e-4 of the noise variance
            all_fits[key] = fit_effects(pb, names_, p0, abs_tol=1e-4 * n_entries,
                                        max_iter=s.max_iter)
        return all_fits[key]

    while remaining and len(accepted) < s.max_effects:
        fits = {c: fit(accepted + [c], current) for c in remaining}
        every = paired_gain(current.sse_cv, torch.stack([fits[c].sse_cv for c in remaining]),
                            n_entries)  # all candidates' tests at once
        tests = {c: {k: float(v[i]) for k, v in every.items()} for i, c in enumerate(remaining)}
        order = sorted(remaining, key=lambda c: -tests[c]["gain"])
        best = order[0]
        need = _required_gain(current.mse_cv, s)
        alpha_b = s.alpha / len(remaining)

        passing = {c for c in remaining
                   if tests[c]["p"] < alpha_b and tests[c]["gain"] >= need}
        ok = best in passing
        step = {
            "step": len(selection) + 1,
            "model": list(accepted),
            "held_out_mse": current.mse_cv,
            "required_gain": need,
            "alpha": alpha_b,
            "candidates": [{"name": c, **tests[c], "passes": c in passing,
                            "parameters": fits[c].p[fits[c].slices[c]].tolist()}
                           for c in order],
            "accepted": best if ok else None,
        }
        selection.append(step)
        say(f"step {step['step']}: best {best} gain {tests[best]['gain']:.3g} "
            f"(p={tests[best]['p']:.2g}, needs {need:.3g}) -> "
            + ("accepted" if ok else "stop"))
        if not ok:
            break
        fb = fits[best]
        base_cols = fb.J[:, [i for n in accepted for i in range(fb.slices[n].start,
                                                                  fb.slices[n].stop)]]
        Jb, pbest = fb.J[:, fb.slices[best]], fb.p[fb.slices[best]]
        group = []
        for c in order[1:]:
            if c not in passing:
                continue
            fc = fits[c]
            Jc, pc = fc.J[:, fc.slices[c]], fc.p[fc.slices[c]]
            col = max(signature_collinearity(Jb, pbest, Jc, base_cols),
                      signature_collinearity(Jc, pc, Jb, base_cols))
            diff = paired_gain(fc.sse_cv, fb.sse_cv, n_entries)  # H1: best predicts better
            # indistinguishable: the winner's edge on held-out cycles is not significant (a
            # significant edge makes the runner-up a look-alike the data rule out)
            close = diff["p"] >= s.confound_alpha
            if col >= s.confound_collinearity and not close:
                look_alikes.setdefault(best, []).append(
                    {"name": c, "collinearity": col, "gain": tests[c]["gain"],
                     "gain_difference": diff["gain"], "p_worse": diff["p"]})
            if col >= s.confound_collinearity and close:
                group.append({"name": c, "collinearity": col, "gain": tests[c]["gain"],
                              "p_worse": diff["p"], "gain_difference": diff["gain"],
                              "principal_cosine": principal_cosine(Jb, Jc, base_cols),
                              "parameters": pc.tolist()})
        if group:
            confounded.append({"best": best, "others": group, "accepted_before": list(accepted),
                               "gain": tests[best]["gain"]})
        gains_at_accept[best] = tests[best]
        accepted.append(best)
        current = fb
        remaining.remove(best)

    # every accepted effect must still earn its place next to the others
    changed = True
    while changed and len(accepted) > 1:
        changed = False
        for e in list(accepted):
            reduced = fit([n for n in accepted if n != e], current)
            t = paired_gain(reduced.sse_cv, current.sse_cv, n_entries)
            if not (t["p"] < s.alpha and t["gain"] >= s.min_gain):
                say(f"backward check: {e} no longer earns its place (gain {t['gain']:.3g}); "
                    "dropped")
                accepted.remove(e)
                current = reduced
                confounded = [c for c in confounded if c["best"] != e]
                changed = True
                break
            gains_at_accept[e] = t

    if accepted:
        # polish the final joint fit: parameters to a small fraction of their standard errors
        current = fit_effects(pb, list(current.names), current.p, abs_tol=1e-3,
                              max_iter=4 * s.max_iter)
        all_fits[tuple(current.names)] = current

    # is anything left that the physics does not explain?
    F = _flexible_columns(pb, s.flex_order)
    st = cycle_stats(current.rho, torch.cat([current.J, F], 1), pb.cycle, pb.n_cycles, pb.fold)
    flex_cv, _ = st.held_out()
    flex = paired_gain(current.sse_cv, flex_cv, n_entries)
    final_params = {n: v.detach() for n, v in current.params().items()}
    _, floor_after = fm.noise_floor(final_params)
    res_before = _held_out_residual(base, pb)
    res_after = _held_out_residual(current, pb)
    gap_before = dict(zip(COMPONENTS, torch.sqrt((res_before ** 2).mean(0)).tolist(),
                          strict=True))
    gap_after = dict(zip(COMPONENTS, torch.sqrt((res_after ** 2).mean(0)).tolist(), strict=True))
    floor = dict(zip(COMPONENTS, floor_after.tolist(), strict=True))
    excess_after = float(sum(gap_after[c] ** 2 / floor[c] ** 2 for c in COMPONENTS) / 3 - 1)
    phase_locked = flex["p"] < s.alpha and flex["gain"] >= s.unexplained_min_gain
    too_big = excess_after > s.max_unexplained_excess
    say(f"flexible residual model: gain {flex['gain']:.3g} (p={flex['p']:.2g}); "
        f"excess over the floor after the model {excess_after:.3g}")

    profiles = {
        "before": phase_profile(_scatter(res_before, m), m, n_bins=s.n_bins, n_boot=s.n_boot,
                                seed=s.seed),
        "after": phase_profile(_scatter(res_after, m), m, n_bins=s.n_bins, n_boot=s.n_boot,
                               seed=s.seed),
    }
    entries = _effect_entries(current, system, s.ci_level, m.n_cycles - 1, gains_at_accept)
    conf_out = []
    for c in confounded:
        if c["best"] not in accepted:
            continue
        for other in c["others"]:
            entry = {"effects": [c["best"], other["name"]],
                     "collinearity": other["collinearity"],
                     "principal_cosine": other["principal_cosine"],
                     "gains": {c["best"]: c["gain"], other["name"]: other["gain"]},
                     "p_value_difference": other["p_worse"],
                     "gain_difference": other["gain_difference"],
                     "parameters": {other["name"]: other["parameters"]}}
            if s.experiments:
                entry["experiments"] = _experiments_for(c, other, all_fits, fm, pb)
                good = [x for x in entry["experiments"] if x["collinearity"] is not None
                        and x["name"] != "as_recorded"]
                entry["separating_experiment"] = good[0]["name"] if good else None
            entry["message"] = _confound_message(entry)
            conf_out.append(entry)
        for e in entries:
            if e["name"] == c["best"]:
                e["confounded_with"] = [o["name"] for o in c["others"]]
    for e in entries:
        e["look_alikes"] = look_alikes.get(e["name"], [])

    unexplained = None
    if phase_locked or too_big:
        where = _where(profiles["after"], gap_after, floor)
        why = []
        if phase_locked:
            why.append(f"a flexible residual model still predicts held-out cycles better "
                       f"(gain {flex['gain']:.3g} of the noise variance, p = {flex['p']:.2g})")
        if too_big:
            why.append(f"the held-out gap stays {math.sqrt(1 + excess_after):.2f}x the noise "
                       "floor")
        best_text = (f" after {', '.join(accepted)}" if accepted else "")
        unexplained = {
            "message": f"a significant discrepancy that no candidate explains{best_text}: "
                       + "; ".join(why),
            "flexible_gain": flex["gain"], "flexible_p": flex["p"],
            "excess_over_floor": excess_after, "where": where,
        }
        verdict = "unexplained"
    elif accepted:
        verdict = "effect"
    else:
        verdict = "none"

    terms = None
    if s.compare_terms:
        try:
            terms = compare_terms(_recording(m), system, twin=_twin(fm, s.seed),
                                  phase=m.phase, n_bins=s.n_bins)
        except (ValueError, RuntimeError) as err:  # the local model needs enough data per bin
            say(f"term-by-term comparison skipped: {err}")

    model_effects = final_params if verdict == "effect" else {}
    model = AugmentedModel(nominal=system, effects=model_effects,
                           meta={"verdict": verdict, "source": traj.meta.get("source")})
    data = {
        "n_trials": m.n_trials, "n_cycles": m.n_cycles, "n_samples": m.n_samples, "dt": m.dt,
        "usable_samples": int(m.mask.sum()), "smoothing_half_width": m.half_width,
        "noise_std": {ch: float(v) for ch, v in zip(
            ("x", "y", "theta"), fm.noise_variance.mean(0).sqrt().tolist(), strict=True)},
        "noise_floor_nominal": dict(zip(COMPONENTS, fm.floor.tolist(), strict=True)),
        "held_out_mse_before": base.mse_cv, "held_out_mse_after": current.mse_cv,
        "flexible_model": flex,
    }
    return DiscrepancyReport(
        verdict=verdict,
        effects=entries if verdict == "effect" else [],
        partial_effects=entries if verdict == "unexplained" else [],
        confounded_with=conf_out,
        gap_before=gap_before, gap_after=gap_after, noise_floor=floor,
        unexplained=unexplained, selection=selection, terms=terms, profiles=profiles,
        data=data, settings=_settings_dict(s, system), model=model,
        fits={"base": base, "final": current, "problem": pb, "measurement": m},
    )


def _recording(m: Measurement) -> Trajectory:
    """The measurement as a flat ``(B,)`` trajectory (gaps filled) for Stage 4's estimator."""
    return Trajectory(t=m.t, pose=m.pose, r=m.r, phase=m.phase)


def _twin(fm: ForwardModel, seed: int) -> Trajectory:
    """The nominal simulator's own recording of the measured shapes: poses integrated from
    them, plus white noise of the level measured in the recording's poses."""
    m = fm.m
    gen = torch.Generator().manual_seed(int(seed))
    noise = torch.randn(m.pose.shape, generator=gen, dtype=torch.float64)
    pose = fm.integrate_poses() + noise * fm.noise_variance.sqrt()[:, None, :]
    return Trajectory(t=m.t, pose=pose, r=m.r, phase=m.phase)


def _required_gain(mse: float, s: DiscrepancySettings) -> float:
    """The practical bar, as a held-out mean-square gain (noise-variance units).

    A candidate must gain at least ``min_gain``, and shrink the held-out RMS gap by at least
    ``excess_fraction`` of its excess over the noise floor (RMS units: ``√mse − 1``).
    """
    rms = math.sqrt(max(mse, 0.0))
    target = rms - s.excess_fraction * max(rms - 1.0, 0.0)
    return max(s.min_gain, mse - target * target)


def _settings_dict(s: DiscrepancySettings, system) -> dict:
    d = asdict(s)
    d["system"] = repr(system)
    return d


def _experiments_for(c: dict, other: dict, all_fits: dict, fm: ForwardModel, pb: Problem):
    acc = c["accepted_before"]
    fa = all_fits[tuple(acc + [c["best"]])]
    fo = all_fits[tuple(acc + [other["name"]])]

    def evaluate_columns(fm_exp: ForwardModel, weight: Tensor):
        pe = Problem(fm_exp, weight=weight)
        _, Ja = pe.evaluate(fa.names, fa.p)
        _, Jo = pe.evaluate(fo.names, fo.p)
        base_idx = [i for n in acc for i in range(fa.slices[n].start, fa.slices[n].stop)]
        return (Ja[:, base_idx], Ja[:, fa.slices[c["best"]]], fa.p[fa.slices[c["best"]]],
                Jo[:, fo.slices[other["name"]]], fo.p[fo.slices[other["name"]]])

    return separating_experiments(fm.system, fm.m, pb.weight, evaluate_columns, c["best"],
                                  other["name"])


def _confound_message(entry: dict) -> str:
    a, b = entry["effects"]
    msg = (f"{a} and {b} explain the data equally well on this recording: their signatures are "
           f"{entry['collinearity']:.1%} collinear and their held-out gains "
           f"{entry['gains'][a]:.3g} and {entry['gains'][b]:.3g} differ by "
           f"{entry['gain_difference']:.2g}")
    msg += f" (not significant, p = {entry['p_value_difference']:.2g})"
    msg += f"; {a} is reported, but {b} cannot be ruled out"
    exp = entry.get("experiments")
    if exp:
        best = next((x for x in exp if x["collinearity"] is not None
                     and x["name"] != "as_recorded"), None)
        ref = next((x for x in exp if x["name"] == "as_recorded"), None)
        if best is not None:
            msg += (f". To separate them: {best['description']} (simulated collinearity "
                    f"{best['collinearity']:.1%}")
            if ref is not None and ref["collinearity"] is not None:
                msg += f" vs {ref['collinearity']:.1%} for the recorded gait"
            msg += ")"
    return msg
