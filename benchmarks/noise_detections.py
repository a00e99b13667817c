"""How often the noise test calls recordings noisy: clean recordings (false detections) and
recordings at a given ω (detections, and the level found): flat floor, low-rate gait-shaped floor and
the increments projected out of the cycle's first derivatives at each sample's estimated phase
(``normal``; the 3-link's is ``flat``'s, :func:`~torchconn.noise.normal_span`).

Recordings from the paper's SDE (α = 0.05, η = 0.025; ``benchmarks/accuracy.py``'s gaits),
``R`` recordings per cell, each either ``pooled`` (4 trials × 30 cycles) or ``single`` (one
trial of 10 cycles). Per trial :func:`torchconn.noise.estimate_noise` runs on
the joint angles with the trial's estimated cycle and samples per cycle (as
``benchmarks/noise_estimate.py``'s gait column); per recording the joints' mean ``σ̂²`` over
its trials is tested against 2 standard errors with the joints' correlation
(:meth:`NoiseEstimate.pooled_mean`, what ``NoiseAwareRegression`` corrects for). Per cell and
floor the table prints the recordings called noisy, the mean and spread of that test's ``z``
(near 0 and 1 on clean data for an unbiased, honest estimate) and, at ω > 0, ``√(mean σ̂²)/ω``
over the cell's recordings and how many recordings are within 20 % of ω.

Recording ``r``'s trial ``i`` has seed ``1000 (first + r) + i + 7``. Run by hand::

    python benchmarks/noise_detections.py --first 60 --recordings 20          # clean, all cells
    python benchmarks/noise_detections.py --omega 0.002 --first 100 --links 3 9 --gaits reference
    python benchmarks/noise_detections.py --first 80 --links 9 --floors normal normal@0.05
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch
from accuracy import gait_for  # beside this file

from torchconn import ConnectionEstimator, NLinkSwimmer, observe, simulate
from torchconn.noise import NoiseEstimate, estimate_noise
from torchconn.phase.limit_cycle import phase_rate
from torchconn.regression.estimator import prepare

ETA = 0.025
#: recording kinds: (trials, cycles)
KINDS = {"pooled": (4, 30), "single": (1, 10)}
#: NoiseEstimate fields with a leading batch dim
_FIELDS = ("measurement", "process", "variance_se", "band_low", "variance", "correlation")


def recording_seeds(first: int, n_recordings: int, n_trials: int) -> np.ndarray:
    """``(n_recordings * n_trials,)`` seeds, recording-major."""
    r = np.arange(n_recordings)[:, None] + first
    return (1000 * r + np.arange(n_trials)[None, :] + 7).reshape(-1)


def recording_z(est: NoiseEstimate, n_recordings: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R,)`` mean ``σ̂²`` over each recording's trials and joints, and its standard error,
    from per-trial estimates ``(R * trials, d)``."""
    def by_trial(x: torch.Tensor) -> torch.Tensor:  # (R * trials, ...) -> (trials, R, ...)
        return x.reshape((n_recordings, -1) + tuple(x.shape[1:])).transpose(0, 1)

    est = NoiseEstimate(**{name: by_trial(getattr(est, name)) for name in _FIELDS})
    mean, se = est.pooled_mean(1, channels=True)
    return mean[:, 0], se[:, 0]


def run_cell(n_links: int, gait: str, per_cycle: int, kind: str, omega: float, floors,
             *, first: int, n_recordings: int) -> str:
    n_trials, n_cycles = KINDS[kind]
    seeds = recording_seeds(first, n_recordings, n_trials)
    clean = simulate(NLinkSwimmer(n_links), gait_for(n_links, gait), eta=ETA,
                     n_cycles=n_cycles, samples_per_cycle=per_cycle, seeds=seeds)
    traj = observe(clean, omega, seeds=seeds)
    prep = prepare(traj)
    cycle = ConnectionEstimator().cycle.fit(prep, pool=False).gamma
    spc = 2 * math.pi / (phase_rate(prep.phase, traj.dt) * traj.dt)
    cells = []
    for floor in floors:
        method, _, low = floor.partition("@")
        est = estimate_noise(traj.r, cycle=cycle, samples_per_cycle=spc, floor=method,
                             band=(float(low), 0.5) if low else None,
                             phase=prep.phase if method == "normal" else None)
        mean, se = recording_z(est, n_recordings)
        z = mean / se
        text = (f"{floor}: {int((z > 2).sum()):>2}/{n_recordings} z {float(z.mean()):+.2f} "
                f"sd {float(z.std()):.2f}")
        if omega > 0:
            ratio = mean.clamp_min(0).sqrt() / omega
            text += (f" w/omega {float(mean.mean().clamp_min(0).sqrt()) / omega:.2f} "
                     f"within 20 % {int(((ratio - 1).abs() < 0.2).sum()):>2}")
        cells.append(text)
    return f"{n_links:>5} {gait:>9} {per_cycle:>4} {kind:>6} | " + " | ".join(cells)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5, 9])
    p.add_argument("--gaits", nargs="+", default=["circle", "reference"])
    p.add_argument("--per-cycle", type=int, nargs="+", default=[64, 126])
    p.add_argument("--kinds", nargs="+", default=list(KINDS), choices=list(KINDS))
    p.add_argument("--floors", nargs="+", default=["flat", "low_rate", "normal"],
                   help="flat, low_rate or normal; FLOOR@F fits the band [F, 0.5] (e.g. flat@0.1)")
    p.add_argument("--omega", type=float, default=0.0)
    p.add_argument("--first", type=int, default=60, help="first recording's seed block")
    p.add_argument("--recordings", type=int, default=20)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    for n in args.links:
        for gait in args.gaits:
            for spc in args.per_cycle:
                for kind in args.kinds:
                    print(run_cell(n, gait, spc, kind, args.omega, args.floors,
                                   first=args.first, n_recordings=args.recordings), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
