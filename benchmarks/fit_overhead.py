"""Per-call overhead of the default fit: torch calls and CPU time of ``ConnectionEstimator().fit``.

On a GPU the default fit is bound by how many small torch calls it makes (each a kernel launch,
some a device-to-host sync), not by its arithmetic. This prints, per recording (``--links``-link
swimmer on its reference gait (other link counts: a circle of radius 0.7), ``--trials`` trials x
``--cycles`` cycles, motion-capture noise ``--omega``, simulated with seeds ``0..trials-1``):

- ``torch calls``: every torch function and tensor method the fit calls (counted by a
  ``TorchFunctionMode``, in a separate fit from the timed one);
- ``syncs``: the calls among them that copy a value to the host (``item``, ``tolist``,
  ``nonzero``, ``bool`` / ``int`` / ``float`` of a tensor, ``any``/``all`` turned into a
  Python bool are counted by their ``__bool__``);
- ``CPU s``: the least process time of ``--repeats`` default fits (one thread);
- with ``--top K``, the K torch calls made most often;
- with ``--save FILE`` / ``--compare FILE``: the fitted models' tensors (``model_``'s bins and
  series, the cycle, the noise estimates, the complexity) are saved, or compared with a saved
  fit (``torch.equal``, else the largest relative difference), so a change of the code can be
  checked to leave every result as it was.

Calls that grow with ``--trials`` are Python loops over trials or chunks of bins.

Run by hand (one thread)::

    python benchmarks/fit_overhead.py --links 9 --trials 8 32
    python benchmarks/fit_overhead.py --links 3 5 9 --trials 8 --save /tmp/before.pt
"""

from __future__ import annotations

import argparse
import collections
import time
import warnings
import zlib

import numpy as np
import torch
from accuracy import circle_gait  # beside this file
from torch.overrides import TorchFunctionMode

from torchconn import ConnectionEstimator, NLinkSwimmer, observe, simulate
from torchconn.physics.gaits import reference_gait
from torchconn.regression import _wls

#: the calls that bring a value to the host (a GPU->CPU synchronisation on CUDA)
SYNCS = {"item", "tolist", "nonzero", "__bool__", "__int__", "__float__", "__index__",
         "numpy", "argwhere"}


class CallCounter(TorchFunctionMode):
    """Counts every torch function / tensor method call by name."""

    def __init__(self):
        super().__init__()
        self.calls: collections.Counter[str] = collections.Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", str(func))
        if name == "__get__":  # attribute reads (.shape, .device, ...): no kernel
            name = getattr(getattr(func, "__self__", None), "__name__", "attribute")
            self.calls["(attribute)"] += 1
        else:
            self.calls[name] += 1
        return func(*args, **(kwargs or {}))


def recording(links: int, trials: int, cycles: int, omega: float, device: str = "cpu"):
    seeds = np.arange(trials)
    eta = torch.tensor(0.025, dtype=torch.float64, device=device)
    gait = reference_gait(f"{links}link") if links in (3, 9) else circle_gait(links, 0.7)
    traj = simulate(NLinkSwimmer(links), gait, eta=eta, n_cycles=cycles, seeds=seeds)
    return observe(traj, omega, seeds=seeds)


def fit(traj):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ConnectionEstimator().fit(traj)


def results(est) -> dict[str, torch.Tensor]:
    """Every tensor of the fitted model, cycle, noise estimate and complexity, by a name."""
    out = {}

    def walk(name, obj, depth=0):
        if isinstance(obj, torch.Tensor):
            out[name] = obj.detach().cpu()
        elif depth < 4 and isinstance(obj, dict):
            for k, v in obj.items():
                walk(f"{name}[{k}]", v, depth + 1)
        elif depth < 4 and isinstance(obj, (list, tuple)):
            for k, v in enumerate(obj):
                walk(f"{name}[{k}]", v, depth + 1)
        elif depth < 4 and hasattr(obj, "__dict__") and not isinstance(obj, type):
            for k, v in vars(obj).items():
                walk(f"{name}.{k}", v, depth + 1)
        elif isinstance(obj, (int, float, bool)):
            out[name] = torch.tensor(float(obj), dtype=torch.float64)
        elif isinstance(obj, str) or obj is None:
            out[name] = torch.tensor(zlib.crc32(str(obj).encode()), dtype=torch.float64)

    for attr in ("model_", "forecast_model_", "limit_cycle_", "complexity_", "held_out_skill_",
                 "regression_"):
        walk(attr, getattr(est, attr, None))
    walk("phase", est.trajectory_.phase)
    return out


def compare(now: dict, before: dict) -> tuple[int, int, float, str]:
    """(equal, compared, worst relative difference, its name) over the common names."""
    equal, worst, where = 0, 0.0, ""
    common = sorted(set(now) & set(before))
    for k in common:
        a, b = now[k], before[k]
        if a.shape != b.shape or a.dtype != b.dtype:
            worst, where = float("inf"), k + " (shape/dtype)"
            continue
        if torch.equal(a, b) or (a.is_floating_point() and torch.equal(a.isnan(), b.isnan())
                                 and torch.equal(a.nan_to_num(), b.nan_to_num())):
            equal += 1
            continue
        if not a.is_floating_point():
            worst, where = float("inf"), k
            continue
        fin = a.isfinite() & b.isfinite()
        scale = b[fin].abs().max().clamp_min(1e-300) if fin.any() else torch.tensor(1.0)
        rel = float(((a - b)[fin].abs().max() / scale) if fin.any() else 0.0)
        if not torch.equal(a.isfinite(), b.isfinite()):
            rel = float("inf")
        if rel > worst:
            worst, where = rel, k
    return equal, len(common), worst, where


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[9])
    p.add_argument("--trials", type=int, nargs="+", default=[8])
    p.add_argument("--cycles", type=int, default=30)
    p.add_argument("--omega", type=float, default=0.002)
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--top", type=int, default=0, help="print the K most frequent calls")
    p.add_argument("--no-time", action="store_true", help="count calls only")
    p.add_argument("--chunk-mib", type=float, default=None,
                   help="bins' chunk budget on the CPU in MiB (default: the library's, 8; "
                        "1024 makes the chunks a GPU makes, to count its calls here)")
    p.add_argument("--save", help="save the fitted tensors of every recording to this file")
    p.add_argument("--compare", help="compare the fitted tensors with this saved file")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.chunk_mib is not None:
        _wls._CHUNK_BYTES = int(args.chunk_mib * 2**20)
    saved, before = {}, torch.load(args.compare) if args.compare else {}
    print(f"{'links':>5} {'trials':>6} {'torch calls':>12} {'syncs':>7} {'CPU s':>8}"
          + ("   same as saved" if args.compare else ""))
    for links in args.links:
        for trials in args.trials:
            traj = recording(links, trials, args.cycles, args.omega)
            counter = CallCounter()
            with counter:
                est = fit(traj)
            best = float("nan")
            if not args.no_time:
                best = float("inf")
                for _ in range(args.repeats):
                    start = time.process_time()
                    est = fit(traj)
                    best = min(best, time.process_time() - start)
            total = sum(counter.calls.values()) - counter.calls["(attribute)"]
            syncs = sum(v for k, v in counter.calls.items() if k in SYNCS)
            key = f"{links}x{trials}"
            line = f"{links:>5} {trials:>6} {total:>12} {syncs:>7} {best:>8.2f}"
            now = results(est)
            saved[key] = now
            if args.compare:
                if key in before:
                    eq, n, worst, where = compare(now, before[key])
                    line += f"   {eq}/{n} equal" + (f", worst {worst:.1e} ({where})"
                                                    if eq < n else "")
                else:
                    line += "   (not saved)"
            print(line, flush=True)
            for name, n in counter.calls.most_common(args.top):
                print(f"{'':>14}{n:>9}  {name}")
    if args.save:
        torch.save(saved, args.save)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
