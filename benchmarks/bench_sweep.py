"""Sweep timing: serial vs Dask workers on the Fig. 4A config, per-cell cost, stages, scaling.

Run by hand: ``python benchmarks/bench_sweep.py [--workers 2] [--block 20] [--stages]``, or
``python benchmarks/bench_sweep.py --default --skip-cells`` for the default sweep alone.

1. **Cells** (the default part): runs ``configs/fig4a.toml`` (one experiment, 8 levels x 20
   trials) through :func:`run_sweep` serially and on a local Dask cluster with ``--workers``
   worker processes, into fresh folders; checks that ``results.csv`` is byte-identical; prints
   both wall times and their ratio. Then it times one 4-trial and one 20-trial cell to split a
   cell's cost into a fixed part (the time loops of the rollout and the smoother run once per
   cell whatever its size) and a part per trial, and projects the wall time of the experiment
   on N workers for several block sizes (longest-first assignment of the cells, plus the
   measured cluster start-up), against the serial run of the whole experiment as one batch.
2. **Stages** (``--stages``): the paper experiments (Fig. 4A + 4B) split by stage.
3. **Scaling** (``--scaling``): time against trials and cycles on a smaller 9-link
   experiment, against the same pipeline run one trial at a time.
4. **One cell by stage in CPU seconds** (``--cell fig4a:3``, repeatable; ``--skip-cells`` to
   run only these): a whole-level cell of a packaged config (``NAME:LEVEL_INDEX``), run
   ``--repeat`` times after a warm-up, the best CPU time of this process per stage -- on a
   shared machine wall time mostly measures the other processes. Run it with two versions of
   the package, alternating, to compare them on one machine state.
5. **The default sweep** (``--default``): ``torchconn-sweep`` with no arguments but ``--out``
   (a temporary folder) and ``--quiet``, as a user runs it (its default ``--jobs``): its wall
   time, its CPU time (its own and its job processes', user + system) and the jobs it ran;
   the same command again into that folder, every cell stored (what the command does besides
   its cells: start-up, reading the stored cells, tables, claims, figures); then the same cells
   one after another in this process, with the stage clocks reading this process's CPU time:
   the CPU seconds of each stage and of all cells. On a shared machine the wall time is the
   other processes' too: the load average is printed, and the wall time on an idle machine
   with a core per job is estimated from ``run.json``'s CPU times, the command's process's
   (start-up, tables, figures) plus its busiest job's.

The machine's load average is printed: on a shared machine compare ratios within one run.
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np
import torch

from torchconn import _cli
from torchconn.sweep import experiment
from torchconn.sweep.config import load_config
from torchconn.sweep.experiment import experiment_cells, run_cell, run_experiment
from torchconn.sweep.runner import run_sweep

STAGES = ("rollout", "observe", "smoothing_phase", "regression", "evaluation")


def load() -> str:
    return "load average " + ", ".join(f"{x:.1f}" for x in os.getloadavg()) + \
        f" on {os.cpu_count()} cores"


def makespan(times: list[float], workers: int) -> float:
    """Finish time of ``times`` assigned longest-first to the least loaded of ``workers``."""
    heap = [0.0] * workers
    for t in sorted(times, reverse=True):
        heapq.heappush(heap, heapq.heappop(heap) + t)
    return max(heap)


def _cell_time(config, cell) -> float:
    t0 = time.perf_counter()
    run_cell(config, cell)
    return time.perf_counter() - t0


def cells_part(block: int, workers: int) -> None:
    config = load_config("fig4a", [f"block_trials={block}"])
    exp = config.experiments[0]
    cells = experiment_cells(exp, block)
    warm = load_config("fig4a", ["experiment.trials=4", "simulation.n_cycles=6",
                                 "experiment.levels=[1.0]"])
    run_cell(warm, experiment_cells(warm.experiments[0], 4)[0])  # imports, allocator warm-up
    print(f"Fig. 4A: {len(exp.levels)} levels x {exp.trials} trials x "
          f"{exp.simulation.n_cycles} cycles, block {block} -> {len(cells)} cells; {load()}")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        run_sweep(config, Path(tmp) / "serial", quiet=True, figures=False)
        serial = time.perf_counter() - t0
        print(f"serial:        {serial:7.1f} s   ({load()})")
        t0 = time.perf_counter()
        run_sweep(config, Path(tmp) / "dask", workers=workers, quiet=True, figures=False)
        dask = time.perf_counter() - t0
        print(f"--workers {workers}:   {dask:7.1f} s   ({load()})")
        same = (Path(tmp) / "serial" / "results.csv").read_bytes() == (
            Path(tmp) / "dask" / "results.csv").read_bytes()
        print(f"speed-up {serial / dask:.2f}x on {workers} workers; results.csv identical: {same}")

    from distributed import Client, LocalCluster

    t0 = time.perf_counter()
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        client.submit(sum, [1, 2]).result()
    startup = time.perf_counter() - t0
    mid = exp.levels.index(1.0) if 1.0 in exp.levels else 0
    small = [c for c in experiment_cells(exp, 4) if c.level == mid][0]
    large = [c for c in experiment_cells(exp, 20) if c.level == mid][0]
    t_small, t_large = _cell_time(config, small), _cell_time(config, large)
    per_trial = (t_large - t_small) / (large.stop - large.start - (small.stop - small.start))
    fixed = t_small - per_trial * (small.stop - small.start)
    one_batch = fixed + per_trial * exp.trials * len(exp.levels)
    print(f"cell cost: {fixed:.1f} s fixed + {per_trial:.2f} s per trial (from a 4- and a 20-trial "
          f"cell, {load()}); cluster start-up {startup:.1f} s")
    print(f"projected wall time on N workers vs {one_batch:.0f} s for the whole experiment as "
          "one batch (speed-up):")
    for b in (4, 8, 12, 20):
        sizes = [c.stop - c.start for c in experiment_cells(exp, b)]
        times = [fixed + per_trial * n for n in sizes]
        row = []
        for n in (1, 2, 4, 8, 16):
            wall = makespan(times, n) + (startup if n > 1 else 0.0)
            row.append(f"N={n}: {wall:5.0f} s ({one_batch / wall:4.1f}x)")
        print(f"  block {b:2d} ({len(sizes):2d} cells)  " + "  ".join(row))


def stages_part() -> None:
    grand = 0.0
    for name in ("fig4a", "fig4b"):
        config = load_config(name)
        for exp in config.experiments:
            t0 = time.perf_counter()
            t = run_experiment(config, exp, config.block_trials).timings
            total = time.perf_counter() - t0
            grand += total
            cells = len(exp.levels) * exp.trials
            print(f"{name} {exp.name}: {cells} trials x {exp.simulation.n_cycles} cycles: "
                  + ", ".join(f"{s} {t[s]:.1f}s" for s in STAGES) + f"; total {total:.1f}s")
    print(f"paper-scale sweep (Fig. 4A + 4B): {grand:.1f} s serial ({load()})")


def timed(config) -> float:
    t0 = time.perf_counter()
    exp = config.experiments[0]
    run_experiment(config, exp, exp.trials + (-exp.trials) % 4)  # one cell per level
    return time.perf_counter() - t0


def scaling_part() -> None:
    base = ["experiment.levels=[1.0]"]
    fig4a = "fig4a"
    timed(load_config(fig4a, base + ["experiment.trials=2", "simulation.n_cycles=6"]))
    trials, cycles = np.array([10, 20, 40]), np.array([10, 20, 40])
    by_trials = [timed(load_config(fig4a, base + [f"experiment.trials={n}",
                                                  "simulation.n_cycles=20"])) for n in trials]
    by_cycles = [timed(load_config(fig4a, base + ["experiment.trials=10",
                                                  f"simulation.n_cycles={n}"])) for n in cycles]
    st = np.polyfit(np.log(trials), np.log(by_trials), 1)[0]
    sc = np.polyfit(np.log(cycles), np.log(by_cycles), 1)[0]
    print(f"time vs trials {trials.tolist()}: {np.round(by_trials, 2).tolist()} s (slope {st:.2f})")
    print(f"time vs cycles {cycles.tolist()}: {np.round(by_cycles, 2).tolist()} s (slope {sc:.2f})")
    t1 = timed(load_config(fig4a, base + ["experiment.trials=1", "simulation.n_cycles=20"]))
    n = int(trials[-1])
    print(f"one trial at a time: {t1:.2f} s per trial -> {n * t1:.1f} s for {n} trials vs "
          f"{by_trials[-1]:.1f} s batched ({n * t1 / by_trials[-1]:.1f}x)")


def cell_part(spec: str, repeat: int) -> None:
    name, _, level = spec.partition(":")
    config = load_config(name)
    exp = config.experiments[0]
    cell = [c for c in experiment_cells(exp, exp.trials) if c.level == int(level or 0)][0]
    clock = experiment.time
    experiment.time = types.SimpleNamespace(perf_counter=time.process_time)  # stage clocks: CPU
    try:
        run_cell(config, cell)  # warm-up: imports, caches
        best: dict[str, float] = {}
        for _ in range(repeat):
            t0 = time.process_time()
            timings = run_cell(config, cell).timings
            timings["total"] = time.process_time() - t0
            best = {k: min(v, best.get(k, v)) for k, v in timings.items()}
    finally:
        experiment.time = clock
    print(f"{name} cell (level {exp.levels[cell.level]}, {exp.trials} trials x "
          f"{exp.simulation.n_cycles} cycles), best CPU s of {repeat}: "
          + ", ".join(f"{k} {v:.3f}" for k, v in best.items()) + f" ({load()})")


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _timed_command(out: str) -> tuple[float, float]:
    """Wall and CPU time (user + system, its job processes included) of the default sweep
    into ``out``."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    cpu0, t0 = _children_cpu(), time.perf_counter()
    # (run from the output's folder: python -m puts the working folder first on the path)
    subprocess.run([sys.executable, "-m", "torchconn.sweep", "--out", out, "--quiet"], env=env,
                   check=True, cwd=Path(out).parent)
    return time.perf_counter() - t0, _children_cpu() - cpu0


def default_part() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        wall, cpu = _timed_command(f"{tmp}/out")
        run = json.loads(Path(f"{tmp}/out/run.json").read_text())
        print(f"default sweep (torchconn-sweep): wall {wall:.1f} s, CPU {cpu:.1f} s (user + "
              f"system, its jobs included), {run.get('jobs', 1)} jobs of {run['torch_threads']} "
              f"thread(s) ({load()})")
        if "cpu_time_s" in run:
            own, jobs = run["cpu_time_s"]["this_process"], run["cpu_time_s"]["jobs"]
            print(f"  CPU s of the command's process {own:.1f}, of its jobs "
                  f"{[round(j, 1) for j in jobs]}: on an idle machine with a core per job "
                  f"about {own + max(jobs, default=0.0):.1f} s wall")
        wall, cpu = _timed_command(f"{tmp}/out")
        print(f"  again, every cell stored (start-up, reading the cells, tables, claims, "
              f"figures): wall {wall:.1f} s, CPU {cpu:.1f} s")
    config = load_config(None)
    getattr(_cli, "hold_freed_memory", lambda: None)()  # as the command's processes do
    clock = experiment.time
    experiment.time = types.SimpleNamespace(perf_counter=time.process_time)  # stage clocks: CPU
    totals: dict[str, float] = {}
    try:
        for exp in config.experiments:
            t0 = time.process_time()
            timings = run_experiment(config, exp, config.block_trials).timings
            timings["total"] = time.process_time() - t0
            print(f"  {exp.name}: " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items())
                  + " CPU s")
            totals = {k: totals.get(k, 0.0) + v for k, v in timings.items()}
    finally:
        experiment.time = clock
    cells = totals.pop("total")
    print("  all cells, CPU s: " + ", ".join(f"{k} {v:.1f}" for k, v in totals.items())
          + f"; total {cells:.1f} ({load()})")


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--block", type=int, default=20, help="trials per cell (multiple of 4)")
    p.add_argument("--skip-cells", action="store_true", help="skip serial vs workers")
    p.add_argument("--stages", action="store_true", help="Fig. 4A + 4B split by stage")
    p.add_argument("--scaling", action="store_true", help="time vs trials and cycles")
    p.add_argument("--cell", action="append", default=[], metavar="NAME:LEVEL",
                   help="one cell by stage in CPU seconds, e.g. fig4a:3 (repeatable)")
    p.add_argument("--repeat", type=int, default=3, help="runs per --cell")
    p.add_argument("--default", action="store_true",
                   help="the default sweep: wall and CPU time of the command, CPU s by stage")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    if not args.skip_cells:
        cells_part(args.block, args.workers)
    if args.stages:
        stages_part()
    if args.scaling:
        scaling_part()
    for spec in args.cell:
        cell_part(spec, args.repeat)
    if args.default:
        default_part()


if __name__ == "__main__":
    main()
