"""The RTS smoother's time recursions: the sequential loop vs the parallel scan, per size.

Run by hand: ``python benchmarks/bench_smoother.py [--trials 1 4 20 80] [--samples 1000 4000]
[--channels 11] [--orders 2 3] [--dropouts 0 0.05] [--repeat 3] [--threads 1] [--device cpu]``.

Each size is ``trials × channels`` rows (11 channels: the 9-link swimmer's x, y, θ and 8 joint
angles) of ``samples`` noisy, drifting harmonics, with each sample lost with probability
``--dropouts`` (0: the scan composes the identical covariance steps of rows without drop-outs
once per round, the simulated sweeps' case). Both algorithms smooth the
same rows with the same noise parameters (estimated once by ``noise_parameters``), so the time
is the filter and smoother only; the best of ``--repeat`` runs is kept. Printed per size:
seconds of each (CPU seconds of this process on the CPU, wall time on a GPU), the ratio
loop / scan (> 1: the scan is faster), what ``algorithm="auto"`` picks, and the largest
difference between the two outputs relative to the signal's size. The machine's load still
distorts CPU times (shared caches); compare the ratios, taken in the same run.
"""

from __future__ import annotations

import argparse
import itertools
import math
import time

import torch

from torchconn.phase.smoothing import _SCAN_MAX_ROWS_CPU, noise_parameters, rts_smooth


def _data(trials: int, samples: int, channels: int, dropout: float, device) -> torch.Tensor:
    gen = torch.Generator().manual_seed(trials * 7919 + samples)
    t = torch.arange(samples, dtype=torch.float64) * (2 * math.pi / 64)
    amp = torch.rand(trials, 1, channels, generator=gen, dtype=torch.float64)
    drift = torch.randn(trials, 1, channels, generator=gen, dtype=torch.float64)
    y = amp * torch.sin(t[:, None] + amp) + 0.05 * drift * t[:, None]
    y = y + 0.02 * torch.randn(y.shape, generator=gen, dtype=torch.float64)
    lost = torch.rand(y.shape, generator=gen) < dropout
    lost[:, 0] = False  # the first sample of every channel is recorded
    y[lost] = float("nan")
    return y.to(device)


def _best(fn, repeat: int, device) -> tuple[float, tuple[torch.Tensor, torch.Tensor]]:
    # on the CPU the process's CPU time: on a shared machine wall time mostly measures the others
    clock = time.perf_counter if device.type == "cuda" else time.process_time
    best, out = math.inf, None
    for _ in range(repeat):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = clock()
        out = fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        best = min(best, clock() - t0)
    return best, out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, nargs="+", default=[1, 4, 20, 80])
    p.add_argument("--samples", type=int, nargs="+", default=[1000, 4000])
    p.add_argument("--channels", type=int, default=11)
    p.add_argument("--orders", type=int, nargs="+", default=[2, 3])
    p.add_argument("--dropouts", type=float, nargs="+", default=[0.0, 0.05])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--device", default="cpu")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    dt = 2 * math.pi / 64
    print(f"# torch {torch.__version__}, {args.threads} thread(s), device {device}; "
          f"auto uses the scan on the CPU for <= {_SCAN_MAX_ROWS_CPU} rows (per order)")
    print("order  drop  trials  rows  samples   loop s   scan s  loop/scan  auto  max rel diff")
    for order, dropout, samples, trials in itertools.product(args.orders, args.dropouts,
                                                     args.samples, args.trials):
        y = _data(trials, samples, args.channels, dropout, device)
        q, R = noise_parameters(y, dt, order=order)

        def run(algorithm, y=y, q=q, R=R, order=order):
            return rts_smooth(y, dt, order=order, process_noise=q, measurement_noise=R,
                              algorithm=algorithm)

        t_loop, (v_loop, d_loop) = _best(lambda: run("loop"), args.repeat, device)
        t_scan, (v_scan, d_scan) = _best(lambda: run("scan"), args.repeat, device)
        auto = "scan" if torch.equal(run("auto")[1], d_scan) else "loop"
        diff = max(float((v_scan - v_loop).abs().max() / v_loop.abs().max()),
                   float((d_scan - d_loop).abs().max() / d_loop.abs().max()))
        rows = trials * args.channels
        print(f"{order:5d} {dropout:5.2f} {trials:7d} {rows:5d} {samples:8d} {t_loop:8.3f} "
              f"{t_scan:8.3f} {t_loop / t_scan:10.2f}  {auto:4s}  {diff:.1e}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
