"""Â's harmonic shrink for one model per trial (``NoiseAwareRegression(resolved_harmonics=
"per_trial")``) against the plain series of the same bins (the default for unpooled fits).

One model per trial of ``--cycles`` cycles at 64 samples per cycle (the sweep's setting),
recordings as ``accuracy.py``'s (``recording``: trials ``1000 · seed + i``), scored as there:
relative RMS error of ``Â(φ)`` along the fitted cycle against the exact connection. The bins
are fitted once with the option; the plain series is the order-12 least-squares series of those
bins (what the default returns, bit for bit). Prints the mean over all trials and seeds per
cell, plain → shrunk, and how many one-trial fits got worse.

Run by hand (about a minute on one core for the defaults)::

    PYTHONPATH=. python benchmarks/trial_shrink.py --threads 1
"""
import argparse
import dataclasses
import itertools
import sys
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from accuracy import connection_errors, recording  # noqa: E402

from torchconn import ConnectionEstimator, NoiseAwareRegression  # noqa: E402
from torchconn.phase.fourier import fit_fourier  # noqa: E402


def errors(links: int, gait: str, omega: float, seed: int, trials: int, cycles: int):
    """Â's error ``(trials,)`` per one-trial fit: plain series, shrunk series."""
    traj = recording(links, gait, omega, n_cycles=cycles, seed=seed, n_trials=trials,
                     samples_per_cycle=64)
    est = ConnectionEstimator(pool=False, regression=NoiseAwareRegression(
        metric=False, resolved_harmonics="per_trial"), complexity="fixed", held_out_folds=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(traj)
    shrunk = est.model_
    plain = dataclasses.replace(shrunk, A=fit_fourier(shrunk.bins.phase, shrunk.bins.A,
                                                      shrunk.A.order, value_ndim=2))
    return connection_errors(plain, links)["A"], connection_errors(shrunk, links)["A"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5])
    p.add_argument("--gaits", nargs="+", default=["circle", "reference"])
    p.add_argument("--omega", type=float, nargs="+", default=[0.0, 0.002, 0.005, 0.01])
    p.add_argument("--seeds", type=int, nargs="+", default=[3, 4, 7, 8])
    p.add_argument("--trials", type=int, default=4)
    p.add_argument("--cycles", type=int, default=30)
    p.add_argument("--threads", type=int, default=None)
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    print("| links | gait | ω | Â plain → shrunk | fits worse |")
    print("|---|---|---|---|---|")
    for links, gait, omega in itertools.product(args.links, args.gaits, args.omega):
        pairs = [errors(links, gait, omega, s, args.trials, args.cycles) for s in args.seeds]
        plain = torch.cat([a.reshape(-1) for a, _ in pairs])
        shrunk = torch.cat([b.reshape(-1) for _, b in pairs])
        print(f"| {links} | {gait} | {omega:g} | {100 * float(plain.mean()):.2f} → "
              f"{100 * float(shrunk.mean()):.2f} % | {int((shrunk > plain).sum())} of "
              f"{plain.numel()} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
