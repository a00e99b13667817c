"""Typed results of the discrepancy workflow's stages, and the report they add up to.

Each stage of :func:`~torchconn.discrepancy.workflow.diagnose` returns one of these frozen
dataclasses; dicts appear only at the edge, in :meth:`DiscrepancyReport.to_dict` (the layout of
``report.json``). Records can also be read by key (``entry["name"]``), as the dicts of the
previous release were, for one release.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .._output import write_bytes_atomic, write_table
from .._provenance import jsonable, write_sidecar
from ..physics.systems.swimmer import NLinkSwimmer
from ..report import Report
from .model import AugmentedModel
from .residuals import COMPONENTS

__all__ = ["CandidateTest", "SelectionStep", "LookAlike", "Implausible", "Confound",
           "EffectEstimate", "FlexibleTest", "Where", "Unexplained", "DiscrepancyReport",
           "VERDICTS"]

VERDICTS = ("none", "effect", "unexplained")


class _Record:
    """Read access by key for the typed records (the dicts of the previous release)."""

    def __getitem__(self, key: str):
        try:
            return getattr(self, key)
        except AttributeError:
            raise KeyError(key) from None

    def get(self, key: str, default=None):
        return getattr(self, key, default)

    def to_dict(self) -> dict:
        return jsonable(asdict(self))


# ============================================================================ selection
@dataclass(frozen=True, kw_only=True)
class CandidateTest(_Record):
    """One candidate at one selection step: its held-out gain over the current model.

    ``gain``: drop of the held-out mean square (noise-variance units); ``t``, ``p``: the one-sided
    paired test over cycles; ``parameters``: its fitted values (fit units); ``out_of_range``:
    physical values outside the effect's range (a look-alike, never accepted); ``passes``: clears
    the statistical and practical bars and is in range.
    """

    name: str
    gain: float
    t: float
    p: float
    passes: bool
    parameters: tuple[float, ...]
    out_of_range: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class SelectionStep(_Record):
    """One forward-selection step: the model so far, the bars, every candidate's test and the
    effect accepted (None: the selection stops)."""

    step: int
    model: tuple[str, ...]
    held_out_mse: float
    required_gain: float
    alpha: float
    candidates: tuple[CandidateTest, ...]
    accepted: str | None


@dataclass(frozen=True, kw_only=True)
class LookAlike(_Record):
    """A collinear runner-up that the data rule out (the winner predicts significantly better)."""

    name: str
    collinearity: float
    gain: float
    gain_difference: float
    p_worse: float


@dataclass(frozen=True, kw_only=True)
class Implausible(_Record):
    """A candidate that would explain part of the residual, but only with physical values
    outside its range (``values``; ``out_of_range`` the offending ones): a look-alike of some
    other discrepancy, not this effect."""

    name: str
    gain: float
    p: float
    values: Mapping[str, float]
    out_of_range: Mapping[str, float]
    ranges: Mapping[str, tuple[float, float]]

    @property
    def message(self) -> str:
        bad = ", ".join(f"{k} = {v:.4g} (range {_range_text(self.ranges[k])})"
                        for k, v in self.out_of_range.items())
        return (f"{self.name} would gain {self.gain:.3g} of the noise variance only with {bad}: "
                f"not that effect, a look-alike of something else")


@dataclass(frozen=True, kw_only=True)
class Confound(_Record):
    """Two effects the data cannot tell apart: ``effects = (reported, not ruled out)``."""

    effects: tuple[str, str]
    accepted_before: tuple[str, ...]
    collinearity: float
    principal_cosine: float
    gains: Mapping[str, float]
    p_value_difference: float
    gain_difference: float
    parameters: Mapping[str, tuple[float, ...]]
    experiments: tuple[Mapping, ...] | None = None
    separating_experiment: str | None = None

    @property
    def message(self) -> str:
        a, b = self.effects
        msg = (f"{a} and {b} explain the data equally well on this recording: their signatures "
               f"are {self.collinearity:.1%} collinear and their held-out gains "
               f"{self.gains[a]:.3g} and {self.gains[b]:.3g} differ by "
               f"{self.gain_difference:.2g} (not significant, p = {self.p_value_difference:.2g})"
               f"; {a} is reported, but {b} cannot be ruled out")
        if self.experiments:
            best = next((x for x in self.experiments if x["collinearity"] is not None
                         and x["name"] != "as_recorded"), None)
            ref = next((x for x in self.experiments if x["name"] == "as_recorded"), None)
            if best is not None:
                msg += (f". To separate them: {best['description']} (simulated collinearity "
                        f"{best['collinearity']:.1%}")
                if ref is not None and ref["collinearity"] is not None:
                    msg += f" vs {ref['collinearity']:.1%} for the recorded gait"
                msg += ")"
        return msg

    def to_dict(self) -> dict:
        return {**super().to_dict(), "message": self.message}


# ============================================================================ effects
@dataclass(frozen=True, kw_only=True)
class EffectEstimate(_Record):
    """A named effect: physical values with intervals, and how it was chosen.

    ``parameters`` and ``fitted`` are corrected for ``bias``, the estimator's own error estimated
    on simulated twins with the fitted values and the recording's observation noise (time
    stepping, smoothing, noisy shapes driving the forward model); ``bias`` is its size. The
    interval half-width is ``q · √(se² + bias²) · lack_of_fit``: ``se`` the cluster-robust
    standard error over cycles (noise), ``bias`` an allowance for the correction's own error, and
    ``lack_of_fit`` ``√max(1, held-out mean square)`` of the final model (what the model does not
    reproduce inflates every interval alike). The intervals of one effect are simultaneous at
    ``ci_level`` (``q`` the Bonferroni-corrected Student-t quantile over its values).
    """

    name: str
    description: str
    parameters: Mapping[str, float]
    ci: Mapping[str, tuple[float, float]]
    se: Mapping[str, float]
    bias: Mapping[str, float]
    lack_of_fit: float
    units: Mapping[str, str]
    fitted: Mapping[str, float]
    fitted_se: Mapping[str, float]
    ci_level: float
    gain: float
    p_value: float
    confounded_with: list[str] = field(default_factory=list)
    look_alikes: list[LookAlike] = field(default_factory=list)


# ============================================================================ what is left
@dataclass(frozen=True, kw_only=True)
class FlexibleTest(_Record):
    """Held-out gain of a flexible residual model (Fourier series in phase per component, heading
    and per-trial terms) over the final physical model: pooled and per component (each in its
    own noise-variance units)."""

    gain: float
    t: float
    p: float
    component_gain: Mapping[str, float]
    component_p: Mapping[str, float]


@dataclass(frozen=True, kw_only=True)
class Where(_Record):
    """Where a residual lives in one component: its gap, and the phase bins whose
    cycle-bootstrap band excludes zero."""

    component: str
    phase_bins: tuple[float, ...]
    peak: float
    peak_phase: float
    gap: float
    noise_floor: float
    text: str


@dataclass(frozen=True, kw_only=True)
class Unexplained(_Record):
    """A structured residual that no accepted effect explains, and where it lives."""

    message: str
    flexible_gain: float
    flexible_p: float
    excess_over_floor: float
    components: tuple[str, ...]
    where: tuple[Where, ...]


# ============================================================================ the report
@dataclass(eq=False)
class DiscrepancyReport:
    """The outcome of :func:`~torchconn.discrepancy.workflow.diagnose` (see :meth:`to_dict`
    for the JSON layout).

    ``effects`` are the named effects of an ``effect`` verdict; with ``unexplained`` the effects
    that explain part of the residual are ``partial_effects`` and ``unexplained`` says where the
    rest lives.
    """

    verdict: str
    effects: list[EffectEstimate]
    partial_effects: list[EffectEstimate]
    confounded_with: list[Confound]
    implausible: list[Implausible]
    gap_before: dict[str, float]
    gap_after: dict[str, float]
    noise_floor: dict[str, float]
    unexplained: Unexplained | None
    selection: list[SelectionStep]
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
            "effects": [e.to_dict() for e in self.effects],
            "partial_effects": [e.to_dict() for e in self.partial_effects],
            "confounded_with": [c.to_dict() for c in self.confounded_with],
            "implausible": [{**x.to_dict(), "message": x.message} for x in self.implausible],
            "gap_before": self.gap_before,
            "gap_after": self.gap_after,
            "noise_floor": self.noise_floor,
            "unexplained": None if self.unexplained is None else self.unexplained.to_dict(),
            "selection": [s.to_dict() for s in self.selection],
            "terms": _terms_summary(self.terms),
            "profiles": {k: {kk: vv.tolist() for kk, vv in v.items()}
                         for k, v in self.profiles.items()},
            "data": jsonable(self.data),
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
            lines.append(f"  effect {e.name}: {e.description}")
            for k, v in e.parameters.items():
                lo, hi = e.ci[k]
                lines.append(f"      {k} = {v:.5g}  [{lo:.5g}, {hi:.5g}]  {e.units[k]}")
            lines.append(f"      held-out gain {e.gain:.3g} (noise-variance units), "
                         f"p = {e.p_value:.2g}")
        for e in self.partial_effects:
            pars = ", ".join(f"{k}={v:.4g}" for k, v in e.parameters.items())
            lines.append(f"  partly explained by {e.name} ({pars}), but not within noise")
        for x in self.implausible:
            lines.append(f"  look-alike: {x.message}")
        if self.unexplained:
            lines.append(f"  unexplained discrepancy: {self.unexplained.message}")
            for w in self.unexplained.where:
                lines.append(f"      {w.component}: {w.text}")
        for c in self.confounded_with:
            lines.append(f"  CONFOUNDED: {c.message}")
        lines.append("  held-out gap (RMS residual)      before       after   noise floor")
        for k in COMPONENTS:
            lines.append(f"      {k:6s} {self.gap_before[k]:23.4g} {self.gap_after[k]:11.4g} "
                         f"{self.noise_floor[k]:13.4g}")
        return "\n".join(lines)

    def report(self, title: str = "torchconn-discrepancy", figures: dict | None = None
               ) -> Report:
        """The verdict in plain words, the gaps before and after, and ``figures`` (file name
        -> (PNG bytes, caption), :func:`~torchconn.plotting.render_png`) as a
        :class:`~torchconn.report.Report` (``report.html``)."""
        report = Report(title)
        verdict = {
            "none": "The simulator agrees with the measurements within their noise: no "
                    "missing effect is needed.",
            "effect": "The simulator misses an effect; adding "
                      + " and ".join(e.name for e in self.effects)
                      + " closes the gap to the measurements.",
            "unexplained": "The simulator and the measurements disagree beyond the noise, "
                           "and no registered effect explains it fully.",
        }[self.verdict]
        report.section("Verdict", [verdict])
        for e in self.effects + self.partial_effects:
            lines = [e.description] + [
                f"{k} = {v:.4g} {e.units[k]} (95 % interval {e.ci[k][0]:.4g} to "
                f"{e.ci[k][1]:.4g})" for k, v in e.parameters.items()]
            lines.append(f"held-out p-value {e.p_value:.2g}: how likely a gain this large "
                         "would be by chance")
            report.section(f"Effect: {e.name}" + ("" if e in self.effects
                                                  else " (explains part of it)"), lines)
        cautions = [x.message for x in self.implausible] + [c.message
                                                             for c in self.confounded_with]
        if self.unexplained:
            cautions.append(f"unexplained: {self.unexplained.message}")
            cautions += [f"{w.component}: {w.text}" for w in self.unexplained.where]
        if cautions:
            report.section("Read with care", cautions)
        report.table(
            "The gap between simulator and measurements, on held-out cycles (RMS residual)",
            ["component", "before", "after", "noise floor"],
            [[k, f"{self.gap_before[k]:.3g}", f"{self.gap_after[k]:.3g}",
              f"{self.noise_floor[k]:.3g}"] for k in COMPONENTS],
            note="v_x, v_y in body lengths per time unit, omega in rad per time unit; 'after' "
                 "is with the named effects added. A gap at the noise floor is all the data "
                 "can show.")
        for name, (png, caption) in (figures or {}).items():
            report.figure(png, caption or name)
        return report

    def save(self, out: str | Path, *, figures: bool = True) -> dict[str, Path]:
        """Write ``report.json``, ``report.html`` (:meth:`report`), ``augmented_model.json``,
        ``residual_profile.csv`` and the figures into ``out``, each file atomically; returns
        the paths."""
        out = Path(out)
        paths = {}
        paths["report"] = out / "report.json"
        write_sidecar(paths["report"], self.to_dict())
        if isinstance(self.model.nominal, NLinkSwimmer):
            paths["model"] = self.model.save(out / "augmented_model.json")
        paths["profile_csv"] = write_table(
            out / "residual_profile.csv",
            ["model", "component", "phase", "mean", "lo", "hi", "disagrees", "noise_floor"],
            [[label, comp, f"{ph:.6g}", f"{prof['mean'][i, k]:.6g}", f"{prof['lo'][i, k]:.6g}",
              f"{prof['hi'][i, k]:.6g}", int(prof["disagrees"][i, k]),
              f"{self.noise_floor[comp]:.6g}"]
             for label, prof in self.profiles.items()
             for i, ph in enumerate(prof["centres"]) for k, comp in enumerate(COMPONENTS)])
        drawn = {}  # each figure rendered once, for its file and for the report
        if figures:
            # lazy: the figures import matplotlib, which only a report with figures needs
            from ..plotting import render_png
            from .figures import plot_residual_profiles, plot_terms

            drawn["residual_vs_phase.png"] = render_png(plot_residual_profiles(self))
            if self.terms is not None:
                drawn["terms_vs_simulator.png"] = render_png(plot_terms(self.terms))
        paths["html"] = self.report(figures=drawn).write(out / "report.html")
        for key, name in (("figure", "residual_vs_phase.png"),
                          ("terms_figure", "terms_vs_simulator.png")):
            if name in drawn:
                paths[key] = write_bytes_atomic(out / name, drawn[name][0])
        return paths


def _range_text(r: tuple[float, float]) -> str:
    lo, hi = r
    if math.isinf(hi):
        return f">= {lo:g}"
    if math.isinf(lo):
        return f"<= {hi:g}"
    return f"[{lo:g}, {hi:g}]"


def _terms_summary(terms: dict | None) -> dict | None:
    if terms is None:
        return None
    return {"phase": terms["phase"], "reference": terms["reference"],
            "summary": {k: v["summary"] for k, v in terms["terms"].items()},
            "z": {k: v["z"] for k, v in terms["terms"].items()}}
