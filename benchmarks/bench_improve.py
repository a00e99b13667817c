"""The improvement loop against its ceiling and the model-free baseline, in recorded cycles.

For each swimmer, observation noise ``--omega`` and seed: the loop (:func:`torchconn.improve.improve`,
its defaults: recordings of ``trials × cycles``, one pooled model from every recording,
proposals when the gain interval excludes zero, excitation otherwise) from a circle gait of
radius 0.5, for ``--rounds`` recordings. Judged by the simulator's exact, penalised objective
(:func:`torchconn.improve.true_score`) of the gait the loop keeps, against the ceiling
(:func:`torchconn.improve.ceiling`: the optimum that an ascent with the true connection reaches
from the loop's start gait in the loop's own family, joint and turning limits; the best of many
starts is printed beside it -- the family has many local optima), and against the model-free
finite-difference optimiser given ``--fd-factor`` × the loop's cycles. Prints one Markdown row
per loop (cycles to 80/90/95 % of the ceiling, coverage of the gain intervals of the proposals
moved to, the largest fall between kept gaits in standard errors), then per link count and
noise level one line
``cycles-to-90: links=L omega=W cycles=C per_link=P``: C the median over seeds of the cycles
recorded until the kept gait first reaches 90 % of the ceiling (``none`` if not reached).

    python benchmarks/bench_improve.py --links 3 5 9 --seeds 0 1 2 --omega 0 0.002 0.005
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import math
import statistics
import time

import torch

from torchconn import NLinkSwimmer
from torchconn.improve import LoopSettings, ceiling, circle_gait, improve, true_score
from torchconn.improve.baselines import finite_difference_baseline


def median_cycles(values: list[int | None]) -> float | None:
    """The median over seeds, a seed that never reached counting as infinitely many cycles;
    None when the median is not reached."""
    med = statistics.median(math.inf if v is None else v for v in values)
    return None if math.isinf(med) else med


def cycles_to(result, cap: float | None, fraction: float) -> int | None:
    """Cycles recorded until (and including) the step after which the kept gait's exact,
    penalised objective first reaches ``fraction`` of ``cap``; None if it never does."""
    if cap is None:
        return None
    return next((r.cycles_used for r in result.rounds if r.kept_true >= fraction * cap), None)


def worst_fall(result) -> float:
    """The largest fall of the exact objective between consecutive kept gaits, in standard
    errors of the kept gait's observed objective (0 when it never fell)."""
    falls, last = [0.0], None
    for r in result.rounds:
        if last is not None and r.kept is not last.kept:
            falls.append((last.kept_true - r.kept_true) / max(last.observed_se, 1e-12))
        last = r
    return max(falls)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5, 9])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--rounds", type=int, default=None,
                   help="recordings per loop (default: 5 cycles per link's worth, doubled)")
    p.add_argument("--omega", type=float, nargs="+", default=[0.0, 0.002, 0.005])
    p.add_argument("--fd-factor", type=float, default=3.0,
                   help="the model-free baseline gets this many times the loop's cycles")
    p.add_argument("--ceiling-iterations", type=int, default=1000,
                   help="L-BFGS evaluations of the ceiling's ascent from the start gait")
    p.add_argument("--best-known-iterations", type=int, default=300,
                   help="L-BFGS evaluations per start of the best-known (multi-start) value")
    p.add_argument("--no-baseline", action="store_true")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    fractions = (0.8, 0.9, 0.95)
    print("| links | ω | seed | ceiling from the start / best known | start/ceiling | "
          "kept/ceiling | cycles to 80/90/95 % | covered | worst fall (SE) | "
          "model-free cycles to 90 % | loop s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    reached, covered = {}, {}
    for links, omega in itertools.product(args.links, args.omega):
        system = NLinkSwimmer(links)
        start = circle_gait(links - 1, 0.5)
        for seed in args.seeds:
            base = LoopSettings(seed=seed, omega=omega)
            rounds = args.rounds or math.ceil(2 * 5 * links / (base.trials * base.cycles))
            settings = dataclasses.replace(base, rounds=rounds)
            # the optimum the true connection's ascent reaches from the loop's start (the
            # targets' ceiling), and the best of many starts (a lower bound on the family's)
            cap = ceiling(system, "displacement", settings, starts=[start], peaks=(),
                          random_starts=0, max_iter=args.ceiling_iterations).value
            best_known = ceiling(system, "displacement", settings,
                                 max_iter=args.best_known_iterations).value
            t0 = time.perf_counter()
            res = improve(system, start, settings)
            loop_s = time.perf_counter() - t0
            to = [cycles_to(res, cap, f) for f in fractions]
            reached.setdefault((links, omega), []).append(to[1])
            moved = [r.covered for r in res.rounds if r.moved]
            hits = covered.setdefault((links, omega), [0, 0])
            hits[0], hits[1] = hits[0] + sum(moved), hits[1] + len(moved)
            fd = "—"
            if not args.no_baseline:
                steps = finite_difference_baseline(
                    system, start, budget=int(args.fd_factor * res.rounds[-1].cycles_used),
                    trials=1, cycles=settings.cycles, seed=seed)
                hit = [s.cycles_used for s in steps
                       if true_score(system, s.gait, settings) >= 0.9 * cap]
                fd = hit[0] if hit else f"not in {steps[-1].cycles_used if steps else 0}"
            print(f"| {links} | {omega:g} | {seed} | {cap:.4f} / {best_known:.4f} | "
                  f"{res.start_true / cap:.0%} | "
                  f"{res.rounds[-1].kept_true / cap:.0%} | "
                  f"{' / '.join('—' if c is None else str(c) for c in to)} | "
                  f"{sum(moved)}/{len(moved)} | {worst_fall(res):.1f} | {fd} | {loop_s:.0f} |",
                  flush=True)
    print("\n| links | ω | proposals moved to whose interval held the realised objective |")
    print("|---|---|---|")
    for (links, omega), (hit, n) in covered.items():
        print(f"| {links} | {omega:g} | {hit}/{n} ({hit / max(n, 1):.0%}) |")
    print()
    for (links, omega), per_seed in reached.items():
        med = median_cycles(per_seed)
        cyc, per_link = ("none", "none") if med is None else (f"{med:g}", f"{med / links:.1f}")
        print(f"cycles-to-90: links={links} omega={omega:g} cycles={cyc} per_link={per_link}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
