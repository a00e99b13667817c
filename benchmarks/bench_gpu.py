"""The pipeline on CUDA beside the CPU: the paper-scale sweep, a 100x larger one, agreement.

Run by hand on a machine with a GPU: ``python benchmarks/bench_gpu.py [--large-cpu]``.
Without CUDA it prints one line saying so and exits 0.

1. **Paper-scale sweep** (``configs/fig4a`` + ``configs/fig4b``, each level one cell): time per
   stage (rollout, observe, smoothing + phase, regression, evaluation) on CUDA, and on the CPU
   with 1 thread and with all threads. CUDA stage times are taken after a device synchronise.
2. **100x larger** (Fig. 4A's 8 levels x 2000 trials x 30 cycles, 9-link, each level one cell):
   per stage on CUDA; on the CPU only with ``--large-cpu`` (hours at one thread).
3. **Agreement**: one 9-link recording (40 trials x 30 cycles) simulated on the CPU, fitted on
   the CPU and on CUDA; the largest difference of Â along the gait relative to its largest
   value (target 1e-10 in float64). CPU and CUDA draw different random numbers, so the sweeps
   of parts 1-2 are different samples of the same experiments, not copies.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, observe, simulate
from torchconn.physics.gaits import reference_gait
from torchconn.sweep.config import load_config
from torchconn.sweep.experiment import run_experiment

#: a small valid Fig. 4A sweep (one level, 4 trials x 30 cycles) that compiles and caches kernels
WARM_UP = ["experiment.trials=4", "experiment.levels=[1.0]"]
STAGES = ("rollout", "observe", "smoothing_phase", "regression", "evaluation")


def sweep(configs: list[tuple[str, list[str]]], device: str, threads: int) -> dict[str, float]:
    """Per-stage and total seconds of the experiments of ``configs`` on ``device``."""
    torch.set_num_threads(threads)
    stages = dict.fromkeys(STAGES, 0.0)
    t0 = time.perf_counter()
    for name, overrides in configs:
        config = load_config(name, overrides)
        for exp in config.experiments:
            block = exp.trials + (-exp.trials) % 4  # one cell per level
            t = run_experiment(config, exp, block, device=device).timings
            for s in STAGES:
                stages[s] += t[s]
    stages["total"] = time.perf_counter() - t0
    return stages


def table(title: str, rows: dict[str, dict[str, float] | None]) -> None:
    print(f"\n{title}")
    print(f"{'':>16}" + "".join(f"{s:>17}" for s in (*STAGES, "total")))
    for label, t in rows.items():
        if t is None:
            print(f"{label:>16}  not run")
            continue
        print(f"{label:>16}" + "".join(f"{t[s]:16.1f}s" for s in (*STAGES, "total")))


def agreement(n_trials: int = 40) -> float:
    seeds = np.arange(n_trials)
    traj = simulate(NLinkSwimmer(9), reference_gait("9link"), eta=0.025, n_cycles=30,
                    seeds=seeds)
    traj = observe(traj, 0.002, seeds=seeds)
    phi = torch.linspace(0, 2 * np.pi, 97, dtype=torch.float64)
    a_cpu = ConnectionEstimator().fit(traj).model_.connection(phi)
    a_gpu = ConnectionEstimator().fit(traj.to("cuda")).model_.connection(phi.cuda()).cpu()
    return float((a_gpu - a_cpu).abs().max() / a_cpu.abs().max())


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--large-cpu", action="store_true",
                   help="also run the 100x larger sweep on the CPU (hours)")
    args = p.parse_args()
    if not torch.cuda.is_available():
        print("bench_gpu: needs CUDA (torch.cuda.is_available() is False); nothing measured")
        return 0
    cores = os.cpu_count() or 1
    print(f"{torch.cuda.get_device_name()}, torch {torch.__version__}, {cores} CPU cores")
    paper = [("fig4a", []), ("fig4b", [])]
    # warm-up: one level of 4 trials at the config's own 30 cycles (fewer cycles than the
    # 9-link's 81 regressors need is refused by the fit)
    sweep([("fig4a", WARM_UP)], "cuda", 1)
    table("paper-scale sweep (Fig. 4A + 4B)", {
        "cuda": sweep(paper, "cuda", 1),
        "cpu, 1 thread": sweep(paper, "cpu", 1),
        f"cpu, {cores} threads": sweep(paper, "cpu", cores),
    })
    large = [("fig4a", ["experiment.trials=2000"])]
    table("100x larger (8 levels x 2000 trials x 30 cycles, 9-link)", {
        "cuda": sweep(large, "cuda", 1),
        "cpu, 1 thread": sweep(large, "cpu", 1) if args.large_cpu else None,
        f"cpu, {cores} threads": sweep(large, "cpu", cores) if args.large_cpu else None,
    })
    torch.set_num_threads(cores)
    rel = agreement()
    print(f"\nCPU vs CUDA fit of the same 9-link data (40 trials x 30 cycles): max |dA| / max |A| "
          f"= {rel:.1e} (target 1e-10: {'met' if rel <= 1e-10 else 'NOT met'})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
