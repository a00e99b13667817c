"""Gait optimisation: maximise one cycle's x-displacement over Fourier coefficients.

The objective is differentiated by autograd through the fourth-order Magnus integration of
:mod:`torchconn.physics.gaits.evaluate` and maximised with L-BFGS (strong-Wolfe line search). Run as
``python -m torchconn.physics.gaits.optimize --out FILE.toml`` to recompute the optimised gaits
(the repository's ``configs/gaits.toml``, packaged as ``torchconn.configs``, was written with
``--out configs/gaits.toml`` from the repository root; read another file with
``reference_gait(system, path=FILE.toml)``).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from ..._output import write_bytes_atomic
from ..systems import NLinkSwimmer
from ..systems.base import LocomotionSystem
from .evaluate import displacement, evaluate
from .gait import ModalGait, PolarGait
from .reference import nine_link_modes, three_link_gait

__all__ = ["OptimisedGait", "optimise_gait", "main", "NINE_LINK_MAX_RADIUS"]

#: bound on the 9-link modal amplitude: every joint angle stays within ±π/2, short of the
#: coiled shapes where the body would cross itself.
NINE_LINK_MAX_RADIUS = math.pi / 2


@dataclass(frozen=True)
class OptimisedGait:
    gait: PolarGait | ModalGait
    x_displacement: float
    iterations: int


def _build(params: Tensor, direction: int, modes: Tensor | None, max_radius: float):
    plane = PolarGait(params.new_zeros(2), params, direction, max_radius)
    return plane if modes is None else ModalGait(modes, plane)


def optimise_gait(
    system: LocomotionSystem,
    *,
    modes: Tensor | None = None,
    order: int = 4,
    radius: float = 1.0,
    max_radius: float = math.pi,
    direction: int = 1,
    component: int | str = 0,
    max_turn: float | None = None,
    n_steps: int = 128,
    max_iter: int = 300,
) -> OptimisedGait:
    """Maximise one component (0 = x; "planar": |(x, y)|) of a cycle's displacement over simple
    planar loops.

    The gait is a :class:`PolarGait` centred on the straight shape (radius a bounded Fourier
    series of ``order``, at most ``max_radius``) in the shape plane (``d = 2``) or in the
    plane of ``modes (d, 2)``. The optimisation is local: it finds the extremal loop nearest
    the starting circle (the zero contour of the curvature around the straight shape).
    Richer families (a free Fourier series per joint) are unbounded: extra sub-loops inside a
    sign-definite region of the curvature add displacement without limit, the cycle ambiguity
    noted in the paper's Sec. 2.1.

    Args:
        system: the locomotion system; modes: ``(d, 2)`` or None when ``d = 2``.
        radius, direction: the starting circle (``direction`` +1 counter-clockwise).
        max_radius: bound on the loop's distance from the straight shape (rad).
        max_turn: largest net rotation ``|θ|`` per cycle (rad; None: any), enforced by a
            quadratic penalty ``10³ · max(|θ| − max_turn, 0)²`` as the improvement loop's
            proposals are (:class:`torchconn.improve.TrustRegion`).
        n_steps: Magnus steps per cycle inside the objective (O(n⁻⁴) error).
    Returns:
        the optimised gait, its displacement component (evaluated at 4·n_steps) and the number
        of objective evaluations.
    """
    if modes is None and system.shape_dim != 2:
        raise ValueError(f"a {system.shape_dim}-joint system needs modes (d, 2) to span a plane")
    if not 0 < radius < max_radius:
        raise ValueError(f"radius must lie in (0, max_radius={max_radius}), got {radius}")
    if max_turn is not None and not max_turn >= 0:
        raise ValueError(f"max_turn must be >= 0 or None, got {max_turn!r}")
    params = torch.zeros(2 * order + 1, dtype=torch.float64)
    params[0] = math.log(radius / (max_radius - radius))
    params.requires_grad_(True)
    opt = torch.optim.LBFGS(
        [params], lr=1, max_iter=max_iter, tolerance_grad=1e-10, tolerance_change=1e-14,
        history_size=20, line_search_fn="strong_wolfe",
    )
    count = [0]

    def closure() -> Tensor:
        opt.zero_grad()
        disp = displacement(system, _build(params, direction, modes, max_radius), n_steps)
        loss = -_component(disp, component)
        if max_turn is not None:
            loss = loss + 1e3 * torch.relu(disp[2].abs() - max_turn).pow(2)
        loss.backward()
        count[0] += 1
        return loss

    opt.step(closure)
    best = _build(params.detach(), direction, modes, max_radius)
    value = float(_component(displacement(system, best, 4 * n_steps), component))
    return OptimisedGait(best, value, count[0])


def _component(disp: Tensor, component: int | str) -> Tensor:
    """One displacement component, or ``"planar"``: the distance ``|(x, y)|`` moved per cycle."""
    if component == "planar":
        return torch.linalg.vector_norm(disp[:2])
    if component in (0, 1, 2):
        return disp[component]
    raise ValueError(f"component must be 0, 1, 2 or 'planar', got {component!r}")


def polar_params(gait: PolarGait | ModalGait) -> dict:
    """The stored form of an optimised gait."""
    plane = gait.plane_gait if isinstance(gait, ModalGait) else gait
    return {
        "radius_logit": [float(v) for v in plane.logit.coeffs[:, 0]],
        "direction": plane.direction,
        "max_radius": plane.max_radius,
    }


def _toml_entry(name: str, comment: str, run: OptimisedGait, extra: str = "") -> str:
    p = polar_params(run.gait)
    return (
        f"[{name}]\n# {comment}\n{extra}"
        f"x_displacement = {run.x_displacement!r}\n"
        f"direction = {p['direction']}\n"
        f"max_radius = {p['max_radius']!r}\n"
        f"radius_logit = {p['radius_logit']!r}\n\n"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m torchconn.physics.gaits.optimize",
        description="Optimise the x-extremal 3- and 9-link gaits and write them to a TOML file "
        "(the format of the packaged gaits.toml; read it back with "
        "torchconn.physics.gaits.reference_gait(system, path=FILE)).",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="FILE.toml",
                        help="where to write the gaits (e.g. configs/gaits.toml in a checkout)")
    parser.add_argument("--order", type=int, default=4, help="Fourier order of the log-radius")
    args = parser.parse_args(argv)

    runs3 = [
        optimise_gait(NLinkSwimmer(3), order=args.order, radius=rad, direction=sign)
        for rad in (1.5, 2.0) for sign in (1, -1)
    ]
    best3 = max(runs3, key=lambda run: run.x_displacement)
    ref_x = float(evaluate(NLinkSwimmer(3), three_link_gait("extremal"), 512).displacement[0])
    runs9 = [
        optimise_gait(NLinkSwimmer(9), modes=nine_link_modes(), order=args.order, radius=rad,
                      max_radius=NINE_LINK_MAX_RADIUS, direction=sign)
        for rad in (0.5, 1.0) for sign in (1, -1)
    ]
    best9 = max(runs9, key=lambda run: run.x_displacement)
    text = (
        "# Optimised x-extremal gaits, written by `python -m torchconn.physics.gaits.optimize`.\n"
        "# Each is a PolarGait: r(phi) = max_radius * sigmoid(f(phi)) (cos s phi, sin s phi),\n"
        "# s = direction, f = radius_logit as Fourier rows [a0, a1, b1, a2, b2, ...].\n\n"
        + _toml_entry("three_link_x_extremal", "in the (r1, r2) shape plane", run=best3,
                      extra=f"reference_x_displacement = {ref_x!r}\n")
        + _toml_entry("nine_link_x_extremal",
                      "in the (a1, a2) plane: r_k = a1 sin(2 pi k / 8) + a2 cos(2 pi k / 8)", best9)
    )
    write_bytes_atomic(args.out, text.encode())
    for name, runs, best in (("3-link", runs3, best3), ("9-link", runs9, best9)):
        print(f"{name}: optimised x-displacement {best.x_displacement:.6f} (starts: "
              f"{[round(r.x_displacement, 6) for r in runs]})")
    print(f"3-link reference extremal gait: {ref_x:.6f}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
