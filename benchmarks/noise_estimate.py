"""Motion-capture noise estimates against the simulator's known ω: the previous estimator and
:func:`torchconn.noise.estimate_noise`, across links, gaits, sampling rates,
recording lengths, noise levels and drop-outs.

Recordings from the paper's SDE (α = 0.05, η = 0.025; ``benchmarks/accuracy.py``'s gaits)
observed with Gaussian noise ω on x, y, θ and every r_i. Per cell the table prints, over the
joint angles of every trial (``mean [min-max]``):

- ``old ω̂/ω``: the previous estimator (a plain periodogram's line fitted above the 6th harmonic,
  ``6 / samples per cycle`` within [0.1, 0.3], unweighted), kept here as the reference, per
  joint the root of its (clamped) variance averaged over the trials;
- ``flat ω̂/ω``: :func:`estimate_noise` with a flat process floor (multitaper, Whittle fit,
  band from the data; ``NoiseAwareRegression``'s default, ``noise_floor="flat"``), per
  joint the root of its unclamped ``variance`` averaged over the trials;
- ``new ω̂/ω``: the same with the floor shaped by the gait (:func:`phase_noise_floor`, from
  each trial's cycle and phase rate as ``ConnectionEstimator`` estimates them: what
  ``NoiseAwareRegression(noise_floor="low_rate")`` uses at 32 or fewer samples per cycle);
- ``rig ω̂/ω``: the new estimate's ``pooled_variance`` over the trials and joints (what
  ``NoiseAwareRegression(noise_floor="low_rate")`` corrects for when pooling: zeroed where not 2
  standard errors above 0, the joints' estimates correlated by their shared phase noise);
- ``z sd``: the spread of the new ``(σ̂² − ω²) / variance_se`` over joints and trials (1 =
  honest standard errors);
- ``pose``: new ω̂/ω on x, y, θ;
- ``floor``: the fitted process floor over its closed form ``η √Δt √(1 + ⟨γ'_i(φ)²⟩)`` (the
  shape offset's increments plus the phase noise's, ``γ'`` of the reference gait), mean over
  the joints;
- ``ms``: milliseconds of one new :func:`estimate_noise` call on the cell's joints, and ``t/old``
  its ratio to the previous estimator on the same input (a single plain periodogram).

A last line sums up the standard errors' calibration over every joint estimate at ω > 0
(new, and flat in brackets).

At ω = 0 the ratios are replaced by ``ω̂`` itself (rad) and ``rig`` by the fraction of joints
whose pooled variance is not zeroed (0 = nothing corrected on clean data).

The estimator's band rule (``_BAND_Z``) was set on seeds 0-1 (9-link reference gait, 64
samples per cycle) and on random walks, the gait-shaped floor checked on seeds 5-6; the
default seed here is 2. Run by hand::

    python benchmarks/noise_estimate.py                       # the default grid, seed 2
    python benchmarks/noise_estimate.py --links 9 --gaits reference --per-cycle 64 --seed 3
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
from accuracy import gait_for  # beside this file

from torchconn import NLinkSwimmer, observe, simulate
from torchconn.noise import estimate_noise
from torchconn.phase.limit_cycle import phase_rate
from torchconn.regression import ConnectionEstimator
from torchconn.regression.estimator import prepare

ETA = 0.025
#: recording lengths: (trials, cycles)
LENGTHS = {"1x10": (1, 10), "4x30": (4, 30)}


def old_estimate(x: torch.Tensor, samples_per_cycle: float) -> torch.Tensor:
    """The previous estimator's measurement standard deviation ``(..., C)`` (reference only):
    an unweighted line of the increments' plain periodogram against ``4 sin²(πf)`` over
    ``[6 / samples per cycle (within [0.1, 0.3]), 0.5]``."""
    lo = min(max(6 / samples_per_cycle, 0.1), 0.3)
    n = x.shape[-2] - 1
    u = torch.diff(x, dim=-2)
    finite = torch.isfinite(u)
    frac = finite.to(x.dtype).mean(-2, keepdim=True).clamp_min(1e-12)
    u = torch.where(finite, u, 0.0)
    u = torch.where(finite, u - u.sum(-2, keepdim=True) / (frac * n), 0.0)
    power = torch.fft.rfft(u, dim=-2).abs().square() / (frac * n)
    f = torch.fft.rfftfreq(n, dtype=x.dtype)
    keep = f >= lo
    z = 4 * torch.sin(math.pi * f[keep]).square()
    p = power[..., keep, :]
    zc = z - z.mean()
    slope = (zc[:, None] * p).sum(-2) / zc.square().sum()
    return slope.clamp_min(0).sqrt()


def floor_truth(gait, dt: float) -> torch.Tensor:
    """``(d,)`` closed-form process floor ``η √Δt √(1 + ⟨γ'_i²⟩)`` of the joint increments:
    the shape offset's ``η dW`` plus the phase noise ``η dW_φ`` carried by the gait's slope."""
    phi = torch.linspace(0, 2 * math.pi, 4097, dtype=torch.float64)[:-1]
    h = 1e-5
    slope = (gait(phi + h) - gait(phi - h)) / (2 * h)  # (P, d)
    return ETA * math.sqrt(dt) * (1 + slope.square().mean(0)).sqrt()


def _range(x: torch.Tensor, fmt: str = "{:.2f}") -> str:
    x = x.flatten()
    x = x[torch.isfinite(x)]
    if x.numel() == 0:
        return "-"
    return (fmt.format(float(x.mean())) + " [" + fmt.format(float(x.min())) + "-"
            + fmt.format(float(x.max())) + "]")


#: every (σ̂² − ω²) / SE of the run's joints at ω > 0, for the calibration summary (new, flat)
Z_ALL: list[torch.Tensor] = []
Z_FLAT: list[torch.Tensor] = []


def gait_noise(traj):
    """:func:`estimate_noise` of ``traj.r`` with the floor of each trial's own estimated cycle
    and samples per cycle (as ``NoiseAwareRegression`` unpooled)."""
    prep = prepare(traj)
    cycle = ConnectionEstimator().cycle.fit(prep, pool=False)
    per_cycle = 2 * math.pi / (phase_rate(prep.phase, traj.dt) * traj.dt)
    return estimate_noise(traj.r, cycle=cycle.gamma, samples_per_cycle=per_cycle,
                          floor="low_rate")


def run_cell(n_links: int, gait: str, per_cycle: int, length: str, omegas, *, seed: int,
             dropout: float) -> list[str]:
    n_trials, n_cycles = LENGTHS[length]
    seeds = np.arange(n_trials) + 1000 * seed
    g = gait_for(n_links, gait)
    clean = simulate(NLinkSwimmer(n_links), g, eta=ETA, n_cycles=n_cycles,
                     samples_per_cycle=per_cycle, seeds=seeds)
    floor = floor_truth(g, clean.dt)
    rate = float(phase_rate(clean.truth.phase, clean.dt).mean())
    spc = 2 * math.pi / (rate * clean.dt)
    rows = []
    for omega in omegas:
        traj = observe(clean, omega, seeds=seeds, dropout=dropout)
        flat = estimate_noise(traj.r)
        start = time.perf_counter()
        new = gait_noise(traj)
        seconds = time.perf_counter() - start
        start = time.perf_counter()
        old = old_estimate(traj.r, spc)
        old_seconds = time.perf_counter() - start
        pose = estimate_noise(traj.pose, angular=torch.tensor([False, False, True]))
        rig = new.pooled_variance(1, channels=True)
        scale, fmt = (omega, "{:.2f}") if omega > 0 else (1.0, "{:.4f}")
        o = _range(old.square().mean(0).sqrt() / scale, fmt)
        fl = _range(flat.variance.mean(0).clamp_min(0).sqrt() / scale, fmt)
        nw = _range(new.variance.mean(0).clamp_min(0).sqrt() / scale, fmt)
        ps = _range(pose.measurement / scale, fmt)
        if omega > 0:
            rg = f"{float(rig.mean().sqrt()) / omega:.2f}"
        else:
            rg = f"{float((rig > 0).to(torch.float64).mean()):.2f}"
        z = (new.variance - omega**2) / new.variance_se
        if omega > 0:
            Z_ALL.append(z.flatten())
            Z_FLAT.append(((flat.variance - omega**2) / flat.variance_se).flatten())
        fr = float((new.process / floor).mean())
        rows.append(f"{n_links:>5} {gait:>9} {per_cycle:>4} {length:>5} {dropout:>4.2f} "
                    f"{omega:>6.3f} {o:>20} {fl:>20} {nw:>20} {rg:>6} {float(z.std()):>5.2f} "
                    f"{ps:>20} {fr:>5.2f} {1000 * seconds:>6.1f} "
                    f"{seconds / max(old_seconds, 1e-9):>6.0f}")
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5, 9])
    p.add_argument("--gaits", nargs="+", default=["circle", "reference"])
    p.add_argument("--per-cycle", type=int, nargs="+", default=[64, 126, 300])
    p.add_argument("--lengths", nargs="+", default=list(LENGTHS), choices=list(LENGTHS))
    p.add_argument("--omega", type=float, nargs="+",
                   default=[0.0, 0.001, 0.002, 0.005, 0.01, 0.02])
    p.add_argument("--dropout", type=float, nargs="+", default=[0.0])
    p.add_argument("--seed", type=int, default=2)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    print(f"{'links':>5} {'gait':>9} {'spc':>4} {'len':>5} {'drop':>4} {'omega':>6} "
          f"{'old w/omega':>20} {'flat w/omega':>20} {'new w/omega':>20} {'rig':>6} {'z sd':>5} "
          f"{'pose flat':>20} "
          f"{'floor':>5} {'ms':>6} {'t/old':>6}")
    for n in args.links:
        for gait in args.gaits:
            for spc in args.per_cycle:
                for length in args.lengths:
                    for drop in args.dropout:
                        for row in run_cell(n, gait, spc, length, args.omega, seed=args.seed,
                                            dropout=drop):
                            print(row, flush=True)
    if Z_ALL:
        z, zf = torch.cat(Z_ALL), torch.cat(Z_FLAT)
        print(f"calibration over {z.numel()} joint estimates at ω > 0: (σ̂² − ω²)/SE has mean "
              f"{float(z.mean()):.2f} ({float(zf.mean()):.2f}), sd {float(z.std()):.2f} "
              f"({float(zf.std()):.2f}), |z| > 2 in "
              f"{100 * float((z.abs() > 2).to(torch.float64).mean()):.1f} % "
              f"({100 * float((zf.abs() > 2).to(torch.float64).mean()):.1f} %) "
              f"(normal: 0, 1, 4.6 %)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
