"""``torchconn-sweep`` (``python -m torchconn.sweep``): run the paper's experiments and check
its claims.

Exit codes: 0 done, 2 bad input or an unusable output folder (one line says what to fix),
1 an internal error.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .._cli import InputError, hold_freed_memory, resolve_device, run_command, set_threads
from ..cli.common import add_common
from .config import load_config, sweep_config_names
from .runner import default_jobs, run_sweep

PROG = "torchconn-sweep"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Batched sweeps over system and observation noise (the paper's Sec. 5). "
        "With no arguments, runs the packaged default sweep (about 30 s on 2 cores). "
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
    p.add_argument("--block", type=int, help="shortcut for --set block_trials=N (trials per "
                   "stored cell, a multiple of 4; the results do not depend on it)")
    p.add_argument("--device", metavar="DEVICE",
                   help="where the cells run: cpu, cuda or cuda:N (shortcut for --set "
                   "device=...; default: the config's device, cpu). CPU and CUDA draw different "
                   "random numbers from the same seeds: each device's results are reproducible, "
                   "and run.json records the device")
    p.add_argument("--jobs", type=int, metavar="N",
                   help="run N cells at once, each in a local process with --threads threads "
                   "(default: one per usable CPU core, as memory allows, or 1 with --device "
                   "cuda; 1: one after another in this process). The results are the same for "
                   "any N")
    p.add_argument("--workers", type=int, default=0,
                   help="run cells on a local Dask cluster with N workers")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler, tcp://HOST:PORT")
    p.add_argument("--wait", action="store_true",
                   help="if another run is writing --out, wait for it instead of exiting")
    add_common(p, device=False, quiet_help="no progress bar or log lines")  # --device above
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)

    def body() -> int:
        set_threads(args.threads)
        hold_freed_memory()
        overrides = list(args.overrides)
        for flag, key in (("trials", "experiment.trials"), ("cycles", "simulation.n_cycles"),
                          ("block", "block_trials")):
            if getattr(args, flag) is not None:
                overrides.append(f"{key}={getattr(args, flag)}")
        if args.device is not None:
            resolve_device(args.device)  # the flag's own message, before the config's
            overrides.append(f'device="{args.device}"')
        config = load_config(args.config, overrides)
        if args.workers < 0:
            raise InputError(f"--workers must be >= 0, got {args.workers}")
        if args.jobs is not None and (args.workers or args.scheduler):
            raise InputError("give either --jobs (local processes) or --workers/--scheduler "
                             "(Dask), not both")
        jobs = default_jobs(config, args.threads) if args.jobs is None else args.jobs
        summary = run_sweep(config, args.out or Path("runs") / config.name,
                            workers=args.workers, scheduler=args.scheduler, jobs=jobs,
                            quiet=args.quiet, figures=not args.no_figures, wait=args.wait)
        if not args.quiet:
            print(f"results in {summary.out}")
        return 0

    return run_command(PROG, body)


if __name__ == "__main__":
    sys.exit(main())
