"""Run a sweep: experiments in-process or on Dask, stored as they finish, then assembled.

Outputs in ``OUT/``: ``results.csv`` (tidy: experiment, system, noise_kind, level, trial, model,
component, metric, value), ``phase_errors.csv`` (error per phase bin), ``traces.csv``
(body-velocity traces for Fig. 3B), ``claims.csv`` (claim, holds, evidence), ``run.json``
(config, seeds, versions, timings) and the figures ``fig*.png``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import torch

from .._provenance import write_sidecar
from .claims import check_claims
from .config import SweepConfig
from .experiment import (
    PHASE_COLUMNS,
    RESULT_COLUMNS,
    TRACE_COLUMNS,
    experiment_seeds,
    run_experiment,
)
from .figures import make_figures
from .store import ResultStore, write_csv

__all__ = ["run_sweep", "Progress"]


class Progress:
    """A one-line text progress bar (stderr), silent when ``quiet``."""

    def __init__(self, total: int, done: int = 0, quiet: bool = False, width: int = 30):
        self.total, self.done, self.quiet, self.width = total, done, quiet, width
        self.start = time.perf_counter()
        self.fresh = 0

    def update(self, label: str) -> None:
        self.done += 1
        self.fresh += 1
        if self.quiet:
            return
        elapsed = time.perf_counter() - self.start
        remaining = (self.total - self.done) * elapsed / self.fresh
        filled = int(self.width * self.done / max(self.total, 1))
        bar = "#" * filled + "-" * (self.width - filled)
        print(f"[{bar}] {self.done}/{self.total} {label}  elapsed {elapsed:5.0f}s  "
              f"left ~{remaining:4.0f}s", file=sys.stderr, flush=True)


def _in_worker(config: SweepConfig, experiment, threads: int):
    """Dask task: the same computation as the serial run, with the same thread count."""
    torch.set_num_threads(threads)
    return run_experiment(config, experiment)


def run_sweep(
    config: SweepConfig,
    out_dir: Path | str,
    *,
    workers: int = 0,
    scheduler: str | None = None,
    quiet: bool = False,
    figures: bool = True,
) -> dict:
    """Run (or resume) a sweep and write its outputs; returns a summary dict.

    Args:
        config: the sweep.
        out_dir: output directory; finished experiments already stored there are skipped.
        workers: > 0 runs experiments on a local Dask cluster with that many worker processes.
        scheduler: address of an existing Dask scheduler (``tcp://HOST:PORT``).
        quiet: no progress bar or log lines.
        figures: write the PNG figures.
    """
    out = Path(out_dir)
    store = ResultStore(out)
    plan = [(exp, config.fingerprint(exp)) for exp in config.experiments]
    pending = [(e, fp) for e, fp in plan if not store.is_done(e.name, fp)]
    log = (lambda *a: None) if quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))
    log(f"sweep {config.name!r}: {len(plan)} experiments, {len(plan) - len(pending)} already "
        f"done in {out}")
    progress = Progress(len(plan), len(plan) - len(pending), quiet)
    t0 = time.perf_counter()
    if pending and (workers or scheduler):
        _run_dask(config, pending, store, progress, workers, scheduler)
    else:
        for exp, fp in pending:
            store.save(exp.name, fp, run_experiment(config, exp))
            progress.update(exp.name)
    wall = time.perf_counter() - t0
    return _assemble(config, out, store, plan, wall, figures, log)


def _run_dask(config, pending, store, progress, workers, scheduler) -> None:
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise RuntimeError(
            "--workers/--scheduler need Dask: pip install 'torchconn[dask]'"
        ) from err
    threads = torch.get_num_threads()
    cluster = None
    if scheduler:
        client = Client(scheduler)
    else:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    try:
        futures = {client.submit(_in_worker, config, exp, threads, pure=False): (exp, fp)
                   for exp, fp in pending}
        for fut in as_completed(futures):
            exp, fp = futures[fut]
            store.save(exp.name, fp, fut.result())
            progress.update(exp.name)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _assemble(config, out, store, plan, wall, figures, log) -> dict:
    results, phase_errors, traces, timings = [], [], [], {}
    for exp, fp in plan:
        res = store.load(exp.name, fp)
        results += res.results
        phase_errors += res.phase_errors
        traces += res.traces
        timings[exp.name] = res.timings
    write_csv(out / "results.csv", RESULT_COLUMNS, results)
    write_csv(out / "phase_errors.csv", PHASE_COLUMNS, phase_errors)
    write_csv(out / "traces.csv", TRACE_COLUMNS, traces)
    claims = check_claims(results, phase_errors, config.experiments, RESULT_COLUMNS,
                          PHASE_COLUMNS)
    write_csv(out / "claims.csv", ("claim", "holds", "evidence"), claims)
    made = []
    if figures:
        as_dicts = [
            [dict(zip(cols, r, strict=False)) for r in rows]
            for rows, cols in ((results, RESULT_COLUMNS), (phase_errors, PHASE_COLUMNS),
                               (traces, TRACE_COLUMNS))
        ]
        made = make_figures(out, *as_dicts, config.experiments)
    sidecar = {
        "config": config.raw,
        "estimator": config.estimator,
        "root_seed": config.seed,
        "seeds": {e.name: experiment_seeds(config, e).tolist() for e, _ in plan},
        "fingerprints": {e.name: fp for e, fp in plan},
        "timings_s": timings,
        "wall_time_s_this_run": wall,
        "torch_threads": torch.get_num_threads(),
    }
    write_sidecar(out / "run.json", sidecar)
    for claim, holds, evidence in claims:
        log(f"{'HOLDS' if holds is True else 'FAILS' if holds is False else 'n/a  '}  {claim}\n"
            f"       {evidence}")
    log(f"wrote {out}/results.csv, claims.csv, run.json and {len(made)} figures")
    return {"out": out, "claims": claims, "figures": made, "timings": timings}
