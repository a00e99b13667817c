"""Benchmark: batched phase-bin connection regression vs a per-trial, per-bin lstsq loop.

The paper's 9-link scale: d = 8 joints (P = 81 regressors), 160 trials × 30 cycles × 64 samples
per cycle, M = 16 (and 32) phase bins. Prints both times, their ratio, the achieved GFLOP/s of
the batched solver and this machine's float64 matmul peak (measured in the same run).
``--kernel tricube`` (the estimator's default bins) times the weighted path, whose standard
errors are sandwich estimates, against a weighted lstsq loop.

    python benchmarks/bench_regression.py [--trials 160] [--bins 16 32] [--loop-trials 20]
                                          [--threads 2] [--kernel tricube]

Times are the best of ``--repeat`` runs, both wall-clock and CPU time of this process
(``time.process_time``): with one thread on a shared, loaded machine the CPU time is the steadier
measure (waiting for a core does not count), so both ratios are printed. The last lines per bin
count give the ceiling of per-bin normal equations on this machine: the dense kernels alone
(the Gram matrix, Cholesky, triangular inverse and the Cholesky solve for the coefficients; with
the binning), and the essential flops (the Gram matrix's lower half, Cholesky and triangular
inverse) at the matmul peak.

One trial holds 30 × 64 = 1920 samples, so at M = 32 a half-spacing window leaves 60 samples per
bin for 81 regressors; the bins are widened to ``window = 0.5 · M / 16`` (overlapping, ~120
samples each, every sample in M/16 bins) unless ``--window`` is given. The loop is timed on
``--loop-trials`` trials and scaled to all trials (it is linear in them).
OpenBLAS runs single-threaded for the loop: on small lstsq problems its threading is much slower
(measured ~40x here), so this is the loop's best case.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads OpenBLAS

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchconn.physics.systems import AffineConnectionSystem  # noqa: E402
from torchconn.regression import _wls, assign_bins, connection_regression  # noqa: E402


def make_data(n_trials: int, n_cycles: int, per_cycle: int, d: int, seed: int = 0):
    """Noisy samples around a two-mode 9-link-like cycle; xi from an affine toy connection."""
    gen = torch.Generator().manual_seed(seed)
    n = n_cycles * per_cycle
    t = torch.arange(n, dtype=torch.float64) * (2 * math.pi / per_cycle)
    phase = t + 0.05 * torch.randn(n_trials, n, generator=gen, dtype=torch.float64).cumsum(-1) / 8
    k = torch.arange(1, d + 1, dtype=torch.float64) * (2 * math.pi / d)
    modes = torch.stack([torch.sin(k), torch.cos(k)], -1)  # (d, 2)

    def gamma(p):
        return torch.stack([torch.cos(p), torch.sin(p)], -1) @ modes.T

    def gamma_dot(p):
        return torch.stack([-torch.sin(p), torch.cos(p)], -1) @ modes.T

    r = gamma(phase) + 0.1 * torch.randn(n_trials, n, d, generator=gen, dtype=torch.float64)
    r_dot = gamma_dot(phase) + 0.1 * torch.randn(n_trials, n, d, generator=gen,
                                                 dtype=torch.float64)
    system = AffineConnectionSystem.random(d, seed=seed)
    xi = system.body_velocity(r, r_dot) + 1e-3 * torch.randn(n_trials, n, 3, generator=gen,
                                                             dtype=torch.float64)
    return phase, r, r_dot, xi, gamma, gamma_dot


def loop_reference(phase, r, r_dot, xi, gm, gdm, n_bins, window, kernel="box"):
    """The plain way: for each trial, for each bin, select rows, build X, ``np.linalg.lstsq``
    (rows scaled by √w for the tricube kernel: weighted least squares)."""
    phase, r, r_dot, xi = (x.numpy() for x in (phase, r, r_dot, xi))
    gm, gdm = gm.numpy(), gdm.numpy()
    h = 2 * math.pi / n_bins
    out = []
    for trial in range(r.shape[0]):
        for m in range(n_bins):
            off = np.remainder(phase[trial] - m * h + math.pi, 2 * math.pi) - math.pi
            sel = (off >= -window * h) & (off < window * h)
            delta = r[trial, sel] - gm[m]
            delta_dot = r_dot[trial, sel] - gdm[m]
            cross = (delta_dot[:, :, None] * delta[:, None, :]).reshape(len(delta), -1)
            x = np.concatenate([np.ones((len(delta), 1)), delta, delta_dot, cross], 1)
            sw = np.ones((len(delta), 1))
            if kernel == "tricube":
                sw = np.sqrt((1 - np.minimum(np.abs(off[sel]) / (window * h), 1) ** 3) ** 3)
                sw = sw[:, None]
            out.append(np.linalg.lstsq(sw * x, sw * xi[trial, sel], rcond=None)[0])
    return out


def flops(n_rows_padded: int, p: int, k: int, n_systems: int, weighted: bool = False) -> float:
    """Useful flops of the batched solver per the algorithm: ``[X|y]ᵀW[X|y]`` on the padded rows,
    Cholesky ``P³/3``, ``cholesky_solve`` ``2P²K``, triangular inverse ``P³/3``, residuals; with
    kernel weights also the sandwich standard errors: ``A⁻¹ = L⁻ᵀL⁻¹`` ``2P³`` (a full GEMM)
    and ``Q = (W X) A⁻¹`` ``2nP²``."""
    n = n_rows_padded
    per = 2 * n * (p + k) ** 2 + p**3 / 3 + 2 * p * p * k + p**3 / 3 + 2 * n * p * k
    if weighted:
        per += 2 * p**3 + 2 * n * p * p
    return per * n_systems


def primitive_floor(n_systems: int, n_rows: int, p: int, k: int, repeat: int) -> dict:
    """Per-bin CPU time (µs) of the dense kernels every bin needs, on the real shapes."""
    b = min(n_systems, 256)  # one cache-sized chunk, as the solver runs them
    xy = torch.randn(b, n_rows, p + k, dtype=torch.float64)
    full = xy.mT @ xy
    gram, rhs = full[:, :p, :p].contiguous(), full[:, :p, p:]
    chol = torch.linalg.cholesky(gram)
    eye = torch.eye(p, dtype=torch.float64).expand(b, p, p)
    kernels = {
        "Gram [X|y]ᵀ[X|y]": lambda: xy.mT @ xy,
        "Cholesky": lambda: torch.linalg.cholesky_ex(gram),
        "triangular inverse": lambda: _wls._triangular_inverse(chol),
        "Cholesky solve": lambda: torch.cholesky_solve(rhs, chol),
        "(one triangular solve against I, before)":
            lambda: torch.linalg.solve_triangular(chol, eye, upper=False),
    }
    return {name: best_times(fn, repeat)[1] / b * 1e6 for name, fn in kernels.items()}


def best_times(fn, repeat: int) -> tuple[float, float]:
    """Best wall-clock and best CPU time (this process) of ``repeat`` runs of ``fn``."""
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return min(wall), min(cpu)


def essential_flops(n_rows: int, p: int, k: int) -> float:
    """Flops no per-bin normal-equation solver avoids: the lower half of ``[X|y]ᵀ[X|y]``,
    Cholesky ``P³/3`` and the triangular inverse ``P³/3`` for the standard errors."""
    return n_rows * (p + k) * (p + k + 1) + 2 * p**3 / 3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=160)
    ap.add_argument("--cycles", type=int, default=30)
    ap.add_argument("--per-cycle", type=int, default=64)
    ap.add_argument("--d", type=int, default=8)
    ap.add_argument("--bins", type=int, nargs="+", default=[16, 32])
    ap.add_argument("--loop-trials", type=int, default=20)
    ap.add_argument("--window", type=float, default=None)
    ap.add_argument("--kernel", default="box",
                    help="bin kernel: box (0/1 weights) or tricube (the estimator's default)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.kernel not in ("box", "tricube"):
        ap.error(f"--kernel must be box or tricube, got {args.kernel!r}")

    a = torch.randn(2048, 2048, dtype=torch.float64)
    a @ a
    peak, peak_cpu = (2 * 2048**3 / t / 1e9 for t in best_times(lambda: a @ a, 3))
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; "
          f"float64 matmul 2048² peak: {peak:.1f} GFLOP/s wall, {peak_cpu:.1f} GFLOP/s CPU "
          "(CPU time sums the threads); load average "
          + ", ".join(f"{x:.1f}" for x in os.getloadavg())
          + " (on a shared machine compare ratios within one run)")

    phase, r, r_dot, xi, gamma, gamma_dot = make_data(args.trials, args.cycles, args.per_cycle,
                                                      args.d)
    p = 1 + 2 * args.d + args.d**2
    print(f"d = {args.d}, P = {p}, {args.trials} trials × {args.cycles} cycles × "
          f"{args.per_cycle} samples = {r.shape[0] * r.shape[1]} samples")
    for n_bins in args.bins:
        window = args.window or 0.5 * max(1.0, n_bins / 16)
        bins = assign_bins(phase, n_bins, window=window, kernel=args.kernel)
        centres = bins.centres()
        gm, gdm = gamma(centres), gamma_dot(centres)

        def batched(n_bins=n_bins, gm=gm, gdm=gdm, window=window):
            b = assign_bins(phase, n_bins, window=window, kernel=args.kernel)
            return connection_regression(r, r_dot, xi, b, gm, gdm)

        fit = batched()
        t_batched, c_batched = best_times(batched, args.repeat)
        t_bin, c_bin = best_times(lambda n_bins=n_bins, window=window: assign_bins(
            phase, n_bins, window=window, kernel=args.kernel), args.repeat)

        lt = min(args.loop_trials, args.trials)
        sl = slice(0, lt)
        t0, c0 = time.perf_counter(), time.process_time()
        ref = loop_reference(phase[sl], r[sl], r_dot[sl], xi[sl], gm, gdm, n_bins, window,
                             args.kernel)
        t_loop = (time.perf_counter() - t0) * args.trials / lt
        c_loop = (time.process_time() - c0) * args.trials / lt
        ref = torch.from_numpy(np.stack(ref)).reshape(lt, n_bins, p, 3)
        err = ((fit.coef[sl] - ref).abs().max() / ref.abs().max()).item()

        gflop = flops(bins.max_count, p, 3, args.trials * n_bins, args.kernel != "box") / 1e9
        print(f"\nM = {n_bins} bins, window {window:g}: Nmax = {bins.max_count}, "
              f"mean bin count {bins.count.double().mean():.1f}")
        print(f"  batched (binning + regression + SEs): {t_batched * 1e3:8.1f} ms "
              f"(binning {t_bin * 1e3:.1f} ms)")
        print(f"  lstsq loop (scaled from {lt} trials): {t_loop * 1e3:8.1f} ms")
        print(f"  CPU time: batched {c_batched * 1e3:.1f} ms, loop {c_loop * 1e3:.1f} ms")
        print(f"  speed-up: {t_loop / t_batched:.1f}x wall, {c_loop / c_batched:.1f}x CPU;  "
              f"max rel. diff vs lstsq: {err:.2e}")
        print(f"  batched: {gflop:.2f} GFLOP -> {gflop / t_batched:.1f} GFLOP/s wall "
              f"({100 * gflop / t_batched / peak:.0f}% of matmul peak), "
              f"{gflop / c_batched:.1f} GFLOP/s CPU ({100 * gflop / c_batched / peak_cpu:.0f}%)")
        n_sys = args.trials * n_bins
        floor = primitive_floor(n_sys, bins.max_count, p, 3, args.repeat)
        loop_bin, batched_bin = c_loop / n_sys * 1e6, c_batched / n_sys * 1e6
        print(f"  per bin (CPU): batched {batched_bin:.0f} µs, loop {loop_bin:.0f} µs; "
              "dense kernels alone: " + ", ".join(f"{k} {v:.0f} µs" for k, v in floor.items()))
        kernels = sum(v for k, v in floor.items() if not k.startswith("("))
        binning = c_bin / n_sys * 1e6
        at_peak = essential_flops(bins.max_count, p, 3) / (peak_cpu * 1e3)
        print(f"  ceiling: the four kernels alone allow {loop_bin / kernels:.1f}x the loop, "
              f"with the binning ({binning:.0f} µs per bin) {loop_bin / (kernels + binning):.1f}x; "
              f"the essential flops at the matmul peak take {at_peak:.0f} µs per bin "
              f"({loop_bin / at_peak:.1f}x); 10x needs {loop_bin / 10:.0f} µs per bin in all")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
