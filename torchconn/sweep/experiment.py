"""Run one experiment of a sweep: all its noise levels × trials in one batched pipeline.

simulate → observe → prepare (smooth, phase) → fit → reference models → tidy rows. The
function is pure (inputs: the config and the experiment; output: tables of rows), so the
serial runner and a Dask worker produce identical results for the same seeds.
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
    phase_bin_errors,
    reference_models,
)
from ..physics.gaits import reference_gait
from ..physics.systems import NLinkSwimmer
from ..simulation.observe import observe
from ..simulation.rollout import simulate
from .config import Experiment, SweepConfig

__all__ = ["ExperimentResult", "run_experiment", "experiment_seeds", "make_system"]

RESULT_COLUMNS = ("experiment", "system", "noise_kind", "level", "trial", "model", "component",
                  "metric", "value")
PHASE_COLUMNS = ("experiment", "system", "noise_kind", "level", "trial", "model", "component",
                 "phase", "mean", "rms", "se")
TRACE_COLUMNS = ("experiment", "system", "level", "trial", "t", "model", "component", "value")

#: cycles whose body-velocity traces are kept for the Fig. 3B panel (the paper's 13-18)
TRACE_CYCLES = (13, 18)


@dataclass
class ExperimentResult:
    """Tidy rows of one experiment, and how long each stage took."""

    results: list[tuple] = field(default_factory=list)
    phase_errors: list[tuple] = field(default_factory=list)
    traces: list[tuple] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)


def make_system(name: str) -> NLinkSwimmer:
    return NLinkSwimmer({"3link": 3, "9link": 9}[name])


def experiment_seeds(config: SweepConfig, experiment: Experiment) -> np.ndarray:
    """Seeds ``(levels, trials)``: cell (i, j) of experiment e gets
    ``SeedSequence(root, spawn_key=(e, i, j))`` (:func:`torchconn._provenance.spawn_seeds`).

    Keyed by position, so a cell's seed does not depend on which other cells run, in which
    order, or on which backend.
    """
    e = [x.name for x in config.experiments].index(experiment.name)
    return spawn_seeds(config.seed, (len(experiment.levels), experiment.trials), key=(e,))


def run_experiment(config: SweepConfig, experiment: Experiment) -> ExperimentResult:
    """All levels × trials of one experiment, batched; returns its tidy rows."""
    out = ExperimentResult()
    clock = time.perf_counter
    sim = experiment.simulation
    system = make_system(experiment.system)
    gait = reference_gait(experiment.system)
    levels = torch.tensor(experiment.levels, dtype=torch.float64)[:, None]  # (L, 1)
    seeds = experiment_seeds(config, experiment)
    if experiment.noise_kind == "system":
        eta, omega = sim.eta * levels, experiment.omega
    else:
        eta, omega = sim.eta * experiment.eta_factor, levels

    t0 = clock()
    traj = simulate(system, gait, eta=eta, alpha=sim.alpha, n_cycles=sim.n_cycles,
                    samples_per_cycle=sim.samples_per_cycle, substeps=sim.substeps, seeds=seeds)
    out.timings["rollout"] = clock() - t0
    t0 = clock()
    if experiment.noise_kind == "observation" or experiment.omega > 0:
        traj = observe(traj, omega, seeds=seeds)
    out.timings["observe"] = clock() - t0

    # the sweep scores body-velocity models only, so the metric is not fitted (at low noise its
    # quadratic regressors can be too thin to fit, which should not stop a connection study)
    estimator = config.make_estimator().set_params(regression__metric=False)
    phase = traj.truth.phase if config.phase == "true" else None
    t0 = clock()
    prepared = estimator.prepare(traj, phase=phase)
    out.timings["smoothing_phase"] = clock() - t0
    t0 = clock()
    estimator.fit(prepared)
    out.timings["regression"] = clock() - t0

    t0 = clock()
    noisy = experiment.noise_kind == "observation" or experiment.omega > 0
    clean = clean_trajectory(traj) if noisy else None
    preds = reference_models(system, estimator.model_, estimator.trajectory_, clean)
    observed = estimator.trajectory_.smoothed.xi
    _collect(out, config, experiment, preds, observed, estimator.trajectory_)
    out.timings["evaluation"] = clock() - t0
    return out


def _collect(out, config, experiment, preds, observed, traj) -> None:
    key = (experiment.name, experiment.system, experiment.noise_kind)
    truth = preds["ground_truth"]
    L, n = len(experiment.levels), experiment.trials
    for model in MODELS:
        p = preds[model]
        stats = {
            "rms_vs_ground_truth": error_summary(p, truth),
            "rms_vs_observed": error_summary(p, observed),
            "mean_vs_ground_truth": torch.nanmean(p - truth, dim=-2),
        }
        for i in range(L):
            for j in range(n):
                for c, comp in enumerate(COMPONENTS):
                    for metric, values in stats.items():
                        out.results.append(key + (experiment.levels[i], j, model, comp, metric,
                                                  float(values[i, j, c])))
        if model == "ground_truth":
            continue
        centres, mean, rms, se = phase_bin_errors(p, truth, traj.phase, config.error_bins)
        for i in range(L):
            for j in range(n):
                for c, comp in enumerate(COMPONENTS):
                    for b in range(config.error_bins):
                        out.phase_errors.append(key + (
                            experiment.levels[i], j, model, comp, float(centres[b]),
                            float(mean[i, j, b, c]), float(rms[i, j, b, c]),
                            float(se[i, j, b, c])))
    if experiment.traces:
        _collect_traces(out, experiment, preds, observed, traj)


def _collect_traces(out, experiment, preds, observed, traj) -> None:
    """Body velocity over cycles 13-18 of trial 0 at the level closest to 1 (Fig. 3B)."""
    levels = np.asarray(experiment.levels)
    i = int(np.argmin(np.abs(levels - (1.0 if experiment.noise_kind == "system" else 0.0))))
    t = traj.t
    lo, hi = (2 * math.pi * c for c in TRACE_CYCLES)
    keep = torch.nonzero((t >= lo) & (t < hi)).flatten()
    series = dict(preds)
    series["observed"] = observed
    for model, values in series.items():
        for c, comp in enumerate(COMPONENTS):
            for k in keep.tolist():
                out.traces.append((experiment.name, experiment.system, experiment.levels[i], 0,
                                   float(t[k]), model, comp, float(values[i, 0, k, c])))
