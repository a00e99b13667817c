"""A and M for 10^6 shapes of the 9-link swimmer: batched torch vs a plain per-shape NumPy loop.

Run by hand: ``python benchmarks/bench_swimmer.py [--shapes 1000000] [--loop-shapes 2000]``.
The loop is timed on the first ``--loop-shapes`` shapes and reported per shape; the ratio
compares shapes per second on the same inputs, and the two results are compared numerically.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from torchconn import NLinkSwimmer
from torchconn.testing.numpy_swimmer import connection_and_metric_numpy


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--shapes", type=int, default=1_000_000)
    p.add_argument("--loop-shapes", type=int, default=2000)
    p.add_argument("--chunk", type=int, default=8_192)
    args = p.parse_args()

    rng = np.random.default_rng(0)
    shapes = rng.normal(scale=0.6, size=(args.shapes, 8))
    swimmer = NLinkSwimmer(9)
    r = torch.from_numpy(shapes)

    t0 = time.perf_counter()
    for chunk in r.split(args.chunk):
        a, m = swimmer.connection_and_metric(chunk)
    t_batched = time.perf_counter() - t0

    lengths = np.full(9, 1 / 9)
    t0 = time.perf_counter()
    ref = [connection_and_metric_numpy(x, lengths) for x in shapes[: args.loop_shapes]]
    t_loop = time.perf_counter() - t0

    a_head, m_head = swimmer.connection_and_metric(r[: args.loop_shapes])
    err = max(np.abs(a_head.numpy() - np.stack([x[0] for x in ref])).max(),
              np.abs(m_head.numpy() - np.stack([x[1] for x in ref])).max())
    rate_b = args.shapes / t_batched
    rate_l = args.loop_shapes / t_loop
    print(f"torch threads: {torch.get_num_threads()}")
    print(f"batched torch : {args.shapes} shapes in {t_batched:.2f} s = {rate_b:,.0f} shapes/s")
    print(f"numpy loop    : {args.loop_shapes} shapes in {t_loop:.2f} s = {rate_l:,.0f} shapes/s")
    print(f"ratio         : {rate_b / rate_l:.0f}x   (max |difference| {err:.1e})")


if __name__ == "__main__":
    main()
