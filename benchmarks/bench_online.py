"""Benchmark: one cycle added to :class:`~torchconn.regression.online.OnlineConnection` against
refitting every cycle so far (:func:`~torchconn.regression.connection_regression`).

The swimmer records ``--trials`` trials of ``--cycles`` cycles (true phase, shapes and body
velocities, η = 0.025) of the loop's start gait; the statistics pool the trials and take one
cycle (64 samples) of every trial per update. Per cycle it prints the time of the update (including its
confidence and the solve after it), the time of a batch refit of every cycle so far (with standard errors, as
the update gives them), the
largest relative difference of their per-bin coefficients, and the confidence
(predictive ``R²`` of the new cycle, relative standard error of ``∂Â/∂r``).

    python benchmarks/bench_online.py [--links 3] [--trials 4] [--cycles 20] [--bins 48]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from torchconn import NLinkSwimmer, simulate
from torchconn.improve.loop import circle_gait
from torchconn.phase.fourier import FourierSeries
from torchconn.regression import assign_bins, connection_regression
from torchconn.regression.online import OnlineConnection


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--links", type=int, default=3)
    parser.add_argument("--trials", type=int, default=4)
    parser.add_argument("--cycles", type=int, default=20)
    parser.add_argument("--bins", type=int, default=48)
    parser.add_argument("--window", type=float, default=2.0)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    gait = circle_gait(args.links - 1)
    traj = simulate(NLinkSwimmer(args.links), gait, eta=0.025, n_cycles=args.cycles,
                    samples_per_cycle=64, seeds=np.arange(args.trials))
    truth = traj.truth
    spc = 64  # samples per cycle: cycle c is the samples [64c, 64(c + 1))
    online = OnlineConnection(FourierSeries(gait.coeffs, 1), 1.0, n_bins=args.bins,
                              window=args.window, fourier_order=min(12, (args.bins - 1) // 2))
    d = args.links - 1
    print(f"links={args.links} d={d} P={1 + 2 * d + d * d} bins={args.bins} "
          f"window={args.window} trials={args.trials}")
    print("cycle  update_ms  refit_ms  max_rel_diff  r2_mean  dA_rel_se")
    for c in range(args.cycles):
        now = slice(spc * c, spc * (c + 1))
        samples = tuple(x[:, now] for x in (truth.phase, truth.r, truth.r_dot, truth.xi))
        t0 = time.perf_counter()
        conf = online.update(*samples)
        coef = online.fit().coef
        t1 = time.perf_counter()
        so_far = slice(0, spc * (c + 1))
        phase = truth.phase[:, so_far].reshape(-1)
        bins = assign_bins(phase, args.bins, window=args.window, kernel="tricube")
        batch = connection_regression(
            *(x[:, so_far].reshape(-1, x.shape[-1]) for x in (truth.r, truth.r_dot, truth.xi)),
            bins, online.gamma_m, online.gamma_dot_m, on_ill_conditioned="warn",
        ) if bool(conf.fitted_bins == args.bins) else None
        t2 = time.perf_counter()
        if batch is None:
            diff, refit = float("nan"), float("nan")
        else:
            err = (coef - batch.coef).flatten(-2).norm(dim=-1)
            diff = float((err / batch.coef.flatten(-2).norm(dim=-1)).max())
            refit = 1e3 * (t2 - t1)
        print(f"{c + 1:5d}  {1e3 * (t1 - t0):9.1f}  {refit:8.1f}  {diff:12.2e}  "
              f"{float(conf.score):7.5f}  {float(conf.dA_relative_se):9.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
