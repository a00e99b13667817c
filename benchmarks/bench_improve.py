"""The improvement loop against its ceiling and a model-free baseline (issue 17's table).

For each swimmer: the loop from a circle gait of radius 0.5 (K rounds of trials × cycles, the
paper's SDE), the realised objective of each proposal (the simulator's exact value), the
coverage of the prediction intervals, the optimiser's best gait with the true connection (the
ceiling, 3- and 9-link: ``configs/gaits.toml``), and the model-free finite-difference optimiser
given 3x the loop's recorded cycles. Prints a Markdown table; ``--links 3 5 9``, ``--seed``.

    python benchmarks/bench_improve.py --links 3 9 --rounds 8
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from torchconn import NLinkSwimmer
from torchconn.improve import LoopSettings, ceiling, circle_gait, improve, true_objective
from torchconn.improve.baselines import finite_difference_baseline
from torchconn.physics.gaits import ModalGait, evaluate, nine_link_modes, optimised_gait


def ceiling_value(links: int) -> tuple[float, float] | tuple[None, None]:
    """The optimiser's best with the true connection, in its gait family (simple loops about
    the straight shape, |r| ≤ π): ``(|(x, y)| maximised, x of the stored x-extremal gait)``."""
    if links == 3:
        stored = optimised_gait("three_link_x_extremal")
    elif links == 9:
        stored = ModalGait(nine_link_modes(), optimised_gait("nine_link_x_extremal"))
    else:
        return None, None
    x = float(evaluate(NLinkSwimmer(links), stored, 1024).displacement[0])
    return ceiling(NLinkSwimmer(links)).x_displacement, x


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5, 9])
    p.add_argument("--rounds", type=int, default=8)
    p.add_argument("--trials", type=int, default=4)
    p.add_argument("--cycles", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fd-factor", type=float, default=3.0,
                   help="the model-free baseline gets this many times the loop's cycles")
    p.add_argument("--no-baseline", action="store_true")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    for links in args.links:
        system = NLinkSwimmer(links)
        start = circle_gait(links - 1, 0.5)
        t0 = time.perf_counter()
        res = improve(system, start, LoopSettings(rounds=args.rounds, trials=args.trials,
                                                  cycles=args.cycles, seed=args.seed))
        loop_s = time.perf_counter() - t0
        phi = torch.linspace(0, 2 * math.pi, 256, dtype=torch.float64)
        print(f"\n{links}-link, start {res.start_true:.4f}, loop {loop_s:.0f} s")
        print("| round | cycles | measured | true | accepted | predicted [95%] | realised | covered "
              "| max abs r |")
        print("|---|---|---|---|---|---|---|---|---|")
        for r in res.rounds:
            shape = float(torch.linalg.vector_norm(r.proposal(phi), dim=-1).max())
            print(f"| {r.index} | {r.cycles_used} | {r.measured:.4f} ± {r.measured_se:.4f} | "
                  f"{r.true:.4f} | {r.accepted} | {r.predicted:.4f} [{r.predicted_low:.4f}, "
                  f"{r.predicted_high:.4f}] | {r.realised:.4f} | {r.covered} | {shape:.2f} |")
        best = max(r.realised for r in res.rounds)
        kept = [r.true for r in res.rounds if r.accepted]  # the gaits the loop moved on from
        falls = [kept[k] - kept[k + 1] for k in range(len(kept) - 1)]
        worst_fall = max([0.0] + falls)
        cap, cap_x = ceiling_value(links)
        last = evaluate(system, max(res.rounds, key=lambda r: r.realised).proposal).displacement
        print(f"best proposal's displacement per cycle (x, y, θ): {last.numpy().round(4)}; "
              f"ceiling |(x, y)| {cap}, stored x-extremal x {cap_x}")
        fd_best, fd_cycles, fd_match = None, None, None
        if not args.no_baseline:
            budget = int(args.fd_factor * res.rounds[-1].cycles_used)
            steps = finite_difference_baseline(system, start, budget=budget, trials=1,
                                               cycles=args.cycles, seed=args.seed)
            if steps:
                fd_best = max(true_objective(system, s.gait, "displacement") for s in steps)
                fd_cycles = steps[-1].cycles_used
                gain = best - res.start_true
                match = [s.cycles_used for s in steps
                         if true_objective(system, s.gait, "displacement") - res.start_true
                         >= gain]
                fd_match = match[0] if match else None
        rows.append((links, res.start_true, best, cap, res.coverage, worst_fall,
                     res.rounds[-1].cycles_used, fd_best, fd_cycles, fd_match, loop_s))
    print("\n| links | start | best realised | ceiling (true A) | best/ceiling | improvement "
          "| intervals covering | worst fall of true between rounds | loop cycles "
          "| model-free best (cycles) | model-free cycles to match |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for (links, start, best, cap, cov, fall, cyc, fdb, fdc, fdm, _) in rows:
        ratio = "—" if cap is None else f"{best / cap:.0%}"
        capt = "—" if cap is None else f"{cap:.4f}"
        fd = "—" if fdb is None else f"{fdb:.4f} ({fdc})"
        fdm_s = "not reached" if fdb is not None and fdm is None else (fdm or "—")
        print(f"| {links} | {start:.4f} | {best:.4f} | {capt} | {ratio} | "
              f"{best / start - 1:+.0%} | {cov:.0%} | {fall:.4f} | {cyc} | {fd} | {fdm_s} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
