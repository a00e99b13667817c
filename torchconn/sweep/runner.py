"""Run a sweep: cells in-process or on Dask, stored as they finish, then assembled.

The unit of work and storage is a cell (one noise level of one experiment, ``block_trials``
trials; see :class:`~torchconn.sweep.experiment.Cell`), so a killed run loses only the cells
in flight, and ``--jobs`` (local processes, by default one per core) and ``--workers`` (Dask)
spread even a single experiment. Only one run writes a folder at a time
(:class:`~torchconn._output.FolderLock`); stored cells are checked on load and damaged ones
recomputed (:class:`~torchconn.sweep.store.ResultStore`). Per-experiment summaries (claims,
figures) are computed from all cells once they are loaded.

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

import ctypes
import hashlib
import json
import multiprocessing
import os
import signal
import sys
import threading
import time
import warnings
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import torch

from .._cli import InputError, hold_freed_memory, prepare_output
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
    make_system,
    run_cell,
)
from .store import ResultStore

__all__ = ["run_sweep", "SweepSummary", "Progress", "cell_fingerprint", "default_jobs"]


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


#: the memory a job process is given room for: torch and torchconn, and per trial-sample of
#: the largest cell (a 12-trial 9-link cell of 1,920 samples peaked at 0.7 GB, and a job keeps
#: what its cells freed for reuse, :func:`~torchconn._cli.hold_freed_memory`)
_JOB_BASE_BYTES = 512 << 20
_JOB_BYTES_PER_TRIAL_SAMPLE = 60_000


def default_jobs(config: SweepConfig, threads: int) -> int:
    """How many cells ``torchconn-sweep`` runs at once by default: one per ``threads`` CPU
    cores this process may use, as many as the available memory has room for (:func:`run_sweep`
    runs no more than there are cells to compute); 1 when the cells run on a GPU."""
    if torch.device(config.device).type != "cpu":
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    largest = max(min(config.block_trials, e.trials) * e.simulation.n_cycles
                  * e.simulation.samples_per_cycle for e in config.experiments)
    room = _available_memory() // (_JOB_BASE_BYTES + _JOB_BYTES_PER_TRIAL_SAMPLE * largest)
    return max(1, min(cores // max(threads, 1), room))


def _available_memory() -> int:
    """Bytes of memory available to new processes (Linux: ``MemAvailable``; elsewhere the
    free physical memory, or without a way to tell, no limit)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return 1 << 62


#: Linux ``prctl`` option: the signal a process gets when its parent ends
_PR_SET_PDEATHSIG = 1


def _start_job(threads: int, parent: int) -> None:
    """A local job process: the parent's thread count, freed memory kept for reuse
    (:func:`~torchconn._cli.hold_freed_memory`); an interrupt is the parent's to handle (it
    stops the jobs), not every job's. The job ends with its parent (process ``parent``): a
    job left behind would wait for work forever, and a forked one holds the output folder's
    lock, which a parent killed with ``kill -9`` must not leave held."""
    torch.set_num_threads(threads)
    hold_freed_memory()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:  # Linux: killed with the parent
        ctypes.CDLL(None).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError, TypeError):  # elsewhere: look once a second
        threading.Thread(target=_end_with, args=(parent,), daemon=True).start()
    if os.getppid() != parent:  # the parent ended already
        os._exit(1)


def _end_with(parent: int) -> None:
    """End this process once ``parent`` is no longer its parent."""
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(1)


def _job(config: SweepConfig, cell: Cell) -> tuple[ExperimentResult, list, int, float]:
    """One cell in a job process; the warnings it showed (those its filters, a fork of the
    parent's, let through), as ``(category, message)`` for the parent to give again where the
    command shows them; the process's id and the CPU seconds it has used so far."""
    caught = []
    with warnings.catch_warnings():
        warnings.showwarning = lambda message, category, *args, **kwargs: caught.append(
            (category, str(message)))
        result = run_cell(config, cell)
    return result, caught, os.getpid(), time.process_time()


def _cell_cost(cell: Cell) -> int:
    """A cell's relative cost, to start the longest first: samples times links."""
    sim = cell.experiment.simulation
    links = make_system(cell.experiment.system).n_links
    return (cell.stop - cell.start) * sim.n_cycles * sim.samples_per_cycle * links


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
    jobs: int = 1,
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
        jobs: without Dask, how many cells run at once, each in a local process with this
            process's torch thread count (1: one after another, in this process). The rows
            are the same bit for bit for any ``jobs``; the longest cells start first.
        quiet: no progress bar or log lines (the warnings are still given).
        figures: write the PNG figures.
        wait: when another run holds ``out_dir``, wait for it instead of raising
            :class:`~torchconn._output.FolderBusy`.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise InputError(f"--workers must be an integer >= 0, got {workers!r}")
    if workers and scheduler:
        raise InputError("give either --workers (a local cluster) or --scheduler, not both")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise InputError(f"--jobs must be an integer >= 1, got {jobs!r}")
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
        local = 1 if dask else min(jobs, max(len(pending), 1))
        job_cpu = []
        if pending and dask:
            _run_dask(dask, config, pending, store, done, progress, workers, scheduler)
        elif local > 1:
            job_cpu = _run_jobs(config, pending, store, done, progress, local)
        else:
            for cell, fp in pending:
                done[cell.name] = run_cell(config, cell)
                store.save(cell, fp, done[cell.name])
                progress.update(cell.name)
        wall = time.perf_counter() - t0
        return _assemble(config, out, done, plan, wall, figures, log, jobs=local,
                         job_cpu=job_cpu, computed=tuple(c.name for c, _ in pending),
                         damaged=tuple(damaged), removed=tuple(removed),
                         temporary=tuple(temporary))


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


def _run_jobs(config, pending, store, done, progress, jobs: int) -> list[float]:
    """The pending cells on ``jobs`` local processes, longest first; each cell stored as it
    finishes. On an error or an interrupt the jobs still running are stopped (the cells
    already stored are kept). Returns the CPU seconds of each job process."""
    threads = torch.get_num_threads()
    # fork: the jobs start at once with torchconn imported; spawn (imports anew) elsewhere and
    # for jobs of several threads (OpenMP's thread pool does not survive a fork)
    method = "fork" if sys.platform.startswith("linux") and threads == 1 else "spawn"
    pool = ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context(method),
                               initializer=_start_job, initargs=(threads, os.getpid()))
    cpu: dict[int, float] = {}
    try:
        running = {pool.submit(_job, config, cell): (cell, fp)
                   for cell, fp in sorted(pending, key=lambda p: -_cell_cost(p[0]))}
        while running:
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                cell, fp = running.pop(fut)
                try:
                    result, caught, pid, cpu[pid] = fut.result()
                except BrokenProcessPool:
                    raise RuntimeError(
                        f"a job process ended abruptly (killed, or out of memory?) with "
                        f"{len(running) + 1} cells unfinished; the cells finished are kept: run "
                        "again, with fewer --jobs to use less memory") from None
                for category, message in caught:
                    warnings.warn(message, category, stacklevel=1)
                done[cell.name] = result
                store.save(cell, fp, result)
                progress.update(cell.name)
    except BaseException:
        _stop_jobs(pool)
        raise
    pool.shutdown()
    return sorted(cpu.values())


def _stop_jobs(pool: ProcessPoolExecutor) -> None:
    """Cancel the queued cells and end the job processes now (not after their cells)."""
    # (the executor has no public way to end its processes before Python 3.14; shutdown
    # forgets them)
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for process in processes:
        process.terminate()
    pool.shutdown(wait=False, cancel_futures=True)


def _device_record(name: str) -> dict:
    """The device the cells ran on, for ``run.json`` (CPU and CUDA draw different numbers)."""
    device = torch.device(name)
    out = {"device": str(device), "type": device.type}
    if device.type == "cuda":
        out["name"] = torch.cuda.get_device_name(device)
        out["cuda"] = torch.version.cuda
    return out


def _assemble(config, out, done, plan, wall, figures, log, *, jobs, job_cpu, computed,
              damaged, removed, temporary) -> SweepSummary:
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
        "jobs": jobs,
        # this process's CPU time (start-up included, and the cells where it ran them) and
        # each job process's: on an idle machine, with a core per job, the wall time is
        # about this process's and the busiest job's together
        "cpu_time_s": {"this_process": time.process_time(), "jobs": job_cpu},
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
