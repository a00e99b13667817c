"""The estimator: recordings in, a local connection model out (the paper's Sec. 4).

:class:`ConnectionEstimator` joins five stages, each a small immutable option object with one
job, in the manner of pysindy's ``SINDy(differentiation_method=…, feature_library=…,
optimizer=…)``::

    ConnectionEstimator(
        smoother=RTSSmoother(order=2),          # phase/smoothing.py: smooth(traj) -> traj
        phaser=Phaser(order="auto"),            # phase/phaser.py: fit(r) -> fitted, transform(r)
        cycle=SelfConsistentCycle(order=8),     # phase/limit_cycle.py: fit(traj) -> LimitCycle
        regression=NoiseAwareRegression(n_bins=48),  # regression/noise_aware: fit(traj, cycle)
        metric=TiedMetric(order=6),             # regression/metric: fit(traj, cycle), attach
        pool=False,                             # one model per trial, or one for all trials
    )

Swapping a stage is a keyword argument; a new method is a new subclass of the stage's base
(:class:`~torchconn.phase.smoothing.Smoother`, :class:`~torchconn.phase.phaser.PhaseEstimator`,
:class:`~torchconn.phase.limit_cycle.CycleEstimator`, :class:`~torchconn.regression.base.Regression`,
:class:`~torchconn.regression.metric.MetricEstimator`).
``get_params`` / ``set_params`` follow scikit-learn (``regression__n_bins`` keys), so
``sklearn.base.clone`` and grid searches work without torchconn depending on scikit-learn.

:func:`estimator_from_settings` builds an estimator from a nested mapping (the sweep's TOML
``[estimator]`` table) and :func:`estimator_settings` writes one back. The steps are also
functions: :func:`prepare` (smooth, phase) and :func:`fit_local_model` (the regressions).
"""

from __future__ import annotations

import contextlib
import dataclasses
import warnings
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from .. import _checks
from .._checks import unknown_keys_message
from ..cycles import cycle_blocks, cycles_note
from ..io.preflight import MAX_GAP_CYCLES, preflight
from ..phase.limit_cycle import CycleEstimator, LimitCycle, SelfConsistentCycle
from ..phase.phaser import PhaseEstimator, Phaser
from ..phase.smoothing import RTSSmoother, Smoother
from ..trajectory import Trajectory, for_estimation, pool_batch, power_problem
from . import selection
from ._wls import IllConditionedBinWarning
from .base import Regression, check_bin_count
from .metric import FittedMetric, MetricEstimator, TiedMetric
from .model import LocalConnectionModel
from .noise_aware import NoiseAwareRegression
from .reference import FAMILIES, PhysicsReference, default_frame, fit_reference
from .tube import TubeRegression

__all__ = [
    "ConnectionEstimator", "estimator_from_settings", "estimator_settings", "STAGES",
    "prepare", "fit_local_model",
]

#: the estimator's stages: keyword -> (base class, {method name: class}); the first method is
#: the default. A settings table picks one with ``method = "name"``.
STAGES: dict[str, tuple[type, dict[str, type]]] = {
    "smoother": (Smoother, {"rts": RTSSmoother}),
    "phaser": (PhaseEstimator, {"phaser": Phaser}),
    "cycle": (CycleEstimator, {"self_consistent": SelfConsistentCycle}),
    "regression": (Regression, {"noise_aware": NoiseAwareRegression, "tube": TubeRegression}),
    "metric": (MetricEstimator, {"tied": TiedMetric}),
}

#: the estimator's own options besides its stages (settings-table keys beside the stages)
OPTIONS = ("pool", "complexity", "held_out_folds", "prior")
#: how the regression's complexity (bins, Fourier order, ridge) is set; see ConnectionEstimator
COMPLEXITY = ("auto", "fixed", "cv")

class ConnectionEstimator:
    """Estimate a local connection (and metric) around the gait in recorded trials.

    Args:
        smoother: smooths poses and shapes and derives velocities (:class:`RTSSmoother`).
        phaser: estimates the phase when none is given (:class:`Phaser`).
        cycle: fits the limit cycle γ(φ) to the phased shapes (:class:`SelfConsistentCycle`).
        regression: fits the local model around the cycle (:class:`NoiseAwareRegression`:
            raw interval differences corrected for the motion-capture noise, shrunk towards
            the smoothed fit where the data cannot support the correction;
            :class:`TubeRegression`: Kalman-smoothed velocities, torchconn 0.1's method).
        metric: fits the dissipation metric from a recorded power channel
            (:class:`~torchconn.regression.metric.TiedMetric`; its ``enabled`` says whether:
            None, when the data carry power; True, required; False, never). One metric fit
            serves every candidate model of a recording.
        pool: fit one model to all trials together (their phases must share a Poincaré section,
            which Phaser's phase 0 provides) instead of one model per trial.
        complexity: the regression's bins, Fourier order and ridge: ``"fixed"`` as given;
            ``"cv"`` chosen by held-out error over blocks of whole cycles
            (:func:`~torchconn.regression.selection.select_complexity`), where each component
            is predicted by the full model, the connection alone or the phase-averaged
            velocity, whichever clearly wins held out (in ``forecast_model_``; ``model_``
            keeps every component's terms, its complexity chosen with ``Â`` unpenalised);
            ``"auto"`` (default): as given, unless on held-out blocks the fit loses to the
            phase-averaged velocity or a component's full model is not the one to keep
            (short recordings), then chosen as by ``"cv"``. Where no candidate can be
            fitted without one block (video rates: 5-link, 3-12 cycles at 10-32 samples per
            cycle), the recording is checked with the connection alone ``c + Âδ̇`` regressed
            (:func:`~torchconn.regression.selection.select_connection_alone`: it predicts the
            components where it clearly beats the phase average held out, and it is
            ``model_``, ``b̂`` and ``∂Â/∂r`` 0); where that cannot be scored either, the
            phase average is presumed on up to 6 cycles and the given fit kept unchecked on
            more.
        held_out_folds: blocks of whole cycles of the held-out check every fit runs (0: no
            check). The fit warns (:class:`~torchconn.regression.selection.PoorHeldOutSkillWarning`)
            where the model predicts held-out cycles worse than their phase-averaged velocity.
            The fits without each block come from downdating the bins' normal equations
            (:mod:`~torchconn.regression.held_out`), not from refits.
        prior: the physics reference family (a name in
            :data:`~torchconn.regression.reference.FAMILIES`; default the viscous N-link
            swimmer) fitted as a baseline and used as the forecasts' prior: per component the
            forecasts are shrunk towards the fitted reference by the weight that minimises
            their error on held-out cycles, kept only where it lowers that error clearly
            (:mod:`~torchconn.regression.selection.prior`; ``prior_weight_``). It acts on
            short recordings, where the reference predicts held-out cycles better, and
            leaves long ones as fitted. None: no prior (the swimmer is still the baseline).

    scikit-learn manners: the constructor only stores its arguments, :meth:`fit` returns
    ``self``, fitted attributes end in ``_``:

    - ``trajectory_``: the prepared :class:`~torchconn.trajectory.Trajectory` (smoothed, phase);
    - ``phaser_``: the fitted phaser (its ``model_`` can phase new recordings with the same
      origin), or None when the phase was given or already in the trajectory;
    - ``limit_cycle_``: the :class:`~torchconn.phase.limit_cycle.LimitCycle`;
    - ``model_``: the :class:`~torchconn.regression.model.LocalConnectionModel`, the
      connection (``Â``, ``∂Â/∂r``, ``M̂`` and their bands) to read, save and design gaits
      with: every row estimated, and where the complexity was chosen by held-out error among
      ridges that shrink ``Â``, the complexity chosen and fitted the same way with
      ``Â`` unpenalised (the full model of ``regression.replace(ridge_connection=False)``;
      its settings in ``meta["settings"]``). Where it differs from ``forecast_model_``,
      ``meta["forecast_model"]`` says how;
    - ``forecast_model_``: the model :meth:`predict`, :meth:`score`, :meth:`cross_validate`
      and the held-out check use: the fit of ``regression_`` (the chosen ridge on ``Â`` too)
      with the components ``complexity_`` gave to the phase average or the connection alone
      predicted so. It is ``model_`` itself where nothing was shrunk or zeroed (no complexity
      chosen, as on long recordings and with ``complexity="fixed"``; or no ridge chosen and
      every component's full model kept);
    - ``regression_``: the regression stage fitted for ``forecast_model_`` (``regression``
      with the chosen complexity);
    - ``complexity_``: the :class:`~torchconn.regression.selection.ComplexityChoice` when the
      complexity was chosen by held-out error, else None; its ``phase_averaged`` names the
      components (per trial) predicted by the phase-averaged velocity because their shape
      terms did not beat it on held-out cycles (their rows of ``b``, ``A``, ``∂A/∂r`` are 0 in
      ``forecast_model_``), its ``connection_only`` those predicted by ``c + Aδ̇`` because
      ``b`` and ``∂A/∂r`` did not add to the connection held out (their rows of ``b`` and
      ``∂A/∂r`` are 0 there, ``A`` kept);
    - ``held_out_skill_``: the held-out :class:`~torchconn.regression.selection.Skill` of the
      check, of ``forecast_model_`` (None when ``held_out_folds=0`` or the regression is not
      a built-in one), each block of cycles left out in turn (interleaved blocks); beside
      the phase average and the template, the physics reference (``r2_physics``, fitted
      without each block) and zero (``r2_zero``);
    - ``forward_skill_``: the same check on the last block of cycles alone, from the fit
      without it (every training cycle earlier): a forward-in-time split (None likewise);
    - ``reference_``: the physics reference
      (:class:`~torchconn.regression.reference.PhysicsReference`: the viscous swimmer of
      ``d + 1`` links in :func:`~torchconn.regression.reference.default_frame`, or in
      ``trajectory.meta["frame"]`` where the recording names its frame) with its drag ratio
      fitted to the whole recording as the regression sees it; fitted where the held-out
      check runs, else on the first :meth:`score` (None until then);
    - ``prior_weight_``: ``(..., 3)`` the share of the physics reference in each component of
      ``forecast_model_`` (0: the fitted model alone, 1: the reference alone), or None where
      the held-out check is off or ``prior`` is None.

    Example::

        est = ConnectionEstimator(regression=NoiseAwareRegression(n_bins=48, fourier_order=12))
        est.fit(traj)
        xi_hat = est.predict(traj)               # (..., T, 3), by forecast_model_
        A_on_cycle = est.model_.connection(phi)  # (..., P, 3, d)
        est.set_params(regression__n_bins=24)    # a new regression stage, unfitted settings
    """

    def __init__(
        self,
        *,
        smoother: Smoother = RTSSmoother(),
        phaser: PhaseEstimator = Phaser(),
        cycle: CycleEstimator = SelfConsistentCycle(),
        regression: Regression = NoiseAwareRegression(),
        metric: MetricEstimator = TiedMetric(),
        pool: bool = False,
        complexity: str = "auto",
        held_out_folds: int = 3,
        prior: str | None = "swimmer",
    ):
        self.smoother = smoother
        self.phaser = phaser
        self.cycle = cycle
        self.regression = regression
        self.metric = metric
        self.pool = pool
        self.complexity = complexity
        self.held_out_folds = held_out_folds
        self.prior = prior
        _check_arguments(**self.get_params(deep=False))

    # ------------------------------------------------------------------ scikit-learn params
    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor's arguments; with ``deep`` also each stage's fields as
        ``stage__field`` (scikit-learn's protocol)."""
        params = {name: getattr(self, name) for name in (*STAGES, *OPTIONS)}
        if deep:
            for name in STAGES:
                for key, value in getattr(self, name).get_params().items():
                    params[f"{name}__{key}"] = value
        return params

    def set_params(self, **params: Any) -> "ConnectionEstimator":
        """Set constructor arguments or stage fields (``regression__n_bins=24``); returns self.

        A stage field is changed by replacing the stage with a changed copy, so option objects
        shared with other estimators are never modified.
        """
        valid = self.get_params(deep=True)
        unknown = set(params) - set(valid)
        if unknown:
            raise ValueError(unknown_keys_message("ConnectionEstimator.set_params", unknown, valid))
        new = {k: v for k, v in params.items() if "__" not in k}
        nested: dict[str, dict[str, Any]] = {}
        for key, value in params.items():
            if "__" in key:
                stage, field = key.split("__", 1)
                nested.setdefault(stage, {})[field] = value
        for stage, changes in nested.items():
            new[stage] = new.get(stage, getattr(self, stage)).replace(**changes)
        _check_arguments(**{**self.get_params(deep=False), **new})  # all or nothing
        for key, value in new.items():
            setattr(self, key, value)
        return self

    # ------------------------------------------------------------------ fitting
    def fit(self, traj: Trajectory, phase: Tensor | None = None) -> "ConnectionEstimator":
        """Fit to recordings ``traj`` (batch dims ``...``: one model per trial unless pooled).

        The pipeline: check the input; smooth (``smoother``) and phase (``phaser``); fit the
        limit cycle (``cycle``); fit the connection (``regression``) and the metric
        (``metric``); select the forecasts' complexity on held-out cycles; deliver the
        fitted attributes.

        Args:
            traj: a :class:`~torchconn.trajectory.Trajectory` (simulated, or read with
                :func:`torchconn.io.trajectory_files.read_csv`).
            phase: optional ``(..., T)`` phase to use instead of the phaser's estimate.
        """
        traj = self._checked(traj, phase)
        traj, fitted_phaser = _prepare(traj, phase, self.smoother, self.phaser)
        cycle = self.cycle.fit(traj, pool=self.pool)
        with _cycles_in_errors(traj, self.regression, self.complexity):
            connection = self._connection(traj, cycle)
            metric = self._fit_metric(traj, cycle)
            outcome = self._selection(traj, cycle, connection, metric)
        self._deliver(traj, fitted_phaser, cycle, outcome, metric)
        return self

    # ------------------------------------------------------------------ the pipeline's steps
    def _checked(self, traj: Trajectory, phase: Tensor | None) -> Trajectory:
        """``traj`` checked for estimation: shapes, the power channel the metric stage needs
        (or refuses), and no more phase bins than samples."""
        traj = for_estimation(traj, "ConnectionEstimator.fit", phase)
        if self.metric.enabled is not False and traj.power is not None:
            for k, p in enumerate(traj.power.reshape(-1, traj.n_samples)):
                problem = power_problem(p)
                if problem is not None:
                    raise ValueError(f"ConnectionEstimator.fit: power of trial {k} (flattened "
                                     f"batch): {problem}; or fit the connection alone "
                                     "(metric__enabled=False)")
        if self.metric.enabled is True and traj.power is None:
            raise ValueError(
                "the metric stage requires a power channel (metric__enabled=True) but the data "
                "have none (CSV column 'power', or Trajectory.power): record the dissipated "
                "power to estimate the metric, or use metric__enabled=None (fit it when power "
                "is present) / False to fit the connection alone"
            )
        check_bin_count(self.regression.n_bins, int(torch.isfinite(traj.r).all(-1).sum()),
                        "ConnectionEstimator.fit: regression")
        return traj

    def _connection(self, traj: Trajectory, cycle: LimitCycle) -> LocalConnectionModel | None:
        """The given regression's fit (no metric yet); None with ``complexity="cv"`` (the
        complexity is chosen first) and, with ``"auto"``, where the recording cannot carry its
        coefficients (the selection chooses them)."""
        if self.complexity == "cv":
            return None
        try:
            return self.regression.fit(traj, cycle, pool=self.pool)
        except ValueError:
            if self.complexity != "auto" or not selection.downdates(self.regression):
                raise
            return None

    def _selection(self, traj: Trajectory, cycle: LimitCycle,
                   connection: LocalConnectionModel | None, metric) -> _Outcome:
        """The forecasts' regression and model: the first of these candidates that the
        recording supports, in order:

        1. the given complexity (always with ``"fixed"``; with ``"auto"`` where it passes the
           held-out check);
        2. the complexity chosen by held-out error (always with ``"cv"``);
        3. the connection alone, where no candidate with ``b̂`` and ``∂Â/∂r`` can be scored;
        4. the given fit unchecked (the phase average presumed on few cycles).
        """
        given = _Given(self.regression, _with_metric(connection, metric), connection=connection)
        if given.model is not None:
            few = bool(selection.few_cycles(traj.phase, self.pool).any())
            given.held, given.forward, given.full = self._held_out(
                traj, cycle, given.regression, given.model,
                terms=self.complexity == "auto" and few)
        for candidate in (self._as_given, self._by_held_out, self._alone, self._unchecked):
            outcome = candidate(traj, cycle, metric, given)
            if outcome is not None:
                return outcome
        raise AssertionError("the last candidate always returns")  # pragma: no cover

    def _as_given(self, traj, cycle, metric, given: _Given) -> _Outcome | None:
        """Candidate 1: the given complexity's fit, where it is kept."""
        if given.model is None or self.complexity == "cv":
            return None
        if self.complexity == "auto" and given.held is not None and bool(
                (given.held.worse_than_phase_average | given.held.unscored[..., None]
                 | ~given.full).any()):
            return None  # the given complexity overfits this recording
        return _Outcome(given.regression, given.model, given.held, forward=given.forward)

    def _by_held_out(self, traj, cycle, metric, given: _Given) -> _Outcome | None:
        """Candidate 2: the complexity chosen by held-out error, fitted; None with ``"auto"``
        where no candidate can be scored (the error kept for candidate 4)."""
        try:
            chosen, choice, free = self._select(traj, cycle, given)
        except ValueError as err:
            if self.complexity != "auto":
                raise
            given.error = err
            return None
        model = _refit(chosen, given.regression, given.model, traj, cycle, self.pool, metric)
        held, forward, _ = self._held_out(traj, cycle, chosen, model, choice)
        return _Outcome(chosen, model, held, choice, free, forward=forward)

    def _alone(self, traj, cycle, metric, given: _Given) -> _Outcome | None:
        """Candidate 3: the connection alone (``1 + d`` regressors per bin), which the check
        can score: it predicts where it clearly beats the phase average, and it is the
        connection delivered."""
        alone = self._connection_alone(traj, cycle, given.regression, given.held, given.model)
        if alone is None:
            return None
        delivered = _connection_delivered(alone, given.model, given.regression, traj, cycle,
                                          self.pool, metric)
        return _Outcome(alone.regression, alone.model, alone.held_out, alone.choice,
                        delivered=delivered, forward=alone.forward)

    def _unchecked(self, traj, cycle, metric, given: _Given) -> _Outcome:
        """Candidate 4: the given fit unchecked; on few cycles the simpler model is presumed
        and the phase average predicts. Raises the selection's error where there is no fit."""
        if given.model is None:
            raise given.error
        choice = selection.unchecked_choice(given.held, given.regression,
                                            selection.few_cycles(traj.phase, self.pool))
        return _Outcome(given.regression, given.model, given.held, choice, searched=True,
                        forward=given.forward)

    def _deliver(self, traj: Trajectory, fitted_phaser: PhaseEstimator | None,
                 cycle: LimitCycle, outcome: _Outcome, metric) -> None:
        """Set the fitted attributes from the selection's ``outcome``: the forecasting model
        (the components its choice gave to the phase average or the connection alone
        predicted so) and the connection model (every row as estimated; where the choice
        penalised ``Â``, the complexity chosen with ``Â`` unpenalised); warn where the
        held-out check found the forecasts poor."""
        regression, model, choice = outcome.regression, outcome.model, outcome.choice
        view = selection.regression_view(traj, regression, model, pool=self.pool)
        self.phase_average_ = selection.phase_average(view, regression.fourier_order)
        forecast = model
        if choice is not None and (choice.phase_averaged_names()
                                   or choice.connection_only_names()):
            forecast = selection.with_phase_average(model, self.phase_average_,
                                                    *_masks(choice, model.device))
            # one order for both, so that score() finds them tied exactly
            self.phase_average_ = self.phase_average_.padded(forecast.c.order)
        unshrunk = _unshrunk(regression, outcome.free)
        connection = outcome.delivered if outcome.delivered is not None else model \
            if unshrunk is None else _fit(unshrunk, traj, cycle, self.pool, metric)
        self.trajectory_, self.phaser_, self.limit_cycle_ = traj, fitted_phaser, cycle
        self.regression_, self.complexity_ = regression, choice
        self.held_out_skill_, self.forward_skill_, self.reference_ = outcome.held, None, None
        self.prior_weight_ = None
        if outcome.held is not None:
            references, fold = self._baselines(traj, view, outcome)
            if self.prior is not None:
                forecast = self._with_prior(traj, cycle, view, outcome, forecast, references,
                                            fold)
        self.forecast_model_ = _with_settings(forecast, estimator_settings(self, regression))
        self.model_ = self.forecast_model_
        if forecast is not connection:
            self.model_ = _with_settings(connection,
                                         estimator_settings(self, unshrunk or regression),
                                         forecast_model=_forecast_meta(choice, regression,
                                                                        self.prior_weight_))
        if outcome.held is not None:
            selection.warn_if_poor(outcome.held, stacklevel=4, choice=choice,
                                   searched=outcome.searched)

    def _baselines(self, traj: Trajectory, view: "selection.RegressionView",
                   outcome: _Outcome) -> tuple[list, Tensor]:
        """The physics reference fitted to the whole recording (``reference_``) and without
        each block of cycles, scored beside the held-out check's model (``r2_physics`` of
        ``held_out_skill_`` and ``forward_skill_``); ``view``: the samples the outcome's
        regression fitted (pooled as the fit). Returns the references without each block
        and the samples' blocks."""
        unflat = selection.regression_view(traj, outcome.regression, outcome.model,
                                           pool=self.pool, flatten=False)
        fold = cycle_blocks(unflat.phase, self.held_out_folds)
        fold = pool_batch(fold, 0) if self.pool else fold
        frame = self._reference_frame(traj)
        folds = self.held_out_folds
        references = selection.fold_references(view, fold, folds, self.pool, frame=frame,
                                               family=self._family)
        self.held_out_skill_ = selection.with_physics(outcome.held, view, fold, references)
        if outcome.forward is not None:
            self.forward_skill_ = selection.with_physics(outcome.forward, view, fold,
                                                         references, (folds - 1,))
        self.reference_ = self._fit_reference(traj, view)
        return references, fold

    def _with_prior(self, traj: Trajectory, cycle: LimitCycle,
                    view: "selection.RegressionView", outcome: _Outcome,
                    forecast: LocalConnectionModel, references: list, fold: Tensor
                    ) -> LocalConnectionModel:
        """The forecasting model shrunk towards the physics reference
        (:mod:`~torchconn.regression.selection.prior`): per component the weight that
        minimises the held-out squared error of the blend of the forecasts' fits without
        each block with the references fitted without it, kept where it clearly lowers it
        (``prior_weight_``, ``(..., 3)``: 0 model, 1 the physics reference), and 1 where the
        reference predicts better than that blend on every held-out block and on the forward
        one (:func:`~torchconn.regression.selection.prior.forward_checked`). The connection
        ``model_`` is kept as estimated."""
        choice = outcome.choice
        models = selection.fold_models(
            traj, cycle, outcome.regression, outcome.model, pool=self.pool,
            n_folds=self.held_out_folds, refit=False,
            connection_regressed=choice is not None and choice.connection_regressed)
        fitted, physics = selection.held_out_predictions(
            models[1], view, fold, outcome.regression, *_masks(choice, outcome.model.device),
            references=references)
        weight = selection.prior_weights(view.xi, fitted, physics, models[4].reshape(
            view.phase.shape))
        forward = fold == self.held_out_folds - 1
        if self.forward_skill_ is not None:
            weight = selection.forward_checked(weight, view.xi, fitted, physics, forward)
        self.prior_weight_ = weight
        if not bool((weight > 0).any()):
            return forecast
        # the checks' skill is of the forecasts delivered: the blend, held out
        self.held_out_skill_ = dataclasses.replace(
            self.held_out_skill_, r2=selection.blended_r2(view.xi, fitted, physics, weight))
        if self.forward_skill_ is not None:
            self.forward_skill_ = dataclasses.replace(
                self.forward_skill_, r2=selection.blended_r2(
                    view.xi, fitted, physics, weight, forward))
        return selection.blend(forecast, self.reference_.local_model(forecast), weight)

    @staticmethod
    def _reference_frame(traj: Trajectory) -> str:
        """The body frame of the recording's velocities: ``traj.meta["frame"]`` where it
        says, else :func:`~torchconn.regression.reference.default_frame`."""
        return (traj.meta or {}).get("frame") or default_frame(traj.shape_dim + 1)

    def _fit_reference(self, traj: Trajectory, view: "selection.RegressionView"
                       ) -> PhysicsReference:
        """The physics reference fitted to ``view``, the samples of ``traj`` the regression
        fitted (pooled as the fit), in the recording's frame: of the family ``prior`` (the
        swimmer where it is None)."""
        return fit_reference(view.r, view.r_dot, view.xi, pool=self.pool,
                             family=self._family, frame=self._reference_frame(traj))

    @property
    def _family(self) -> str:
        return self.prior or "swimmer"

    def _reference(self) -> PhysicsReference:
        """``reference_``, fitted to the training recording's view on first use."""
        if getattr(self, "reference_", None) is None:
            self.reference_ = self._fit_reference(self.trajectory_, selection.regression_view(
                self.trajectory_, self.regression_, self.forecast_model_, pool=self.pool))
        return self.reference_

    def _fit_metric(self, traj: Trajectory, cycle: LimitCycle
                    ) -> tuple[MetricEstimator, FittedMetric] | None:
        """The metric stage and its fit to ``traj``, or None where no metric is fitted."""
        if not self.metric.wanted(traj.power):
            return None
        return self.metric, self.metric.fit(traj, cycle, pool=self.pool)

    def _folds(self) -> int:
        return self.held_out_folds or 3

    def _select(self, traj: Trajectory, cycle: LimitCycle, given: _Given | None = None
                ) -> tuple[Regression, "selection.ComplexityChoice", Regression | None]:
        """The given regression with the complexity chosen by held-out error
        (:func:`~torchconn.regression.selection.select_complexity`), its choice, and, where its
        ridges penalise ``Â`` (``ridge_connection``; whichever ridge wins, 0 included), the
        connection's regression: the complexity chosen the same way with ``Â`` unpenalised
        (the bins, order and ridge whose unshrunk connection predicts held-out cycles best,
        not those whose shrunk one did; where no such candidate scores, the forecasts'
        complexity), else None. One search serves both: the candidates they fit alike (ridge
        0) are fitted once (:func:`~torchconn.regression.selection.select_complexities`), and
        the ``given`` complexity's fit, where it is a candidate, is not fitted again."""
        regressions = (self.regression,)
        if getattr(self.regression, "ridge_connection", False):
            regressions += (self.regression.replace(ridge_connection=False),)
        fitted = () if given is None or given.connection is None else (
            (given.regression, given.connection),)
        (chosen, choice), *free = selection.select_complexities(
            traj, cycle, regressions, pool=self.pool, n_folds=self._folds(), fitted=fitted)
        if not free:
            return chosen, choice, None
        return chosen, choice, (chosen.replace(ridge_connection=False) if free[0] is None
                                else free[0][0])

    def _connection_alone(self, traj, cycle, regression, held, model
                          ) -> "selection.ConnectionAlone | None":
        """Where no model with ``b̂`` and ``∂Â/∂r`` can be scored held out, the connection
        alone scored instead (:func:`~torchconn.regression.selection.select_connection_alone`);
        None where it cannot be scored either, or where the check is off (``held`` None) and
        the given complexity's fit ``model`` stands."""
        if held is None and model is not None:
            return None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IllConditionedBinWarning)
            try:
                return selection.select_connection_alone(traj, cycle, regression, pool=self.pool,
                                                     n_folds=self._folds())
            except ValueError:
                return None

    def _held_out(self, traj, cycle, regression, model, choice=None, terms=False
                  ) -> tuple[selection.Skill | None, selection.Skill | None, Tensor]:
        """The held-out check's skill (downdated fits; the components ``choice`` gave to the
        phase average or the connection alone predicted so) and its forward one (the last
        block), or None, None when it is off; and ``(..., 3)`` True where the full model is
        the one to keep (``terms``: :func:`~torchconn.regression.selection.checked_terms`;
        else all True)."""
        every = torch.ones(3, dtype=torch.bool, device=model.device)
        if not self.held_out_folds or not selection.downdates(regression):
            return None, None, every
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IllConditionedBinWarning)
            if terms and choice is None:
                return selection.checked_terms(traj, cycle, regression, model, pool=self.pool,
                                           n_folds=self.held_out_folds)
            fallback, conn = _masks(choice, model.device)
            return (*selection.held_out_checks(
                traj, cycle, regression, pool=self.pool, n_folds=self.held_out_folds,
                model=model, phase_averaged=fallback, connection_only=conn), every)

    # ------------------------------------------------------------------ held-out skill
    def score(self, traj: Trajectory, phase: Tensor | None = None) -> selection.Skill:
        """Skill of ``forecast_model_`` on recordings ``traj`` the fit did not see, beside the
        phase-averaged velocity of the training data, the template ``ĉ(φ) = Â(γ)γ̇`` of the
        connection ``model_``, the physics reference fitted to the training data
        (``reference_``) and zero (:class:`~torchconn.regression.selection.Skill`; the
        forecasting model's own ``ĉ`` is the phase average where a component falls back to
        it).

        The target is the observed velocity the way the regression sees it. ``traj`` is
        phased with the fitted phaser (same origin) unless ``phase`` is given.
        """
        model = self._fitted()
        traj = self._prepare_new(traj, phase)
        view = selection.regression_view(traj, self.regression_, model, pool=self.pool)
        return selection.skill.skill(model, self.phase_average_, view, template=self.model_,
                                     reference=self._reference())

    def cross_validate(self, n_folds: int = 3, *, forward: bool = False) -> selection.Skill:
        """Held-out skill of ``forecast_model_``'s regression on the training recordings over
        ``n_folds`` blocks of whole cycles (:func:`~torchconn.regression.selection.cross_validate`),
        beside the physics reference fitted without each block and zero; ``forward``: the
        last block alone, fitted on the earlier ones. The regression's own forecasts are
        scored, without the physics prior (``held_out_skill_`` scores them with it)."""
        model = self._fitted()
        fallback, conn = _masks(self.complexity_, model.device)
        return selection.cross_validate(
            self.trajectory_, self.limit_cycle_, self.regression_, pool=self.pool,
            n_folds=n_folds, model=model, phase_averaged=fallback, connection_only=conn,
            connection_regressed=getattr(self.complexity_, "connection_regressed", False),
            forward=forward, reference=self._family,
            frame=self._reference_frame(self.trajectory_))

    def check_held_out(self, n_folds: int = 3) -> selection.Skill:
        """:meth:`cross_validate`, warning (:class:`~torchconn.regression.selection.
        PoorHeldOutSkillWarning`) where the model loses to the phase-averaged velocity."""
        result = self.cross_validate(n_folds)
        selection.warn_if_poor(result, stacklevel=3, choice=self.complexity_)
        self.held_out_skill_ = result
        return result

    def select_complexity(self, traj: Trajectory, phase: Tensor | None = None,
                          n_folds: int = 3) -> "ConnectionEstimator":
        """Choose the regression's bins, Fourier order and ridge by held-out error over
        ``n_folds`` blocks of whole cycles, then fit with them; returns self.

        The choice is in ``complexity_``
        (:class:`~torchconn.regression.selection.ComplexityChoice`) and in ``regression`` (which
        is set to the chosen stage, so that a refit keeps it).
        """
        if not isinstance(traj, Trajectory):
            raise TypeError(f"traj must be a torchconn.Trajectory, got {type(traj).__name__}")
        _checks.integer(n_folds, "n_folds", minimum=2, fn="select_complexity")
        complexity, folds = self.complexity, self.held_out_folds
        self.complexity = "cv"
        self.held_out_folds = n_folds if folds else 0
        try:
            self.fit(traj, phase)
        finally:
            self.complexity, self.held_out_folds = complexity, folds
        self.regression = self.regression_
        return self

    def prepare(self, traj: Trajectory, phase: Tensor | None = None) -> Trajectory:
        """:func:`prepare` with this estimator's smoother and phaser (smoothing, phase)."""
        traj = for_estimation(traj, "ConnectionEstimator.prepare", phase)
        return _prepare(traj, phase, self.smoother, self.phaser)[0]

    def predict(self, traj: Trajectory) -> Tensor:
        """Body velocity ``(..., T, 3)`` the forecasting model (``forecast_model_``) predicts
        for (prepared) recordings.

        A trajectory without smoothed state is smoothed with this estimator's smoother; one
        without phase and with the training data's batch shape (the same trials, recorded
        later) is phased by the *fitted* phaser (``phaser_.transform``: the training data's
        phase origin and corrections, not a fresh estimate); other batches are phased afresh.
        """
        model = self._fitted()
        traj = self._prepare_new(traj, None)
        return model.predict(traj.phase, traj.smoothed.r, traj.smoothed.r_dot)

    def _prepare_new(self, traj: Trajectory, phase: Tensor | None) -> Trajectory:
        """New recordings smoothed and phased with the fitted phase model when there is one."""
        traj = for_estimation(traj, "ConnectionEstimator", phase)
        fitted = getattr(self, "phaser_", None)
        # one fitted phase model per training trial: it applies to recordings of the same
        # batch shape (the same trials, later); other batches are phased afresh (Phaser's
        # section puts phase 0 at the same place on the cycle)
        same_batch = fitted is not None and tuple(fitted.phase_.shape[:-1]) == tuple(
            traj.batch_shape)
        if phase is None and traj.phase is None and same_batch:
            if traj.smoothed is None:
                traj = self.smoother.smooth(traj)
            phase = fitted.transform(traj.smoothed.r)
        return self.prepare(traj, phase)

    def _fitted(self) -> LocalConnectionModel:
        """The forecasting model (``forecast_model_``), or an error before :meth:`fit`."""
        if not hasattr(self, "forecast_model_") or not hasattr(self, "regression_"):
            raise RuntimeError("this ConnectionEstimator is not fitted yet: call fit(traj) first")
        return self.forecast_model_

    def __repr__(self) -> str:
        default = ConnectionEstimator()
        changed = [f"{k}={v!r}" for k, v in self.get_params(deep=False).items()
                   if v != getattr(default, k)]
        return "ConnectionEstimator(" + ", ".join(changed) + ")"


@dataclasses.dataclass
class _Given:
    """The given regression's fit and its held-out check, as the selection's candidates see
    them: ``model`` None where it could not be fitted (or with ``complexity="cv"``; with the
    metric attached, ``connection`` the regression's own fit without it); ``held`` the
    check's skill (None: off), ``full`` ``(..., 3)`` True where each component's full model is
    the one to keep; ``error`` the selection's error where no candidate scored."""

    regression: Regression
    model: LocalConnectionModel | None
    held: "selection.Skill | None" = None
    full: Tensor | None = None
    error: ValueError | None = None
    forward: "selection.Skill | None" = None
    connection: LocalConnectionModel | None = None


@dataclasses.dataclass(frozen=True)
class _Outcome:
    """A selection candidate's result: the regression fitted for the forecasts and its
    ``model``, the held-out skill, the complexity ``choice`` (None: as given), ``free`` the
    connection's regression where it differs (``Â`` unpenalised), ``delivered`` the
    connection where it is not the forecasts' fit, ``searched``: the search ran and no
    candidate could be scored, and ``forward``: the held-out skill on the last block."""

    regression: Regression
    model: LocalConnectionModel
    held: "selection.Skill | None" = None
    choice: "selection.ComplexityChoice | None" = None
    free: Regression | None = None
    delivered: LocalConnectionModel | None = None
    searched: bool = False
    forward: "selection.Skill | None" = None


def _with_metric(model: LocalConnectionModel | None,
                 metric: tuple[MetricEstimator, FittedMetric] | None
                 ) -> LocalConnectionModel | None:
    """``model`` with the recording's one ``metric`` fit (stage, fit) attached (None: no
    metric, or no model)."""
    if model is None or metric is None:
        return model
    return metric[0].attach(model, metric[1])


def _fit(regression: Regression, traj: Trajectory, cycle: LimitCycle, pool: bool,
         metric: tuple[MetricEstimator, FittedMetric] | None) -> LocalConnectionModel:
    """``regression.fit`` with the recording's one ``metric`` fit attached."""
    return _with_metric(regression.fit(traj, cycle, pool=pool), metric)


def _refit(chosen: Regression, given: Regression, model: LocalConnectionModel | None,
           traj: Trajectory, cycle: LimitCycle, pool: bool,
           metric: tuple[MetricEstimator, FittedMetric] | None) -> LocalConnectionModel:
    """The fit of the regression ``chosen`` by held-out error, after ``given`` fitted
    ``model`` (None where it could not) to the same data with ``metric``: ``model`` itself
    where the choice is the given complexity, else a new fit that takes the metric's
    coefficients from the metric where its settings are unchanged: the same results as fitting
    ``chosen`` afresh, without fitting anything twice."""
    if model is not None and chosen == given:
        return model
    return _fit(chosen, traj, cycle, pool, metric)


def _connection_delivered(alone: "selection.ConnectionAlone", given: LocalConnectionModel | None,
                          regression: Regression, traj: Trajectory, cycle: LimitCycle,
                          pool: bool, metric: tuple[MetricEstimator, FittedMetric] | None
                          ) -> LocalConnectionModel:
    """The connection delivered where the connection alone was checked (``alone``, chosen
    after the given ``regression`` fitted ``given``, or could not: None): ``alone.model``,
    with the metric where ``given`` has one, or where it could not be fitted and
    ``regression`` asks for the metric of a recording with a power channel (a fit at the
    chosen bins, the metric's coefficients from ``metric``).

    Raises:
        ValueError: the metric asked for cannot be fitted at the chosen bins either.
    """
    if metric is None:
        return alone.model
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        fitted = _fit(alone.regression.replace(on_ill_conditioned="warn"), traj, cycle, pool,
                      metric)
    return selection.connection_alone_model(fitted, alone.coef, alone.regression.fourier_order)


def _forecast_meta(choice: "selection.ComplexityChoice | None", regression: Regression,
                   prior_weight: Tensor | None = None) -> dict:
    """How the forecasting model (the fit of ``regression``, with ``choice``'s components
    zeroed, shrunk towards the physics reference by ``prior_weight``) differs from the
    connection model (``meta["forecast_model"]`` of ``model_``; JSON-ready): its bins and
    Fourier order, the ridge it puts on ``Â`` (0: none), the components it predicts by the
    phase average or by the connection alone (nested lists of bools shaped like the model's
    batch dims x 3, or None) and the prior's weight per component (or None)."""
    def listed(mask, names):
        return None if choice is None or not names else selection.nested_list(mask)

    penalised = getattr(regression, "ridge_connection", False)
    shrunk = prior_weight is not None and bool((prior_weight > 0).any())
    return {"n_bins": regression.n_bins, "fourier_order": regression.fourier_order,
            "A_ridge": float(regression.ridge) if penalised else 0.0,
            "phase_averaged": listed(choice and choice.phase_averaged,
                                     choice and choice.phase_averaged_names()),
            "connection_only": listed(choice and choice.connection_only,
                                      choice and choice.connection_only_names()),
            "prior_weight": prior_weight.tolist() if shrunk else None}


def _with_settings(model: LocalConnectionModel, settings: dict, **meta: Any
                   ) -> LocalConnectionModel:
    """``model`` with the estimator's settings (and ``meta``) added to its ``meta``."""
    return dataclasses.replace(model, meta={**(model.meta or {}), "settings": settings, **meta})


def _masks(choice: "selection.ComplexityChoice | None", device) -> tuple[Tensor | None,
                                                                   Tensor | None]:
    """The components ``choice`` predicts by the phase average and by the connection alone,
    ``(..., 3)`` bool each (None, None without a choice)."""
    if choice is None:
        return None, None
    return choice.phase_average_mask(device), choice.connection_only_mask(device)


def _check_arguments(*, pool: Any, complexity: Any, held_out_folds: Any, prior: Any,
                     **stages: Any) -> None:
    """The constructor's arguments: each stage an instance of its kind's base, pool a bool,
    complexity one of :data:`COMPLEXITY`, held_out_folds 0 or an integer >= 2, prior None or
    a name in :data:`~torchconn.regression.reference.FAMILIES`."""
    for name, (base, methods) in STAGES.items():
        value = stages[name]
        if not isinstance(value, base):
            raise TypeError(
                f"ConnectionEstimator: {name} must be a {base.__name__} (e.g. "
                f"{next(iter(methods.values())).__name__}()), got {type(value).__name__}"
            )
    if not isinstance(pool, bool):
        raise ValueError(f"ConnectionEstimator: pool must be true or false, got {pool!r}")
    if complexity not in COMPLEXITY:
        raise ValueError(f"ConnectionEstimator: complexity must be one of {COMPLEXITY}, got "
                         f"{complexity!r}")
    if (isinstance(held_out_folds, bool) or not isinstance(held_out_folds, int)
            or held_out_folds < 0 or held_out_folds == 1):
        raise ValueError("ConnectionEstimator: held_out_folds must be 0 (no held-out check) or "
                         f"an integer >= 2, got {held_out_folds!r}")
    if prior is not None and prior not in FAMILIES:
        raise ValueError(f"ConnectionEstimator: prior must be None (no physics prior) or a "
                         f"registered reference family ({', '.join(FAMILIES)}), got {prior!r}")


@contextlib.contextmanager
def _cycles_in_errors(traj: Trajectory, regression: Regression, complexity: str):
    """Add to a "bins cannot be fitted" error how many cycles the recording has and how many
    the regression's complexity asks for."""
    try:
        yield
    except ValueError as err:
        text = str(err)
        if "cannot be fitted" not in text and "no candidate could be fitted" not in text:
            raise
        advice = ("; complexity='auto' or 'cv' (torchconn-fit --complexity) chooses fewer "
                  "coefficients" if complexity == "fixed" else "")
        note = cycles_note(traj, regression, alone=complexity == "auto")
        raise ValueError(f"{text} [{note}{advice}]") from None


# ---------------------------------------------------------------------- settings tables
def estimator_from_settings(settings: Mapping[str, Any] | None = None, *,
                            where: str = "estimator") -> ConnectionEstimator:
    """Build an estimator from a nested mapping, e.g. the sweep's TOML ``[estimator]`` table.

    Keys: ``pool``, ``complexity``, ``held_out_folds``, ``prior`` (a reference family's name,
    or false or None for none), and one sub-table per stage (``smoother``, ``phaser``, ``cycle``,
    ``regression``) holding that stage's fields and optionally ``method`` (a name in
    :data:`STAGES`, default its first). Example::

        [estimator]
        pool = false
        [estimator.phaser]
        order = 4
        [estimator.regression]
        n_bins = 32
        fourier_order = 10

    Raises:
        ValueError: an unknown key (the valid ones are listed, with the closest match), a
            value of the wrong type or out of range (the key is named), an unknown method.
    """
    settings = dict(settings or {})
    if not isinstance(settings, Mapping):
        raise ValueError(f"{where} must be a table (mapping), got {type(settings).__name__}")
    unknown = set(settings) - {*STAGES, *OPTIONS}
    if unknown:
        raise ValueError(unknown_keys_message(where, unknown, [*STAGES, *OPTIONS]))
    stages = {}
    for name, (_, methods) in STAGES.items():
        table = settings.get(name, {})
        if not isinstance(table, Mapping):
            raise ValueError(f"{where}.{name} must be a table of {name} options, got {table!r}")
        table = dict(table)
        method = table.pop("method", next(iter(methods)))
        if method not in methods:
            raise ValueError(unknown_keys_message(f"{where}.{name}.method", {method}, methods))
        cls = methods[method]
        valid = [f.name for f in dataclasses.fields(cls)]
        bad = set(table) - set(valid)
        if bad:
            raise ValueError(unknown_keys_message(f"{where}.{name} ({cls.__name__})", bad,
                                              [*valid, "method"]))
        try:
            stages[name] = cls(**table)
        except ValueError as err:
            raise ValueError(f"{where}.{name}: {err}") from None
    pool = settings.get("pool", False)
    if not isinstance(pool, bool):
        raise ValueError(f"{where}.pool must be true or false, got {pool!r}")
    options = {k: settings[k] for k in ("complexity", "held_out_folds", "prior")
               if k in settings}
    if options.get("prior", None) is False:  # TOML has no None
        options["prior"] = None
    try:
        return ConnectionEstimator(**stages, pool=pool, **options)
    except ValueError as err:
        raise ValueError(f"{where}: {str(err).removeprefix('ConnectionEstimator: ')}") from None


def estimator_settings(estimator: ConnectionEstimator,
                       regression: Regression | None = None) -> dict[str, Any]:
    """The nested settings table of ``estimator`` (the inverse of
    :func:`estimator_from_settings`; JSON-ready except that None stays None); ``regression``
    replaces the estimator's regression stage (e.g. the fitted ``regression_``)."""
    out: dict[str, Any] = {}
    for name, (_, methods) in STAGES.items():
        stage = getattr(estimator, name) if name != "regression" or regression is None \
            else regression
        method = next((m for m, cls in methods.items() if type(stage) is cls),
                      f"{type(stage).__module__}.{type(stage).__qualname__}")
        out[name] = {"method": method, **stage.get_params()}
    for key in OPTIONS:
        out[key] = getattr(estimator, key)
    return out


# ---------------------------------------------------------------------- the steps as functions
def prepare(
    traj: Trajectory,
    *,
    phase: Tensor | None = None,
    smoother: Smoother = RTSSmoother(),
    phaser: PhaseEstimator = Phaser(),
) -> Trajectory:
    """Add smoothed state and phase to a trajectory (steps that do not depend on the model).

    Args:
        traj: recordings ``(..., T, ·)``; NaN drop-outs allowed; shorter trials padded with NaN.
        phase: ``(..., T)`` phase to use instead of estimating one (a robot's gait clock, or the
            true phase of a simulation). An existing ``traj.phase`` is used likewise, and an
            existing ``traj.smoothed`` is kept.
        smoother, phaser: the stages (see :class:`ConnectionEstimator`).

    Returns:
        the trajectory with ``smoothed`` and ``phase`` set.
    """
    return _prepare(traj, phase, smoother, phaser)[0]


def _prepare(traj, phase, smoother, phaser) -> tuple[Trajectory, PhaseEstimator | None]:
    if traj.smoothed is None:
        traj = smoother.smooth(traj)
    if phase is not None:
        return traj.with_fields(phase=phase), None
    if traj.phase is not None:
        return traj, None
    try:
        fitted = phaser.fit(traj.smoothed.r)
    except ValueError as err:
        gap = _gap_note(traj) if "covers only about" in str(err) else ""
        if not gap:
            raise
        raise ValueError(f"{err}; {gap}") from None
    return traj.with_fields(phase=fitted.phase_), fitted


def _gap_note(traj: Trajectory) -> str:
    """Where the phase could not be followed: the longest gap of a trial of ``traj`` (missing
    samples the smoother bridged without data) if it spans more than
    :data:`~torchconn.io.preflight.MAX_GAP_CYCLES`, and what to do; else "". A bridged gap
    carries no oscillation, so the phase stalls across it (a tracked zebrafish, 60 "RPM",
    94 of 203 samples missing in one run of 9.7 cycles: "covers only about 1.0 cycles", where
    the 11.3 cycles before the gap fit)."""
    found = preflight(traj)
    k = max(range(len(found.longest_gap)), key=found.longest_gap.__getitem__)
    if found.longest_gap[k] <= MAX_GAP_CYCLES:
        return ""
    return (f"here trial {k} has a gap of {found.longest_gap[k]:.1f} cycles with no samples, "
            "which the smoother bridges without the gait's oscillation, so the phase cannot be "
            "followed across it: split the recording at its gaps and fit the parts as trials "
            "(torchconn-convert --max-gap, or Trajectory.slice_time)")


def fit_local_model(traj: Trajectory, cycle: LimitCycle,
                    regression: Regression = NoiseAwareRegression(), *,
                    pool: bool = False) -> LocalConnectionModel:
    """The regressions in every phase bin and their Fourier series in phase:
    ``regression.fit(traj, cycle, pool=pool)``.

    Args:
        traj: a prepared trajectory (``smoothed`` and ``phase`` set), batch dims ``...``.
        cycle: its limit cycle (batch dims ``...``, or none when ``pool``).
        regression: the regression stage.

    Returns:
        a :class:`LocalConnectionModel` with batch dims ``...`` (none when pooled).
    """
    return regression.fit(traj, cycle, pool=pool)


def _unshrunk(regression: Regression, free: Regression | None) -> Regression | None:
    """The regression of the connection ``model_`` where it is not the forecasts'
    ``regression``: ``free`` (:meth:`ConnectionEstimator._select`'s, ``Â`` unpenalised);
    None where that is ``regression``'s own fit (nothing chosen, ``Â`` never penalised, or
    the same complexity without a ridge)."""
    if free is None or (free.ridge == 0 and free.replace(ridge_connection=True) == regression):
        return None
    return free
