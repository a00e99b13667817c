"""Accuracy of the connection estimate: methods x observation noise x 3-, 5- and 9-link.

Recordings from the paper's SDE (α = 0.05, η = 0.025) observed with Gaussian motion-capture
noise ω on x, y, θ and every r_i, in two settings: ``pooled`` (4 trials x 30 cycles at
Δt ≈ 0.05, 126 samples per cycle, pooled into one model) and ``single`` (the sweep's setting:
one model per trial of 30 cycles at 64 samples per cycle, 3 trials, mean and range reported).
Scored against the swimmer's exact connection on the *fitted* cycle, independently of the
estimator: relative RMS error of ``Â(φ)`` against ``NLinkSwimmer(N).connection(γ̂(φ))`` (and of
``∂Â/∂r`` against the exact Jacobian, and its bands: the squared error at the bin centres
over the squared standard errors, ``dA e²/se²``, 1 for honest bands), plus the scale factor
``s`` of the least-squares fit ``Â ≈ s A`` (1 = no attenuation bias; below 1: Â shrunk
towards 0).

Methods: ``tube`` = ``TubeRegression()`` (the default: Kalman-smoothed velocities);
``noise_aware`` = ``NoiseAwareRegression()`` (the noise-corrected estimate shrunk towards the
smoothed one where the data cannot support the correction);
``noise_aware_low_rate`` = ``NoiseAwareRegression(noise_floor="low_rate")`` (the noise fit's
floor shaped by the gait where it has few samples per cycle);
``noise_aware_normal`` = ``NoiseAwareRegression(noise_floor="normal")`` (the noise fitted on the
joint increments projected out of the cycle's first derivatives; 5- and 9-link only, the
3-link's is the default's bit for bit);
``noise_aware_cv`` = the default with ``ConnectionEstimator.select_complexity``.

Run by hand (minutes on 2 cores)::

    python benchmarks/accuracy.py                 # the full table, seed 0
    python benchmarks/accuracy.py --links 3 --omega 0 0.005 --methods tube noise_aware

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
from torchconn.regression.metric import TiedMetric

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


#: the two settings: (trials, samples per cycle, pooled into one model)
SETTINGS = {"pooled": (4, SAMPLES_PER_CYCLE, True), "single": (3, 64, False)}


def recording(n_links: int, gait: str, omega: float, *, n_cycles: int = 30, n_trials: int = 4,
              seed: int = 0, eta: float = 0.025, samples_per_cycle: int = SAMPLES_PER_CYCLE):
    """``n_trials`` noisy recordings of the ``n_links`` swimmer on ``gait``."""
    seeds = np.arange(n_trials) + 1000 * seed
    traj = simulate(NLinkSwimmer(n_links), gait_for(n_links, gait), eta=eta, n_cycles=n_cycles,
                    samples_per_cycle=samples_per_cycle, seeds=seeds)
    return observe(traj, omega, seeds=seeds)


def connection_errors(model, n_links: int, n_phase: int = 200) -> dict:
    """Errors of a model's ``Â`` and ``∂Â/∂r`` along its fitted cycle: ``(...)`` tensors, one
    per batch element (a pooled model: scalars)."""
    system = NLinkSwimmer(n_links)
    phi = torch.linspace(0, 2 * math.pi, n_phase + 1, dtype=torch.float64)[:-1]
    phi = phi.expand(tuple(model.batch_shape) + (n_phase,))
    gamma = model.gamma_at(phi).detach()
    a_true = system.connection(gamma)
    da_true = system.connection_jacobian(gamma)
    a_hat, da_hat = model.connection(phi), model.connection_jacobian(phi)

    def rel(est, true):
        dims = tuple(range(-true.ndim + len(model.batch_shape), 0))
        return (est - true).square().sum(dims).sqrt() / true.square().sum(dims).sqrt()

    dims = (-3, -2, -1)
    scale = (a_hat * a_true).sum(dims) / a_true.square().sum(dims)
    # the bands of ∂Â/∂r: squared error over squared standard error at the bin centres
    bins = model.bins
    da_bins = system.connection_jacobian(bins.gamma)
    bin_dims = (-4, -3, -2, -1)
    coverage = ((bins.dA - da_bins).square().nansum(bin_dims)
                / bins.dA_se.square().nansum(bin_dims))
    return {"A": rel(a_hat, a_true), "dA": rel(da_hat, da_true), "scale": scale,
            "dA_coverage": coverage}


def metric_errors(model, n_links: int) -> dict:
    """The metric rows (M̂γ̇, on-cycle power, full M̂, band coverage) with the metric
    benchmark's own scoring (``benchmarks/metric_accuracy.py``), when the model has a metric."""
    if model.M is None:
        return {}
    from metric_accuracy import score  # beside this file
    return score(model, NLinkSwimmer(n_links))


def run_one(n_links: int, gait: str, omega: float, method: str, *, n_cycles: int = 30,
            seed: int = 0, metric: bool = False, setting: str = "pooled") -> dict:
    n_trials, per_cycle, pool = SETTINGS[setting]
    traj = recording(n_links, gait, omega, n_cycles=n_cycles, seed=seed, n_trials=n_trials,
                     samples_per_cycle=per_cycle)
    # the table's complexity is fixed (48 bins, order 12), the fit's own held-out check off
    est = ConnectionEstimator(pool=pool, regression=METHODS[method],
                              metric=TiedMetric(enabled=bool(metric)), complexity="fixed",
                              held_out_folds=0)
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if method.endswith("_cv"):
            est.select_complexity(traj)
        else:
            est.fit(traj)
    seconds = (time.perf_counter() - start) / (1 if pool else n_trials)
    extra = metric_errors(est.model_, n_links) if pool else {}
    return {**connection_errors(est.model_, n_links), **extra, "seconds": seconds}


#: the regression stage of each method in the table (see the module's docstring)
METHODS = {
    "tube": TubeRegression(),
    "noise_aware": NoiseAwareRegression(),
    "noise_aware_low_rate": NoiseAwareRegression(noise_floor="low_rate"),
    "noise_aware_normal": NoiseAwareRegression(noise_floor="normal"),
    "noise_aware_cv": NoiseAwareRegression(),  # bins, order, ridge by select_complexity
}

#: issue 12's targets for Â (pooled 4 x 30 cycles, 3- and 5-link), by ω
TARGETS = {0.0: 0.003, 0.002: 0.03, 0.005: 0.07, 0.01: 0.15}


def _pct(x) -> str:
    """A batch of errors as ``mean [min-max]`` in %, a scalar as a number."""
    x = torch.as_tensor(x) * 100
    if x.ndim == 0:
        return f"{float(x):.2f}%"
    return f"{float(x.mean()):.1f}% [{float(x.min()):.0f}-{float(x.max()):.0f}]"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5, 9])
    p.add_argument("--omega", type=float, nargs="+",
                   default=[0.0, 0.002, 0.005, 0.01, 0.02, 0.04])
    p.add_argument("--gaits", nargs="+", default=["circle", "reference"])
    p.add_argument("--methods", nargs="+", default=["tube", "noise_aware"],
                   choices=list(METHODS))
    p.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    p.add_argument("--cycles", type=int, default=30)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--metric", action="store_true",
                   help="also fit the metric and print its rows (M̂γ̇, power, M̂, coverage; "
                   "pooled only)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    print("targets for Â (pooled, 3-/5-link): "
          + ", ".join(f"ω = {k:g}: ≤ {100 * v:g} %" for k, v in TARGETS.items()))
    print(f"{'links':>5} {'gait':>9} {'setting':>7} {'method':>14} {'omega':>6} "
          f"{'A err':>16} {'dA err':>16} {'scale':>6} {'s/fit':>6} {'vs tube':>8} {'dA e²/se²':>9}")
    for n in args.links:
        for gait in args.gaits:
            for setting in args.settings:
                for omega in args.omega:
                    ref = None
                    for method in args.methods:
                        r = run_one(n, gait, omega, method, n_cycles=args.cycles,
                                    seed=args.seed, metric=args.metric, setting=setting)
                        err = float(torch.as_tensor(r["A"]).mean())
                        ref = err if method == "tube" else ref
                        ratio = f"{err / ref:8.2f}" if ref else f"{'':>8}"
                        extra = "".join(f" {k} {100 * r[k]:.1f}%"
                                        for k in ("Mgd", "power", "M", "coverage") if k in r)
                        print(f"{n:>5} {gait:>9} {setting:>7} {method:>14} {omega:>6.3f} "
                              f"{_pct(r['A']):>16} {_pct(r['dA']):>16} "
                              f"{float(torch.as_tensor(r['scale']).mean()):>6.3f} "
                              f"{r['seconds']:>6.2f} {ratio} "
                              f"{float(torch.as_tensor(r['dA_coverage']).mean()):>9.2f}" + extra,
                              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
