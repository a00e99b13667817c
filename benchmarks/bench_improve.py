"""The improvement loop against its ceiling and a model-free baseline (issue 17's table).

For each swimmer and seed: the loop from a circle gait of radius 0.5 (K rounds of trials ×
cycles, the paper's SDE, observation noise ``--omega``), the true value of the gait recorded in
each round and of each proposal (the simulator's exact value), the coverage of the prediction
intervals, the ceiling (:func:`torchconn.improve.ceiling`: the best gait with the true connection
in the loop's own gait family, joint limits and turning limit, for every link count), and the
model-free finite-difference optimiser given ``--fd-factor`` × the loop's recorded cycles.
Prints Markdown tables, then per link count and noise level one line
``cycles-to-90: links=L omega=W cycles=C per_link=P``: C the median over seeds of the cycles
recorded until the true objective of a recorded gait first reaches 90 % of the ceiling
(``none`` if not reached).

    python benchmarks/bench_improve.py --links 3 5 9 --seeds 0 1 --rounds 8 --omega 0 0.002
    python benchmarks/bench_improve.py --links 3 --max-turn none   # the loop may turn too
"""

from __future__ import annotations

import argparse
import itertools
import math
import statistics
import time

import torch

from torchconn import NLinkSwimmer
from torchconn.improve import (
    LoopSettings,
    TrustRegion,
    ceiling,
    circle_gait,
    improve,
    true_objective,
)
from torchconn.improve.baselines import finite_difference_baseline
from torchconn.physics.gaits import evaluate


def cycles_to(result, cap: float | None, fraction: float) -> int | None:
    """Cycles recorded until (and including) the first recording of a gait whose true
    objective reaches ``fraction`` of ``cap``; None if no recorded gait does (or no cap)."""
    if cap is None:
        return None
    return next((r.cycles_used for r in result.rounds if r.true >= fraction * cap), None)


def median_cycles(values: list[int | None]) -> float | None:
    """The median over seeds, a seed that never reached counting as infinitely many cycles;
    None when the median is not reached."""
    med = statistics.median(math.inf if v is None else v for v in values)
    return None if math.isinf(med) else med


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5, 9])
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--rounds", type=int, default=8)
    p.add_argument("--trials", type=int, default=4)
    p.add_argument("--cycles", type=int, default=20)
    p.add_argument("--omega", type=float, nargs="+", default=[0.0],
                   help="observation noise levels (one loop per level, link count and seed)")
    p.add_argument("--max-turn", default="0.05",
                   help="the loop's turning limit per cycle (rad), or 'none'")
    p.add_argument("--fd-factor", type=float, default=3.0,
                   help="the model-free baseline gets this many times the loop's cycles")
    p.add_argument("--no-baseline", action="store_true")
    p.add_argument("--no-ceiling", action="store_true")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    max_turn = None if args.max_turn.lower() == "none" else float(args.max_turn)
    rows, covered, reached = [], {}, {}
    for omega, links in itertools.product(args.omega, args.links):
        system = NLinkSwimmer(links)
        start = circle_gait(links - 1, 0.5)
        for seed in args.seeds:
            settings = LoopSettings(rounds=args.rounds, trials=args.trials, cycles=args.cycles,
                                    seed=seed, omega=omega,
                                    trust_region=TrustRegion(scale=3.0, max_turn=max_turn))
            # the same family for every seed and noise level: computed once (cached)
            cap = None if args.no_ceiling else ceiling(system, "displacement", settings).value
            t0 = time.perf_counter()
            res = improve(system, start, settings)
            loop_s = time.perf_counter() - t0
            phi = torch.linspace(0, 2 * math.pi, 256, dtype=torch.float64)
            print(f"\n{links}-link, seed {seed}, ω {omega}, start {res.start_true:.4f}, "
                  f"loop {loop_s:.0f} s")
            print("| round | cycles | observed | true | accepted | step (rad) | predicted [95%] "
                  "| realised | covered | max abs r |")
            print("|---|---|---|---|---|---|---|---|---|---|")
            for r in res.rounds:
                shape = float(torch.linalg.vector_norm(r.proposal(phi), dim=-1).max())
                print(f"| {r.index} | {r.cycles_used} | {r.observed:.4f} ± {r.observed_se:.4f} "
                      f"| {r.true:.4f} | {r.accepted} | {r.step:.3f} | {r.predicted:.4f} "
                      f"[{r.predicted_low:.4f}, {r.predicted_high:.4f}] | {r.realised:.4f} | "
                      f"{r.covered} | {shape:.2f} |")
            reached.setdefault((links, omega), []).append(cycles_to(res, cap, 0.9))
            hits = covered.setdefault((omega, links), [0, 0])
            hits[0] += sum(r.covered for r in res.rounds)
            hits[1] += len(res.rounds)
            # the loop moves on from accepted gaits: their true values, round by round
            kept = [r.true for r in res.rounds if r.accepted]
            worst_fall = max([0.0] + [kept[k] - kept[k + 1] for k in range(len(kept) - 1)])
            best = max(res.rounds, key=lambda r: r.realised)
            disp = evaluate(system, best.proposal).displacement
            print(f"best proposal's displacement per cycle (x, y, θ): {disp.numpy().round(4)}")
            fd_best = fd_cycles = fd_match = None
            if not args.no_baseline:
                budget = int(args.fd_factor * res.rounds[-1].cycles_used)
                steps = finite_difference_baseline(system, start, budget=budget, trials=1,
                                                   cycles=args.cycles, seed=seed,
                                                   max_turn=max_turn)
                if steps:
                    values = [true_objective(system, s.gait, "displacement") for s in steps]
                    fd_best, fd_cycles = max(values), steps[-1].cycles_used
                    gain = best.realised - res.start_true
                    match = [s.cycles_used for s, v in zip(steps, values, strict=True)
                             if v - res.start_true >= gain]
                    fd_match = match[0] if match else None
            rows.append((omega, links, seed, res.start_true, [r.true for r in res.rounds],
                         best.realised, cap, res.coverage, worst_fall,
                         res.rounds[-1].cycles_used, fd_best, fd_cycles, fd_match))
    print(f"\nturning limit {max_turn} rad per cycle; 'rounds' lists the true "
          "|(x, y)| per cycle of the gait recorded in each round")
    print("\n| ω | links | seed | start | rounds 1.. | best realised | ceiling (true A) | best/ceiling "
          "| intervals covering | worst fall between accepted gaits | loop cycles "
          "| model-free best (cycles) | model-free cycles to match |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for (omega, links, seed, start, per_round, best, cap, cov, fall, cyc, fdb, fdc, fdm) in rows:
        trail = " → ".join(f"{v:.3f}" for v in per_round[1:])
        ratio = "—" if cap is None else f"{best / cap:.0%}"
        capt = "—" if cap is None else f"{cap:.4f}"
        fd = "—" if fdb is None else f"{fdb:.4f} ({fdc})"
        fdm_s = "not reached" if fdb is not None and fdm is None else (fdm or "—")
        print(f"| {omega:g} | {links} | {seed} | {start:.4f} | {trail} | {best:.4f} | {capt} | {ratio} | "
              f"{cov:.0%} | {fall:.4f} | {cyc} | {fd} | {fdm_s} |")
    print("\n| ω | links | intervals covering the realised value |")
    print("|---|---|---|")
    for (omega, links), (hit, n) in covered.items():
        print(f"| {omega:g} | {links} | {hit}/{n} ({hit / n:.0%}) |")
    print()
    for (links, omega), per_seed in reached.items():
        med = median_cycles(per_seed)
        cyc, per_link = ("none", "none") if med is None else (f"{med:g}", f"{med / links:.1f}")
        print(f"cycles-to-90: links={links} omega={omega:g} cycles={cyc} per_link={per_link}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
