"""How the connection estimate degrades with few samples per gait cycle.

Sets the sampling-rate warning of the checks before fitting
(``torchconn.io.preflight.MIN_SAMPLES_PER_CYCLE``). The default estimator
(``ConnectionEstimator(pool=True)``, ``NoiseAwareRegression``) on recordings of the paper's SDE
(η = 0.025, 3 trials × 20 cycles, two seed sets of three trials each), observed with
motion-capture noise ω, at 8 to 64 samples per cycle (the recording's power column dropped).
Per cell: the relative RMS error of the pooled model's Â along its cycle against the swimmer's
exact A there (mean over the seed sets, then each set), and the noise estimate σ̂/ω (the shape
channels' mean estimated standard deviation over ω; at ω = 0 σ̂ itself, with how many seed sets
declared noise). Gaits as in ``benchmarks/accuracy.py`` (``reference``: the 3-/9-link
reference gaits, the 5-link a circle of radius 0.7). An accuracy study, not a timing: run by
hand, one thread (about 2 minutes for the default table on a loaded 2-core machine)::

    python benchmarks/bench_sampling_rate.py
    python benchmarks/bench_sampling_rate.py --links 3 --gaits circle --seeds 303 404
    python benchmarks/bench_sampling_rate.py --links 3 5 --gaits reference circle \
        --spc 12 16 20 32 --noise-floor low_rate   # README "Few samples per cycle"
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import warnings

import numpy as np
import torch
from accuracy import gait_for  # beside this file

from torchconn import ConnectionEstimator, NLinkSwimmer, observe, simulate
from torchconn.regression import NoiseAwareRegression


def cell(n_links: int, gait_kind: str, spc: int, omega: float, seed: int,
         n_cycles: int = 20, trials: int = 3, noise_floor: str = "flat") -> tuple[float, float]:
    """(relative RMS error of Â on the cycle, mean σ̂ of the shape channels) of one pooled fit
    to ``trials`` recordings of seeds ``seed, seed + 1, ...`` (``NoiseAwareRegression``'s
    ``noise_floor``)."""
    swimmer, gait = NLinkSwimmer(n_links), gait_for(n_links, gait_kind)
    seeds = np.arange(seed, seed + trials)
    traj = simulate(swimmer, gait, eta=0.025, n_cycles=n_cycles, samples_per_cycle=spc,
                    seeds=seeds)
    # no power channel: the metric (which needs many more samples) is not fitted
    traj = dataclasses.replace(observe(traj, omega, seeds=seeds), power=None)
    regression = NoiseAwareRegression(noise_floor=noise_floor)
    model = ConnectionEstimator(pool=True, regression=regression).fit(traj).model_
    phi = torch.linspace(0, 2 * math.pi, 200, dtype=torch.float64)[:-1]
    a_hat, a_true = model.connection(phi), swimmer.connection(model.gamma_at(phi))
    err = float((a_hat - a_true).pow(2).mean().sqrt() / a_true.pow(2).mean().sqrt())
    sigma = float(np.mean(model.meta.get("noise_r", [0.0])))
    return err, sigma


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5, 9])
    p.add_argument("--gaits", nargs="+", default=["reference"])
    p.add_argument("--omega", type=float, nargs="+", default=[0.0, 0.002, 0.005])
    p.add_argument("--spc", type=int, nargs="+", default=[8, 10, 12, 16, 20, 24, 32, 64],
                   help="samples per cycle")
    p.add_argument("--seeds", type=int, nargs="+", default=[101, 202])
    p.add_argument("--noise-floor", default="flat", choices=["flat", "low_rate", "normal"],
                   help="NoiseAwareRegression's noise_floor")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    warnings.simplefilter("ignore")  # the sampling-rate warning itself, among others
    print("| gait | samples/cycle | " + " | ".join(f"ω = {w:g}: Â err (seeds); σ̂/ω"
                                                  for w in a.omega) + " |")
    print("|---|---|" + "---|" * len(a.omega))
    for n in a.links:
        for kind in a.gaits:
            for spc in a.spc:
                cols = []
                for w in a.omega:
                    try:
                        res = [cell(n, kind, spc, w, s, noise_floor=a.noise_floor)
                               for s in a.seeds]
                    except ValueError as e:  # e.g. a phase bin with too few samples
                        print(f"  {n}-link {kind}, {spc}, ω = {w:g}: {str(e)[:160]}",
                              flush=True)
                        cols.append("fails")
                        continue
                    errs, sig = [r[0] for r in res], [r[1] for r in res]
                    e = (f"{100 * np.mean(errs):.1f} % ("
                         + " / ".join(f"{100 * x:.1f}" for x in errs) + ")")
                    if w > 0:
                        s = " / ".join(f"{x / w:.2f}" for x in sig)
                    else:
                        s = (f"{max(sig):.1e} ({sum(x > 0 for x in sig)}/{len(sig)} "
                             "declared)")
                    cols.append(f"{e}; {s}")
                print(f"| {n}-link {kind} | {spc} | " + " | ".join(cols) + " |", flush=True)


if __name__ == "__main__":
    main()
