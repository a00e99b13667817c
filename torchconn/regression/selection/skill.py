"""Held-out skill of a fitted local model against its baselines.

The skill is ``R² = 1 − SSE/SST`` per body-velocity component against the observed velocity
the way the regression sees it (:func:`regression_view`: raw interval differences for
:class:`~torchconn.regression.noise_aware.NoiseAwareRegression`, the smoothed velocity for
:class:`~torchconn.regression.tube.TubeRegression`), beside

- the phase-averaged velocity of the training data (a Fourier series in phase of the observed
  velocity, ignoring the shape), and
- the template ``ĉ(φ) = Â(γ)γ̇``, the model on the cycle;
- the physics reference (:mod:`~torchconn.regression.reference`: the viscous N-link swimmer,
  its drag ratio fitted to the training samples), where asked for;
- zero body velocity.

Held-out blocks are contiguous whole cycles of every trial (:mod:`torchconn.cycles`), so
nothing is random and a choice made on them is reproducible. The fits without each block come
from downdating the regression's normal equations
(:mod:`~torchconn.regression.selection.held_out`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ... import _linalg
from ...cycles import cycle_blocks, cycle_index
from ...noise import VELOCITY_KERNEL, interval_noise_gains, interval_view
from ...phase.fourier import FourierSeries, fit_fourier, fourier_design
from ...phase.limit_cycle import LimitCycle
from ...trajectory import Trajectory, pool_batch
from .. import _wls
from ..base import Regression
from ..binning import assign_bins, auto_window
from ..connection import split_coefficients, unpenalised_columns
from ..diagnostics import RegressionDiagnostics
from ..model import LocalConnectionModel
from ..noise_aware import NoiseAwareRegression, eiv_correction
from ..reference import PhysicsReference, fit_reference
from ..tube import TubeRegression, intercept_series
from .held_out import leave_blocks_out

__all__ = ["Skill", "PoorHeldOutSkillWarning", "COMPONENTS", "RegressionView",
           "regression_view", "phase_average", "phase_average_orders", "skill",
           "cross_validate", "with_phase_average", "downdates", "held_out_coefficients",
           "blended_held_out", "with_coefficients", "connection_columns", "fold_models",
           "score_folds", "variant_scores", "held_out_checks", "fold_references",
            "with_physics", "fold_predictors", "held_out_predictions", "ForwardPrediction",
            "forward_prediction"]

#: the body-velocity components, in the order of the last axis of ξ
COMPONENTS = ("v_x", "v_y", "omega")


class PoorHeldOutSkillWarning(UserWarning):
    """The fitted model predicted held-out cycles worse than their phase-averaged velocity."""


@dataclass(frozen=True)
class Skill:
    """Skill ``R²`` per component ``(v_x, v_y, ω)`` of a model and of its baselines.

    Attributes:
        r2: ``(..., 3)`` the fitted model ``ĉ + b̂δ + Âδ̇ + ∂Â/∂r (δ̇⊗δ)``.
        r2_phase_average: ``(..., 3)`` the training data's phase-averaged velocity.
        r2_template: ``(..., 3)`` the template ``ĉ(φ) = Â(γ)γ̇``.
        n_samples: ``(...)`` samples scored.
        r2_physics: ``(..., 3)`` the physics reference
            (:class:`~torchconn.regression.reference.PhysicsReference`) with its parameters
            fitted to the training samples; None where it was not scored.
        r2_zero: ``(..., 3)`` zero body velocity, ``1 − Σy²/SST`` (negative unless the scored
            samples' mean is 0).
    """

    r2: Tensor
    r2_phase_average: Tensor
    r2_template: Tensor
    n_samples: Tensor
    r2_physics: Tensor | None = None
    r2_zero: Tensor | None = None

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
class RegressionView:
    """The samples a regression fits and is scored on (:func:`regression_view`).

    Attributes:
        phase: ``(..., N)`` phase in radians (NaN: not a sample).
        r: ``(..., N, d)`` joint angles in radians.
        r_dot: ``(..., N, d)`` their rates in radians per time unit.
        xi: ``(..., N, 3)`` body velocity ``(v_x, v_y, ω)``.
    """

    phase: Tensor
    r: Tensor
    r_dot: Tensor
    xi: Tensor


def regression_view(traj: Trajectory, regression: Regression, model: LocalConnectionModel,
                    *, pool: bool, flatten: bool = True) -> RegressionView:
    """The samples of ``traj`` as ``regression`` regressed them into ``model``.

    A :class:`~torchconn.regression.noise_aware.NoiseAwareRegression` regresses interval
    samples (``N = T − h``, ``h`` the shortest of the trials' intervals, a longer one's
    trial padded with NaN; velocities as interval differences) at the velocity interval its
    fit chose
    (:attr:`~torchconn.regression.model.LocalConnectionModel.diagnostics`); other regressions
    regress the smoothed trajectory (``N = T``).

    Args:
        traj: a prepared trajectory (smoothed and phased), batch dims ``...``.
        regression: the regression stage that fitted ``model``.
        model: its fit to ``traj``.
        pool: the fit pooled the trials; with ``flatten`` (default) the view is pooled too,
            every field flattened to ``(B·N, ·)`` (:func:`~torchconn.trajectory.pool_batch`).

    Returns:
        :class:`RegressionView`, ``(..., N, ·)``, or pooled ``(B·N, ·)``.
    """
    if isinstance(regression, NoiseAwareRegression):
        diag = model.diagnostics
        iv = interval_view(traj, torch.as_tensor(diag.velocity_interval, device=traj.r.device),
                           diag.velocity_kernel or VELOCITY_KERNEL)
        view = RegressionView(iv.phase, iv.r, iv.r_dot, iv.xi)
    else:
        sm = traj.smoothed
        view = RegressionView(traj.phase, sm.r, sm.r_dot, sm.xi)
    if pool and flatten:
        view = RegressionView(pool_batch(view.phase, 0), pool_batch(view.r, 1),
                              pool_batch(view.r_dot, 1), pool_batch(view.xi, 1))
    return view


def phase_average(view: RegressionView, order: int, orders: Tensor | None = None) -> FourierSeries:
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


def phase_average_orders(view: RegressionView, max_order: int, pool: bool, n_folds: int = 3
                         ) -> Tensor:
    """``(..., 3)`` (pooled: ``(3,)``) per component the order, at most ``max_order``, of the
    phase-averaged velocity with the least held-out squared error over the ``n_folds`` blocks
    of whole cycles the models are scored on (:func:`cycle_blocks`; ``view`` unflattened,
    ``(..., N, ·)``; the lowest order on ties). One set of normal equations per block gives
    every order (their designs are nested). A stronger baseline than :func:`phase_average` at
    the model's own order, which overfits the few cycles of a short recording; the
    estimator's checks use the model's order, ``benchmarks/short_recordings.py`` scores
    against both."""
    fold = cycle_blocks(view.phase, n_folds)
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


def skill(model: LocalConnectionModel, baseline, view: RegressionView,
          template: LocalConnectionModel | None = None,
          reference: PhysicsReference | None = None) -> Skill:
    """:class:`Skill` of ``model`` and ``baseline`` (a phase-averaged velocity) on ``view``;
    the template is ``ĉ`` of ``template`` (default ``model``): a forecasting model whose
    component falls back to the phase average has that for its ``ĉ`` there, so pass the
    connection it came from. ``reference``: a fitted physics reference scored beside them
    (``r2_physics``; its batch dims the view's, or none)."""
    out = _from_sums(*_sums(model, baseline, view, None, template=template)[0][:6])
    if reference is None:
        return out
    return with_physics(out, view, torch.zeros_like(view.phase, dtype=torch.long), [reference])


def cross_validate(traj: Trajectory, cycle: LimitCycle, regression: Regression, *,
                   pool: bool, n_folds: int = 3, noise_corrected: bool = False,
                   model: LocalConnectionModel | None = None, refit: bool = False,
                   phase_averaged: Tensor | None = None,
                   connection_only: Tensor | None = None,
                   connection_regressed: bool = False, forward: bool = False,
                   reference: str | None = None, frame: str | None = None) -> Skill:
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
    ``diagnostics`` give the window, interval and noise level).

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

    ``forward``: score only the last block, from the fit without it (every cycle it was fitted
    on comes earlier): a forward-in-time split, beside the phase average of the earlier
    blocks. ``reference``: a family of :data:`~torchconn.regression.reference.FAMILIES`
    (e.g. ``"swimmer"``) scored beside the model (``r2_physics``), its parameters fitted
    without each scored block (:func:`fold_references`; ``frame`` its body frame, default
    :func:`~torchconn.regression.reference.default_frame`); None: not scored.

    Raises:
        ValueError: ``refit`` and a block that cannot be fitted (the solver's message). The
            downdated fits never raise: a bin that cannot be fitted without a block predicts
            NaN, and the skill of that trial is NaN (see :attr:`Skill.unscored`).
    """
    reg, models, view, fold, _ = _checked_fold_models(
        traj, cycle, regression, model, pool, n_folds, refit, connection_regressed)
    folds = (n_folds - 1,) if forward else None
    references = None if reference is None else fold_references(
        view, fold, n_folds, pool, family=reference, frame=frame, folds=folds)
    return score_folds(models, view, fold, reg, traj.dt, pool, noise_corrected,
                       phase_averaged, connection_only, folds=folds, references=references)[0]


def held_out_checks(traj: Trajectory, cycle: LimitCycle, regression: Regression, *,
                    pool: bool, n_folds: int = 3, model: LocalConnectionModel | None = None,
                    phase_averaged: Tensor | None = None,
                    connection_only: Tensor | None = None,
                    connection_regressed: bool = False) -> tuple[Skill, Skill]:
    """:func:`cross_validate`'s interleaved skill and its forward one (``forward=True``)
    from one set of fits without each block (no physics reference: :func:`with_physics`
    adds it)."""
    reg, models, view, fold, _ = _checked_fold_models(
        traj, cycle, regression, model, pool, n_folds, False, connection_regressed)
    return tuple(score_folds(models, view, fold, reg, traj.dt, pool, False, phase_averaged,
                             connection_only, folds=folds)[0]
                 for folds in (None, (n_folds - 1,)))


def _checked_fold_models(traj, cycle, regression, model, pool, n_folds, refit,
                         connection_regressed):
    """:func:`fold_models` after checking :func:`cross_validate`'s arguments."""
    _checks_folds(n_folds)
    if connection_regressed and (refit or not downdates(regression)):
        raise ValueError("cross_validate: connection_regressed needs the downdated fits of a "
                         "TubeRegression or NoiseAwareRegression (refit=False)")
    return fold_models(traj, cycle, regression, model, pool=pool, n_folds=n_folds,
                       refit=refit, connection_regressed=connection_regressed)


def _checks_folds(n_folds) -> None:
    if isinstance(n_folds, bool) or not isinstance(n_folds, int) or n_folds < 2:
        raise ValueError(f"n_folds must be an integer >= 2, got {n_folds!r}")


def fold_references(view: RegressionView, fold: Tensor, n_folds: int, pool: bool, *,
                    family: str = "swimmer", frame: str | None = None,
                    folds=None) -> list[PhysicsReference | None]:
    """Per block ``f`` (those in ``folds``, default all ``n_folds``; None at the others) the
    physics reference :func:`~torchconn.regression.reference.fit_reference` fitted to the
    samples of ``view`` outside block ``f`` (and with a finite phase); ``fold``: the
    samples' blocks as :func:`score_folds` takes them; ``pool``: one parameter set for all
    trials (else one per trial). None also where a block's training samples are too few."""
    out: list[PhysicsReference | None] = [None] * n_folds
    for f in range(n_folds) if folds is None else folds:
        train = (fold != f) & torch.isfinite(view.phase)
        r = torch.where(train[..., None], view.r, torch.nan)
        try:
            out[f] = fit_reference(r, view.r_dot, view.xi, family=family, frame=frame,
                                   pool=pool)
        except ValueError as err:
            if "usable samples" not in str(err):
                raise
    return out


def with_physics(result: Skill, view: RegressionView, fold: Tensor,
                 references, folds=None) -> Skill:
    """``result`` (scored on the blocks ``folds`` of ``view``, default all; ``fold`` as
    :func:`score_folds` takes it) with ``r2_physics``: ``references[f]``'s prediction scored
    on block ``f`` (a reference that is None scores NaN), summed over the blocks."""
    sse = sy = syy = n = 0.0
    for f in range(len(references)) if folds is None else folds:
        ok, _, r, r_dot, y = _scored(view, fold == f)
        w = ok.to(y.dtype)[..., None]
        ref = references[f]
        pred = torch.full_like(y, torch.nan) if ref is None else ref.predict(r, r_dot)
        sse = sse + ((y - pred).square() * w).sum(-2)
        sy, syy, n = sy + (y * w).sum(-2), syy + (y.square() * w).sum(-2), n + w.sum(-2)
    sst = syy - sy.square() / n
    return dataclasses.replace(result, r2_physics=1 - sse / sst)


def fold_models(traj, cycle, regression, model, *, pool, n_folds, refit,
                 connection_regressed=False):
    """The regression, its fits without each of ``n_folds`` blocks of cycles
    (downdated ones of the connection alone where ``connection_regressed``), the view they
    are scored on, its block index and its cycle index (:func:`cycle_index`)."""
    reg = regression
    if model is None:
        model = reg.fit(traj, cycle, pool=pool)  # the view's interval, from the whole recording
    unflat = regression_view(traj, reg, model, pool=pool, flatten=False)
    view = regression_view(traj, reg, model, pool=pool)
    fold = cycle_blocks(unflat.phase, n_folds)
    if refit or not downdates(reg):
        sample_fold = cycle_blocks(traj.phase, n_folds)
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
            cycle_index(unflat.phase, pool))


def variant_scores(models, view: RegressionView, fold: Tensor, reg: Regression, dt: float, pool: bool,
                    cycle: Tensor, noise_corrected: bool = True
                    ) -> tuple[tuple[Skill, Tensor], tuple[Skill, Tensor]]:
    """:func:`score_folds` (with the per-cycle gaps) of the fold models as fitted and of the
    connection alone (their rows of ``b̂`` and ``∂Â/∂r`` set to 0): the candidates of
    :func:`_choose_terms`."""
    every = torch.ones(3, dtype=torch.bool, device=view.phase.device)
    return (score_folds(models, view, fold, reg, dt, pool, noise_corrected, cycle=cycle),
            score_folds(models, view, fold, reg, dt, pool, noise_corrected,
                         connection_only=every, cycle=cycle))


def score_folds(models, view: RegressionView, fold: Tensor, reg: Regression, dt: float, pool: bool,
                 noise_corrected: bool, phase_averaged: Tensor | None = None,
                 connection_only: Tensor | None = None,
                 cycle: Tensor | None = None, folds=None,
                 references=None) -> tuple[Skill, Tensor | None]:
    """:class:`Skill` of ``models[f]`` on block ``f`` of ``view``, summed over the blocks,
    beside the phase-averaged velocity of the other blocks (noise-corrected as asked); with
    ``cycle`` (:func:`cycle_index`) also, per held-out cycle, the ``SSE`` of the model
    minus that of the phase average and the phase average's own ``(..., C, 3, 2)``, as
    observed: the model's error on the noisy inputs, what a user's held-out data show.

    ``phase_averaged``: ``(..., 3)`` components each fold's model predicts by that baseline;
    ``connection_only``: ``(..., 3)`` components whose ``b̂`` and ``∂Â/∂r`` rows it zeroes.
    ``folds``: the blocks scored (default all; ``(len(models) − 1,)``: the last, a forward
    split). ``references``: per block the physics reference fitted without it
    (:func:`fold_references`), scored as ``r2_physics`` (:func:`with_physics`)."""
    sums, gaps = [], []
    n_cycles = None if cycle is None else int(cycle.amax()) + 1
    for f in range(len(models)) if folds is None else folds:
        fold_model, base, template = fold_predictors(models, view, fold, reg, f,
                                                     phase_averaged, connection_only)
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
    result = _from_sums(total[0] - total[6], *total[1:6])
    if references is not None:
        result = with_physics(result, view, fold, references, folds)
    return result, per_cycle


def fold_predictors(models, view: RegressionView, fold: Tensor, reg: Regression, f: int,
                    phase_averaged: Tensor | None = None,
                    connection_only: Tensor | None = None
                    ) -> tuple[LocalConnectionModel, FourierSeries, LocalConnectionModel]:
    """What :func:`score_folds` scores on block ``f``: the forecasting model fitted without it
    (``models[f]`` with the components ``phase_averaged`` predicted by the baseline and those
    ``connection_only`` by ``c + Aδ̇``), the baseline (the phase-averaged velocity of the
    other blocks of ``view``, at the regression's order or the highest the other blocks
    determine) and the template's model (``models[f]`` as fitted)."""
    fold_model = models[f]
    train = torch.where(fold != f, view.phase, torch.nan)
    # on a few cycles at video rates the other blocks may hold fewer samples than the
    # model's order needs: the baseline then takes the highest order they determine
    n_train = int(torch.isfinite(train).sum(-1).min())
    base = phase_average(RegressionView(train, view.r, view.r_dot, view.xi),
                         min(reg.fourier_order, max((n_train - 1) // 2, 0)))
    template = fold_model  # Â(γ)γ̇ of the fold's fit, even where it falls back
    if phase_averaged is not None or connection_only is not None:
        fold_model = with_phase_average(fold_model, base, phase_averaged, connection_only)
        base = base.padded(fold_model.c.order)  # the same sums: an exact tie
    return fold_model, base, template


@dataclass(frozen=True)
class ForwardPrediction:
    """The forward-in-time held-out check's predictions, sample by sample
    (:func:`forward_prediction`).

    Attributes:
        view: the samples, :class:`RegressionView` ``(..., N, ·)`` per trial (not pooled).
        held_out: ``(..., N)`` bool, the samples of the last block of cycles (finite).
        predicted: ``(..., N, 3)`` body velocity predicted by the forecasting model fitted
            without that block (the same units as ``view.xi``).
        phase_average: ``(..., N, 3)`` the phase-averaged velocity of the earlier blocks.
    """

    view: RegressionView
    held_out: Tensor
    predicted: Tensor
    phase_average: Tensor


def forward_prediction(traj: Trajectory, cycle: LimitCycle, regression: Regression,
                       model: LocalConnectionModel, *, pool: bool, n_folds: int = 3,
                       phase_averaged: Tensor | None = None,
                       connection_only: Tensor | None = None,
                       connection_regressed: bool = False, prior_weight: Tensor | None = None,
                       family: str = "swimmer", frame: str | None = None) -> ForwardPrediction:
    """The predictions :func:`cross_validate` scores with ``forward=True``: on the last of
    ``n_folds`` blocks of cycles of every trial, the forecasting model fitted without it and
    the phase average of the earlier blocks (arguments as :func:`cross_validate`'s;
    ``model``: the regression's fit to the whole recording). With ``prior_weight``
    (``(..., 3)``, the estimator's ``prior_weight_``) the forecasts are blended with the
    physics reference of ``family`` (in ``frame``) fitted to the earlier blocks, as the
    estimator delivers them."""
    _checks_folds(n_folds)
    reg, models, view, fold, _ = fold_models(traj, cycle, regression, model, pool=pool,
                                             n_folds=n_folds, refit=False,
                                             connection_regressed=connection_regressed)
    last = n_folds - 1
    fold_model, base, _ = fold_predictors(models, view, fold, reg, last, phase_averaged,
                                          connection_only)
    unflat = regression_view(traj, reg, model, pool=pool, flatten=False)
    ok, phase, r, r_dot, _ = _scored(unflat, cycle_blocks(unflat.phase, n_folds) == last)
    nan = torch.tensor(torch.nan, dtype=unflat.xi.dtype, device=unflat.xi.device)
    predicted = fold_model.predict(phase, r, r_dot)
    if prior_weight is not None and bool((prior_weight > 0).any()):
        reference = fold_references(view, fold, n_folds, pool, family=family, frame=frame,
                                    folds=(last,))[last]
        if reference is not None:
            predicted = predicted + prior_weight.unsqueeze(-2) * (
                reference.predict(r, r_dot) - predicted)
    return ForwardPrediction(unflat, ok, torch.where(ok[..., None], predicted, nan),
                             torch.where(ok[..., None], base(phase), nan))


def held_out_predictions(models, view: RegressionView, fold: Tensor, reg: Regression,
                         phase_averaged: Tensor | None = None,
                         connection_only: Tensor | None = None,
                         references=None) -> tuple[Tensor, Tensor | None]:
    """Each sample of ``view`` predicted by the fold model fitted without its block
    (:func:`fold_predictors`), ``(..., N, 3)`` (NaN where not scored), and with
    ``references`` (per block the physics reference fitted without it,
    :func:`fold_references`) likewise that reference's prediction (else None)."""
    out = torch.full_like(view.xi, torch.nan)
    ref_out = None if references is None else torch.full_like(view.xi, torch.nan)
    for f in range(len(models)):
        ok, phase, r, r_dot, _ = _scored(view, fold == f)
        forecast = fold_predictors(models, view, fold, reg, f, phase_averaged,
                                   connection_only)[0]
        out = torch.where(ok[..., None], forecast.predict(phase, r, r_dot), out)
        if references is not None and references[f] is not None:
            ref_out = torch.where(ok[..., None], references[f].predict(r, r_dot), ref_out)
    return out, ref_out


def _scored(view: RegressionView, mask: Tensor | None):
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
                          model: LocalConnectionModel, view: RegressionView, fold: Tensor,
                          n_folds: int, *, pool: bool,
                          ridges: tuple[float, ...] | None = None,
                          columns: Tensor | None = None, window=None) -> Tensor:
    """Per-bin coefficients ``(R, F, ..., M, P, 3)`` of ``regression`` fitted without each of
    the ``F = n_folds`` blocks (:func:`~torchconn.regression.held_out.leave_blocks_out`), for
    each ridge in ``ridges`` (default: the regression's own).

    ``model`` is the regression's fit to the whole recording (its bins' centres and
    ``diagnostics``: velocity interval, noise level); ``view`` and ``fold`` ``(..., N)`` are the samples it
    regressed on (:func:`regression_view` with ``flatten=False``) and their blocks. ``window``:
    the bins' half-width (default: the regression's own, or its rule applied to the samples
    outside one block, :func:`_fold_windows`).
    """
    ridges = (regression.ridge,) if ridges is None else tuple(ridges)
    diag = model.diagnostics
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
        var_delta, var_rate = (v.reshape(n, d) for v in _interval_noise(diag, batch, traj.dt,
                                                                         **kw))
    if window is None:
        window = _fold_windows(regression, diag, phase, fold, d)
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
    (``model.diagnostics.corrected_weight``, as the window and the interval are the whole
    recording's). Without this the check would score the corrected estimate alone, which is
    far off where the fit falls back to the smoothed one. Other regressions: ``coef``.
    ``columns``: as :func:`held_out_coefficients`'s (``coef`` fitted with them);
    ``sample_fold``: ``(..., T)`` block of every sample (default: ``n_folds`` blocks of whole
    cycles, :func:`cycle_blocks`)."""
    if not isinstance(regression, NoiseAwareRegression):
        return coef
    smoothed = TubeRegression(**{f.name: getattr(regression, f.name)
                                 for f in dataclasses.fields(TubeRegression)})
    sm = traj.smoothed
    view = RegressionView(traj.phase, sm.r, sm.r_dot, sm.xi)
    if sample_fold is None:
        sample_fold = cycle_blocks(traj.phase, n_folds)
    coef_s = held_out_coefficients(traj, smoothed, model, view, sample_fold, n_folds, pool=pool,
                                   ridges=ridges, columns=columns)
    d = model.shape_dim
    term = torch.tensor([0] + [1] * d + [2] * d + [3] * d * d, device=coef.device)
    w = torch.as_tensor(model.diagnostics.corrected_weight, dtype=coef.dtype,
                        device=coef.device)[..., term]  # (..., P)
    w = w[..., None, :, None]  # (..., 1, P, 1): over bins and outputs
    # exact ends, so that a bin only one of the two could fit keeps the other's coefficients
    return torch.where(w == 1, coef, torch.where(w == 0, coef_s, coef_s + w * (coef - coef_s)))


def _fold_windows(regression: Regression, diag: RegressionDiagnostics, phase: Tensor,
                  fold: Tensor, d: int):
    """The bins' half-width(s) the regression's own rule gives on the samples outside one
    block (block 0; the blocks are about equal): a refit on fewer cycles widens its windows,
    and keeping the whole recording's narrower ones would handicap the models with more
    regressors.

    ``phase``, ``fold``: ``(..., N)`` (pooled: ``(N,)``). Returns a float or a ``(...)`` list.
    """
    if regression.window is not None:
        return regression.window
    train = torch.where(fold == 0, torch.nan, phase)
    if not isinstance(regression, NoiseAwareRegression):
        return auto_window(train, regression.n_bins, 1 + 2 * d + d * d,
                            regression.samples_per_regressor)
    ratio = torch.as_tensor(diag.noise_ratio, dtype=torch.float64, device=phase.device)
    if train.ndim == 1:  # pooled: the window the fit chose, widened as fewer cycles need
        return max(float(diag.window), auto_window(train, regression.n_bins,
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

    c_order = model.diagnostics.intercept_order
    if c_order is not None:
        c_order = torch.as_tensor(c_order, device=coef.device)
    # the coefficients are the regression's own: its δ̇⊗δ one is what predictions use
    c_series = intercept_series(centres, c, order, c_order)
    return dataclasses.replace(model, c=masked(c_series), b=series(b, 2), A=series(a, 2),
                               dA=series(da, 3), dA_fit=None)


def _noise_of(model: LocalConnectionModel, dt: float, pool: bool):
    """Noise variances of the view's ``δ`` and ``δ̇`` from a noise-aware model's
    ``diagnostics``, shaped to broadcast against the view's ``(..., N, d)``."""
    kw = dict(dtype=model.phase_rate.dtype, device=model.phase_rate.device)
    diag = model.diagnostics
    batch = () if pool else tuple(torch.as_tensor(diag.velocity_interval, **kw).shape)
    var_delta, var_rate = _interval_noise(diag, batch, dt, **kw)
    if not pool:
        var_rate, var_delta = var_rate.unsqueeze(-2), var_delta.unsqueeze(-2)
    return var_delta, var_rate


def _interval_noise(diag: RegressionDiagnostics, batch: tuple, dt: float, **kw
                    ) -> tuple[Tensor, Tensor]:
    """Noise variances ``(*batch, d)`` of ``δ`` and ``δ̇`` in a noise-aware fit's interval
    samples, from its diagnostics (noise level, velocity interval and filter; the gains of
    :func:`~torchconn.noise.interval_noise_gains`)."""
    sigma2 = torch.as_tensor(diag.noise_r, **kw).square()
    sigma2 = sigma2.expand(batch + sigma2.shape[-1:])
    h = torch.as_tensor(diag.velocity_interval, device=kw.get("device")).expand(batch)
    h = h.reshape(-1).tolist()
    kernel = diag.velocity_kernel or VELOCITY_KERNEL
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


def _sums(model: LocalConnectionModel, baseline, view: RegressionView, mask: Tensor | None,
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
                 r2_template=1 - sse_template / sst, n_samples=n, r2_zero=1 - syy / sst)
