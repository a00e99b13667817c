"""Batched stochastic rollouts at the paper's 9-link scale vs a per-trial loop of the same code.

Run by hand: ``python benchmarks/bench_rollout.py [--levels 8] [--trials 20] [--cycles 30]
[--loop-trials 4] [--threads N]``.

The batched run simulates ``levels × trials`` cells at once (η scaled by factors 0.25 … 4 of the
paper's 0.025). The loop calls :func:`torchconn.simulation.rollout.simulate` once per trial on the same
seeds; it is timed on the first ``--loop-trials`` trials and extrapolated to all of them (said
so in the output), and its results are compared with the batched cells. Peak memory is the
process's ``ru_maxrss``.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time

import numpy as np
import torch

from torchconn import NLinkSwimmer
from torchconn.physics.gaits import ModalGait, nine_link_modes, reference_gait
from torchconn.simulation.rollout import simulate

ETA, ALPHA = 0.025, 0.05


def nine_link_gait():
    try:
        return reference_gait("9link"), "reference_gait('9link')"
    except (FileNotFoundError, KeyError):
        coeffs = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
        return ModalGait(nine_link_modes(), coeffs), "ModalGait a1 = cos φ, a2 = sin φ"


def peak_mb() -> float:
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024 if sys.platform != "darwin" else kb / 2**20


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--levels", type=int, default=8)
    p.add_argument("--trials", type=int, default=20)
    p.add_argument("--cycles", type=int, default=30)
    p.add_argument("--loop-trials", type=int, default=4)
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    args = p.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)

    system = NLinkSwimmer(9)
    gait, gait_name = nine_link_gait()
    factors = np.geomspace(0.25, 4.0, args.levels)
    eta = torch.tensor(ETA * factors, dtype=torch.float64)[:, None]  # (L, 1)
    seeds = np.random.SeedSequence(20240601).generate_state(args.levels * args.trials)
    seeds = seeds.reshape(args.levels, args.trials)
    n_cells = seeds.size
    kw = dict(alpha=ALPHA, n_cycles=args.cycles)
    print(f"9-link swimmer, gait {gait_name}; {args.levels} noise levels × {args.trials} trials "
          f"× {args.cycles} cycles ({n_cells} cells), 64 samples/cycle, 8 substeps, "
          f"torch threads {torch.get_num_threads()}")
    fine_points = n_cells * args.cycles * 64 * 8

    simulate(system, gait, eta=ETA, n_cycles=1, seeds=[0])  # warm-up
    t0 = time.perf_counter()
    batched = simulate(system, gait, eta=eta, seeds=seeds, **kw)
    t_batched = time.perf_counter() - t0
    mem_batched = peak_mb()
    print(f"batched: {t_batched:.2f} s  ({fine_points / t_batched / 1e6:.2f} M fine steps/s "
          f"over all cells), peak RSS {mem_batched:.0f} MB")

    n_loop = min(args.loop_trials, n_cells)
    cells = [np.unravel_index(i, seeds.shape) for i in
             np.linspace(0, n_cells - 1, n_loop).round().astype(int)]
    t0 = time.perf_counter()
    worst = 0.0
    for lvl, k in cells:
        one = simulate(system, gait, eta=float(eta[lvl, 0]), seeds=int(seeds[lvl, k]), **kw)
        worst = max(worst, float((one.pose - batched.pose[lvl, k]).abs().max()))
    t_loop_part = time.perf_counter() - t0
    t_loop = t_loop_part / n_loop * n_cells
    how = "measured" if n_loop == n_cells else f"extrapolated from {n_loop} trials"
    print(f"per-trial loop: {t_loop_part / n_loop:.2f} s per trial -> {t_loop:.1f} s for "
          f"{n_cells} trials ({how})")
    print(f"speed-up batched / loop: {t_loop / t_batched:.1f}x")
    print(f"max |pose difference| loop vs batched cells: {worst:.1e}")
    print(f"peak RSS (whole process): {peak_mb():.0f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
