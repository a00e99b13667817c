"""Which stage of the default fit amplifies a last-bit change of the data.

CPU and CUDA round differently in the last bit, so their fits of the same recording can agree
no better than the fit's own amplification of such a change. This fits a recording (the
3-link test recording of ``tests/test_devices.py``: 4 trials x 12 cycles, ω = 0.002) and the
same recording with every pose and shape sample multiplied by ``1 + ε z`` (``z`` standard
normal, ``ε = --eps``, default 1e-15), and prints, stage by stage in the pipeline's order, the
largest change relative to the largest value (``max |a − b| / max |b|``) and its ratio to the
data's own relative change (the amplification). Discrete choices (window, interval, order) are
printed as changed or not.

Run by hand (a few seconds)::

    python benchmarks/fit_sensitivity.py
    python benchmarks/fit_sensitivity.py --links 9 --trials 4 --cycles 30
"""

from __future__ import annotations

import argparse
import dataclasses
import warnings

import numpy as np
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, observe, simulate
from torchconn.physics.gaits import reference_gait


def recording(links: int, trials: int, cycles: int, omega: float):
    seeds = np.arange(trials)
    eta = torch.tensor(0.025, dtype=torch.float64)
    traj = simulate(NLinkSwimmer(links), reference_gait(f"{links}link"), eta=eta,
                    n_cycles=cycles, seeds=seeds)
    return observe(traj, omega, seeds=seeds)


def stages(est) -> list[tuple[str, object]]:
    """The fit's results in pipeline order, by name."""
    m, prep = est.model_, est.trajectory_
    out = [("smoothed r", prep.smoothed.r), ("phase", prep.phase),
           ("cycle γ coeffs", est.limit_cycle_.gamma.coeffs),
           ("cycle phase rate", est.limit_cycle_.phase_rate)]
    for key in ("noise_r", "noise_ratio", "metric_noise_std", "window", "velocity_interval",
                "intercept_order", "metric_order", "corrected_weight", "tube_rms"):
        if key in m.meta:
            out.append((f"meta {key}", m.meta[key]))
    out.append(("complexity_", est.complexity_))
    for f in ("c", "b", "A", "dA", "A_se", "M"):
        out.append((f"bins {f}", getattr(m.bins, f)))
    for f in ("A", "dA", "c", "b"):
        out.append((f"model_ {f} coeffs", getattr(m, f).coeffs))
    # what tests/test_devices.py compares between CPU and CUDA
    phi = torch.linspace(0, 2 * np.pi, 33, dtype=torch.float64)
    out.append(("model_.connection(φ)", m.connection(phi)))
    return out


def as_tensor(x) -> torch.Tensor | None:
    if isinstance(x, torch.Tensor):
        return x.detach().double()
    try:
        return torch.as_tensor(np.asarray(x, dtype=float))
    except (TypeError, ValueError):
        return None


def relative(a, b) -> float | str:
    ta, tb = as_tensor(a), as_tensor(b)
    if ta is None or tb is None or ta.shape != tb.shape:
        return "same" if repr(a) == repr(b) else "CHANGED"
    fin = ta.isfinite() & tb.isfinite()
    if not torch.equal(fin, ta.isfinite() | tb.isfinite()):
        return "NaN pattern CHANGED"
    if not fin.any():
        return 0.0
    scale = tb[fin].abs().max()
    return float((ta - tb)[fin].abs().max() / scale) if scale > 0 else 0.0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, default=3)
    p.add_argument("--trials", type=int, default=4)
    p.add_argument("--cycles", type=int, default=12)
    p.add_argument("--omega", type=float, default=0.002)
    p.add_argument("--eps", type=float, default=1e-15)
    p.add_argument("--seed", type=int, default=0, help="seed of the perturbation")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    traj = recording(args.links, args.trials, args.cycles, args.omega)
    gen = torch.Generator().manual_seed(args.seed)

    def bump(x: torch.Tensor) -> torch.Tensor:
        return x * (1 + args.eps * torch.randn(x.shape, generator=gen, dtype=x.dtype))

    moved = dataclasses.replace(traj, r=bump(traj.r), pose=bump(traj.pose))
    data = max(relative(moved.r, traj.r), relative(moved.pose, traj.pose))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a, b = ConnectionEstimator().fit(moved), ConnectionEstimator().fit(traj)
    print(f"{args.links}-link, {args.trials} trials x {args.cycles} cycles, ω = {args.omega}; "
          f"data changed by {data:.1e} (relative)")
    print(f"{'stage':<26}{'max |Δ| / max |x|':>20}{'amplification':>15}")
    for (name, x), (_, y) in zip(stages(a), stages(b), strict=True):
        rel = relative(x, y)
        if isinstance(rel, str):
            print(f"{name:<26}{rel:>20}")
        else:
            print(f"{name:<26}{rel:>20.1e}{rel / data:>15.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
