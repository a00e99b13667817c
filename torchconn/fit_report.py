"""The fit's report in plain words: what was fitted, how well it predicts, what to trust, what next.

:func:`fit_report` turns a fitted :class:`~torchconn.regression.estimator.ConnectionEstimator`
into a :class:`~torchconn.report.Report`: ``torchconn-fit`` prints its text and writes it,
with the figures, as ``report.html``. Units: time in the recording's (seconds for recorded
data, as ``torchconn-convert`` writes), lengths in body lengths (BL), angles in radians.
"""

from __future__ import annotations

import math

from .cycles import cycles_spanned
from .regression.selection import COMPONENTS
from .report import Report, trust

__all__ = ["fit_report", "trusted_parts", "GOOD_R2"]

#: the body-velocity components in words, with their units
_NAMES = {"v_x": "forward speed v_x (BL/s)", "v_y": "sideways speed v_y (BL/s)",
          "omega": "turning rate ω (rad/s)"}
#: R² above which a component counts as well predicted
GOOD_R2 = 0.7


def trusted_parts(model) -> list[tuple[str, str, float]]:
    """``(part, word, ratio)`` for ``Â``, ``∂Â/∂r`` and ``M̂`` (where fitted): how well each is
    determined, by :func:`~torchconn.report.trust` on its per-bin estimates and standard
    errors."""
    bins = model.bins
    parts = [("the connection Â", bins.A, bins.A_se),
             ("its shape derivative ∂Â/∂r", bins.dA, bins.dA_se)]
    if bins.M is not None:
        parts.append(("the dissipation metric M̂", bins.M, bins.M_se))
    out = []
    for name, value, se in parts:
        word, ratio = trust(value.detach().cpu().numpy(), se.detach().cpu().numpy())
        out.append((name, word, ratio))
    return out


def _r2_row(label: str, r2) -> list[str]:
    values = ["—" if r2 is None else f"{float(v):.2f}" for v in
              (r2.reshape(-1, 3).mean(0) if r2 is not None else [None] * 3)]
    return [label, *values]


def fit_report(est, *, title: str, n_links: int, frame: str, frequency_hz: float,
               reference: str = "", figures: list[tuple[object, str]] = (),
               details: list[str] = ()) -> Report:
    """The plain-language report of a fitted estimator.

    Args:
        est: a fitted ``ConnectionEstimator``.
        title: the page's heading (the command and its data).
        n_links: the body's links; frame: the body frame of the velocities.
        frequency_hz: the gait's frequency (cycles per second of the recording's ``t``).
        reference: the physics reference and its fitted parameters, in words.
        figures: ``(Figure, caption)`` pairs, in order (the first: recorded against predicted
            velocity on held-out cycles).
        details: the fit's choices in a specialist's words (complexity, files), last.
    """
    model = est.model_
    traj = est.trajectory_
    n_trials = traj.batch_shape.numel()
    cycles = float(cycles_spanned(traj.phase).min())  # the fewest of any trial
    per_cycle = 2 * math.pi / max(float(model.phase_rate.double().mean()) * traj.dt, 1e-12)
    report = Report(title)
    report.section("What was fitted", [
        f"{n_trials} trial(s), {traj.n_samples} samples each, about {cycles:.1f} gait cycles "
        f"per trial at {per_cycle:.0f} samples per cycle",
        f"gait frequency {frequency_hz:.3g} Hz (period {1 / frequency_hz:.3g} s)",
        f"{n_links} links ({n_links - 1} joint angles, joint 1 nearest the tail), velocities "
        f"in the {frame} body frame",
    ])
    held, forward = est.held_out_skill_, est.forward_skill_
    if held is not None:
        rows = [_r2_row("this model", held.r2),
                _r2_row("phase-averaged velocity", held.r2_phase_average),
                _r2_row("physics (resistive-force theory)", held.r2_physics),
                _r2_row("no motion (zero)", held.r2_zero)]
        if forward is not None:
            rows.insert(1, _r2_row("this model, later cycles only", forward.r2))
        report.table(
            "How well it predicts cycles it did not see (R², 1 is perfect, 0 no better than "
            "the mean)", ["predictor", *(_NAMES[c] for c in COMPONENTS)], rows,
            note=f"Each of {est.held_out_folds} blocks of whole cycles left out in turn and "
            "predicted by the fit to the others; 'later cycles' predicts the last block from "
            "the earlier ones. Physics: " + (reference or "the viscous swimmer")
            + ", refitted without the cycles predicted.")
        report.section("In words", _verdicts(est))
    trusted = trusted_parts(model)
    report.section("Which parts of the model can be trusted", [
        f"{name}: {word} determined (95 % band ±{ratio:.0%} of its size)"
        if math.isfinite(ratio) else f"{name}: {word}" for name, word, ratio in trusted],
        note="'well': band under 10 % of the estimate's size; 'roughly': under 30 %; "
        "'poorly': wider.")
    report.section("What to do next", _advice(est, trusted))
    for fig, caption in figures:
        report.figure(fig, caption)
    if details:
        report.section("Details (for the methods section)", list(details))
    return report


def _verdicts(est) -> list[str]:
    """One sentence per velocity component: how well the delivered forecasts predict it held
    out, against the best baseline."""
    held = est.held_out_skill_
    weight = est.prior_weight_
    out = []
    for k, name in enumerate(COMPONENTS):
        r2 = float(held.r2[..., k].mean())
        base = {"the phase-averaged velocity": held.r2_phase_average,
                "the physics reference": held.r2_physics}
        best_name, best = max(((n, float(v[..., k].mean())) for n, v in base.items()
                               if v is not None and math.isfinite(float(v[..., k].mean()))),
                              key=lambda x: x[1], default=("", -math.inf))
        grade = "well" if r2 >= GOOD_R2 else "partly" if r2 > 0 else "not"
        line = f"{_NAMES[name]} is predicted {grade} (R² {r2:.2f})"
        if best_name:
            line += (f", better than {best_name} ({best:.2f})" if r2 >= best - 0.02
                     else f", worse than {best_name} ({best:.2f})")
        if weight is not None and float(weight[..., k].mean()) > 0:
            line += (f"; the forecast leans on the physics reference "
                     f"({float(weight[..., k].mean()):.0%})")
        out.append(line)
    return out


def _advice(est, trusted) -> list[str]:
    """What a user can do about the weak parts of the fit."""
    out = []
    held = est.held_out_skill_
    if held is None:
        out.append("No held-out check ran (--folds 0): run with the default --folds 3 to "
                   "learn how well the model predicts.")
    else:
        if bool(held.worse_than_phase_average.any()) or bool(held.without_skill.any()):
            out.append("Some components are predicted no better than their phase average: "
                       "record more cycles, or cycles that vary the gait (amplitude, "
                       "frequency), so the shape terms can be estimated.")
        weight = est.prior_weight_
        if weight is not None and bool((weight > 0).any()):
            out.append("The physics reference predicts held-out cycles better than the "
                       "data-driven model for some components: with more cycles the data "
                       "will outweigh it.")
    for name, word, _ in trusted:
        if word == "poorly" and "derivative" in name:
            out.append("∂Â/∂r is poorly determined: it needs cycles that leave the gait "
                       "further (vary the amplitude between cycles or trials); do not "
                       "design gaits with it yet.")
        elif word == "poorly" and "metric" in name:
            out.append("M̂ is poorly determined off the gait: trust M̂γ̇ and the power on the "
                       "cycle (identified by the gait itself), not the full matrix.")
        elif word == "poorly":
            out.append("Â is poorly determined: record more cycles, or reduce tracking "
                       "noise (more keypoints, higher frame rate).")
    if not out:
        out.append("Nothing is weak: the model can be used to predict and to design gaits "
                   "near this one.")
    return out
