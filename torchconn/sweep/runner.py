"""Run a sweep: cells in-process or on Dask, stored as they finish, then assembled.

The unit of work and storage is a cell (one noise level of one experiment, ``block_trials``
trials; see :class:`~torchconn.sweep.experiment.Cell`), so a killed run loses only the cells
in flight and ``--workers`` spreads even a single experiment. Only one run writes a folder at
a time (:class:`~torchconn._output.FolderLock`); stored cells are checked on load and
damaged ones recomputed (:class:`~torchconn.sweep.store.ResultStore`). Per-experiment
summaries (claims, figures) are computed from all cells once they are loaded.

Outputs in ``OUT/``: ``results.csv`` (tidy: experiment, system, noise_kind, level, trial, model,
component, metric, value), ``phase_errors.csv`` (error per phase bin), ``traces.csv``
(body-velocity traces for Fig. 3B), ``claims.csv`` (claim, holds, evidence), ``run.json``
(config, seeds, versions, timings) and the figures ``fig*.png``. Each file is written
atomically; ``run.json`` is the completion record: removed before the tables are rewritten and
written last, so tables beside a ``run.json`` are all of the run it describes. Outputs of the
previous run that this one does not write again (figures, with ``--no-figures``) are removed.
A folder that is neither empty nor a sweep's (no ``cells/``) is refused.
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

from .._cli import InputError, prepare_output
from .._output import OS_LITTER, FolderLock, write_table
from .._provenance import write_sidecar
from .claims import check_claims
from .config import SweepConfig
from .experiment import (
    PHASE_COLUMNS,
    RESULT_COLUMNS,
    TRACE_COLUMNS,
    Cell,
    ExperimentResult,
    experiment_cells,
    experiment_seeds,
    run_cell,
)
from .store import ResultStore

__all__ = ["run_sweep", "SweepSummary", "Progress", "cell_fingerprint"]


@dataclass(frozen=True, kw_only=True)
class SweepSummary:
    """What :func:`run_sweep` did: the output folder, the claims, the figures written, stage
    timings per experiment, the cells computed by this run, how many stored cells were reused,
    the damaged cells that were recomputed and the stale cell folders that were removed (each
    with the reason), and the temporary files of a killed run that were removed."""

    out: Path
    claims: list
    figures: list
    timings: dict
    computed: tuple[str, ...]
    reused: int
    damaged: tuple[tuple[str, str], ...]
    removed: tuple[tuple[str, str], ...] = ()
    temporary: tuple[str, ...] = ()


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


def cell_fingerprint(config: SweepConfig, cell: Cell) -> str:
    """Hash of everything that determines a cell's rows, torchconn's code included."""
    payload = {**config.fingerprint(cell.experiment), "cell": [cell.level, cell.start, cell.stop]}
    text = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _in_worker(config: SweepConfig, cell: Cell, threads: int) -> ExperimentResult:
    """Dask task: the same computation as the serial run, with the same thread count."""
    torch.set_num_threads(threads)
    return run_cell(config, cell)


def _dask():
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise InputError("--workers/--scheduler need Dask, which is not installed: "
                         "pip install 'torchconn[dask]' (or run without them)") from None
    return Client, LocalCluster, as_completed


def run_sweep(
    config: SweepConfig,
    out_dir: Path | str,
    *,
    workers: int = 0,
    scheduler: str | None = None,
    quiet: bool = False,
    figures: bool = True,
    wait: bool = False,
) -> SweepSummary:
    """Run (or resume) a sweep and write its outputs.

    Args:
        config: the sweep.
        out_dir: output folder, new, empty or an earlier sweep's; intact cells already stored
            there are reused, damaged ones recomputed, stale ones removed (each reported on
            stderr with the reason: through :func:`warnings.warn`, which a command prints as
            ``prog: warning: ...``).
        workers: > 0 runs cells on a local Dask cluster with that many worker processes.
        scheduler: address of an existing Dask scheduler (``tcp://HOST:PORT``).
        quiet: no progress bar or log lines (the warnings are still given).
        figures: write the PNG figures.
        wait: when another run holds ``out_dir``, wait for it instead of raising
            :class:`~torchconn._output.FolderBusy`.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise InputError(f"--workers must be an integer >= 0, got {workers!r}")
    if workers and scheduler:
        raise InputError("give either --workers (a local cluster) or --scheduler, not both")
    dask = _dask() if (workers or scheduler) else None
    _check_sweep_folder(Path(out_dir))
    out = prepare_output(out_dir)
    log = (lambda *a: None) if quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))
    # a stale lock taken over, files deleted and damaged cells are warned about, even when quiet
    with FolderLock(out, wait=wait, log=warnings.warn):
        _check_sweep_folder(out)  # again: it may have changed while we waited
        store = ResultStore(out)
        plan = [(cell, cell_fingerprint(config, cell)) for exp in config.experiments
                for cell in experiment_cells(exp, config.block_trials)]
        temporary, removed = store.clean(plan, log=warnings.warn)
        done, pending, damaged = {}, [], []
        for cell, fp in plan:
            result, problem = store.load(cell, fp)
            if result is not None:
                done[cell.name] = result
                continue
            pending.append((cell, fp))
            if problem:
                damaged.append((cell.name, problem))
                warnings.warn(f"recomputing cell {cell.name}: {problem}", stacklevel=2)
        log(f"sweep {config.name!r}: {len(config.experiments)} experiments in {len(plan)} cells, "
            f"{len(done)} already done in {out}")
        progress = Progress(len(plan), len(done), quiet)
        t0 = time.perf_counter()
        if pending and dask:
            _run_dask(dask, config, pending, store, done, progress, workers, scheduler)
        else:
            for cell, fp in pending:
                done[cell.name] = run_cell(config, cell)
                store.save(cell, fp, done[cell.name])
                progress.update(cell.name)
        wall = time.perf_counter() - t0
        return _assemble(config, out, done, plan, wall, figures, log,
                         computed=tuple(c.name for c, _ in pending), damaged=tuple(damaged),
                         removed=tuple(removed), temporary=tuple(temporary))


def _check_sweep_folder(out: Path) -> None:
    """Refuse an output folder that is neither missing, empty nor a sweep's (with ``cells/``):
    the sweep would overwrite files of the same names in it."""
    if not out.is_dir() or (out / "cells").is_dir():
        return
    try:
        entries = {p.name for p in out.iterdir()} - OS_LITTER - {".lock"}
    except OSError:
        return  # prepare_output says why
    if entries:
        raise InputError(f"--out {out}: the folder is not empty and holds no sweep (no cells/ "
                         "folder); choose a new or empty folder (its contents are never "
                         "deleted)")


def _run_dask(dask, config, pending, store, done, progress, workers, scheduler) -> None:
    Client, LocalCluster, as_completed = dask
    threads = torch.get_num_threads()
    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, ValueError, TypeError) as err:
            raise InputError(f"--scheduler {scheduler}: cannot connect ({err})") from None
    else:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    try:
        futures = {client.submit(_in_worker, config, cell, threads, pure=False): (cell, fp)
                   for cell, fp in pending}
        for fut in as_completed(futures):
            cell, fp = futures[fut]
            done[cell.name] = fut.result()
            store.save(cell, fp, done[cell.name])
            progress.update(cell.name)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _device_record(name: str) -> dict:
    """The device the cells ran on, for ``run.json`` (CPU and CUDA draw different numbers)."""
    device = torch.device(name)
    out = {"device": str(device), "type": device.type}
    if device.type == "cuda":
        out["name"] = torch.cuda.get_device_name(device)
        out["cuda"] = torch.version.cuda
    return out


def _assemble(config, out, done, plan, wall, figures, log, *, computed, damaged, removed,
              temporary) -> SweepSummary:
    previous = _previous_outputs(out)
    (out / "run.json").unlink(missing_ok=True)  # the completion record goes first, comes last
    per_experiment = {e.name: ExperimentResult() for e in config.experiments}
    for cell, _ in plan:  # plan order: experiment, level, trials -- independent of block size
        per_experiment[cell.experiment.name].extend(done[cell.name])
    results, phase_errors, traces, timings = [], [], [], {}
    for name, res in per_experiment.items():
        results += res.results
        phase_errors += res.phase_errors
        traces += res.traces
        timings[name] = res.timings
    write_table(out / "results.csv", RESULT_COLUMNS, results)
    write_table(out / "phase_errors.csv", PHASE_COLUMNS, phase_errors)
    write_table(out / "traces.csv", TRACE_COLUMNS, traces)
    claims = check_claims(results, phase_errors, config.experiments, RESULT_COLUMNS,
                          PHASE_COLUMNS)
    write_table(out / "claims.csv", ("claim", "holds", "evidence"), claims)
    made = []
    if figures:
        # lazy: the figures import matplotlib, which only a run that draws them needs
        from .figures import make_figures

        as_dicts = [
            [dict(zip(cols, r, strict=False)) for r in rows]
            for rows, cols in ((results, RESULT_COLUMNS), (phase_errors, PHASE_COLUMNS),
                               (traces, TRACE_COLUMNS))
        ]
        made = make_figures(out, *as_dicts, config.experiments)
    outputs = ["results.csv", "phase_errors.csv", "traces.csv", "claims.csv"] + [
        Path(p).name for p in made]
    for name in sorted(previous - set(outputs)):  # the previous run's, not written again
        (out / name).unlink(missing_ok=True)
    sidecar = {
        "config": config.raw,
        "estimator": config.estimator,
        "root_seed": config.seed,
        "seeds": {e.name: experiment_seeds(config, e).tolist() for e in config.experiments},
        "block_trials": config.block_trials,
        "cells": {cell.name: fp for cell, fp in plan},
        "cells_computed_this_run": list(computed),
        "cells_damaged_and_recomputed": [{"cell": c, "reason": r} for c, r in damaged],
        "cells_removed_stale": [{"cell": c, "reason": r} for c, r in removed],
        "temporary_files_removed": list(temporary),
        "outputs": outputs,
        "timings_s": timings,
        "wall_time_s_this_run": wall,
        "torch_threads": torch.get_num_threads(),
        "device": _device_record(config.device),
    }
    write_sidecar(out / "run.json", sidecar)
    for claim, holds, evidence in claims:
        log(f"{'HOLDS' if holds is True else 'FAILS' if holds is False else 'n/a  '}  {claim}\n"
            f"       {evidence}")
    log(f"wrote {out}/results.csv, claims.csv, run.json and {len(made)} figures")
    return SweepSummary(out=out, claims=claims, figures=made, timings=timings, computed=computed,
                        reused=len(plan) - len(computed), damaged=damaged, removed=removed,
                        temporary=temporary)


def _previous_outputs(out: Path) -> set[str]:
    """The files the previous run listed in its ``run.json`` (plain names in ``out``)."""
    try:
        names = json.loads((out / "run.json").read_text(encoding="utf-8")).get("outputs", [])
    except (OSError, ValueError, AttributeError):
        return set()
    if not isinstance(names, list):
        return set()
    return {n for n in names if isinstance(n, str) and n == Path(n).name
            and n not in ("run.json", "cells", ".lock") and (out / n).is_file()}
