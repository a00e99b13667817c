"""``python -m torchconn``: a one-screen check that the install works.

Prints the 3-link swimmer's connection and curvature at the straight shape (compare with the
closed forms in docs/conventions.md) and the reference gait's displacement, cost and efficiency.
"""

from __future__ import annotations

import sys

import torch

from . import NLinkSwimmer
from .physics.gaits import evaluate, three_link_gait


def main(argv: list[str] | None = None) -> int:
    swimmer = NLinkSwimmer(3)
    straight = torch.zeros(2, dtype=torch.float64)
    torch.set_printoptions(precision=6)
    print(f"{swimmer}\nA(0) =\n{swimmer.connection(straight)}")
    print(f"DA(0) = {swimmer.curvature(straight)[:, 0]}  (DA_x = -5/243 = {-5 / 243:.6f})")
    m = evaluate(swimmer, three_link_gait("extremal"))
    print(f"reference extremal gait: displacement {m.displacement}, cost {m.cost:.6f}, "
          f"efficiency {m.efficiency:.6f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
