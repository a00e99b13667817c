"""Speed a user feels: CPU time of ``import torch``, ``import torchconn`` and ``torchconn-fit``.

Each is run ``--repeats`` times in a fresh Python process, one of each per round (so that a
change of the machine's load affects them alike); the CPU time of a run is the user + system
time of that child (``resource.getrusage(RUSAGE_CHILDREN)`` before and after: CPU time, not
wall time, which on a shared machine depends on the other jobs), and the least of the repeats
is kept. The fit is ``torchconn-fit`` on the shipped prickleback (711 samples, 5 links)
converted to a trajectory CSV as the README converts it, with the default options (figures
and report on), written into a temporary folder. Every child runs with ``OMP_NUM_THREADS`` =
``MKL_NUM_THREADS`` = ``--threads``.

It prints each best CPU time and the two ratios of the speed issue:

- ``import torchconn`` over ``import torch``, as added seconds (target <= 0.3 s);
- ``torchconn-fit`` over ``import torch``, as a ratio (target <= 2);

and, for where the time goes, the same fit with ``--no-figures``.

``--profile`` writes a cProfile of one fit (``fit.prof`` in the current folder) and prints its
top functions by cumulative time.

    python benchmarks/bench_startup.py [--repeats 5] [--threads 1] [--profile]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import pstats
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

#: the fit, the way the console script ``torchconn-fit`` starts it (argv from the command line)
FIT = "import sys; from torchconn.fit import main; sys.exit(main(sys.argv[1:]))"


def cpu_seconds(cmd: list[str], env: dict[str, str], cwd: Path) -> float:
    """User + system CPU seconds of one run of ``cmd`` in ``cwd`` (its output discarded)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, env=env, cwd=cwd, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def best_of(commands: dict[str, list[str]], env: dict[str, str], cwd: Path, repeats: int
            ) -> dict[str, float]:
    """The least CPU seconds of ``repeats`` runs of each command, run in turn (one of each per
    round), so that a change of the machine's load affects them alike."""
    times: dict[str, list[float]] = {name: [] for name in commands}
    for _ in range(repeats):
        for name, cmd in commands.items():
            times[name].append(cpu_seconds(cmd, env, cwd))
    return {name: min(t) for name, t in times.items()}


def converted_prickleback(folder: Path, env: dict[str, str]) -> Path:
    """The prickleback as a trajectory CSV (``torchconn-convert`` with the recording's flags)."""
    code = ("import sys, torchconn.datasets as d; from torchconn.convert import main; "
            "sys.exit(main(d.prickleback().convert_args() + ['--out', sys.argv[1]]))")
    subprocess.run([sys.executable, "-c", code, str(folder / "converted")], env=env,
                   cwd=folder, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    (csv,) = (folder / "converted").glob("*.csv")
    return csv


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=5, help="runs of each; the least CPU time counts")
    p.add_argument("--threads", type=int, default=1, help="OMP/MKL threads of every child")
    p.add_argument("--profile", action="store_true", help="profile one fit into fit.prof")
    args = p.parse_args(argv)
    # the children import the torchconn this interpreter would (not one in their folder)
    package = Path(importlib.util.find_spec("torchconn").origin).parent
    path = os.pathsep.join([str(package.parent), *filter(None, [os.environ.get("PYTHONPATH")])])
    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), MKL_NUM_THREADS=str(args.threads),
               PYTHONPATH=path)
    py = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        csv = converted_prickleback(tmp, env)
        fit = [py, "-c", FIT, str(csv), "--links", "5", "--threads", str(args.threads),
               "--out", str(tmp / "fitted")]
        if args.profile:
            subprocess.run([py, "-m", "cProfile", "-o", str(Path("fit.prof").resolve()), "-m",
                            "torchconn.fit", *fit[3:]], env=env, cwd=tmp, check=True,
                           stdout=subprocess.DEVNULL)
            pstats.Stats("fit.prof").sort_stats("cumulative").print_stats(40)
        best = best_of({"torch": [py, "-c", "import torch"],
                        "torchconn": [py, "-c", "import torchconn"], "fit": fit,
                        "no_figures": [*fit, "--no-figures"]},
                       env, tmp, args.repeats)
    t_torch, t_conn, t_fit = best["torch"], best["torchconn"], best["fit"]
    load = os.getloadavg()[0]
    print(f"torchconn from {package}; CPU seconds, best of {args.repeats}, {args.threads} "
          f"thread(s), load average {load:.1f} on {os.cpu_count()} cores:")
    print(f"  import torch       {t_torch:6.2f}")
    print(f"  import torchconn   {t_conn:6.2f}   adds {t_conn - t_torch:+.2f} s to import torch "
          f"(target <= 0.3 s)")
    print(f"  torchconn-fit      {t_fit:6.2f}   {t_fit / t_torch:.2f}x import torch "
          f"(target <= 2x; prickleback, 711 samples, 5 links, figures on)")
    print(f"    --no-figures     {best['no_figures']:6.2f}   "
          f"{best['no_figures'] / t_torch:.2f}x import torch (the figures cost "
          f"{t_fit - best['no_figures']:.2f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
