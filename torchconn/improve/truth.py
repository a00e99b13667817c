"""The truth for a known system: its exact local model around a gait, and the best gait.

:func:`exact_local_model` is what a perfect estimator would return -- ``A(γ(φ))``,
``∂A/∂r(γ(φ))`` and ``M(γ(φ))`` of the simulator, as Fourier series in phase, with zero standard
errors. :func:`ceiling` runs the existing gait optimiser with the true connection (the best
displacement in its gait family), the ceiling a data-driven loop is judged against.
"""

from __future__ import annotations

import math

import torch

from ..phase.fourier import FourierSeries, fit_fourier
from ..physics.gaits.gait import as_gait
from ..physics.gaits.optimize import NINE_LINK_MAX_RADIUS, OptimisedGait, optimise_gait
from ..physics.gaits.reference import nine_link_modes
from ..physics.systems.base import LocomotionSystem
from ..regression.model import BinEstimates, LocalConnectionModel

__all__ = ["exact_local_model", "ceiling"]


def exact_local_model(
    system: LocomotionSystem, gait, *, n_grid: int = 256, tube_rms: float | None = None
) -> LocalConnectionModel:
    """The exact :class:`LocalConnectionModel` of ``system`` around ``gait`` (phase = gait's θ).

    ``A``, ``∂A/∂r`` and ``M`` along the gait are sampled at ``n_grid`` phases and fitted with
    Fourier series of order ``n_grid/2 − 1`` (smooth periodic functions: their harmonics decay
    exponentially); ``c = A γ̇`` and ``b = ∂A/∂r γ̇`` as the true mechanics has them. Standard
    errors are zero. ``tube_rms`` (rad per joint) sets the tube the gait-distance check uses.
    """
    gait = as_gait(gait)
    d = system.shape_dim
    if gait.shape_dim != d:
        raise ValueError(f"gait has {gait.shape_dim} joints but the system has {d}")
    kw = dict(dtype=torch.float64, device=getattr(gait, "device", None))  # the gait's device
    grid = torch.arange(n_grid, **kw) * (2 * math.pi / n_grid)
    order = n_grid // 2 - 1
    gamma, gamma_dot = gait(grid), gait.velocity(grid)
    a, m = system.connection_and_metric(gamma)
    da = system.connection_jacobian(gamma)
    c = (a @ gamma_dot.unsqueeze(-1)).squeeze(-1)
    b = torch.einsum("...kij,...i->...kj", da, gamma_dot)

    def series(values: torch.Tensor, ndim: int) -> FourierSeries:
        return fit_fourier(grid, values, order, value_ndim=ndim)

    zeros = torch.zeros_like
    bins = BinEstimates(
        phase=grid, gamma=gamma, gamma_dot=gamma_dot, c=c, b=b, A=a, dA=da,
        c_se=zeros(c), b_se=zeros(b), A_se=zeros(a), dA_se=zeros(da),
        n_samples=torch.zeros(n_grid, dtype=torch.int64, device=grid.device), M=m, M_se=zeros(m),
    )
    meta = {"exact": True, "window": 0.5, "settings": {"kernel": "box"}}
    if tube_rms is not None:
        meta["tube_rms"] = [float(tube_rms)] * d
    return LocalConnectionModel(
        gamma=series(gamma, 1), phase_rate=torch.tensor(1.0, **kw),
        c=series(c, 1), b=series(b, 2), A=series(a, 2), dA=series(da, 3), M=series(m, 2),
        bins=bins, meta=meta,
    )


def ceiling(system: LocomotionSystem, *, order: int = 4, starts=(1.0, 2.0),
            component: int | str = "planar", max_turn: float | None = None) -> OptimisedGait:
    """The best displacement per cycle with the true connection, by the existing optimiser.

    ``component``: ``"planar"`` (``|(x, y)|``, the loop's ``"displacement"`` objective) or 0, 1, 2.
    ``max_turn``: the largest net rotation per cycle (rad; None: any) -- the loop's
    :attr:`TrustRegion.max_turn <torchconn.improve.TrustRegion.max_turn>`, for the ceiling of
    the same objective the loop maximises.

    Simple loops star-shaped about the straight shape (:class:`PolarGait`, loop radius ≤ π) in
    the shape plane of a 3-link, or in the two-mode plane of the 9-link (modal radius ≤ π/2);
    both directions and every start radius in ``starts`` (clipped inside the bound) are tried.
    """
    d = system.shape_dim
    if d == 2:
        modes, bound = None, math.pi
    elif d == 8:
        modes, bound = nine_link_modes(), NINE_LINK_MAX_RADIUS
    else:
        raise ValueError(f"the ceiling's gait family is defined for 2 or 8 joints, got {d}")
    runs = [
        optimise_gait(system, modes=modes, order=order, radius=min(r, 0.9 * bound),
                      max_radius=bound, direction=s, component=component, max_turn=max_turn)
        for r in starts for s in (1, -1)
    ]
    return max(runs, key=lambda run: run.x_displacement)


