"""Time per diagnosis: the discrepancy workflow's four timing cases, one thread.

The cases of the discrepancy issue (3-link; 9-link at 64 and at 300 samples per cycle) and the
dense 9-link recording of about 9,400 samples per trial (30 cycles at Δt = 0.02, ~314 samples
per cycle). Each is a simulated recording at the paper's α, η with observation noise
ω = 0.002 and one hidden ``drag_ratio`` change (Δk = 0.3), diagnosed with the default settings
(term-by-term comparison and separating experiments on).

For every case it prints the wall and CPU time of :func:`torchconn.discrepancy.diagnose`, the
load average around it (on a shared machine wall time is only meaningful beside the load), and
the ratio of the diagnosis to a plain reference on the same recording: one nominal forward-model
pass (the swimmer's connection on every fine step, integration, smoothing), timed in the same
run. ``--profile CASE`` prints the cProfile table of one case.

    python benchmarks/bench_discrepancy_time.py [--cases 3link 9link-64 9link-300 9link-dense]
        [--profile 9link-dense] [--threads 1]
"""

from __future__ import annotations

import argparse
import cProfile
import math
import os
import pstats
import sys
import time

import torch

from torchconn.discrepancy import DiscrepancySettings, diagnose, simulate_with_effects
from torchconn.discrepancy.forward import ForwardModel, prepare_measurement
from torchconn.discrepancy.workflow import _upsample
from torchconn.physics.gaits import reference_gait
from torchconn.physics.systems import NLinkSwimmer

#: name -> (links, trials, cycles, samples per cycle)
CASES = {
    "3link": (3, 3, 20, 64),
    "9link-64": (9, 2, 15, 64),
    "9link-300": (9, 2, 15, 300),
    "9link-dense": (9, 2, 30, round(2 * math.pi / 0.02)),
}


def recording(name: str):
    links, trials, cycles, spc = CASES[name]
    system = NLinkSwimmer(3) if links == 3 else NLinkSwimmer(links, frame="com-mean")
    traj = simulate_with_effects(system, reference_gait(f"{links}link"),
                                 {"drag_ratio": {"delta_k": 0.3}}, eta=0.025, alpha=0.05,
                                 n_cycles=cycles, samples_per_cycle=spc,
                                 seeds=list(range(trials)), omega=0.002)
    return traj, system


def _timed(fn, *args):
    load0 = os.getloadavg()[0]
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return out, wall, cpu, 0.5 * (load0 + os.getloadavg()[0])


def reference_pass(traj, system) -> float:
    """CPU seconds of one nominal forward-model pass on the recording (median of 3)."""
    m = prepare_measurement(traj, system)
    fm = ForwardModel(m, system, upsample=_upsample(DiscrepancySettings(), m))
    times = []
    for _ in range(3):
        fm._nominal_twist = None  # no cached twist: the full pass
        _, _, cpu, _ = _timed(fm.residual)
        times.append(cpu)
    return sorted(times)[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--profile", choices=list(CASES), default=None)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    settings = DiscrepancySettings()
    print(f"torch threads {torch.get_num_threads()}, {os.cpu_count()} cores; load average "
          f"before: {os.getloadavg()[0]:.1f}")
    print(f"{'case':12s} {'samples/trial':>13s} {'wall s':>8s} {'CPU s':>8s} {'load':>5s} "
          f"{'ref CPU s':>9s} {'CPU/ref':>8s}  verdict")
    for name in args.cases:
        traj, system = recording(name)
        ref = reference_pass(traj, system)
        prof = cProfile.Profile() if name == args.profile else None
        run = prof.runcall if prof is not None else (lambda f, *a: f(*a))
        report, wall, cpu, load = _timed(run, diagnose, traj, system, settings)
        named = "+".join(e.name for e in report.effects) or "-"
        print(f"{name:12s} {traj.n_samples:13d} {wall:8.1f} {cpu:8.1f} {load:5.1f} "
              f"{ref:9.3f} {cpu / ref:8.0f}  {report.verdict} {named}", flush=True)
        if prof is not None:
            pstats.Stats(prof).sort_stats("cumulative").print_stats(30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
