"""Time per pooled fit of the default regression, as a ratio to its full search on the same inputs.

The pooled ``NoiseAwareRegression`` chooses its velocity interval and bin width among 24
candidates (4 windows x 6 intervals), each corrected for the bins' bias by two more
regressions (``bin_bias_correction``). This prints, per recording (the paper's SDE, 4 trials x
30 cycles at 126 samples per cycle, circle gaits, motion-capture noise ω, as in
``benchmarks/accuracy.py``), the CPU time of the regression stage's pooled fit
(``regression.fit(prepared, cycle, pool=True)``; smoothing, phase and cycle done beforehand,
no metric) for:

- ``full``: every candidate corrected (``NoiseAwareRegression._full_search``, the test hook),
  the reference;
- ``default``: the default (branch and bound: candidates corrected in increasing variance until
  none left can win), with how many of the candidates were corrected.

The default as a ratio to ``full`` in the same run, so that versions can be compared on a
loaded machine. ``identical`` checks that the default's model (every per-bin estimate, its
standard errors, the Fourier series and the meta but for the table of scores) equals the full
search's bit for bit.

Run by hand (one thread; about a minute on a loaded 2-core machine)::

    python benchmarks/pooled_fit_cost.py
    python benchmarks/pooled_fit_cost.py --links 9 --omega 0.002 --gaits reference
"""

from __future__ import annotations

import argparse
import time
import warnings

import torch
from accuracy import recording  # beside this file

from torchconn import ConnectionEstimator, NoiseAwareRegression

FIELDS = ("c", "b", "A", "dA", "c_se", "b_se", "A_se", "dA_se", "n_samples")
#: meta entries that describe the search itself (the others must agree)
SEARCH_META = ("interval_window_scores", "interval_window_bounds", "settings")


def timed(regression, prepared, cycle, repeats: int):
    """The fitted model and the least CPU seconds of ``repeats`` fits."""
    best, model = float("inf"), None
    for _ in range(repeats):
        start = time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = regression.fit(prepared, cycle, pool=True)
        best = min(best, time.process_time() - start)
    return model, best


def same(a, b) -> bool:
    """Bit-for-bit equality of two pooled models, the search's own meta aside."""
    tensors = all(torch.equal(getattr(a.bins, f), getattr(b.bins, f)) for f in FIELDS)
    series = all(torch.equal(getattr(a, f).coeffs, getattr(b, f).coeffs)
                 for f in ("c", "b", "A", "dA"))
    meta = ({k: v for k, v in a.meta.items() if k not in SEARCH_META}
            == {k: v for k, v in b.meta.items() if k not in SEARCH_META})
    return tensors and series and meta


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5, 9])
    p.add_argument("--omega", type=float, nargs="+", default=[0.0, 0.002, 0.005])
    p.add_argument("--gaits", nargs="+", default=["circle"], choices=["circle", "reference"])
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--repeats", type=int, default=1, help="fits per method (the least time)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    default = NoiseAwareRegression()
    print("CPU seconds per pooled fit (regression stage), ratio to the full search, same run")
    print(f"{'links':>5} {'gait':>9} {'omega':>6} {'full s':>8} "
          f"{'default x':>9} {'default s':>9} {'corrected':>9} {'identical':>9}")
    ratios = []
    for n in args.links:
        for gait in args.gaits:
            for omega in args.omega:
                traj = recording(n, gait, omega, seed=args.seed)
                est = ConnectionEstimator(pool=True)
                prepared = est.prepare(traj)
                cycle = est.cycle.fit(prepared, pool=True)
                model, t_default = timed(default, prepared, cycle, args.repeats)
                NoiseAwareRegression._full_search = True
                try:
                    full, t_full = timed(default, prepared, cycle, args.repeats)
                finally:
                    NoiseAwareRegression._full_search = False
                scores = model.meta["interval_window_scores"]
                skipped = model.meta.get("interval_window_bounds", [])
                ratios.append(t_default / t_full)
                print(f"{n:>5} {gait:>9} {omega:>6.3f} {t_full:>8.2f} "
                      f"{t_default / t_full:>9.2f} {t_default:>9.2f} "
                      f"{len(scores) - len(skipped):>4}/{len(scores):<4} "
                      f"{str(same(model, full)):>9}", flush=True)
    geo = torch.tensor(ratios, dtype=torch.float64).log().mean().exp()
    print(f"default / full: {min(ratios):.2f}-{max(ratios):.2f}x, geometric mean {geo:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
