"""Held-out skill of a fitted local model against two baselines, and complexity chosen by it.

The skill is ``R² = 1 − SSE/SST`` per body-velocity component against the observed velocity
the way the regression sees it (raw interval differences for
:class:`~torchconn.regression.noise_aware.NoiseAwareRegression`, the smoothed velocity for
:class:`~torchconn.regression.tube.TubeRegression`), beside

- the phase-averaged velocity of the training data (a Fourier series in phase of the observed
  velocity, ignoring the shape), and
- the template ``ĉ(φ) = Â(γ)γ̇``, the model on the cycle.

Held-out blocks are contiguous whole cycles of every trial, so nothing is random and a
choice made on them is reproducible.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .. import _linalg
from ..phase.fourier import FourierSeries, fit_fourier, fourier_design
from ..phase.limit_cycle import LimitCycle
from ..trajectory import Trajectory, pool_batch
from . import _wls
from ._wls import IllConditionedBinWarning
from .binning import assign_bins
from .connection import split_coefficients, unpenalised_columns
from .held_out import leave_blocks_out
from .model import LocalConnectionModel
from .noise_aware import (
    VELOCITY_KERNEL,
    NoiseAwareRegression,
    eiv_correction,
    interval_noise_gains,
    interval_view,
)
from .tube import Regression, TubeRegression, _auto_window, intercept_series

__all__ = ["Skill", "PoorHeldOutSkillWarning", "ComplexityChoice", "COMPLEXITY_GRID",
           "RIDGE_GRID", "FALLBACK_Z", "FALLBACK_MARGIN", "FALLBACK_CYCLES", "OFFSET_TERMS_Z",
           "COMPONENTS",
           "regression_view", "cross_validate", "checked_terms", "few_cycles",
           "phase_average_orders", "unchecked_choice", "connection_columns",
           "ConnectionAlone", "select_connection_alone", "connection_alone_model",
           "select_complexity", "skill", "with_phase_average", "nested_list"]

#: the body-velocity components, in the order of the last axis of ξ
COMPONENTS = ("v_x", "v_y", "omega")

#: (n_bins, fourier_order) candidates of :func:`select_complexity`, simplest first
COMPLEXITY_GRID = ((12, 3), (24, 6), (48, 12))
#: ridge candidates of :func:`select_complexity` (relative to the standardised normal matrix).
#: Chosen by held-out prediction, which the intercept dominates, a ridge on every shape column
#: shrinks ``Â`` -- the attenuation the noise correction removes (one trial, 3-link circle, 32
#: samples per cycle, ω = 0.005, seed 610, ``noise_floor="low_rate"``: ridge 1 chosen, Â
#: 79.2 % off at scale 0.23); ``TubeRegression(ridge_connection=False)`` leaves ``Â``'s
#: columns alone (12.8 % there; README "The ridge and Â")
RIDGE_GRID = (0.0, 0.1, 1.0, 10.0)
#: a ridge is chosen only when it lowers the best unpenalised held-out loss by more than this
#: fraction: a ridge shrinks Â (the attenuation the noise-aware regression removes), and on
#: long recordings the candidates' losses differ by less than their noise (measured: 5-link,
#: ω = 0.01, 0.38879 with a ridge vs 0.38884 without, and Â 48 % vs 10 % off)
RIDGE_MIN_GAIN = 0.01
#: per component, three models compete on held-out cycles (:func:`select_complexity`): the
#: full model, the connection alone (``ĉ + Âδ̇``: the rows of ``b̂`` and ``∂Â/∂r`` set to 0),
#: and the phase-averaged velocity. A model counts only when it lowers the component's
#: held-out squared error below the phase average's by more than ``FALLBACK_Z`` standard
#: errors (over the held-out cycles) and by more than the fraction ``FALLBACK_MARGIN`` of it;
#: when neither does, the component is predicted by the phase-averaged velocity alone.
#: Held-out blocks of the training cycles flatter the shape terms against later cycles: on
#: short recordings the swimmer's shape offsets wander, and later cycles reach offsets 2-5x
#: those of the training cycles, where ``b̂δ`` and ``∂Â/∂r`` extrapolate (measured with the
#: noise-aware default, 5-link, ω = 0.005, 3-6 cycles, 3 gaits, tuning seeds 30-34, the later
#: 4 cycles scored: lost to the phase average in 37 of 180 components without a fall-back,
#: 17 with the connection alone everywhere, 1 with these settings (4 if the auto fit's check
#: does not choose too, :func:`checked_terms`; held out, seeds 10-14 / 20-24: 37 / 21 -> 5 / 1,
#: all under 0.03 in R²); percomp's earlier
#: full-model-or-phase-average rule, ``z = 1`` and 30 %, left 5 losses but 149 ties: v_x and
#: v_y fell back in 54-56 of 59 recordings)
FALLBACK_Z = 2.5
FALLBACK_MARGIN = 0.1
#: on recordings of up to this many cycles the simpler model is presumed, on longer ones the
#: full model (:func:`few_cycles`, :func:`_choose_terms`): the rule and its margin were
#: measured on 3-6 cycles only
FALLBACK_CYCLES = 6
#: the rows of ``b̂`` and ``∂Â/∂r`` are kept only when the full model's held-out squared error
#: is below the connection alone's by more than this many standard errors (seeds 30-34: 3 and
#: 4 gave the same losses; 3 keeps them wherever the data clearly ask for them)
OFFSET_TERMS_Z = 3.0


class PoorHeldOutSkillWarning(UserWarning):
    """The fitted model predicted held-out cycles worse than their phase-averaged velocity."""


@dataclass(frozen=True)
class Skill:
    """Skill ``R²`` per component ``(v_x, v_y, ω)`` of a model and of two baselines.

    Attributes:
        r2: ``(..., 3)`` the fitted model ``ĉ + b̂δ + Âδ̇ + ∂Â/∂r (δ̇⊗δ)``.
        r2_phase_average: ``(..., 3)`` the training data's phase-averaged velocity.
        r2_template: ``(..., 3)`` the template ``ĉ(φ) = Â(γ)γ̇``.
        n_samples: ``(...)`` samples scored.
    """

    r2: Tensor
    r2_phase_average: Tensor
    r2_template: Tensor
    n_samples: Tensor

    @property
    def unscored(self) -> Tensor:
        """``(...)`` True where the skill is undefined (NaN): some bin could not be fitted
        without one of the held-out blocks (too few cycles for the model's complexity)."""
        return ~torch.isfinite(self.r2).all(-1)

    @property
    def worse_than_phase_average(self) -> Tensor:
        """``(..., 3)`` True where the model loses to a phase-averaged baseline that has skill
        (``R² > 0``)."""
        return (self.r2 < self.r2_phase_average) & (self.r2_phase_average > 0)

    @property
    def without_skill(self) -> Tensor:
        """``(..., 3)`` True where neither the model nor the phase-averaged baseline predicts
        better than the held-out mean (both ``R² ≤ 0``), which
        :attr:`worse_than_phase_average` does not count."""
        return (self.r2 <= 0) & (self.r2_phase_average <= 0)

    def warn_if_poor(self, stacklevel: int = 3, choice: "ComplexityChoice | None" = None,
                     searched: bool = False) -> None:
        """Warn (:class:`PoorHeldOutSkillWarning`) where :attr:`worse_than_phase_average` or
        :attr:`unscored`, and where :attr:`without_skill`; ``choice``: the complexity chosen by
        held-out error, if any (the advice then is more cycles, not fewer bins); ``searched``:
        the search by held-out error ran and no candidate could be scored (the advice then is
        more data too)."""
        self._warn_against_baseline(stacklevel + 1, choice, searched)
        if bool(self.without_skill.any()):
            warnings.warn(
                "neither the model nor the phase-averaged velocity predicts held-out cycles "
                f"better than their mean velocity for {self.without_skill_names()}: these "
                "components are not predictable from the gait's phase and shape on this "
                "recording (noise, or a motion the shape changes do not drive: a flow, a "
                "tether, contact), and their rows of the model are not to be relied on",
                PoorHeldOutSkillWarning, stacklevel=stacklevel)

    def _warn_against_baseline(self, stacklevel: int, choice: "ComplexityChoice | None",
                               searched: bool) -> None:
        """:meth:`warn_if_poor`'s warnings against the phase-averaged baseline."""
        fix = ("record more cycles (the complexity was already chosen by held-out error: "
               f"{choice.n_bins} bins, Fourier order {choice.fourier_order}, ridge "
               f"{choice.ridge:g})" if choice is not None else
               "record more cycles, or more samples per cycle (complexity='auto' already "
               "searched the complexity by held-out error, and no candidate down to "
               f"{COMPLEXITY_GRID[0][0]} bins, Fourier order {COMPLEXITY_GRID[0][1]} could be "
               "fitted without one block of cycles, so the given one is kept unchecked)"
               if searched else
               "choose the complexity by held-out error (ConnectionEstimator(complexity='cv'), "
               "torchconn-fit --complexity cv), or use fewer bins / a lower Fourier order / a "
               "ridge, or record more cycles")
        if bool(self.unscored.any()) and choice is not None and not choice.checked:
            warnings.warn(
                "held-out check: some phase bins cannot be fitted when one block of whole "
                "cycles is left out, at this or any simpler complexity, so the model cannot "
                f"be checked on this short recording; {', '.join(choice.phase_averaged_names())}"
                " are predicted by the phase-averaged velocity of the training data (predict() "
                "and forecast_model_: rows of b̂, Â and ∂Â/∂r 0 in the unchecked trials; "
                "model_ keeps the given complexity's estimates, unchecked); record more cycles",
                PoorHeldOutSkillWarning, stacklevel=stacklevel)
            return
        if bool(self.unscored.any()):
            warnings.warn(
                "held-out check: some phase bins cannot be fitted when one block of whole "
                "cycles is left out, so the model has too many coefficients for this "
                f"recording; {fix}", PoorHeldOutSkillWarning, stacklevel=stacklevel)
            return
        worse = self.worse_than_phase_average.reshape(-1, 3).any(0)
        if not bool(worse.any()):
            fallback = [] if choice is None else choice.phase_averaged_names()
            reduced = [] if choice is None else choice.connection_only_names()
            if choice is not None and choice.connection_regressed:
                predicted = (f"the connection alone ĉ + Âδ̇ predicts {', '.join(reduced)}"
                             if reduced else "")
                averaged = (f"the phase-averaged velocity of the training data predicts "
                            f"{', '.join(fallback)} (the connection alone did not beat it "
                            "held out)" if fallback else "")
                warnings.warn(
                    "held-out check: no model with the offset terms b̂ and ∂Â/∂r can be fitted "
                    "when one block of whole cycles is left out (too few samples per cycle "
                    "for their coefficients), so the connection alone (1 + d regressors per "
                    f"bin) was fitted and checked instead, at {choice.n_bins} bins, Fourier "
                    f"order {choice.fourier_order}: "
                    + "; ".join(p for p in (predicted, averaged) if p)
                    + "; model_ is that connection (b̂ and ∂Â/∂r not estimated: 0); record "
                    "more cycles, or more samples per cycle, to estimate them",
                    PoorHeldOutSkillWarning, stacklevel=stacklevel)
                return
            if reduced:
                warnings.warn(
                    f"the offset terms b̂ and ∂Â/∂r did not improve the held-out prediction of "
                    f"{', '.join(reduced)} beyond the connection Â alone, so the forecasting "
                    "model (predict(), forecast_model_) sets their rows to 0 and keeps Â; "
                    "model_ keeps them as estimated; record more cycles, or cycles that leave "
                    "the gait further, to estimate them",
                    PoorHeldOutSkillWarning, stacklevel=stacklevel)
            if fallback:
                warnings.warn(
                    f"the shape terms do not predict held-out cycles of {', '.join(fallback)} "
                    "better than their phase-averaged velocity, so the forecasting model "
                    "(predict(), forecast_model_) predicts "
                    f"{'it' if len(fallback) == 1 else 'them'} by the phase-averaged velocity "
                    "of the training data: its rows of b̂, Â and ∂Â/∂r for "
                    f"{', '.join(fallback)} are 0; model_ keeps them as estimated, though they "
                    "did not beat it held out; record more cycles to estimate them",
                    PoorHeldOutSkillWarning,
                    stacklevel=stacklevel)
            return
        warnings.warn(
            f"the model predicts held-out cycles worse than their phase-averaged velocity for "
            f"{self.shortfalls()}: its shape terms do not help predict these "
            f"components on this recording (too few cycles for its coefficients, or joint-"
            f"angle noise that swamps the shape deviations); {fix}", PoorHeldOutSkillWarning,
            stacklevel=stacklevel)

    def shortfalls(self) -> str:
        """Each losing component with the model's and the phase average's held-out ``R²`` in
        the trial where it loses most (both from that trial; its index where there are
        several), e.g. ``v_x (held-out R² 0.412 vs phase average 0.455 in trial 2)``, with
        as many decimals (3 to 6) as it takes to tell the two apart (3 where they are equal)."""
        return self._named(self.worse_than_phase_average, self.r2_phase_average - self.r2,
                           " vs")

    def without_skill_names(self) -> str:
        """Each component :attr:`without_skill` with the model's and the phase average's
        held-out ``R²`` in the trial where the model scores lowest, e.g. ``v_y (held-out R²
        -0.392, phase average -0.601)``."""
        return self._named(self.without_skill, -self.r2, ",")

    def _named(self, mask: Tensor, badness: Tensor, joint: str) -> str:
        """The components where ``mask (..., 3)``, each with both ``R²`` of the trial of
        largest ``badness (..., 3)`` (its index where there are several)."""
        model = self.r2.reshape(-1, 3)
        base = self.r2_phase_average.reshape(-1, 3)
        mask = mask.reshape(-1, 3)
        badness = torch.where(mask, badness.reshape(-1, 3), -torch.inf)
        parts = []
        for k, name in enumerate(COMPONENTS):
            if not bool(mask[:, k].any()):
                continue
            trial = int(badness[:, k].argmax())
            where = (f" in trial {_trial_index(trial, self.r2.shape[:-1])}"
                     if model.shape[0] > 1 else "")
            a, b = float(model[trial, k]), float(base[trial, k])
            digits = next((n for n in range(3, 7) if f"{a:.{n}f}" != f"{b:.{n}f}"), 3)
            parts.append(f"{name} (held-out R² {a:.{digits}f}{joint} phase average "
                         f"{b:.{digits}f}{where})")
        return ", ".join(parts)


@dataclass(frozen=True)
class ComplexityChoice:
    """What :func:`select_complexity` chose, and every candidate's mean held-out ``SSE/SST``
    (each component at the better of the model and the phase-averaged velocity, as chosen).

    Attributes:
        n_bins, fourier_order, ridge: the regression's complexity.
        scores: ``(n_bins, fourier_order, ridge, loss)`` of every candidate.
        phase_averaged: nested tuples of bools shaped ``(..., 3)`` (the model's batch dims,
            components ``v_x, v_y, ω``): True where the component is predicted by the
            phase-averaged velocity of the training data, its shape terms set to 0 in the
            forecasting model (``ConnectionEstimator.forecast_model_``; ``model_`` keeps
            them), because they did not beat it on held-out cycles (:data:`FALLBACK_Z`).
        connection_only: likewise: True where the component keeps ``ĉ`` and its row of
            ``Â`` but its rows of ``b̂`` and ``∂Â/∂r`` are set to 0, because the connection
            alone beat the phase average on held-out cycles and those terms did not clearly
            add to it (:data:`OFFSET_TERMS_Z`).
        checked: False where no candidate could be scored held out and the complexity is
            the one given (:func:`unchecked_choice`): ``scores`` is empty and
            ``phase_averaged`` marks the short recordings the check could not score.
        connection_regressed: True where no model with ``b̂`` and ``∂Â/∂r`` could be scored
            held out and the connection alone was regressed and scored instead
            (:func:`select_connection_alone`): the forecasts' ``c + Âδ̇`` come from a fit
            with ``1 + d`` regressors per bin, not from the full model with rows set to 0.
    """

    n_bins: int
    fourier_order: int
    ridge: float
    scores: tuple[tuple[int, int, float, float], ...]
    phase_averaged: tuple = (False, False, False)
    connection_only: tuple = (False, False, False)
    checked: bool = True
    connection_regressed: bool = False

    def phase_average_mask(self, device: torch.device | str) -> Tensor:
        """:attr:`phase_averaged` as a bool tensor ``(..., 3)`` on ``device``."""
        return torch.tensor(self.phase_averaged, dtype=torch.bool, device=device)

    def connection_only_mask(self, device: torch.device | str) -> Tensor:
        """:attr:`connection_only` as a bool tensor ``(..., 3)`` on ``device``."""
        return torch.tensor(self.connection_only, dtype=torch.bool, device=device)

    def phase_averaged_names(self) -> list[str]:
        """The components predicted by the phase-averaged velocity in some batch element."""
        return _names(self.phase_averaged)

    def connection_only_names(self) -> list[str]:
        """The components whose ``b̂`` and ``∂Â/∂r`` rows are 0 in some batch element."""
        return _names(self.connection_only)


def unchecked_choice(held: "Skill | None", regression: Regression, short: Tensor
                     ) -> ComplexityChoice | None:
    """The choice when :func:`select_complexity` has no candidate (too few cycles) and the
    given complexity's fit stands: every component of a batch element that the held-out check
    ``held`` could not score (:attr:`Skill.unscored`) and that spans few cycles (``short``,
    :func:`few_cycles`) is predicted by the phase average, the simpler model presumed there
    (9-link reference gait, 3 cycles, ω = 0.005: the unchecked 48-bin fit scored R² −0.58 /
    0.34 / 0.75 on the next 4 cycles, the phase average 0.54 / 0.84 / 0.96). None where no
    such element (longer recordings keep the fit; the check warns)."""
    if held is None:
        return None
    mask = (held.unscored & short)[..., None].expand(held.r2.shape)
    if not bool(mask.any()):
        return None
    return ComplexityChoice(n_bins=regression.n_bins, fourier_order=regression.fourier_order,
                            ridge=regression.ridge, scores=(), checked=False,
                            phase_averaged=_nested_tuple(mask))


def _names(mask: tuple) -> list[str]:
    """The components True in some row of a nested ``(..., 3)`` tuple of bools."""
    def rows(x):
        return [x] if not isinstance(x[0], tuple) else [r for v in x for r in rows(v)]
    any_ = [any(col) for col in zip(*rows(mask), strict=True)]
    return [n for n, a in zip(COMPONENTS, any_, strict=True) if a]


@dataclass(frozen=True)
class _View:
    phase: Tensor  # (..., N)
    r: Tensor  # (..., N, d)
    r_dot: Tensor
    xi: Tensor  # (..., N, 3)


def regression_view(traj: Trajectory, regression: Regression, model: LocalConnectionModel,
                    *, pool: bool, flatten: bool = True) -> _View:
    """Samples ``(..., N, ·)`` as ``regression`` sees them (pooled to ``(N,)`` when ``pool``
    and ``flatten``); the interval of a noise-aware model comes from its ``meta``."""
    if isinstance(regression, NoiseAwareRegression):
        iv = interval_view(traj, torch.as_tensor(model.meta["velocity_interval"],
                                                 device=traj.r.device),
                           model.meta.get("velocity_kernel", VELOCITY_KERNEL))
        view = _View(iv.phase, iv.r, iv.r_dot, iv.xi)
    else:
        sm = traj.smoothed
        view = _View(traj.phase, sm.r, sm.r_dot, sm.xi)
    if pool and flatten:
        view = _View(pool_batch(view.phase, 0), pool_batch(view.r, 1),
                     pool_batch(view.r_dot, 1), pool_batch(view.xi, 1))
    return view


def phase_average(view: _View, order: int, orders: Tensor | None = None) -> FourierSeries:
    """The phase-averaged velocity: a Fourier series of order ``order`` of ``view.xi``.

    ``orders``: ``(..., 3)`` per component (and batch element, broadcasting against the
    view's batch dims) the order of its own least-squares series, at most ``order``
    (:func:`phase_average_orders`); its harmonics above that are 0. None: ``order`` for all."""
    full = fit_fourier(view.phase, view.xi, order, value_ndim=1)
    if orders is None:
        return full
    coeffs = full.coeffs  # (..., 2 order + 1, 3)
    for k in orders.unique().tolist():
        if k == order:
            continue
        own = fit_fourier(view.phase, view.xi, k, value_ndim=1).padded(order).coeffs
        coeffs = torch.where((orders == k).unsqueeze(-2), own, coeffs)
    return FourierSeries(coeffs, 1)


def phase_average_orders(view: _View, max_order: int, pool: bool, n_folds: int = 3
                         ) -> Tensor:
    """``(..., 3)`` (pooled: ``(3,)``) per component the order, at most ``max_order``, of the
    phase-averaged velocity with the least held-out squared error over the ``n_folds`` blocks
    of whole cycles the models are scored on (:func:`_cycle_blocks`; ``view`` unflattened,
    ``(..., N, ·)``; the lowest order on ties). One set of normal equations per block gives
    every order (their designs are nested). A stronger baseline than :func:`phase_average` at
    the model's own order, which overfits the few cycles of a short recording (5- and 3-link,
    3-6 cycles, ω = 0.005: the order-12 phase average of 2 of 3 cycles scored R² 0.38-0.54 on
    v_x held out, order 3 0.66-0.78); ``benchmarks/short_recordings.py`` scores the default
    against both (the estimator's checks use the model's order: measured against this one they
    fell back on nearly every v_x and v_y and lost mean skill, README "Short recordings")."""
    fold = _cycle_blocks(view.phase, n_folds)
    ok = torch.isfinite(view.phase) & torch.isfinite(view.xi).all(-1)
    x = fourier_design(torch.where(ok, view.phase, 0.0), max_order)  # (..., N, P)
    y = torch.where(ok[..., None], view.xi, 0.0)  # (..., N, 3)
    dims = tuple(range(view.phase.ndim - 1)) if pool else ()
    grams, rhs, yy = [], [], []
    for f in range(n_folds):
        w = ((fold == f) & ok).to(x.dtype)[..., None]
        xw = x * w
        parts = (xw.mT @ x, xw.mT @ y, (y.square() * w).sum(-2))
        if dims:
            parts = tuple(p.sum(dims) for p in parts)
        grams.append(parts[0])
        rhs.append(parts[1])
        yy.append(parts[2])
    gram, xy = sum(grams), sum(rhs)
    scores = []
    for order in range(max_order + 1):
        p = 2 * order + 1
        sse = 0.0
        for f in range(n_folds):  # fit without block f, scored on it
            coef = _linalg.lstsq((gram - grams[f])[..., :p, :p], (xy - rhs[f])[..., :p, :],
                                  "the phase average's normal matrix")  # (..., p, 3)
            g = grams[f][..., :p, :p]
            sse = sse + yy[f] - 2 * (coef * rhs[f][..., :p, :]).sum(-2) + (
                coef * (g @ coef)).sum(-2)
        scores.append(sse)
    return torch.stack(scores).argmin(0)


def skill(model: LocalConnectionModel, baseline, view: _View,
          template: LocalConnectionModel | None = None) -> Skill:
    """:class:`Skill` of ``model`` and ``baseline`` (a phase-averaged velocity) on ``view``;
    the template is ``ĉ`` of ``template`` (default ``model``): a forecasting model whose
    component falls back to the phase average has that for its ``ĉ`` there, so pass the
    connection it came from."""
    return _from_sums(*_sums(model, baseline, view, None, template=template)[0][:6])


def cross_validate(traj: Trajectory, cycle: LimitCycle, regression: Regression, *,
                   pool: bool, n_folds: int = 3, noise_corrected: bool = False,
                   model: LocalConnectionModel | None = None, refit: bool = False,
                   phase_averaged: Tensor | None = None,
                   connection_only: Tensor | None = None,
                   connection_regressed: bool = False) -> Skill:
    """Held-out skill over ``n_folds`` contiguous blocks of whole cycles of every trial.

    Each block in turn is left out of the regression and scored; the phase and the limit
    cycle of the whole recording are kept (they carry little of the model's complexity). The
    metric is not refitted.

    For :class:`~torchconn.regression.tube.TubeRegression` and
    :class:`~torchconn.regression.noise_aware.NoiseAwareRegression` the fits without each block
    come from downdating every bin's normal equations (:mod:`~torchconn.regression.held_out`):
    the window, velocity interval and noise level of the fit to the whole recording are kept,
    and the cost is about one more pass over the data. ``refit=True`` (and any other regression)
    refits the regression without each block instead (its samples get a NaN phase, as
    drop-outs do), re-choosing window, interval and noise level from the remaining cycles.

    ``model``: the regression's fit to the whole recording, when already at hand (its
    ``meta`` gives the window, interval and noise level).

    ``phase_averaged``: ``(..., 3)`` bool, components each fold's model predicts by the
    phase-averaged velocity of its training blocks (:func:`with_phase_average`, as
    :func:`select_complexity` chose): their skill equals the baseline's. ``connection_only``:
    ``(..., 3)`` bool, components whose rows of ``b̂`` and ``∂Â/∂r`` each fold's model sets
    to 0 (likewise). ``connection_regressed``: each fold regresses the connection alone
    (:func:`connection_columns`), as :func:`select_connection_alone` checked it (downdated
    fits only).

    ``noise_corrected`` (noise-aware regressions): subtract from the model's squared error the
    part the joint-angle noise of the held-out *inputs* adds (:func:`_input_noise_variance`),
    so that the score ranks models by how well they predict from the true shapes. Without it,
    held-out error on noisy inputs favours models shrunk towards 0 (the attenuation the
    noise-aware regression removes).

    Raises:
        ValueError: ``refit`` and a block that cannot be fitted (the solver's message). The
            downdated fits never raise: a bin that cannot be fitted without a block predicts
            NaN, and the skill of that trial is NaN (see :attr:`Skill.unscored`).
    """
    if isinstance(n_folds, bool) or not isinstance(n_folds, int) or n_folds < 2:
        raise ValueError(f"n_folds must be an integer >= 2, got {n_folds!r}")
    if connection_regressed and (refit or not downdates(regression)):
        raise ValueError("cross_validate: connection_regressed needs the downdated fits of a "
                         "TubeRegression or NoiseAwareRegression (refit=False)")
    return _held_out_skills(traj, cycle, regression, pool=pool, n_folds=n_folds,
                            noise_corrected=noise_corrected, model=model, refit=refit,
                            phase_averaged=phase_averaged, connection_only=connection_only,
                            connection_regressed=connection_regressed)


def _held_out_skills(traj, cycle, regression, *, pool, n_folds, noise_corrected, model, refit,
                     phase_averaged=None, connection_only=None, variants=False,
                     connection_regressed=False):
    """:func:`cross_validate`'s skill; with ``variants`` instead :func:`_variant_scores` of the
    fold models (noise-corrected)."""
    reg, models, view, fold, cycles = _fold_models(traj, cycle, regression, model, pool=pool,
                                                   n_folds=n_folds, refit=refit,
                                                   connection_regressed=connection_regressed)
    if variants:
        return _variant_scores(models, view, fold, reg, traj.dt, pool, cycles)
    return _score_folds(models, view, fold, reg, traj.dt, pool, noise_corrected,
                        phase_averaged, connection_only)[0]


def checked_terms(traj: Trajectory, cycle: LimitCycle, regression: Regression,
                  model: LocalConnectionModel, *, pool: bool, n_folds: int = 3
                  ) -> tuple[Skill, Tensor]:
    """The held-out check of a fit at a given complexity, from one set of fold fits:
    :func:`cross_validate`'s skill, and ``(..., 3)`` True where :func:`_choose_terms` keeps
    the full model (False: the phase average or the connection alone predicts that
    component better held out, and :func:`select_complexity` should choose)."""
    reg, models, view, fold, cycles = _fold_models(traj, cycle, regression, model, pool=pool,
                                                   n_folds=n_folds, refit=False)
    (held, gaps), (_, gaps_conn) = _variant_scores(models, view, fold, reg, traj.dt, pool,
                                                   cycles, noise_corrected=False)
    fallback, conn = _choose_terms(gaps, gaps_conn, few_cycles(traj.phase, pool))
    return held, ~(fallback | conn)


def few_cycles(phase: Tensor, pool: bool) -> Tensor:
    """``(...)`` (pooled: ``()``) True where a batch element (pooled: the trials together)
    spans at most :data:`FALLBACK_CYCLES` cycles of ``phase (..., T)``, rounded: where
    :func:`_choose_terms` presumes the simpler model (and the auto fit's check runs
    :func:`checked_terms`). A recording of 6 cycles spans 5.9-6.1 of its estimated phase, and
    its held-out blocks hold 7 partial cycles, so the span, not the cycles seen, is counted."""
    finite = torch.isfinite(phase)
    span = (torch.where(finite, phase, -math.inf).amax(-1)
            - torch.where(finite, phase, math.inf).amin(-1)) / (2 * math.pi)
    span = span.clamp(min=0)  # a trial without phase: 0 cycles
    if pool:
        span = span.sum()
    return torch.round(span) <= FALLBACK_CYCLES


def _fold_models(traj, cycle, regression, model, *, pool, n_folds, refit,
                 connection_regressed=False):
    """The regression, its fits without each of ``n_folds`` blocks of cycles
    (downdated ones of the connection alone where ``connection_regressed``), the view they
    are scored on, its block index and its cycle index (:func:`_cycle_index`)."""
    reg = regression
    if model is None:
        model = reg.fit(traj, cycle, pool=pool)  # the view's interval, from the whole recording
    unflat = regression_view(traj, reg, model, pool=pool, flatten=False)
    view = regression_view(traj, reg, model, pool=pool)
    fold = _cycle_blocks(unflat.phase, n_folds)
    if refit or not downdates(reg):
        sample_fold = _cycle_blocks(traj.phase, n_folds)
        models = []
        for f in range(n_folds):
            train = traj.with_fields(phase=torch.where(sample_fold == f, torch.nan, traj.phase))
            models.append(reg.fit(train, cycle, pool=pool))
    else:
        columns = (connection_columns(model.shape_dim, traj.r.device)
                   if connection_regressed else None)
        coef = held_out_coefficients(traj, reg, model, unflat, fold, n_folds, pool=pool,
                                     columns=columns)
        coef = blended_held_out(traj, reg, model, coef, n_folds, pool=pool, columns=columns)[0]
        models = [with_coefficients(model, coef[f], reg.fourier_order) for f in range(n_folds)]
    return (reg, models, view, pool_batch(fold, 0) if pool else fold,
            _cycle_index(unflat.phase, pool))


def _variant_scores(models, view: _View, fold: Tensor, reg: Regression, dt: float, pool: bool,
                    cycle: Tensor, noise_corrected: bool = True
                    ) -> tuple[tuple[Skill, Tensor], tuple[Skill, Tensor]]:
    """:func:`_score_folds` (with the per-cycle gaps) of the fold models as fitted and of the
    connection alone (their rows of ``b̂`` and ``∂Â/∂r`` set to 0): the candidates of
    :func:`_choose_terms`."""
    every = torch.ones(3, dtype=torch.bool, device=view.phase.device)
    return (_score_folds(models, view, fold, reg, dt, pool, noise_corrected, cycle=cycle),
            _score_folds(models, view, fold, reg, dt, pool, noise_corrected,
                         connection_only=every, cycle=cycle))


def _score_folds(models, view: _View, fold: Tensor, reg: Regression, dt: float, pool: bool,
                 noise_corrected: bool, phase_averaged: Tensor | None = None,
                 connection_only: Tensor | None = None,
                 cycle: Tensor | None = None) -> tuple[Skill, Tensor | None]:
    """:class:`Skill` of ``models[f]`` on block ``f`` of ``view``, summed over the blocks,
    beside the phase-averaged velocity of the other blocks (noise-corrected as asked); with
    ``cycle`` (:func:`_cycle_index`) also, per held-out cycle, the ``SSE`` of the model
    minus that of the phase average and the phase average's own ``(..., C, 3, 2)``, as
    observed: the model's error on the noisy inputs, what a user's held-out data show.

    ``phase_averaged``: ``(..., 3)`` components each fold's model predicts by that baseline;
    ``connection_only``: ``(..., 3)`` components whose ``b̂`` and ``∂Â/∂r`` rows it zeroes."""
    sums, gaps = [], []
    n_cycles = None if cycle is None else int(cycle.amax()) + 1
    for f, fold_model in enumerate(models):
        train = torch.where(fold != f, view.phase, torch.nan)
        # on a few cycles at video rates the other blocks may hold fewer samples than the
        # model's order needs: the baseline then takes the highest order they determine
        n_train = int(torch.isfinite(train).sum(-1).min())
        base = phase_average(_View(train, view.r, view.r_dot, view.xi),
                             min(reg.fourier_order, max((n_train - 1) // 2, 0)))
        template = fold_model  # Â(γ)γ̇ of the fold's fit, even where it falls back
        if phase_averaged is not None or connection_only is not None:
            fold_model = with_phase_average(fold_model, base, phase_averaged, connection_only)
            base = base.padded(fold_model.c.order)  # the same sums: an exact tie
        noise = None
        if noise_corrected and isinstance(reg, NoiseAwareRegression):
            noise = _noise_of(fold_model, dt, pool)
        fold_sums, fold_gaps = _sums(fold_model, base, view, fold == f, noise, cycle, n_cycles,
                                     template=template)
        sums.append(fold_sums)
        gaps.append(fold_gaps)
    total = [sum(parts) for parts in zip(*sums, strict=True)]
    per_cycle = None
    if cycle is not None:  # (..., C, 3, 2): the model's SSE minus the phase average's, its
        per_cycle = torch.stack([sum(g[0] for g in gaps), sum(g[1] for g in gaps)], -1)
    return _from_sums(total[0] - total[6], *total[1:6]), per_cycle


def _scored(view: _View, mask: Tensor | None):
    """The samples of ``view`` to score: ``ok (..., N)`` (finite, and in ``mask``), and
    phase, r, r_dot, xi with the others set to 0 (so that nothing NaN reaches a sum)."""
    ok = torch.isfinite(view.phase) & torch.isfinite(view.xi).all(-1)
    ok &= torch.isfinite(view.r).all(-1) & torch.isfinite(view.r_dot).all(-1)
    if mask is not None:
        ok &= mask
    return (ok, torch.where(ok, view.phase, 0.0), torch.where(ok[..., None], view.r, 0.0),
            torch.where(ok[..., None], view.r_dot, 0.0), torch.where(ok[..., None], view.xi, 0.0))


def with_phase_average(model: LocalConnectionModel, baseline: FourierSeries,
                       components: Tensor | None,
                       connection_only: Tensor | None = None) -> LocalConnectionModel:
    """``model`` predicting the components ``components`` (``(..., 3)`` bool, broadcasting
    against its batch dims; None: none) by ``baseline``, a phase-averaged velocity (value
    shape ``(3,)``): their intercept ``c`` becomes the baseline's series, their rows of ``b``,
    ``A`` and ``∂A/∂r`` 0, so that :meth:`~LocalConnectionModel.predict` gives exactly the
    baseline's values for them. The components ``connection_only`` (same shape) keep ``c``
    and ``A`` and get rows of ``b`` and ``∂A/∂r`` of 0: ``c + Aδ̇``. ``meta["phase_averaged"]``
    and ``meta["connection_only"]`` record the masks (each only when some entry is True); the
    per-bin estimates (``model.bins``) are kept as the regression made them."""
    def as_mask(x):
        return (torch.zeros(3, dtype=torch.bool, device=model.device) if x is None
                else torch.as_tensor(x, dtype=torch.bool, device=model.device))

    mask, offsets = as_mask(components), as_mask(connection_only)
    mask, offsets = torch.broadcast_tensors(mask, offsets)
    if not bool((mask | offsets).any()):
        return model
    c = model.c
    if bool(mask.any()):
        order = max(model.c.order, baseline.order)
        coeffs, base = model.c.padded(order).coeffs, baseline.padded(order).coeffs
        c = FourierSeries(torch.where(mask.unsqueeze(-2), base.to(coeffs), coeffs), 1)

    def zeroed(series: FourierSeries, m: Tensor) -> FourierSeries:
        m = m.reshape(m.shape[:-1] + (1, 3) + (1,) * (series.value_ndim - 1))
        return FourierSeries(series.coeffs.masked_fill(m, 0.0), series.value_ndim)

    meta = dict(model.meta or {})
    for key, m in (("phase_averaged", mask), ("connection_only", offsets)):
        if bool(m.any()):
            meta[key] = m.tolist()
    return dataclasses.replace(model, c=c, b=zeroed(model.b, mask | offsets),
                               A=zeroed(model.A, mask), dA=zeroed(model.dA, mask | offsets),
                               dA_fit=None if model.dA_fit is None
                               else zeroed(model.dA_fit, mask | offsets), meta=meta)


def downdates(regression: Regression) -> bool:
    """Whether :func:`held_out_coefficients` knows ``regression``'s design: a
    :class:`TubeRegression` or :class:`NoiseAwareRegression` regressing as they do (a subclass
    that regresses differently is refitted instead)."""
    own = type(regression)._connection_fit
    return own in (TubeRegression._connection_fit, NoiseAwareRegression._connection_fit)


def held_out_coefficients(traj: Trajectory, regression: Regression,
                          model: LocalConnectionModel, view: _View, fold: Tensor,
                          n_folds: int, *, pool: bool,
                          ridges: tuple[float, ...] | None = None,
                          columns: Tensor | None = None, window=None) -> Tensor:
    """Per-bin coefficients ``(R, F, ..., M, P, 3)`` of ``regression`` fitted without each of
    the ``F = n_folds`` blocks (:func:`~torchconn.regression.held_out.leave_blocks_out`), for
    each ridge in ``ridges`` (default: the regression's own).

    ``model`` is the regression's fit to the whole recording (its bins' centres and ``meta``:
    velocity interval, noise level); ``view`` and ``fold`` ``(..., N)`` are the samples it
    regressed on (:func:`regression_view` with ``flatten=False``) and their blocks. ``window``:
    the bins' half-width (default: the regression's own, or its rule applied to the samples
    outside one block, :func:`_fold_windows`).
    """
    ridges = (regression.ridge,) if ridges is None else tuple(ridges)
    meta = model.meta or {}
    bins = model.bins
    d = bins.gamma.shape[-1]
    gamma, gamma_dot = bins.gamma, bins.gamma_dot
    phase, r, r_dot, xi = view.phase, view.r, view.r_dot, view.xi
    if pool:
        phase, r, r_dot, xi, fold = (pool_batch(x, k) for x, k in (
            (phase, 0), (r, 1), (r_dot, 1), (xi, 1), (fold, 0)))
    batch = tuple(phase.shape[:-1])
    n = math.prod(batch)
    kw = dict(dtype=r.dtype, device=r.device)
    var_delta = var_rate = None
    if isinstance(regression, NoiseAwareRegression):
        var_delta, var_rate = (v.reshape(n, d) for v in _interval_noise(meta, batch, traj.dt,
                                                                         **kw))
    if window is None:
        window = _fold_windows(regression, meta, phase, fold, d)
    windows = torch.as_tensor(window, dtype=torch.float64, device=r.device).expand(
        batch).reshape(n)
    flat = [x.reshape((n,) + x.shape[len(batch):]) for x in (phase, r, r_dot, xi, fold)]
    m = regression.n_bins
    g_m = gamma.expand(batch + (m, d)).reshape(n, m, d)
    g_dot = gamma_dot.expand(batch + (m, d)).reshape(n, m, d)
    out = None
    for w in torch.unique(windows).tolist():  # elements sharing a window share their bins
        idx = torch.nonzero(windows == w).flatten()
        ph, rr, rd, y, fo = (x[idx] for x in flat)
        s = _wls.prepare("cross_validate", rr, rd, y, "xi", 3,
                         assign_bins(ph, m, window=w, kernel=regression.kernel),
                         g_m[idx], g_dot[idx])
        correction = None
        if var_delta is not None:
            vd = var_delta[idx].repeat_interleave(m, 0)
            vr = var_rate[idx].repeat_interleave(m, 0)

            def correction(gram, sel, vd=vd, vr=vr):
                return eiv_correction(gram, vd[sel], vr[sel])

        coef = leave_blocks_out(s, fo.reshape(-1), n_folds, ridges=ridges,
                                delta_max=regression.delta_max, correction=correction,
                                columns=columns, ridge_connection=regression.ridge_connection)
        coef = coef.unflatten(1, (idx.numel(), m))  # (R, b, M, F, P, K)
        if out is None:
            out = coef.new_full((len(ridges), n) + coef.shape[2:], torch.nan)
        out[:, idx] = coef
    out = out.movedim(3, 1)  # (R, F, n, M, P, K)
    return out.reshape(out.shape[:2] + batch + out.shape[3:])


def blended_held_out(traj: Trajectory, regression: Regression, model: LocalConnectionModel,
                     coef: Tensor, n_folds: int, *, pool: bool,
                     ridges: tuple[float, ...] | None = None, columns: Tensor | None = None,
                     sample_fold: Tensor | None = None) -> Tensor:
    """Held-out coefficients ``coef (R, F, ..., M, P, 3)`` of a noise-aware regression, which
    shrinks towards the smoothed fit, combined as its fit combines
    them: the smoothed regression's own downdated fits ``β̂_s`` (on the smoothed samples, its
    own window rule, same blocks of whole cycles) and the corrected ones ``β̂_c`` give
    ``β̂_s + w (β̂_c − β̂_s)`` with the whole recording's weights ``w`` per trial and term
    (``model.meta["corrected_weight"]``, as the window and the interval are the whole
    recording's). Without this the check would score the corrected estimate alone, which is
    far off where the fit falls back to the smoothed one. Other regressions: ``coef``.
    ``columns``: as :func:`held_out_coefficients`'s (``coef`` fitted with them);
    ``sample_fold``: ``(..., T)`` block of every sample (default: ``n_folds`` blocks of whole
    cycles, :func:`_cycle_blocks`)."""
    if not isinstance(regression, NoiseAwareRegression):
        return coef
    smoothed = TubeRegression(**{f.name: getattr(regression, f.name)
                                 for f in dataclasses.fields(TubeRegression)})
    sm = traj.smoothed
    view = _View(traj.phase, sm.r, sm.r_dot, sm.xi)
    if sample_fold is None:
        sample_fold = _cycle_blocks(traj.phase, n_folds)
    coef_s = held_out_coefficients(traj, smoothed, model, view, sample_fold, n_folds, pool=pool,
                                   ridges=ridges, columns=columns)
    d = model.shape_dim
    term = torch.tensor([0] + [1] * d + [2] * d + [3] * d * d, device=coef.device)
    w = torch.as_tensor(model.meta["corrected_weight"], dtype=coef.dtype,
                        device=coef.device)[..., term]  # (..., P)
    w = w[..., None, :, None]  # (..., 1, P, 1): over bins and outputs
    # exact ends, so that a bin only one of the two could fit keeps the other's coefficients
    return torch.where(w == 1, coef, torch.where(w == 0, coef_s, coef_s + w * (coef - coef_s)))


def _fold_windows(regression: Regression, meta: dict, phase: Tensor, fold: Tensor, d: int):
    """The bins' half-width(s) the regression's own rule gives on the samples outside one
    block (block 0; the blocks are about equal): a refit on fewer cycles widens its windows,
    and keeping the whole recording's narrower ones would handicap the models with more
    regressors (measured: 3-link reference gait, 3 cycles, ω = 0.005: 12 bins / order 3
    chosen and held-out R² of v_x 0.90, against 24 / 6 and 0.99 with the refits' windows).

    ``phase``, ``fold``: ``(..., N)`` (pooled: ``(N,)``). Returns a float or a ``(...)`` list.
    """
    if regression.window is not None:
        return regression.window
    train = torch.where(fold == 0, torch.nan, phase)
    if not isinstance(regression, NoiseAwareRegression):
        return _auto_window(train, regression.n_bins, 1 + 2 * d + d * d,
                            regression.samples_per_regressor)
    ratio = torch.as_tensor(meta["noise_ratio"], dtype=torch.float64, device=phase.device)
    if train.ndim == 1:  # pooled: the window the fit chose, widened as fewer cycles need
        return max(float(meta["window"]), _auto_window(train, regression.n_bins,
                                                       1 + 2 * d + d * d,
                                                       regression.samples_per_regressor))
    return regression.element_windows(train.reshape(-1, train.shape[-1]), d,
                                      ratio.reshape(-1)).reshape(train.shape[:-1])


def with_coefficients(model: LocalConnectionModel, coef: Tensor, order: int
                      ) -> LocalConnectionModel:
    """``model`` with its connection terms replaced by the Fourier series (order ``order``)
    through per-bin coefficients ``coef (..., M, P, 3)`` of the design ``[1, δ, δ̇, δ̇⊗δ]``."""
    # a batch element with a bin that could not be fitted predicts NaN (it is unscored)
    bad = ~torch.isfinite(coef).flatten(-3).all(-1)
    c, b, a, da = split_coefficients(torch.nan_to_num(coef), model.shape_dim)
    centres = model.bins.phase.to(coef)

    def masked(fitted: FourierSeries) -> FourierSeries:
        mask = bad.reshape(bad.shape + (1,) * (fitted.value_ndim + 1))
        return FourierSeries(fitted.coeffs.masked_fill(mask, torch.nan), fitted.value_ndim)

    def series(values: Tensor, ndim: int):
        return masked(fit_fourier(centres, values, order, value_ndim=ndim))

    c_order = (model.meta or {}).get("intercept_order")
    if c_order is not None:
        c_order = torch.as_tensor(c_order, device=coef.device)
    # the coefficients are the regression's own: its δ̇⊗δ one is what predictions use
    c_series = intercept_series(centres, c, order, c_order)
    return dataclasses.replace(model, c=masked(c_series), b=series(b, 2), A=series(a, 2),
                               dA=series(da, 3), dA_fit=None)


def _noise_of(model: LocalConnectionModel, dt: float, pool: bool):
    """Noise variances of the view's ``δ`` and ``δ̇`` from a noise-aware model's ``meta``,
    shaped to broadcast against the view's ``(..., N, d)``."""
    kw = dict(dtype=model.phase_rate.dtype, device=model.phase_rate.device)
    batch = () if pool else tuple(torch.as_tensor(model.meta["velocity_interval"], **kw).shape)
    var_delta, var_rate = _interval_noise(model.meta, batch, dt, **kw)
    if not pool:
        var_rate, var_delta = var_rate.unsqueeze(-2), var_delta.unsqueeze(-2)
    return var_delta, var_rate


def _interval_noise(meta: dict, batch: tuple, dt: float, **kw) -> tuple[Tensor, Tensor]:
    """Noise variances ``(*batch, d)`` of ``δ`` and ``δ̇`` in a noise-aware fit's interval
    samples, from its ``meta`` (noise level, velocity interval and filter; the gains of
    :func:`~torchconn.regression.noise_aware.interval_noise_gains`)."""
    sigma2 = torch.as_tensor(meta["noise_r"], **kw).square()
    sigma2 = sigma2.expand(batch + sigma2.shape[-1:])
    h = torch.as_tensor(meta["velocity_interval"], device=kw.get("device")).expand(batch)
    h = h.reshape(-1).tolist()
    kernel = meta.get("velocity_kernel", VELOCITY_KERNEL)
    gains = torch.tensor([interval_noise_gains(int(v), dt, kernel) for v in h],
                         **kw).reshape(batch + (2,))
    return sigma2 * gains[..., :1], sigma2 * gains[..., 1:]


def connection_columns(d: int, device: torch.device | str | None = None) -> Tensor:
    """``(1 + d,)`` index of the columns of the design ``[1, δ, δ̇, δ̇⊗δ]`` the connection
    alone ``c + Aδ̇`` keeps (:func:`~torchconn.regression.connection.connection_design`):
    the intercept and ``Â``'s columns (:func:`~torchconn.regression.connection.
    unpenalised_columns`)."""
    keep = unpenalised_columns(d, device)
    keep[0] = True
    return keep.nonzero().squeeze(-1)


@dataclass(frozen=True)
class ConnectionAlone:
    """What :func:`select_connection_alone` chose.

    Attributes:
        regression: the regression at the chosen bins and Fourier order (no ridge).
        choice: its :class:`ComplexityChoice` (``connection_regressed``; ``connection_only``
            where ``c + Âδ̇`` predicts a component, ``phase_averaged`` elsewhere).
        model: the connection alone fitted to the whole recording (``LocalConnectionModel``:
            rows of ``b`` and ``∂A/∂r`` 0; no phase average put in;
            :func:`connection_alone_model`).
        coef: ``(..., M, P, 3)`` its per-bin coefficients of ``[1, δ, δ̇, δ̇⊗δ]`` (those of
            ``δ`` and ``δ̇⊗δ`` 0).
        held_out: the held-out :class:`Skill` of the forecasts so chosen (each fold's
            connection alone, its phase-averaged components predicted by the phase average).
    """

    regression: Regression
    choice: ComplexityChoice
    model: LocalConnectionModel
    coef: Tensor
    held_out: Skill


def connection_alone_model(model: LocalConnectionModel, coef: Tensor, order: int
                           ) -> LocalConnectionModel:
    """``model`` (a fit at the bins of ``coef``) with its connection terms the connection
    alone's: per-bin coefficients ``coef (..., M, P, 3)`` (:func:`with_coefficients`, order
    ``order``), its per-bin estimates ``c``, ``b``, ``A``, ``∂A/∂r`` theirs too (``b`` and
    ``∂A/∂r`` 0: not estimated) with standard errors and ``Â``'s band factors unknown (NaN,
    None), and ``meta["connection_regressed"]`` True. Its metric, if any, is ``model``'s."""
    out = with_coefficients(model, coef, order)
    c, b, a, da = split_coefficients(coef.to(model.bins.A), model.shape_dim)
    bins = dataclasses.replace(
        model.bins, c=c, b=b, A=a, dA=da, c_se=torch.full_like(c, torch.nan),
        b_se=torch.full_like(b, torch.nan), A_se=torch.full_like(a, torch.nan),
        dA_se=torch.full_like(da, torch.nan), A_sampling_factor=None, A_bias_allowance=None,
        dA_correlation=None)
    return dataclasses.replace(out, bins=bins,
                               meta={**(out.meta or {}), "connection_regressed": True})


def select_connection_alone(traj: Trajectory, cycle: LimitCycle, regression: Regression, *,
                            pool: bool, n_folds: int = 3) -> ConnectionAlone:
    """Where no model with ``b̂`` and ``∂Â/∂r`` can be fitted without one block of cycles
    (:func:`select_complexity` raises; e.g. 7-10 cycles at 10 samples per cycle, where a
    quarter-cycle window holds too few samples for the ``1 + 2d + d²`` regressors of each
    bin), the connection alone ``c + Aδ̇`` (``1 + d`` regressors per bin; ``b`` and ``∂A/∂r``
    not estimated) is regressed at each ``(n_bins, fourier_order)`` of
    :data:`COMPLEXITY_GRID` (no ridge) and scored on the held-out blocks of whole cycles (the
    downdated fits, :func:`held_out_coefficients` with :func:`connection_columns`). Per
    component it predicts where it beats the phase average clearly (:func:`_clearly_better`,
    as on short recordings: the simpler model is presumed); the phase average elsewhere.
    The candidate of least mean noise-corrected held-out ``SSE/SST`` (of the model so chosen
    per component) is kept, and fitted to the whole recording the same way.

    Raises:
        ValueError: no candidate can be fitted on ``n_folds − 1`` blocks either.
    """
    best, failures, scores = None, [], []
    for n_bins, order in COMPLEXITY_GRID:
        base = regression.replace(n_bins=n_bins, fourier_order=order, ridge=0.0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IllConditionedBinWarning)
            try:  # the whole recording's window, interval and noise level
                model = base.replace(on_ill_conditioned="warn").fit(traj, cycle, pool=pool)
            except ValueError as err:
                failures.append(f"{n_bins} bins: {err}")
                continue
        _, models, view, flat_fold, cycles = _fold_models(
            traj, cycle, base, model, pool=pool, n_folds=n_folds, refit=False,
            connection_regressed=True)
        scored, gaps = _score_folds(models, view, flat_fold, base, traj.dt, pool, True,
                                    cycle=cycles)
        if bool(scored.unscored.any()):
            failures.append(f"{n_bins} bins: some bins cannot be fitted without one of the "
                            f"{n_folds} blocks of cycles")
            continue
        # the simpler model presumed, as on short recordings: measured (README "Few samples
        # per cycle"), presuming the connection alone unless the phase average beats it
        # clearly lost to the phase average more often and by more
        fallback = ~_clearly_better(gaps)
        loss = float(torch.where(fallback, 1 - scored.r2_phase_average, 1 - scored.r2).mean())
        scores.append((n_bins, order, 0.0, loss))
        if best is None or loss < best[0]:
            best = (loss, base, model, models, view, flat_fold, fallback)
    if best is None:
        raise ValueError("select_connection_alone: no candidate could be fitted on "
                         f"{n_folds - 1} of {n_folds} blocks of cycles ({failures[0]})")
    loss, base, model, models, view, flat_fold, fallback = best
    held = _score_folds(models, view, flat_fold, base, traj.dt, pool, False,
                        phase_averaged=fallback)[0]
    # the whole recording, fitted as the folds were: every sample in block 1 of 2, and the
    # fit without block 0 (empty) taken
    unflat = regression_view(traj, base, model, pool=pool, flatten=False)
    columns = connection_columns(model.shape_dim, traj.r.device)
    whole = torch.ones(unflat.phase.shape, dtype=torch.long, device=unflat.phase.device)
    coef = held_out_coefficients(traj, base, model, unflat, whole, 2, pool=pool,
                                 columns=columns)
    coef = blended_held_out(traj, base, model, coef, 2, pool=pool, columns=columns,
                            sample_fold=torch.ones(traj.phase.shape, dtype=torch.long,
                                                   device=traj.phase.device))
    coef = coef[0, 0]
    choice = ComplexityChoice(
        n_bins=base.n_bins, fourier_order=base.fourier_order, ridge=0.0,
        scores=tuple(scores), phase_averaged=_nested_tuple(fallback),
        connection_only=_nested_tuple(~fallback), connection_regressed=True)
    return ConnectionAlone(regression.replace(n_bins=base.n_bins,
                                              fourier_order=base.fourier_order, ridge=0.0),
                           choice, connection_alone_model(model, coef, base.fourier_order), coef,
                           held)


def select_complexity(traj: Trajectory, cycle: LimitCycle, regression: Regression, *,
                      pool: bool, n_folds: int = 3, fallback_ok: bool = True,
                      ridges: tuple[float, ...] = RIDGE_GRID
                      ) -> tuple[Regression, ComplexityChoice]:
    """The bins, Fourier order and ridge of least mean held-out ``SSE/SST`` among
    :data:`COMPLEXITY_GRID` x ``ridges`` (:func:`cross_validate`, noise-corrected; by default
    :data:`RIDGE_GRID`, applied as the regression applies its own, see its
    ``ridge_connection``); a ridge only when it gains more than :data:`RIDGE_MIN_GAIN` over
    no ridge.

    Per component and batch element two simpler models are candidates too
    (:func:`_choose_terms`): the connection alone (``ĉ + Âδ̇``, the rows of ``b`` and
    ``∂A/∂r`` 0; :attr:`ComplexityChoice.connection_only`) and the phase-averaged velocity
    (``b = A = ∂A/∂r = 0``; :attr:`ComplexityChoice.phase_averaged`), both made by
    :func:`with_phase_average`. A model with shape terms counts only when it lowers the
    held-out squared error of the observed (noisy) inputs below the phase average's by more
    than :data:`FALLBACK_Z` standard errors (of the sum over held-out cycles of the
    per-cycle differences) and :data:`FALLBACK_MARGIN` of it; the full model is kept over the
    connection alone only when it is better by more than :data:`OFFSET_TERMS_Z` standard
    errors (on recordings of up to :data:`FALLBACK_CYCLES` cycles, :func:`few_cycles`; on
    longer ones the full model is kept unless a simpler one is better by as many standard
    errors). Each candidate scores the loss of the model chosen per component in the mean.
    The three components are separate least-squares problems on one design, so one's choice
    leaves the others' fits unchanged. ``fallback_ok=False``: every component keeps the full
    model.

    The blocks are whole cycles in order and nothing is random: the same data give the same
    choice. For the built-in regressions one fit per ``(n_bins, fourier_order)`` and one pass
    over the data give every ridge's fits without each block (:func:`held_out_coefficients`).

    Returns ``regression`` with the chosen fields and the :class:`ComplexityChoice`.

    :func:`select_complexities` makes this choice for several settings of ``ridge_connection``
    at once, sharing every candidate the settings fit alike.

    Raises:
        ValueError: no candidate can be fitted on ``n_folds − 1`` blocks (too few cycles),
            naming the first failure.
    """
    return select_complexities(traj, cycle, (regression,), pool=pool, n_folds=n_folds,
                               fallback_ok=fallback_ok, ridges=ridges)[0]


def select_complexities(traj: Trajectory, cycle: LimitCycle,
                        regressions: Sequence[Regression], *, pool: bool, n_folds: int = 3,
                        fallback_ok: bool = True, ridges: tuple[float, ...] = RIDGE_GRID
                        ) -> list[tuple[Regression, ComplexityChoice] | None]:
    """:func:`select_complexity` of each of ``regressions``, which differ at most in
    ``ridge_connection`` (e.g. ``Â`` penalised and not), in one search: a candidate the
    settings fit alike (every one of ridge 0, which penalises nothing) is fitted and scored
    once, and every ``(n_bins, fourier_order)`` fits its whole-recording model once. Each
    choice is the one :func:`select_complexity` makes for its regression alone.

    Returns one ``(regression, choice)`` per regression; None for a later one none of whose
    candidates could be fitted.

    Raises:
        ValueError: ``regressions`` differ in more than ``ridge_connection``, or no candidate
            of the first can be fitted on ``n_folds − 1`` blocks (too few cycles), naming the
            first failure.
    """
    settings = [_ridge_setting(reg) for reg in regressions]
    first = regressions[0]
    for reg, setting in zip(regressions[1:], settings[1:], strict=True):
        if first != (reg if None in (setting, settings[0])
                     else reg.replace(ridge_connection=settings[0])):
            raise ValueError("select_complexities: the regressions may differ only in "
                             f"ridge_connection, got {first!r} and {reg!r}")
    # a ridge-0 candidate penalises nothing: the first setting's fit serves every setting
    penalties = list(dict.fromkeys(_penalty(ridge, setting, settings[0])
                                   for setting in settings for ridge in ridges))
    short = few_cycles(traj.phase, pool)
    results = {}  # (n_bins, order, ridge, setting) -> (loss, fallback, conn) or the failure
    for n_bins, order in COMPLEXITY_GRID:
        for penalty, result in _candidate_skills(traj, cycle, first, n_bins, order, pool,
                                                 n_folds, penalties).items():
            if not isinstance(result, str):
                (s, gaps), (s_conn, gaps_conn) = result
                # the models must beat the baseline on the held-out data as observed (the
                # noisy inputs); the candidates are ranked by the noise-corrected loss
                if fallback_ok:
                    fallback, conn = _choose_terms(gaps, gaps_conn, short)
                else:
                    fallback = conn = torch.zeros_like(s.r2, dtype=torch.bool)
                loss = torch.where(fallback, 1 - s.r2_phase_average,
                                   torch.where(conn, 1 - s_conn.r2, 1 - s.r2))
                result = float(loss.mean()), fallback, conn
            results[(n_bins, order) + penalty] = result
    out = []
    for k, (reg, setting) in enumerate(zip(regressions, settings, strict=True)):
        own = [(n_bins, order, ridge, results[n_bins, order,
                                              *_penalty(ridge, setting, settings[0])])
               for n_bins, order in COMPLEXITY_GRID for ridge in ridges]
        scores = [row[:3] + (row[3][0],) for row in own if not isinstance(row[3], str)]
        if not scores:
            if k:
                out.append(None)
                continue
            failed = next(row[3] for row in own)
            raise ValueError(f"select_complexity: no candidate could be fitted on {n_folds - 1} "
                             f"of {n_folds} blocks of cycles ({failed}); record more cycles")
        out.append(_chosen(reg, scores, {row[:3]: row[3][1:] for row in own
                                         if not isinstance(row[3], str)}))
    return out


def _ridge_setting(regression: Regression) -> bool | None:
    """The regression's ``ridge_connection`` (None: it has no such setting)."""
    return getattr(regression, "ridge_connection", None)


def _penalty(ridge: float, setting: bool | None, first: bool | None) -> tuple[float, bool | None]:
    """The candidate ``(ridge, ridge_connection)`` that fits ``ridge`` under ``setting``: at
    ridge 0 the first setting's (no column is penalised, so every setting fits alike)."""
    return float(ridge), first if ridge == 0 else setting


def _chosen(regression: Regression, scores: list, fallbacks: dict
            ) -> tuple[Regression, ComplexityChoice]:
    """:func:`select_complexity`'s choice among ``scores`` ``[(n_bins, order, ridge, loss)]``
    (``fallbacks[n_bins, order, ridge]``: the components' phase-average and connection-only
    masks)."""
    best = min(scores, key=lambda row: row[3])
    plain = [row for row in scores if row[2] == 0]
    if plain and best[2] > 0:
        best_plain = min(plain, key=lambda row: row[3])
        if best[3] > (1 - RIDGE_MIN_GAIN) * best_plain[3]:
            best = best_plain
    n_bins, order, ridge, _ = best
    fallback, conn = fallbacks[n_bins, order, ridge]
    choice = ComplexityChoice(n_bins=n_bins, fourier_order=order, ridge=ridge,
                              scores=tuple(scores), phase_averaged=_nested_tuple(fallback),
                              connection_only=_nested_tuple(conn))
    return regression.replace(n_bins=n_bins, fourier_order=order, ridge=ridge), choice


def _clearly_better(gaps: Tensor) -> Tensor:
    """``(..., 3)`` True where the model's held-out squared error is below the phase
    average's by more than :data:`FALLBACK_Z` standard errors of the sum of the per-cycle
    differences and by more than the fraction :data:`FALLBACK_MARGIN` of the phase average's;
    ``gaps (..., C, 3, 2)``: per cycle the difference and the phase average's squared error
    (cycles without scored samples, difference 0, left out)."""
    diff, base = gaps.unbind(-1)
    return _lower_by(diff, FALLBACK_Z) & (diff.sum(-2) < -FALLBACK_MARGIN * base.sum(-2))


def _lower_by(diff: Tensor, z: float) -> Tensor:
    """``(..., 3)`` True where the sum over cycles of ``diff (..., C, 3)`` (per-cycle
    differences of squared errors; 0: a cycle without scored samples, left out) is below 0
    by more than ``z`` standard errors (of that sum, from the cycles' scatter), over at least
    2 cycles."""
    scored = diff != 0
    n = scored.sum(-2)
    total = diff.sum(-2)
    mean = total / n.clamp(min=1)
    var = ((diff - mean.unsqueeze(-2)).square() * scored).sum(-2) / (n - 1).clamp(min=1)
    return (n > 1) & (total < -z * (var * n).sqrt())


def _choose_terms(gaps: Tensor, gaps_conn: Tensor, short: Tensor | bool
                  ) -> tuple[Tensor, Tensor]:
    """Per component ``(..., 3)``: (predict it by the phase average, predict it by the
    connection alone). ``gaps``, ``gaps_conn`` ``(..., C, 3, 2)``: :func:`_score_folds`'s
    per-cycle gaps of the full model and of the connection alone; ``short`` ``(...)``: the
    recording spans at most :data:`FALLBACK_CYCLES` cycles (:func:`few_cycles`).

    On short recordings the simpler model is presumed: the full
    model is kept when it beats the phase average (:func:`_clearly_better`) and either the
    connection alone does not or the full model beats it by :data:`OFFSET_TERMS_Z` standard
    errors; else the connection alone when it beats the phase average; else the phase
    average: few cycles do not span the shape offsets of later ones (their correlation time
    is about 3 cycles in the paper's SDE), so ``b̂δ`` and ``∂Â/∂r δ̇⊗δ`` extrapolate there.

    On longer ones the full model is presumed: the phase average is taken only
    when it beats both models by :data:`FALLBACK_Z` standard errors, the connection alone
    only when it beats the full model by :data:`OFFSET_TERMS_Z`."""
    diff, diff_conn = gaps[..., 0], gaps_conn[..., 0]
    full, conn = _clearly_better(gaps), _clearly_better(gaps_conn)
    keep = full & (_lower_by(diff - diff_conn, OFFSET_TERMS_Z) | ~conn)
    short = torch.as_tensor(short, device=diff.device).unsqueeze(-1)
    fallback = torch.where(short, ~keep & ~conn,
                           _lower_by(-diff, FALLBACK_Z) & _lower_by(-diff_conn, FALLBACK_Z))
    conn_only = torch.where(short, ~keep & conn,
                            ~fallback & _lower_by(diff_conn - diff, OFFSET_TERMS_Z))
    return fallback, conn_only


def nested_list(mask: tuple) -> list:
    """A nested tuple of bools (:attr:`ComplexityChoice.phase_averaged`, ...) as nested lists
    (JSON)."""
    return [nested_list(v) for v in mask] if isinstance(mask, tuple) else mask


def _nested_tuple(mask: Tensor) -> tuple:
    def tup(x):
        return tuple(tup(v) for v in x) if isinstance(x, list) else bool(x)
    return tup(mask.tolist())


def _candidate_skills(traj, cycle, regression, n_bins, order, pool, n_folds, penalties
                      ) -> dict:
    """Per candidate ``(ridge, ridge_connection)`` of ``penalties`` at ``(n_bins, order)``:
    ``((Skill, gaps), (Skill, gaps))`` of the model as fitted and of the connection alone
    (:func:`_variant_scores`), the noise-corrected skill and per held-out cycle the observed
    SSE minus the phase average's; or, for a candidate that cannot be fitted, the failure (a
    string). One whole-recording fit serves every candidate, and one pass over the data every
    ridge of a setting."""
    base = regression.replace(n_bins=n_bins, fourier_order=order, ridge=0.0)

    def penalised(setting):
        return base if setting is None else base.replace(ridge_connection=setting)

    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        if not downdates(base):
            for ridge, setting in penalties:
                try:
                    out[ridge, setting] = _held_out_skills(
                        traj, cycle, penalised(setting).replace(ridge=ridge), pool=pool,
                        n_folds=n_folds, noise_corrected=True, model=None, refit=True,
                        variants=True)
                except ValueError as err:
                    out[ridge, setting] = f"{n_bins} bins, ridge {ridge:g}: {err}"
            return out
        try:
            # the whole recording's window, interval and noise level (bins that need a
            # ridge are NaN here and do not matter: only the fits without each block count)
            model = base.replace(on_ill_conditioned="warn").fit(traj, cycle, pool=pool)
        except ValueError as err:
            return dict.fromkeys(penalties, f"{n_bins} bins: {err}")
    unflat = regression_view(traj, base, model, pool=pool, flatten=False)
    view = regression_view(traj, base, model, pool=pool)
    fold = _cycle_blocks(unflat.phase, n_folds)
    flat_fold = pool_batch(fold, 0) if pool else fold
    cycles = _cycle_index(unflat.phase, pool)
    for setting in dict.fromkeys(setting for _, setting in penalties):
        ridges = tuple(ridge for ridge, s in penalties if s == setting)
        reg = penalised(setting)
        coef = held_out_coefficients(traj, reg, model, unflat, fold, n_folds, pool=pool,
                                     ridges=ridges)
        coef = blended_held_out(traj, reg, model, coef, n_folds, pool=pool, ridges=ridges)
        for k, ridge in enumerate(ridges):
            models = [with_coefficients(model, coef[k, f], order) for f in range(n_folds)]
            full, conn = _variant_scores(models, view, flat_fold, base, traj.dt, pool, cycles)
            if bool(full[0].unscored.any()):
                out[ridge, setting] = (f"{n_bins} bins, ridge {ridge:g}: some bins cannot be "
                                       f"fitted without one of the {n_folds} blocks of cycles")
            else:
                out[ridge, setting] = full, conn
    return out


def _cycle_blocks(phase: Tensor, n_folds: int) -> Tensor:
    """``(..., N)`` block index in ``[0, n_folds)`` of contiguous whole cycles per trial
    (-1 where the phase is NaN)."""
    cyc = _cycles(phase)
    n_cyc = torch.nan_to_num(cyc, nan=-1.0).amax(-1, keepdim=True) + 1
    fold = torch.floor(cyc * n_folds / n_cyc)
    return torch.where(torch.isfinite(fold), fold, -1.0).long()


def _cycles(phase: Tensor) -> Tensor:
    """``(..., N)`` whole cycles since each trial's first sample (float, NaN where the phase
    is NaN)."""
    start = torch.nan_to_num(phase, nan=float("inf")).amin(-1, keepdim=True)
    return torch.floor((phase - start) / (2 * math.pi))


def _cycle_index(phase: Tensor, pool: bool) -> Tensor:
    """``(..., N)`` (pooled: ``(N,)``, as :func:`regression_view` flattens) index of every
    sample's cycle, distinct across trials, -1 where the phase is NaN."""
    cyc = _cycles(phase)
    per_trial = int(torch.nan_to_num(cyc, nan=0.0).amax()) + 1
    trial = torch.arange(math.prod(phase.shape[:-1]), device=phase.device).reshape(
        phase.shape[:-1] + (1,))
    index = torch.where(torch.isfinite(cyc), cyc + trial * per_trial * pool, -1.0).long()
    return pool_batch(index, 0) if pool else index


def _sums(model: LocalConnectionModel, baseline, view: _View, mask: Tensor | None,
          noise=None, cycle: Tensor | None = None, n_cycles: int = 0,
          template: LocalConnectionModel | None = None):
    """SSE of model, baseline and template (``ĉ`` of ``template``, default ``model``) over the
    scored samples; Σy, Σy², count; and the
    part of the model's SSE the inputs' noise adds (:func:`_input_noise_variance`; 0 without
    ``noise``, the inputs' ``(var_delta, var_rate)``). With ``cycle`` (``(..., N)`` index in
    ``[0, n_cycles)``, -1: none) also ``(..., n_cycles, 3)`` the model's squared error minus
    the baseline's and the baseline's, summed per cycle (else None)."""
    ok, phase, r, r_dot, y = _scored(view, mask)
    w = ok.to(y.dtype)[..., None]
    preds = (model.predict(phase, r, r_dot), baseline(phase),
             (model if template is None else template).c(phase))
    squares = [(y - p).square() * w for p in preds]
    sse = [x.sum(-2) for x in squares]
    noise_sse = torch.zeros_like(sse[0]) if noise is None else (
        _input_noise_variance(model, phase, r, r_dot, *noise) * w).sum(-2)
    sums = (*sse, (y * w).sum(-2), (y.square() * w).sum(-2), w.sum(-2)[..., 0], noise_sse)
    if cycle is None:
        return sums, None
    index = torch.where(ok & (cycle >= 0), cycle, n_cycles).unsqueeze(-1).expand(y.shape)
    out = y.new_zeros(y.shape[:-2] + (n_cycles + 1, 3))
    return sums, tuple(out.scatter_add(-2, index, x)[..., :-1, :]
                       for x in (squares[0] - squares[1], squares[1]))


def _input_noise_variance(model: LocalConnectionModel, phase: Tensor, r: Tensor,
                          r_dot: Tensor, var_delta: Tensor, var_rate: Tensor) -> Tensor:
    """``(..., N, 3)`` variance the inputs' noise adds to the model's prediction.

    ``f = c + bδ + Aδ̇ + ∂A(δ̇⊗δ)`` with independent noise of variances ``v_δ``, ``v_δ̇`` on
    ``δ`` and ``δ̇``: ``Var f_k = Σ_j g_kj² v_δj + Σ_i a_ki² v_δ̇i + Σ_ij ∂A_kij² v_δ̇i v_δj``
    with ``g = b + ∂A·δ̇`` and ``a = A + ∂A·δ``; evaluated at the noisy inputs, the squares
    exceed their noise-free values by the last sum each, hence its minus sign below.
    """
    delta, delta_dot = model.offsets(phase, r, r_dot)
    da = model.prediction_dA(phase)  # (..., N, 3, d_i (δ̇), d_j (δ))
    g = model.b(phase) + torch.einsum("...kij,...i->...kj", da, delta_dot)
    a = model.A(phase) + torch.einsum("...kij,...j->...ki", da, delta)
    cross = torch.einsum("...kij,...i,...j->...k", da.square(), var_rate.expand_as(delta_dot),
                         var_delta.expand_as(delta))
    return ((g.square() * var_delta.unsqueeze(-2)).sum(-1)
            + (a.square() * var_rate.unsqueeze(-2)).sum(-1) - cross)


def _trial_index(flat: int, batch_shape: torch.Size) -> str:
    """The batch index of the ``flat``-th trial: ``2`` for one batch dim, ``(1, 0)`` for more."""
    index = torch.unravel_index(torch.tensor(flat), tuple(batch_shape))
    return str(int(index[0])) if len(index) == 1 else str(tuple(int(i) for i in index))


def _from_sums(sse_model, sse_base, sse_template, sy, syy, n) -> Skill:
    sst = syy - sy.square() / n[..., None]
    return Skill(r2=1 - sse_model / sst, r2_phase_average=1 - sse_base / sst,
                 r2_template=1 - sse_template / sst, n_samples=n)


