"""How the connection estimate degrades with few samples per gait cycle.

Sets the sampling-rate warning of the checks before fitting
(``torchconn.io.preflight.MIN_SAMPLES_PER_CYCLE``). For the 3- and 9-link swimmers on their
reference gaits (η = 0.025, ω = 0.002, 3 trials × 20 cycles, two seed sets), the relative RMS
error of the pooled model's Â along its cycle against the swimmer's exact A there, at 8 to 64
samples per cycle. An accuracy study, not a timing: run by hand (about 2 minutes on 2 cores).

    python benchmarks/bench_sampling_rate.py
"""

import math
import warnings

import numpy as np
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, observe, simulate
from torchconn.physics.gaits import reference_gait


def main() -> None:
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")  # no power channel: the metric is not estimated
    phi = torch.linspace(0, 2 * math.pi, 200, dtype=torch.float64)[:-1]
    for n in (3, 9):
        swimmer, gait = NLinkSwimmer(n), reference_gait(f"{n}link")
        for spc in (8, 12, 16, 20, 24, 32, 64):
            errs = []
            for seed in (101, 202):
                seeds = np.array([seed, seed + 1, seed + 2])
                traj = simulate(swimmer, gait, eta=0.025, n_cycles=20, samples_per_cycle=spc,
                                seeds=seeds)
                traj = observe(traj, 0.002, seeds=seeds)
                model = ConnectionEstimator(pool=True).fit(traj).model_
                a_hat, a_true = model.connection(phi), swimmer.connection(model.gamma_at(phi))
                errs.append(float((a_hat - a_true).pow(2).mean().sqrt()
                                  / a_true.pow(2).mean().sqrt()))
            print(f"{n}-link, {spc:3d} samples per cycle: relative RMS error of A on the cycle "
                  f"{np.mean(errs):.3f} (seed sets: {', '.join(f'{e:.3f}' for e in errs)})",
                  flush=True)


if __name__ == "__main__":
    main()
