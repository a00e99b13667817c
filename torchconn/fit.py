"""``torchconn-fit DATA.csv [MORE.csv …] --links N --out DIR``: fit your recordings.

Also runs as ``python -m torchconn.fit``. Reads trajectory CSV files (the format of
docs/conventions.md, section "Trajectory file format"), estimates phase and limit cycle, fits the
local connection (and the metric, when a ``power`` column is present) with all trials pooled
into one model, and writes ``DIR/model.npz``, ``DIR/connection.csv`` (one row per phase on a
uniform grid: ``phase, r1…rd, A_x_i, A_y_i, A_theta_i, dA_<k>_<i>_<j>[, M_<i>_<j>,
M_gamma_dot_<i>, power_on_cycle]``) and PNG plots with 95% confidence bands. ``M_gamma_dot``
(``M̂γ̇``) and ``power_on_cycle`` (``γ̇ᵀM̂γ̇``) are what the gait itself identifies; the full
``M̂`` is only as good as the recording's off-cycle excitation (see the bands in ``metric.png``).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

import torch

from .io.trajectory_files import read_csv
from .phase.phaser import Phaser
from .regression.estimator import ConnectionEstimator
from .regression.model import LocalConnectionModel
from .regression.plots import ROWS, plot_connection, plot_limit_cycle, plot_metric
from .regression.tube import TubeRegression

__all__ = ["connection_table", "write_connection_csv", "main"]


def connection_table(model: LocalConnectionModel, n_points: int = 100):
    """Columns and rows of ``connection.csv`` for an unbatched model, on a uniform phase grid."""
    if model.batch_shape:
        raise ValueError(f"connection_table needs one model, got batch {tuple(model.batch_shape)}")
    d = model.shape_dim
    phi = torch.arange(n_points, dtype=torch.float64) * (2 * math.pi / n_points)
    cols = ["phase"] + [f"r{i + 1}" for i in range(d)]
    blocks = [phi[:, None], model.gamma_at(phi)]
    cols += [f"A_{k}_{i + 1}" for k in ROWS for i in range(d)]
    blocks.append(model.connection(phi).reshape(n_points, -1))
    cols += [f"dA_{k}_{i + 1}_{j + 1}" for k in ROWS for i in range(d) for j in range(d)]
    blocks.append(model.connection_jacobian(phi).reshape(n_points, -1))
    if model.M is not None:
        cols += [f"M_{i + 1}_{j + 1}" for i in range(d) for j in range(d)]
        blocks.append(model.metric(phi).reshape(n_points, -1))
        # the parts of M̂ the gait itself identifies, beside the full M̂
        cols += [f"M_gamma_dot_{i + 1}" for i in range(d)] + ["power_on_cycle"]
        blocks += [model.metric_gamma_dot(phi), model.power_on_cycle(phi)[:, None]]
    return cols, torch.cat(blocks, -1).tolist()


def write_connection_csv(model: LocalConnectionModel, path: Path | str, n_points: int = 100) -> Path:
    """Write :func:`connection_table` to ``path`` (CSV with a header row)."""
    path = Path(path)
    cols, rows = connection_table(model, n_points)
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(cols)
        writer.writerows(rows)
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="torchconn-fit",
        description="Fit one local connection model (and the metric, when the files have a "
        "power column) to your recorded trials, pooled, and write DIR/model.npz, "
        "DIR/connection.csv (one row per phase) and PNG plots with 95% bands. "
        "Also runs as python -m torchconn.fit.",
    )
    p.add_argument("data", nargs="+", type=Path,
                   help="trajectory CSV files: columns t, x, y, theta, r1..rd[, power][, trial], "
                   'one trial per file or several with a trial column (format: '
                   'docs/conventions.md, section "Trajectory file format")')
    p.add_argument("--links", type=int, required=True, help="number of links N (d = N - 1 joints)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    defaults, phaser = TubeRegression(), Phaser()
    p.add_argument("--n-bins", type=int, default=defaults.n_bins,
                   help=f"phase bins (default {defaults.n_bins})")
    p.add_argument("--fourier-order", type=int, default=defaults.fourier_order,
                   help=f"Fourier order in phase (default {defaults.fourier_order})")
    p.add_argument("--window", type=float, default=None,
                   help="bin half-width in bin spacings (default: sized from the data)")
    p.add_argument("--phase-order", type=int, default=phaser.order,
                   help=f"Phaser correction order (default {phaser.order})")
    p.add_argument("--grid", type=int, default=100, help="rows of connection.csv")
    args = p.parse_args(argv)
    if args.links < 2:
        p.error(f"--links must be >= 2, got {args.links}")

    try:
        traj = read_csv(args.data, n_joints=args.links - 1)
        est = ConnectionEstimator(
            phaser=Phaser(order=args.phase_order),
            regression=TubeRegression(n_bins=args.n_bins, fourier_order=args.fourier_order,
                                      window=args.window),
            pool=True,
        ).fit(traj)
    except (ValueError, FileNotFoundError) as err:
        print(f"torchconn-fit: error: {err}", file=sys.stderr)
        return 2
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    model = est.model_
    model.save(out / "model.npz")
    write_connection_csv(model, out / "connection.csv", args.grid)
    plot_connection(model, out / "connection.png")
    plot_limit_cycle(model, out / "limit_cycle.png", est.trajectory_.smoothed.r)
    if model.M is not None:
        plot_metric(model, out / "metric.png")
    print(f"fitted one model to {traj.batch_shape.numel()} trial(s) of {traj.n_samples} "
          f"samples (d = {traj.shape_dim})")
    if model.M is not None:
        noise = (model.meta or {}).get("metric_noise_std")
        if noise is not None:
            print("shape noise estimated for the metric (rad): "
                  + ", ".join(f"r{i + 1} {w:.2g}" for i, w in enumerate(noise)))
        print("metric: M_gamma_dot and power_on_cycle are identified by the gait itself; the "
              "full M only as far as the data leave the cycle (see the bands in metric.png)")
    print(f"wrote {out / 'model.npz'}, {out / 'connection.csv'} and plots")
    return 0


if __name__ == "__main__":
    sys.exit(main())
