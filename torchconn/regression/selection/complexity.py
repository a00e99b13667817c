"""Model complexity chosen by held-out skill: the candidate ladder and the connection alone.

:func:`select_complexity` scores every ``(n_bins, fourier_order, ridge)`` of
:data:`COMPLEXITY_GRID` x :data:`RIDGE_GRID` on held-out blocks of whole cycles
(:mod:`~torchconn.regression.selection.skill`) and, per component ``(v_x, v_y, ω)`` and
batch element, whether the full model, the connection alone ``ĉ + Âδ̇`` or the
phase-averaged velocity predicts it (:class:`ComplexityChoice`). Where no model with ``b̂``
and ``∂Â/∂r`` can be scored, :func:`select_connection_alone` regresses the connection alone
(:class:`ConnectionAlone`).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ...cycles import FALLBACK_CYCLES, cycle_blocks, cycle_index, few_cycles
from ...phase.limit_cycle import LimitCycle
from ...trajectory import Trajectory, pool_batch
from .._wls import IllConditionedBinWarning
from ..base import Regression
from ..connection import split_coefficients
from ..model import LocalConnectionModel
from .skill import (
    COMPONENTS,
    PoorHeldOutSkillWarning,
    Skill,
    blended_held_out,
    connection_columns,
    downdates,
    fold_models,
    held_out_coefficients,
    regression_view,
    score_folds,
    variant_scores,
    with_coefficients,
)

__all__ = ["ComplexityChoice", "ConnectionAlone", "COMPLEXITY_GRID", "RIDGE_GRID",
           "RIDGE_MIN_GAIN", "FALLBACK_Z", "FALLBACK_MARGIN", "FALLBACK_CYCLES",
           "OFFSET_TERMS_Z", "select_complexity", "select_complexities",
           "select_connection_alone", "connection_alone_model", "checked_terms",
           "unchecked_choice", "warn_if_poor", "nested_list"]

#: (n_bins, fourier_order) candidates of :func:`select_complexity`, simplest first
COMPLEXITY_GRID = ((12, 3), (24, 6), (48, 12))
#: ridge candidates of :func:`select_complexity`, relative to the standardised normal matrix
#: and applied as the regression applies its own ridge (``ridge_connection=False``: ``Â``'s
#: columns are not penalised)
RIDGE_GRID = (0.0, 0.1, 1.0, 10.0)
#: a ridge is chosen only when it lowers the best unpenalised candidate's mean held-out loss
#: by more than this fraction of it (a ridge shrinks ``Â``, the attenuation the noise-aware
#: regression removes)
RIDGE_MIN_GAIN = 0.01
#: per component, three models compete on held-out cycles (:func:`select_complexity`): the
#: full model, the connection alone (``ĉ + Âδ̇``: the rows of ``b̂`` and ``∂Â/∂r`` set to 0),
#: and the phase-averaged velocity. A model counts only when it lowers the component's
#: held-out squared error below the phase average's by more than ``FALLBACK_Z`` standard
#: errors (of the sum over held-out cycles of the per-cycle differences) and by more than the
#: fraction ``FALLBACK_MARGIN`` of the phase average's; when neither does, the component is
#: predicted by the phase-averaged velocity alone (:func:`_choose_terms`)
FALLBACK_Z = 2.5
FALLBACK_MARGIN = 0.1
#: the rows of ``b̂`` and ``∂Â/∂r`` are kept only when the full model's held-out squared error
#: is below the connection alone's by more than this many standard errors
OFFSET_TERMS_Z = 3.0


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
    :func:`few_cycles`) is predicted by the phase average, the simpler model presumed there.
    None where no such element (longer recordings keep the fit; the check warns)."""
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


def warn_if_poor(held: Skill, stacklevel: int = 3, choice: ComplexityChoice | None = None,
                 searched: bool = False) -> None:
    """Warn (:class:`PoorHeldOutSkillWarning`) where the held-out skill ``held`` is
    :attr:`~Skill.worse_than_phase_average` or :attr:`~Skill.unscored`, and where
    :attr:`~Skill.without_skill`; ``choice``: the complexity chosen by
    held-out error, if any (the advice then is more cycles, not fewer bins); ``searched``:
    the search by held-out error ran and no candidate could be scored (the advice then is
    more data too)."""
    _warn_against_baseline(held, stacklevel + 1, choice, searched)
    if bool(held.without_skill.any()):
        warnings.warn(
            "neither the model nor the phase-averaged velocity predicts held-out cycles "
            f"better than their mean velocity for {held.without_skill_names()}: these "
            "components are not predictable from the gait's phase and shape on this "
            "recording (noise, or a motion the shape changes do not drive: a flow, a "
            "tether, contact), and their rows of the model are not to be relied on",
            PoorHeldOutSkillWarning, stacklevel=stacklevel)

def _warn_against_baseline(held: Skill, stacklevel: int, choice: ComplexityChoice | None,
                           searched: bool) -> None:
    """:func:`warn_if_poor`'s warnings against the phase-averaged baseline."""
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
    if bool(held.unscored.any()) and choice is not None and not choice.checked:
        warnings.warn(
            "held-out check: some phase bins cannot be fitted when one block of whole "
            "cycles is left out, at this or any simpler complexity, so the model cannot "
            f"be checked on this short recording; {', '.join(choice.phase_averaged_names())}"
            " are predicted by the phase-averaged velocity of the training data (predict() "
            "and forecast_model_: rows of b̂, Â and ∂Â/∂r 0 in the unchecked trials; "
            "model_ keeps the given complexity's estimates, unchecked); record more cycles",
            PoorHeldOutSkillWarning, stacklevel=stacklevel)
        return
    if bool(held.unscored.any()):
        warnings.warn(
            "held-out check: some phase bins cannot be fitted when one block of whole "
            "cycles is left out, so the model has too many coefficients for this "
            f"recording; {fix}", PoorHeldOutSkillWarning, stacklevel=stacklevel)
        return
    worse = held.worse_than_phase_average.reshape(-1, 3).any(0)
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
        f"{held.shortfalls()}: its shape terms do not help predict these "
        f"components on this recording (too few cycles for its coefficients, or joint-"
        f"angle noise that swamps the shape deviations); {fix}", PoorHeldOutSkillWarning,
        stacklevel=stacklevel)


def checked_terms(traj: Trajectory, cycle: LimitCycle, regression: Regression,
                  model: LocalConnectionModel, *, pool: bool, n_folds: int = 3
                  ) -> tuple[Skill, Skill, Tensor]:
    """The held-out check of a fit at a given complexity, from one set of fold fits:
    :func:`cross_validate`'s skill, its forward one (the last block, ``forward=True``), and
    ``(..., 3)`` True where :func:`_choose_terms` keeps the full model (False: the phase
    average or the connection alone predicts that component better held out, and
    :func:`select_complexity` should choose)."""
    reg, models, view, fold, cycles = fold_models(traj, cycle, regression, model, pool=pool,
                                                   n_folds=n_folds, refit=False)
    (held, gaps), (_, gaps_conn) = variant_scores(models, view, fold, reg, traj.dt, pool,
                                                   cycles, noise_corrected=False)
    forward = score_folds(models, view, fold, reg, traj.dt, pool, False,
                          folds=(n_folds - 1,))[0]
    fallback, conn = _choose_terms(gaps, gaps_conn, few_cycles(traj.phase, pool))
    return held, forward, ~(fallback | conn)


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
        forward: the same on the last block alone, fitted on the earlier ones.
    """

    regression: Regression
    choice: ComplexityChoice
    model: LocalConnectionModel
    coef: Tensor
    held_out: Skill
    forward: Skill | None = None


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
        _, models, view, flat_fold, cycles = fold_models(
            traj, cycle, base, model, pool=pool, n_folds=n_folds, refit=False,
            connection_regressed=True)
        scored, gaps = score_folds(models, view, flat_fold, base, traj.dt, pool, True,
                                    cycle=cycles)
        if bool(scored.unscored.any()):
            failures.append(f"{n_bins} bins: some bins cannot be fitted without one of the "
                            f"{n_folds} blocks of cycles")
            continue
        # the simpler model presumed, as on short recordings: the connection alone only
        # where it beats the phase average clearly
        fallback = ~_clearly_better(gaps)
        loss = float(torch.where(fallback, 1 - scored.r2_phase_average, 1 - scored.r2).mean())
        scores.append((n_bins, order, 0.0, loss))
        if best is None or loss < best[0]:
            best = (loss, base, model, models, view, flat_fold, fallback)
    if best is None:
        raise ValueError("select_connection_alone: no candidate could be fitted on "
                         f"{n_folds - 1} of {n_folds} blocks of cycles ({failures[0]})")
    loss, base, model, models, view, flat_fold, fallback = best
    held, forward = (score_folds(models, view, flat_fold, base, traj.dt, pool, False,
                                 phase_averaged=fallback, folds=folds)[0]
                     for folds in (None, (n_folds - 1,)))
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
                           held, forward)


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
                        fallback_ok: bool = True, ridges: tuple[float, ...] = RIDGE_GRID,
                        fitted: Sequence[tuple[Regression, LocalConnectionModel]] = ()
                        ) -> list[tuple[Regression, ComplexityChoice] | None]:
    """:func:`select_complexity` of each of ``regressions``, which differ at most in
    ``ridge_connection`` (e.g. ``Â`` penalised and not), in one search: a candidate the
    settings fit alike (every one of ridge 0, which penalises nothing) is fitted and scored
    once, and every ``(n_bins, fourier_order)`` fits its whole-recording model once. Each
    choice is the one :func:`select_complexity` makes for its regression alone.

    ``fitted``: pairs of a regression and its fit to this recording (pooled alike) that the
    caller already has, e.g. the given complexity's; a candidate whose whole-recording fit
    one of them is takes it instead of fitting it again (:func:`_whole_fit`).

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
                                                 n_folds, penalties, fitted).items():
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
    return lower_by(diff, FALLBACK_Z) & (diff.sum(-2) < -FALLBACK_MARGIN * base.sum(-2))


def lower_by(diff: Tensor, z: float) -> Tensor:
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
    connection alone). ``gaps``, ``gaps_conn`` ``(..., C, 3, 2)``: :func:`score_folds`'s
    per-cycle gaps of the full model and of the connection alone; ``short`` ``(...)``: the
    recording spans at most :data:`FALLBACK_CYCLES` cycles (:func:`few_cycles`).

    On short recordings the simpler model is presumed: the full
    model is kept when it beats the phase average (:func:`_clearly_better`) and either the
    connection alone does not or the full model beats it by :data:`OFFSET_TERMS_Z` standard
    errors; else the connection alone when it beats the phase average; else the phase
    average: few cycles do not span the shape offsets of later ones, so ``b̂δ`` and
    ``∂Â/∂r δ̇⊗δ`` extrapolate there.

    On longer ones the full model is presumed: the phase average is taken only
    when it beats both models by :data:`FALLBACK_Z` standard errors, the connection alone
    only when it beats the full model by :data:`OFFSET_TERMS_Z`."""
    diff, diff_conn = gaps[..., 0], gaps_conn[..., 0]
    full, conn = _clearly_better(gaps), _clearly_better(gaps_conn)
    keep = full & (lower_by(diff - diff_conn, OFFSET_TERMS_Z) | ~conn)
    short = torch.as_tensor(short, device=diff.device).unsqueeze(-1)
    fallback = torch.where(short, ~keep & ~conn,
                           lower_by(-diff, FALLBACK_Z) & lower_by(-diff_conn, FALLBACK_Z))
    conn_only = torch.where(short, ~keep & conn,
                            ~fallback & lower_by(diff_conn - diff, OFFSET_TERMS_Z))
    return fallback, conn_only


def nested_list(mask: tuple) -> list:
    """A nested tuple of bools (:attr:`ComplexityChoice.phase_averaged`, ...) as nested lists
    (JSON)."""
    return [nested_list(v) for v in mask] if isinstance(mask, tuple) else mask


def _nested_tuple(mask: Tensor) -> tuple:
    def tup(x):
        return tuple(tup(v) for v in x) if isinstance(x, list) else bool(x)
    return tup(mask.tolist())


def _candidate_skills(traj, cycle, regression, n_bins, order, pool, n_folds, penalties,
                      fitted=()) -> dict:
    """Per candidate ``(ridge, ridge_connection)`` of ``penalties`` at ``(n_bins, order)``:
    ``((Skill, gaps), (Skill, gaps))`` of the model as fitted and of the connection alone
    (:func:`variant_scores`), the noise-corrected skill and per held-out cycle the observed
    SSE minus the phase average's; or, for a candidate that cannot be fitted, the failure (a
    string). One whole-recording fit serves every candidate (one of ``fitted`` where it is
    that fit, :func:`_whole_fit`), and one pass over the data every ridge of a setting."""
    base = regression.replace(n_bins=n_bins, fourier_order=order, ridge=0.0)

    def penalised(setting):
        return base if setting is None else base.replace(ridge_connection=setting)

    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IllConditionedBinWarning)
        if not downdates(base):
            for ridge, setting in penalties:
                try:
                    reg, models, view, fold, cycles = fold_models(
                        traj, cycle, penalised(setting).replace(ridge=ridge), None, pool=pool,
                        n_folds=n_folds, refit=True)
                    out[ridge, setting] = variant_scores(models, view, fold, reg, traj.dt,
                                                         pool, cycles)
                except ValueError as err:
                    out[ridge, setting] = f"{n_bins} bins, ridge {ridge:g}: {err}"
            return out
        try:
            # the whole recording's window, interval and noise level (bins that need a
            # ridge are NaN here and do not matter: only the fits without each block count)
            model = _whole_fit(base.replace(on_ill_conditioned="warn"), traj, cycle, pool,
                               fitted)
        except ValueError as err:
            return dict.fromkeys(penalties, f"{n_bins} bins: {err}")
    unflat = regression_view(traj, base, model, pool=pool, flatten=False)
    view = regression_view(traj, base, model, pool=pool)
    fold = cycle_blocks(unflat.phase, n_folds)
    flat_fold = pool_batch(fold, 0) if pool else fold
    cycles = cycle_index(unflat.phase, pool)
    for setting in dict.fromkeys(setting for _, setting in penalties):
        ridges = tuple(ridge for ridge, s in penalties if s == setting)
        reg = penalised(setting)
        coef = held_out_coefficients(traj, reg, model, unflat, fold, n_folds, pool=pool,
                                     ridges=ridges)
        coef = blended_held_out(traj, reg, model, coef, n_folds, pool=pool, ridges=ridges)
        for k, ridge in enumerate(ridges):
            models = [with_coefficients(model, coef[k, f], order) for f in range(n_folds)]
            full, conn = variant_scores(models, view, flat_fold, base, traj.dt, pool, cycles)
            if bool(full[0].unscored.any()):
                out[ridge, setting] = (f"{n_bins} bins, ridge {ridge:g}: some bins cannot be "
                                       f"fitted without one of the {n_folds} blocks of cycles")
            else:
                out[ridge, setting] = full, conn
    return out


def _whole_fit(regression: Regression, traj: Trajectory, cycle: LimitCycle, pool: bool,
               fitted: Sequence[tuple[Regression, LocalConnectionModel]]
               ) -> LocalConnectionModel:
    """``regression.fit`` (its ``on_ill_conditioned`` is ``"warn"``), or the model in
    ``fitted`` (pairs of a regression and its fit to the same recording) of a regression that
    differs from it at most in ``on_ill_conditioned = "raise"``: with no bin ill-conditioned
    the two settings fit alike, bit for bit, and a fit that raised nothing had none."""
    for other, model in fitted:
        if getattr(other, "on_ill_conditioned", None) in ("raise", "warn") and other.replace(
                on_ill_conditioned=regression.on_ill_conditioned) == regression:
            return model
    return regression.fit(traj, cycle, pool=pool)
