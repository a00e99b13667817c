"""Paper-scale sweep timing: Fig. 4A + 4B configs, per stage, and scaling with trials/cycles.

Run by hand: ``python benchmarks/bench_sweep.py [--skip-paper] [--threads 1]``. Prints the wall
time of each paper experiment split by stage (rollout, observe, smoothing + phase, regression,
evaluation), the total, and the log-log slope of time against trials and against cycles
(1 = linear) on a smaller 9-link experiment. The reference for the batched pipeline is the same
pipeline run one trial at a time, timed on the scaling experiment.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from torchconn.sweep.config import load_config
from torchconn.sweep.experiment import run_experiment

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("rollout", "observe", "smoothing_phase", "regression", "evaluation")


def timed(config, experiment) -> dict[str, float]:
    t0 = time.perf_counter()
    timings = run_experiment(config, experiment).timings
    timings["total"] = time.perf_counter() - t0
    return timings


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--skip-paper", action="store_true", help="only the scaling study")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    if not args.skip_paper:
        grand = 0.0
        for name in ("fig4a", "fig4b"):
            config = load_config(ROOT / "configs" / f"{name}.toml")
            for exp in config.experiments:
                t = timed(config, exp)
                grand += t["total"]
                cells = len(exp.levels) * exp.trials
                print(f"{name} {exp.name}: {cells} trials x {exp.simulation.n_cycles} cycles: "
                      + ", ".join(f"{s} {t[s]:.1f}s" for s in STAGES) + f"; total {t['total']:.1f}s")
        print(f"paper-scale sweep (Fig. 4A + 4B): {grand:.1f} s on {args.threads} thread(s)")

    base = ["experiment.levels=[1.0]"]
    warm = load_config(ROOT / "configs" / "fig4a.toml",
                       base + ["experiment.trials=2", "simulation.n_cycles=6"])
    timed(warm, warm.experiments[0])  # first-call costs (imports, allocator) out of the study
    trials, cycles = np.array([10, 20, 40]), np.array([10, 20, 40])
    by_trials = [timed(c, c.experiments[0])["total"] for c in
                 (load_config(ROOT / "configs" / "fig4a.toml", base + [f"experiment.trials={n}",
                  "simulation.n_cycles=20"]) for n in trials)]
    by_cycles = [timed(c, c.experiments[0])["total"] for c in
                 (load_config(ROOT / "configs" / "fig4a.toml", base + ["experiment.trials=10",
                  f"simulation.n_cycles={n}"]) for n in cycles)]
    st = np.polyfit(np.log(trials), np.log(by_trials), 1)[0]
    sc = np.polyfit(np.log(cycles), np.log(by_cycles), 1)[0]
    print(f"time vs trials {trials.tolist()}: {np.round(by_trials, 2).tolist()} s (slope {st:.2f})")
    print(f"time vs cycles {cycles.tolist()}: {np.round(by_cycles, 2).tolist()} s (slope {sc:.2f})")
    one = load_config(ROOT / "configs" / "fig4a.toml",
                      base + ["experiment.trials=1", "simulation.n_cycles=20"])
    t1 = timed(one, one.experiments[0])["total"]
    n = int(trials[-1])
    print(f"one trial at a time: {t1:.2f} s per trial -> {n * t1:.1f} s for {n} trials vs "
          f"{by_trials[-1]:.1f} s batched ({n * t1 / by_trials[-1]:.1f}x)")


if __name__ == "__main__":
    main()
