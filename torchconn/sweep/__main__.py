"""``python -m torchconn.sweep``: run the paper's experiments and check its claims."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from .config import load_config, sweep_config_names
from .runner import run_sweep


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="torchconn-sweep",
        description="Batched sweeps over system and observation noise (the paper's Sec. 5). "
        "With no arguments, runs the packaged default sweep (about 80 s on 2 cores). "
        "Also runs as python -m torchconn.sweep.",
    )
    p.add_argument("--config", metavar="NAME|FILE",
                   help="sweep config: the name of a packaged config (%s) or a path to a TOML "
                   "file; default: default" % ", ".join(sweep_config_names()))
    p.add_argument("--out", type=Path, help="output directory (default: runs/<config name>)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set experiment.trials=2 "
                   "--set simulation.n_cycles=10 (repeatable)")
    p.add_argument("--trials", type=int, help="shortcut for --set experiment.trials=N")
    p.add_argument("--cycles", type=int, help="shortcut for --set simulation.n_cycles=N")
    p.add_argument("--workers", type=int, default=0,
                   help="run experiments on a local Dask cluster with N workers")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler, tcp://HOST:PORT")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads per process (default 1: the batched work is made of many "
                   "small tensor ops, which extra threads slow down; use --workers for cores)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or log lines")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    args = p.parse_args(argv)

    overrides = list(args.overrides)
    if args.trials is not None:
        overrides.append(f"experiment.trials={args.trials}")
    if args.cycles is not None:
        overrides.append(f"simulation.n_cycles={args.cycles}")
    try:
        config = load_config(args.config, overrides)
    except (ValueError, FileNotFoundError) as err:
        p.error(str(err))
    if args.threads < 1:
        p.error(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    out = args.out or Path("runs") / config.name
    summary = run_sweep(config, out, workers=args.workers, scheduler=args.scheduler,
                        quiet=args.quiet, figures=not args.no_figures)
    if args.quiet:
        return 0
    print(f"results in {summary['out']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
