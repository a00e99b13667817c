"""Accuracy of the connection estimate: methods x observation noise x 3-, 5- and 9-link.

Recordings from the paper's SDE (α = 0.05, η = 0.025, sampling interval ≈ 0.05) observed with
Gaussian motion-capture noise ω on x, y, θ and every r_i; 4 trials x 30 cycles pooled into one
model. Scored against the swimmer's exact connection on the *fitted* cycle, independently of
the estimator: relative RMS error of ``Â(φ)`` against ``NLinkSwimmer(N).connection(γ̂(φ))``
(and of ``∂Â/∂r`` against the exact Jacobian), plus the scale factor ``s`` of the least-squares fit
``Â ≈ s A`` (1 = no attenuation bias; below 1: Â shrunk towards 0).

Run by hand (minutes on 2 cores)::

    python benchmarks/accuracy.py                 # the full table
    python benchmarks/accuracy.py --links 3 --omega 0 0.005 --methods smoothed

Metric rows (``--metric``): the metric is fitted too and scored by
``benchmarks/metric_accuracy.py``'s own function (M̂γ̇, on-cycle power, full M̂, band coverage).
"""

from __future__ import annotations

import argparse
import math
import time
import warnings

import numpy as np
import torch

from torchconn import (
    ConnectionEstimator,
    NLinkSwimmer,
    NoiseAwareRegression,
    TubeRegression,
    observe,
    simulate,
)
from torchconn.physics.gaits import FourierGait, reference_gait

DT = 0.05
SAMPLES_PER_CYCLE = round(2 * math.pi / DT)  # 126: Δt = 0.0499


def circle_gait(n_links: int, radius: float = 0.9) -> FourierGait:
    """A circle in shape space: a travelling wave ``r_i = ρ cos(φ − 2π i / d)`` (3-link: a circle)."""
    d = n_links - 1
    i = torch.arange(d, dtype=torch.float64)
    lag = 2 * math.pi * i / max(d, 4) if d > 2 else torch.tensor([0.0, math.pi / 2])
    coeffs = torch.zeros(3, d, dtype=torch.float64)
    coeffs[1] = radius * torch.cos(lag)  # cos φ
    coeffs[2] = radius * torch.sin(lag)  # sin φ: cos(φ − lag) = cos φ cos lag + sin φ sin lag
    return FourierGait(coeffs)


def gait_for(n_links: int, kind: str):
    if kind == "circle":
        return circle_gait(n_links)
    if kind == "reference":
        if n_links in (3, 9):
            return reference_gait(f"{n_links}link")
        return circle_gait(n_links, radius=0.7)  # no stored reference: a smaller circle
    raise ValueError(f"gait kind must be 'circle' or 'reference', got {kind!r}")


def recording(n_links: int, gait: str, omega: float, *, n_cycles: int = 30, n_trials: int = 4,
              seed: int = 0, eta: float = 0.025):
    """``n_trials`` noisy recordings of the ``n_links`` swimmer on ``gait``."""
    seeds = np.arange(n_trials) + 1000 * seed
    traj = simulate(NLinkSwimmer(n_links), gait_for(n_links, gait), eta=eta, n_cycles=n_cycles,
                    samples_per_cycle=SAMPLES_PER_CYCLE, seeds=seeds)
    return observe(traj, omega, seeds=seeds)


def connection_errors(model, n_links: int, n_phase: int = 200) -> dict:
    """Errors of a pooled model's ``Â`` and ``∂Â/∂r`` along its fitted cycle."""
    system = NLinkSwimmer(n_links)
    phi = torch.linspace(0, 2 * math.pi, n_phase + 1, dtype=torch.float64)[:-1]
    gamma = model.gamma_at(phi).detach()
    a_true = system.connection(gamma)
    da_true = system.connection_jacobian(gamma)
    a_hat, da_hat = model.connection(phi), model.connection_jacobian(phi)

    def rel(est, true):
        return float((est - true).square().sum().sqrt() / true.square().sum().sqrt())

    scale = float((a_hat * a_true).sum() / a_true.square().sum())
    return {"A": rel(a_hat, a_true), "dA": rel(da_hat, da_true), "scale": scale}


def metric_errors(model, n_links: int) -> dict:
    """The metric rows (M̂γ̇, on-cycle power, full M̂, band coverage) with the metric
    benchmark's own scoring (``benchmarks/metric_accuracy.py``), when the model has a metric."""
    if model.M is None:
        return {}
    from metric_accuracy import score  # beside this file
    return score(model, NLinkSwimmer(n_links))


def run_one(n_links: int, gait: str, omega: float, method: str, *, n_cycles: int = 30,
            seed: int = 0, metric: bool = False) -> dict:
    traj = recording(n_links, gait, omega, n_cycles=n_cycles, seed=seed)
    est = ConnectionEstimator(pool=True, regression=METHODS[method](metric=metric or False))
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if method.endswith("_cv"):
            est.select_complexity(traj)
        else:
            est.fit(traj)
    seconds = time.perf_counter() - start
    return {**connection_errors(est.model_, n_links), **metric_errors(est.model_, n_links),
            "seconds": seconds}


#: the regression stage of each method in the table: "smoothed" is the default TubeRegression
#: (Kalman-smoothed velocities, 48 bins / order 12), "noise_aware" the NoiseAwareRegression
#: (same bins and order), "noise_aware_cv" with ConnectionEstimator.select_complexity
METHODS = {
    "smoothed": TubeRegression,
    "noise_aware": NoiseAwareRegression,
    "noise_aware_cv": NoiseAwareRegression,  # bins, order, ridge by select_complexity
}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5, 9])
    p.add_argument("--omega", type=float, nargs="+", default=[0.0, 0.002, 0.005, 0.01])
    p.add_argument("--gaits", nargs="+", default=["circle", "reference"])
    p.add_argument("--methods", nargs="+", default=list(METHODS))
    p.add_argument("--cycles", type=int, default=30)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--metric", action="store_true",
                   help="also fit the metric and print its rows (M̂γ̇, power, M̂, coverage)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    print(f"{'links':>5} {'gait':>9} {'method':>12} {'omega':>7} {'A err':>8} {'dA err':>8} "
          f"{'scale':>6} {'s/fit':>6}")
    for n in args.links:
        for gait in args.gaits:
            for omega in args.omega:
                for method in args.methods:
                    r = run_one(n, gait, omega, method, n_cycles=args.cycles, seed=args.seed,
                                metric=args.metric)
                    extra = "".join(f" {k} {100 * r[k]:.1f}%" for k in ("Mgd", "power", "M",
                                                                        "coverage") if k in r)
                    print(f"{n:>5} {gait:>9} {method:>12} {omega:>7.3f} {100 * r['A']:>7.2f}% "
                          f"{100 * r['dA']:>7.1f}% {r['scale']:>6.3f} {r['seconds']:>6.2f}"
                          + extra, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
