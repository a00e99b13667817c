"""Benchmark: is ``predict_gait``'s displacement standard error honest?

Recordings as in ``metric_accuracy.py`` (the paper's SDE, α = 0.05, η = 0.025, 4 trials × 30
cycles pooled, 64 samples per cycle, observation noise ω; the 3-link Tam–Hosoi gait, a 5-link
travelling wave of amplitude 0.7, the 9-link reference gait). For each seed set the one-cycle
displacement of the recorded gait is predicted from the fitted model alone and compared with
the exact one
(:func:`~torchconn.physics.gaits.evaluate` on the swimmer). Printed per ω:

- ``z2``: mean over sets of ``(e / se)²`` per component ``(x, y, θ)`` and over all (1 = honest);
- ``bias`` / ``scatter``: the mean of ``e_x`` over sets and its standard deviation across sets
  (a bias is a mean many times the scatter);
- ``along`` / ``across``: for ``Â``'s error along the cycle's tangent (``Âγ̇``, which the
  displacement integrates) and across it, harmonics 0–2, the scatter of the error over sets
  divided by the SD of :func:`~torchconn.regression.gait_prediction.sample_models`' draws
  (1 = the draws have the right width); in brackets against the draws without the bias
  allowance (a bias does not scatter across sets, so this is the sampling part's check), and
  the error's RMS (bias included) against the full draws.

Each set ``s`` records the seeds ``s..s+3``: sets must be at least 4 apart (sets that share
trials scatter less than independent ones).

    python benchmarks/displacement_se.py --links 3 --omega 0 0.002 --seeds 11000 12000 13000
    python benchmarks/displacement_se.py --regression tube   # the smoothed regression
"""

from __future__ import annotations

import argparse
import dataclasses
import warnings

import numpy as np
import torch
from metric_accuracy import gait_for

from torchconn import ConnectionEstimator, NLinkSwimmer, observe, simulate
from torchconn.phase.fourier import fit_fourier
from torchconn.physics.gaits import reference_gait
from torchconn.physics.gaits.evaluate import evaluate
from torchconn.physics.gaits.gait import as_gait
from torchconn.regression.gait_prediction import predict_gait, sample_models
from torchconn.regression.tube import TubeRegression

HELD_OUT = [11000, 12000, 13000, 14000, 15000, 16000, 17000, 18000]
#: ``--regression``: the default; the smoothed regression
REGRESSIONS = {
    "default": lambda: None,
    "tube": TubeRegression,
}


def tangent_parts(model, A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``A (..., M, 3, d)`` at the bins split into ``Aγ̇/|γ̇|`` ``(..., M, 3)`` and the rest."""
    t = model.bins.gamma_dot / model.bins.gamma_dot.norm(dim=-1, keepdim=True)
    along = (A @ t[..., None])[..., 0]
    return along, A - along[..., None] * t[..., None, :]


def low_harmonics(model, values: torch.Tensor, value_ndim: int) -> torch.Tensor:
    return fit_fourier(model.bins.phase, values, 2, value_ndim=value_ndim).coeffs


def one_set(system, gait, exact, seed: int, omega: float, regression, draws: int) -> dict:
    seeds = np.arange(seed, seed + 4)
    traj = simulate(system, gait, eta=0.025, alpha=0.05, n_cycles=30, samples_per_cycle=64,
                    seeds=seeds)
    traj = observe(traj, omega, seeds=seeds)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        kw = {"regression": regression} if regression is not None else {}
        model = ConnectionEstimator(pool=True, **kw).fit(traj).model_
        pred = predict_gait(model, gait, n_draws=draws)
    out = {"e": (pred.displacement - exact).numpy(), "se": pred.displacement_se.numpy()}
    truth = system.connection(model.bins.gamma)
    drawn = sample_models(model, draws).A(model.bins.phase)  # (S, M, 3, d)
    # the draws without the bias allowance: the scatter across sets cannot see a bias, so
    # it is compared with these (the allowance with the mean error instead)
    sampling = dataclasses.replace(model, bins=dataclasses.replace(model.bins,
                                                                   A_bias_allowance=None))
    drawn_s = sample_models(sampling, draws).A(model.bins.phase)
    for k, (est, true, dr, dr_s) in enumerate(zip(
            tangent_parts(model, model.bins.A), tangent_parts(model, truth),
            tangent_parts(model, drawn), tangent_parts(model, drawn_s), strict=True)):
        name = ("along", "across")[k]
        out[name] = low_harmonics(model, est - true, 1 + k).numpy()
        out[name + "_sd"] = low_harmonics(model, dr, 1 + k).std(0).numpy()
        out[name + "_sd_s"] = low_harmonics(model, dr_s, 1 + k).std(0).numpy()
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5])
    p.add_argument("--omega", type=float, nargs="+", default=[0.0, 0.002, 0.005])
    p.add_argument("--seeds", type=int, nargs="+", default=HELD_OUT)
    p.add_argument("--regression", choices=list(REGRESSIONS), default="default")
    p.add_argument("--draws", type=int, default=256)
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    starts = sorted(a.seeds)
    if any(b - s < 4 for s, b in zip(starts, starts[1:], strict=False)):
        # set s records trials s..s+3: sets closer than 4 share trials, and their scatter
        # understates the sampling error (4 consecutive sets: to 0.65 of its SD)
        p.error(f"--seeds must be at least 4 apart (each set records seeds s..s+3), got "
                f"{a.seeds}")
    torch.set_num_threads(a.threads)
    regression = REGRESSIONS[a.regression]()
    for links in a.links:
        gait = reference_gait("9link") if links == 9 else gait_for(links)
        system, gait = NLinkSwimmer(links), as_gait(gait)
        exact = evaluate(system, gait, n_steps=256).displacement
        for omega in a.omega:
            rows = [one_set(system, gait, exact, s, omega, regression, a.draws) for s in a.seeds]
            e = np.array([r["e"] for r in rows])
            z2 = (e / np.array([r["se"] for r in rows])) ** 2
            line = (f"{links}-link ω={omega:g} {a.regression}: z2 {z2.mean():.2f} "
                    f"(x {z2[:, 0].mean():.2f}, y {z2[:, 1].mean():.2f}, θ {z2[:, 2].mean():.2f})"
                    f" | e_x bias {e[:, 0].mean():+.2e} scatter {e[:, 0].std(ddof=1):.2e}")
            for name in ("along", "across"):
                err = np.array([r[name] for r in rows])
                scatter = ((err - err.mean(0)) ** 2).sum(0) / (len(rows) - 1)
                sd2 = np.mean([r[name + "_sd"] ** 2 for r in rows], 0)
                sd2_s = np.mean([r[name + "_sd_s"] ** 2 for r in rows], 0)
                rms2 = (err ** 2).mean(0)
                line += (f" | {name} scatter/draws {np.sqrt(scatter.mean() / sd2.mean()):.2f}"
                         f" (sampling part {np.sqrt(scatter.mean() / sd2_s.mean()):.2f}),"
                         f" rms/draws {np.sqrt(rms2.mean() / sd2.mean()):.2f}")
            print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
