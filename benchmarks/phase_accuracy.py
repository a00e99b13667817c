"""Phase accuracy: channel weighting and correction order, before and after.

Phaser (``torchconn.phase.phaser``) on the shapes the estimator phases (``RTSSmoother``'s
smoothed ``r``) of recordings from the paper's SDE (α = 0.05, η = 0.025, sampling interval
≈ 0.05, 4 trials x 30 cycles per recording), observed with Gaussian motion-capture noise ω on
x, y, θ and every r_i. Scored against the simulator's true phase ``truth.phase``: circular RMS
error after removing the constant offset (:func:`~torchconn.phase.phaser.circular_rms`), mean
over trials and seeds. Plus two synthetic cases with a known phase:

- *harmonic mixture*: ``x, y, xy, x² − y²`` of a circle (the fundamental and its second
  harmonic), phase diffusion 0.05, observation noise 0.01, 20 cycles;
- *mixed SNR*: one good channel (noise 0.02) and four noisy ones (noise 0.3) of a
  non-uniformly traversed cycle, phase diffusion 0.025, 30 cycles.

Methods: ``coherence/3`` (torchconn 0.1: unit phasors through the coherence matrix's leading
eigenvector, order 3), ``coherence/6``, ``snr/3`` (channels weighted by their phase SNR),
``coherence/auto`` and ``snr/auto`` (order chosen by cross-validation over whole cycles; the
default). The ``coherence`` methods run :func:`~torchconn.phase.phaser.estimate_phase` with
``weighting="coherence"`` (no longer a :class:`Phaser` option; their ``[K]`` is not shown).
``t/t0`` is the phaser's time relative to ``coherence/3`` on the same inputs (the smoother and
simulator are not timed).

Run by hand (several minutes on 2 cores)::

    python benchmarks/phase_accuracy.py                     # report seeds 2-4
    python benchmarks/phase_accuracy.py --seeds 0 1         # the seeds the rules were set on
    python benchmarks/phase_accuracy.py --links 9 --omega 0 0.01
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import SAMPLES_PER_CYCLE, gait_for  # noqa: E402  (the connection benchmark's gaits)

from torchconn import NLinkSwimmer, Phaser, RTSSmoother, observe, simulate  # noqa: E402
from torchconn.phase.phaser import (  # noqa: E402
    PhaseAmbiguityWarning,
    circular_rms,
    estimate_phase,
)


def _phaser(order):
    """The Phaser stage: the phase and the mean chosen order of the combined phase."""
    def run(x):
        fitted = Phaser(order=order).fit(x)
        return fitted.phase_, fitted.model_.order.double().mean().item()
    return run


def _coherence(order):
    """torchconn 0.1's unit-phasor weighting (``estimate_phase(weighting="coherence")``)."""
    return lambda x: (estimate_phase(x, order=order, weighting="coherence"), math.nan)


METHODS = {
    "coherence/3": _coherence(3),
    "coherence/6": _coherence(6),
    "snr/3": _phaser(3),
    "coherence/auto": _coherence("auto"),
    "snr/auto": _phaser("auto"),
}


def score(x: torch.Tensor, truth: torch.Tensor) -> dict:
    """Per method: circular RMS error ``(trials,)``, seconds, mean chosen combined order."""
    out = {}
    for name, phaser in METHODS.items():
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PhaseAmbiguityWarning)
            phase, order = phaser(x)
        seconds = time.perf_counter() - t0
        out[name] = (circular_rms(phase, truth).reshape(-1), seconds, order)
    return out


def swimmer_cases(links, gaits, omegas, seeds, n_cycles):
    for n in links:
        for gait in gaits:
            for seed in seeds:
                trial_seeds = np.arange(4) + 1000 * seed
                traj = simulate(NLinkSwimmer(n), gait_for(n, gait), eta=0.025, n_cycles=n_cycles,
                                samples_per_cycle=SAMPLES_PER_CYCLE, seeds=trial_seeds)
                for omega in omegas:
                    obs = observe(traj, omega, seeds=trial_seeds)
                    r = RTSSmoother().smooth(obs).smoothed.r
                    yield (f"{n}-link {gait}", omega), score(r, traj.truth.phase)


def _diffusing_phase(trials, T, step, eta, gen):
    walk = torch.cumsum(torch.randn(trials, T, generator=gen, dtype=torch.float64), -1)
    return torch.arange(T, dtype=torch.float64) * step + eta * math.sqrt(step) * walk


def harmonic_mixture(seed: int, trials: int = 4):
    """``x, y, xy, x² − y²`` of a circle: true phase ``(trials, T)`` and record."""
    gen = torch.Generator().manual_seed(seed)
    spc, cycles = 126, 20
    phi = _diffusing_phase(trials, spc * cycles, 2 * math.pi / spc, 0.05, gen)
    x, y = torch.cos(phi), torch.sin(phi)
    clean = torch.stack([x, y, x * y, x * x - y * y], -1)
    return phi, clean + 0.01 * torch.randn(clean.shape, generator=gen, dtype=torch.float64)


def mixed_snr(seed: int, trials: int = 4):
    """One good channel and four noisy ones of a non-uniformly traversed cycle."""
    gen = torch.Generator().manual_seed(seed)
    spc, cycles = 100, 30
    phi = _diffusing_phase(trials, spc * cycles, 2 * math.pi / spc, 0.025, gen)
    p = phi + 0.3 * torch.sin(phi)  # the cycle is traversed at a non-uniform speed
    clean = torch.stack([torch.cos(p + a) + 0.2 * torch.cos(2 * p + a)
                         for a in (0.0, 0.7, 1.9, 3.0, 4.4)], -1)
    noise = torch.tensor([0.02, 0.3, 0.3, 0.3, 0.3], dtype=torch.float64)
    return phi, clean + noise * torch.randn(clean.shape, generator=gen, dtype=torch.float64)


def synthetic_cases(seeds):
    for name, make in (("harmonic mixture", harmonic_mixture), ("mixed SNR", mixed_snr)):
        for seed in seeds:
            phi, x = make(seed)
            yield (name, None), score(x, phi)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5, 9])
    p.add_argument("--gaits", nargs="+", default=["circle", "reference"])
    p.add_argument("--omega", type=float, nargs="+", default=[0.0, 0.002, 0.005, 0.01, 0.04])
    p.add_argument("--seeds", type=int, nargs="+", default=[2, 3, 4])
    p.add_argument("--cycles", type=int, default=30)
    p.add_argument("--no-synthetic", action="store_true")
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    rows: dict = {}
    cases = swimmer_cases(args.links, args.gaits, args.omega, args.seeds, args.cycles)
    if not args.no_synthetic:
        cases = (*cases, *synthetic_cases(args.seeds))
    for key, result in cases:
        for name, (err, seconds, order) in result.items():
            acc = rows.setdefault(key, {}).setdefault(name, [[], [], []])
            acc[0].append(err)
            acc[1].append(seconds)
            acc[2].append(order)

    names = list(METHODS)
    print(f"circular RMS phase error (rad), mean over 4 trials x seeds {args.seeds}; "
          "[K] = mean chosen order of the combined phase")
    print(f"{'case':<20} {'omega':>6} " + " ".join(f"{n:>15}" for n in names)
          + "  after/before  t/t0 (snr/auto)")
    worst = 0.0
    for (case, omega), by in rows.items():
        means = {n: torch.cat(by[n][0]).mean().item() for n in names}
        cells = []
        for n in names:
            cell = f"{means[n]:.4f}"
            if n.endswith("auto"):
                cell += f" [{np.mean(by[n][2]):.1f}]"
            cells.append(f"{cell:>15}")
        ratio = means["snr/auto"] / means["coherence/3"]
        worst = max(worst, ratio)
        t_ratio = sum(by["snr/auto"][1]) / sum(by["coherence/3"][1])
        om = "" if omega is None else f"{omega:g}"
        print(f"{case:<20} {om:>6} " + " ".join(cells) + f"  {ratio:12.3f}  {t_ratio:4.1f}")
    print(f"worst after/before ratio: {worst:.3f}")


if __name__ == "__main__":
    main()
