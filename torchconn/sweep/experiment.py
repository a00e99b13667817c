"""Run a sweep's experiments cell by cell: one noise level × a block of trials, batched.

simulate → observe → prepare (smooth, phase) → fit → reference models → tidy rows. A cell is
pure (inputs: the config and the cell; output: tables of rows) and every trial has its own
seed, so the serial runner and Dask workers produce identical rows for any block size.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from .._provenance import spawn_seeds
from ..evaluation.models import (
    COMPONENTS,
    MODELS,
    clean_trajectory,
    error_summary,
    observed_view,
    phase_bin_errors,
    reference_models,
    simulator_on_cycle,
)
from ..physics.gaits import reference_gait
from ..physics.systems import NLinkSwimmer
from ..regression.noise_aware import predictions_only
from ..simulation.observe import observe
from ..simulation.rollout import simulate
from .config import Experiment, SweepConfig

__all__ = [
    "ExperimentResult", "Cell", "experiment_cells", "run_cell", "run_experiment",
    "experiment_seeds", "make_system", "trace_level",
]

RESULT_COLUMNS = ("experiment", "system", "noise_kind", "level", "trial", "model", "component",
                  "metric", "value")
PHASE_COLUMNS = ("experiment", "system", "noise_kind", "level", "trial", "model", "component",
                 "phase", "mean", "rms", "se")
TRACE_COLUMNS = ("experiment", "system", "level", "trial", "t", "model", "component", "value")

#: cycles whose body-velocity traces are kept for the Fig. 3B panel (the paper's 13-18)
TRACE_CYCLES = (13, 18)


@dataclass
class ExperimentResult:
    """Tidy rows of one experiment (or one cell of it), and how long each stage took."""

    results: list[tuple] = field(default_factory=list)
    phase_errors: list[tuple] = field(default_factory=list)
    traces: list[tuple] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)

    def extend(self, other: "ExperimentResult") -> None:
        """Append another cell's rows and add its stage timings."""
        self.results += other.results
        self.phase_errors += other.phase_errors
        self.traces += other.traces
        for stage, seconds in other.timings.items():
            self.timings[stage] = self.timings.get(stage, 0.0) + seconds


@dataclass(frozen=True, kw_only=True)
class Cell:
    """The unit of storage and distribution: one noise level of one experiment, trials
    ``[start, stop)``. Its rows do not depend on how the other trials are blocked."""

    experiment: Experiment
    level: int
    start: int
    stop: int

    @property
    def name(self) -> str:
        return f"{self.experiment.name}-L{self.level}-t{self.start}-{self.stop}"


def experiment_cells(experiment: Experiment, block_trials: int) -> list[Cell]:
    """An experiment's cells, level-major, ``block_trials`` trials each (the last may be
    smaller). Concatenating their rows in this order gives the experiment's table."""
    if block_trials < 1:
        raise ValueError(f"block_trials must be >= 1, got {block_trials}")
    return [Cell(experiment=experiment, level=i, start=s,
                 stop=min(s + block_trials, experiment.trials))
            for i in range(len(experiment.levels))
            for s in range(0, experiment.trials, block_trials)]


def make_system(name: str) -> NLinkSwimmer:
    return NLinkSwimmer({"3link": 3, "9link": 9}[name])


def experiment_seeds(config: SweepConfig, experiment: Experiment) -> np.ndarray:
    """Seeds ``(levels, trials)``: cell (i, j) of experiment e gets
    ``SeedSequence(root, spawn_key=(e, i, j))`` (:func:`torchconn._provenance.spawn_seeds`).

    Keyed by position, so a trial's seed does not depend on which other trials run, in which
    order, in which cell, or on which backend.
    """
    e = [x.name for x in config.experiments].index(experiment.name)
    return spawn_seeds(config.seed, (len(experiment.levels), experiment.trials), key=(e,))


def run_experiment(config: SweepConfig, experiment: Experiment,
                   block_trials: int | None = None, *,
                   device: torch.device | str | None = None) -> ExperimentResult:
    """All levels × trials of one experiment, cell by cell; returns its tidy rows.

    ``block_trials`` (default: all trials of a level in one cell) does not change the rows;
    ``device`` (default: the config's) is passed to :func:`run_cell`.
    """
    out = ExperimentResult()
    for cell in experiment_cells(experiment, block_trials or experiment.trials):
        out.extend(run_cell(config, cell, device=device))
    return out


def run_cell(config: SweepConfig, cell: Cell, *,
             device: torch.device | str | None = None) -> ExperimentResult:
    """One cell's trials at one noise level, batched; returns its tidy rows.

    Rows are ordered by trial, then model, component and metric (phase bin), so the rows of
    an experiment are its cells' rows in :func:`experiment_cells` order for any block size.
    The cell is simulated and fitted on ``device`` (default: the config's ``device``); CPU and
    CUDA draw different random numbers from the same seeds, so their rows are different samples
    of the same experiment. The rows are Python numbers (CPU copies).
    """
    experiment = cell.experiment
    out = ExperimentResult()
    device = torch.device(config.device if device is None else device)

    def clock() -> float:  # stage timings: wait for the device's queued work first
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return time.perf_counter()

    sim = experiment.simulation
    system = make_system(experiment.system)
    gait = reference_gait(experiment.system)
    level = torch.tensor([experiment.levels[cell.level]], dtype=torch.float64,
                         device=device)[:, None]  # (1, 1)
    seeds = experiment_seeds(config, experiment)[cell.level:cell.level + 1, cell.start:cell.stop]
    if experiment.noise_kind == "system":
        eta, omega = sim.eta * level, experiment.omega
    else:
        eta, omega = sim.eta * experiment.eta_factor, level

    t0 = clock()
    traj = simulate(system, gait, eta=eta, alpha=sim.alpha, n_cycles=sim.n_cycles,
                    samples_per_cycle=sim.samples_per_cycle, substeps=sim.substeps, seeds=seeds,
                    power=False)  # the metric is not fitted (below)
    out.timings["rollout"] = clock() - t0
    t0 = clock()
    noisy = experiment.noise_kind == "observation" or experiment.omega > 0
    if noisy:
        traj = observe(traj, omega, seeds=seeds)
    out.timings["observe"] = clock() - t0

    # the sweep scores body-velocity models only, so the metric is not fitted (at low noise its
    # quadratic regressors can be too thin to fit, which should not stop a connection study);
    # it scores every trial against the truth, so the held-out check is off, and the paper's
    # fixed complexity is kept unless the config asks for "cv" (the check costs about 0.6x a
    # 9-link trial's fit)
    estimator = config.make_estimator()
    estimator.set_params(metric__enabled=False, held_out_folds=0,
                         complexity="cv" if estimator.complexity == "cv" else "fixed")
    phase = traj.truth.phase if config.phase == "true" else None
    t0 = clock()
    prepared = estimator.prepare(traj, phase=phase)
    out.timings["smoothing_phase"] = clock() - t0
    t0 = clock()
    with predictions_only():  # the tables score predictions only
        estimator.fit(prepared)
    out.timings["regression"] = clock() - t0

    t0 = clock()
    clean = clean_trajectory(traj) if noisy else None
    on_cycle = simulator_on_cycle(system, estimator.model_)  # shared by both sets of samples
    preds = reference_models(system, estimator.model_, estimator.trajectory_, clean,
                             on_cycle=on_cycle)
    # against the observations the way the regression saw them (raw interval differences for
    # the noise-aware regression), every model on the same samples
    observed = observed_view(system, estimator.trajectory_, estimator.regression,
                             estimator.model_, clean, on_cycle=on_cycle)
    _collect(out, config, cell, preds, observed, estimator.trajectory_)
    out.timings["evaluation"] = clock() - t0
    return out


def _collect(out, config, cell, preds, observed, traj) -> None:
    """``observed``: (the observed velocity, the models' predictions on its samples)."""
    observed_xi, on_observed = observed
    experiment = cell.experiment
    key = (experiment.name, experiment.system, experiment.noise_kind)
    level = experiment.levels[cell.level]
    truth = preds["ground_truth"]
    stats, bins = {}, {}
    for model in MODELS:
        p = preds[model]
        stats[model] = {
            "rms_vs_ground_truth": error_summary(p, truth)[0].tolist(),
            "rms_vs_observed": error_summary(on_observed[model], observed_xi)[0].tolist(),
            "mean_vs_ground_truth": torch.nanmean(p - truth, dim=-2)[0].tolist(),
        }
        if model != "ground_truth":
            centres, mean, rms, se = phase_bin_errors(p, truth, traj.phase, config.error_bins)
            bins[model] = (centres.tolist(), mean[0].tolist(), rms[0].tolist(), se[0].tolist())
    for j in range(cell.stop - cell.start):
        trial = cell.start + j
        for model in MODELS:
            for c, comp in enumerate(COMPONENTS):
                for metric, values in stats[model].items():
                    out.results.append(key + (level, trial, model, comp, metric, values[j][c]))
        for model, (centres, mean, rms, se) in bins.items():
            for c, comp in enumerate(COMPONENTS):
                for b, centre in enumerate(centres):
                    out.phase_errors.append(key + (level, trial, model, comp, centre,
                                                   mean[j][b][c], rms[j][b][c], se[j][b][c]))
    if experiment.traces and cell.level == trace_level(experiment) and cell.start == 0:
        _collect_traces(out, experiment, preds, traj.smoothed.xi, traj)


def trace_level(experiment: Experiment) -> int:
    """Index of the level whose trial 0 is kept for Fig. 3B: the one closest to η (system
    noise) or to no observation noise."""
    levels = np.asarray(experiment.levels)
    return int(np.argmin(np.abs(levels - (1.0 if experiment.noise_kind == "system" else 0.0))))


def _collect_traces(out, experiment, preds, observed, traj) -> None:
    """Body velocity over cycles 13-18 of trial 0 at :func:`trace_level` (Fig. 3B); the
    trajectory holds that level only."""
    level = experiment.levels[trace_level(experiment)]
    t = traj.t
    lo, hi = (2 * math.pi * c for c in TRACE_CYCLES)
    keep = torch.nonzero((t >= lo) & (t < hi)).flatten()
    series = dict(preds)
    series["observed"] = observed
    times = t[keep].tolist()
    for model, values in series.items():
        v = values[0, 0, keep].tolist()
        for c, comp in enumerate(COMPONENTS):
            for k, tk in enumerate(times):
                out.traces.append((experiment.name, experiment.system, level, 0, tk, model,
                                   comp, v[k][c]))
