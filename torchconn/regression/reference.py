"""The physics reference: a registered model of the body, its free parameters fitted to the data.

The simplest physics a biologist already has for a swimming or crawling body is resistive-force
theory: the viscous N-link swimmer (:class:`~torchconn.physics.systems.NLinkSwimmer`) with the
recording's link count. Its one free parameter, the lateral/longitudinal drag ratio ``k``, is
fitted to the recorded body velocity by least squares; nothing else is. The fitted reference

- predicts the body velocity of any samples (:meth:`PhysicsReference.predict`), a baseline the
  data-driven model has to beat;
- gives the first-order local model around a fitted cycle
  (:meth:`PhysicsReference.local_model`: ``c = A(γ)γ̇``, ``b = (∂A/∂r)γ̇``, ``A(γ)``,
  ``∂A/∂r(γ)``), the prior the estimator's connection can be shrunk towards.

A reference family is registered in :data:`FAMILIES` by name; a new one is one
:class:`ReferenceFamily` instance (its parameters with their bounds, and how to build the
system from them).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..phase.fourier import fit_fourier
from ..physics.systems.base import LocomotionSystem
from ..physics.systems.swimmer import NLinkSwimmer
from .model import LocalConnectionModel

__all__ = ["ReferenceFamily", "FAMILIES", "PhysicsReference", "fit_reference", "default_frame",
           "LOCAL_ORDER"]

#: the least Fourier order of a reference's local model (:meth:`PhysicsReference.local_model`)
LOCAL_ORDER = 12
#: the most samples a fit evaluates (more are thinned evenly)
MAX_ROWS = 1500
#: points of the coarse log-scale grid a one-parameter fit starts from
GRID_POINTS = 13


@dataclass(frozen=True)
class ReferenceFamily:
    """A family of physical models of a body with ``n_links`` links.

    Attributes:
        name: the key in :data:`FAMILIES`.
        description: one line, for reports.
        parameters: the free parameters, each ``(name, lower, upper)``; fitted on a log scale
            within the bounds.
        build: ``build(n_links, frame, **parameters)`` -> the
            :class:`~torchconn.physics.systems.base.LocomotionSystem`.
    """

    name: str
    description: str
    parameters: tuple[tuple[str, float, float], ...]
    build: Callable[..., LocomotionSystem]


#: the registered reference families
FAMILIES: dict[str, ReferenceFamily] = {
    "swimmer": ReferenceFamily(
        name="swimmer",
        description="viscous N-link swimmer (resistive-force theory), equal links",
        parameters=(("drag_ratio", 1.01, 100.0),),
        build=lambda n_links, frame, drag_ratio: NLinkSwimmer(n_links, drag_ratio=drag_ratio,
                                                              frame=frame),
    ),
}


def default_frame(n_links: int) -> str:
    """The body frame of a recording of ``n_links`` links when none is given: the middle link
    (``"center"``) for an odd count, the mean-rotation frame (``"com-mean"``) for an even one."""
    return "center" if n_links % 2 else "com-mean"


@dataclass(frozen=True)
class PhysicsReference:
    """A physical model standing in for the recorded body, fitted to its recording.

    Attributes:
        family: the :class:`ReferenceFamily`'s name.
        frame: the body frame of its velocities.
        n_links: the body's links (shape dimension + 1).
        parameters: each free parameter's fitted value, ``(...)`` per batch element (``()``
            when pooled).
    """

    family: str
    frame: str
    n_links: int
    parameters: dict[str, Tensor]

    @property
    def batch_shape(self) -> torch.Size:
        return next(iter(self.parameters.values())).shape

    def systems(self) -> list[LocomotionSystem]:
        """The fitted system of every batch element (flattened, C order)."""
        family = FAMILIES[self.family]
        flat = {k: v.reshape(-1) for k, v in self.parameters.items()}
        n = max(1, math.prod(self.batch_shape))
        with torch.device(next(iter(flat.values())).device):  # the system's own tensors
            return [family.build(self.n_links, self.frame,
                                 **{k: float(v[i]) for k, v in flat.items()})
                    for i in range(n)]

    def predict(self, r: Tensor, r_dot: Tensor) -> Tensor:
        """Body velocity ``A(r)ṙ`` of samples ``r, r_dot (..., N, d)`` (batch dims ``...`` the
        reference's, or any when pooled) -> ``(..., N, 3)``; NaN samples give NaN."""
        return _per_element(self, r.shape[:-2], lambda system, i: _body_velocity(
            system, _element(r, i, r.shape[:-2]), _element(r_dot, i, r.shape[:-2])))

    def local_model(self, model: LocalConnectionModel) -> LocalConnectionModel:
        """The reference's first-order model around ``model``'s cycle: ``c = A(γ)γ̇``,
        ``b = (∂A/∂r)γ̇``, ``A(γ)``, ``∂A/∂r(γ)`` (no metric), so that ``predict`` of the two
        models differs only where the data differ from the physics. The series have order
        :data:`LOCAL_ORDER` or ``model``'s, whichever is higher, fitted to the reference on a
        grid of phases (not limited by the model's bins)."""
        order = max(LOCAL_ORDER, model.c.order, model.b.order, model.A.order, model.dA.order)
        phase = torch.arange(4 * order + 4, dtype=model.c.coeffs.dtype,
                             device=model.device) * (2 * math.pi / (4 * order + 4))
        batch = model.batch_shape
        grid = phase.expand(tuple(batch) + phase.shape)
        gamma_all, gamma_dot_all = model.gamma_at(grid), model.gamma_dot_at(grid)

        def expand(system, i):
            gamma, gamma_dot = _element(gamma_all, i, batch), _element(gamma_dot_all, i, batch)
            a, jac = system.connection(gamma), system.connection_jacobian(gamma)
            c = (a @ gamma_dot.unsqueeze(-1)).squeeze(-1)
            b = torch.einsum("...kij,...i->...kj", jac, gamma_dot)
            return torch.cat([c, b.flatten(-2), a.flatten(-2), jac.flatten(-3)], -1)

        d = model.shape_dim
        values = _per_element(self, batch, expand)  # (..., G, 3 + 3d + 3d + 3d²)
        c, b, a, jac = values.split([3, 3 * d, 3 * d, 3 * d * d], -1)

        def series(x: Tensor, shape: tuple):
            return fit_fourier(phase, x.unflatten(-1, shape), order, value_ndim=len(shape))

        return dataclasses.replace(
            model, c=series(c, (3,)), b=series(b, (3, d)), A=series(a, (3, d)),
            dA=series(jac, (3, d, d)), dA_fit=None, M=None, dM=None,
            meta={**(model.meta or {}), "reference": self.describe()})

    def describe(self) -> dict:
        """JSON-ready: the family, its frame and the fitted parameters (nested lists)."""
        return {"family": self.family, "frame": self.frame,
                "parameters": {k: v.tolist() for k, v in self.parameters.items()}}


def fit_reference(r: Tensor, r_dot: Tensor, xi: Tensor, *, family: str = "swimmer",
                  frame: str | None = None, pool: bool = False) -> PhysicsReference:
    """Fit a reference family's free parameters to samples of the body velocity.

    The loss is the body velocity's squared error summed over the samples, each component
    divided by its total sum of squares about its mean (so ``v_x``, ``v_y`` and ``ω`` count
    alike, whatever their units): one minus the mean ``R²`` of the three. Each parameter is
    searched on a log scale within its bounds.

    Args:
        r, r_dot: ``(..., N, d)`` joint angles (rad) and their rates; xi: ``(..., N, 3)`` body
            velocity; NaN samples are skipped.
        family: a name in :data:`FAMILIES`.
        frame: the body frame of ``xi`` (default: :func:`default_frame`).
        pool: one set of parameters for all batch elements (else one per element).

    Raises:
        ValueError: an unknown family, or fewer than two usable samples in an element.
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown reference family {family!r}; registered: "
                         f"{', '.join(FAMILIES)}")
    spec = FAMILIES[family]
    n_links = r.shape[-1] + 1
    frame = frame or default_frame(n_links)
    batch = () if pool else r.shape[:-2]
    rows = [(r, r_dot, xi)] if pool else [
        tuple(_element(x, i, batch) for x in (r, r_dot, xi)) for i in range(math.prod(batch))]
    fitted = np.array([_fit_one(spec, n_links, frame, *row) for row in rows])  # (B, P)
    parameters = {name: torch.tensor(fitted[:, k].tolist(), dtype=torch.float64,
                                     device=r.device).reshape(batch)
                  for k, (name, _, _) in enumerate(spec.parameters)}
    return PhysicsReference(family, frame, n_links, parameters)


def _fit_one(spec: ReferenceFamily, n_links: int, frame: str, r: Tensor, r_dot: Tensor,
             xi: Tensor) -> list[float]:
    """The parameters of ``spec`` minimising the normalised squared error on one set of
    samples (any batch dims, all pooled)."""
    from scipy import optimize  # lazy: scipy.optimize costs 0.3 s at import, needed only here

    r, r_dot, xi = (x.reshape(-1, x.shape[-1]).to(torch.float64) for x in (r, r_dot, xi))
    ok = torch.isfinite(r).all(-1) & torch.isfinite(r_dot).all(-1) & torch.isfinite(xi).all(-1)
    if int(ok.sum()) < 2:
        raise ValueError(f"fit_reference: {int(ok.sum())} usable samples; the {spec.name} "
                         "reference needs at least 2")
    r, r_dot, xi = r[ok], r_dot[ok], xi[ok]
    # evenly spread rows bound the cost of each evaluation (a few parameters, many rows)
    step = -(-r.shape[0] // MAX_ROWS)
    r, r_dot, xi = r[::step], r_dot[::step], xi[::step]
    sst = (xi - xi.mean(0)).square().sum(0).clamp_min(torch.finfo(xi.dtype).tiny)

    def loss(log_p: np.ndarray) -> float:
        values = {name: math.exp(v) for (name, _, _), v in zip(spec.parameters, log_p,
                                                                strict=True)}
        with torch.device(r.device):  # the system's own tensors
            system = spec.build(n_links, frame, **values)
        sse = (xi - system.body_velocity(r, r_dot)).square().sum(0)
        return float((sse / sst).mean())

    bounds = [(math.log(lo), math.log(hi)) for _, lo, hi in spec.parameters]
    if len(bounds) == 1:
        # a coarse grid first (the loss need not be unimodal), then a bounded refinement
        grid = np.linspace(*bounds[0], GRID_POINTS)
        best = int(np.argmin([loss(np.array([g])) for g in grid]))
        lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
        res = optimize.minimize_scalar(lambda v: loss(np.array([v])), bounds=(lo, hi),
                                       method="bounded", options={"xatol": 1e-3})
        return [math.exp(float(res.x))]
    start = np.array([0.5 * (lo + hi) for lo, hi in bounds])
    res = optimize.minimize(loss, start, method="L-BFGS-B", bounds=bounds)
    return [math.exp(float(v)) for v in res.x]


def _element(x: Tensor, i: int, batch: tuple) -> Tensor:
    """Batch element ``i`` (flattened, C order) of ``x`` whose leading dims are ``batch``
    (all of ``x`` where ``batch`` is empty)."""
    if not batch:
        return x
    return x.reshape((-1,) + x.shape[len(batch):])[i]


def _per_element(ref: PhysicsReference, batch: tuple, fn) -> Tensor:
    """``fn(system, i)`` for every element ``i`` of the data's ``batch`` dims, with the
    reference's system for that element (its one system when pooled), stacked to
    ``batch + ...``."""
    systems = ref.systems()
    n = max(1, math.prod(batch))
    if len(systems) not in (1, n):
        raise ValueError(f"PhysicsReference: fitted for batch {tuple(ref.batch_shape)}, "
                         f"data batch {tuple(batch)}")
    out = [fn(systems[i if len(systems) > 1 else 0], i) for i in range(n)]
    return torch.stack(out).reshape(tuple(batch) + out[0].shape)


def _body_velocity(system: LocomotionSystem, r: Tensor, r_dot: Tensor) -> Tensor:
    """``A(r)ṙ`` with NaN where a sample is missing (the system refuses NaN shapes)."""
    ok = torch.isfinite(r).all(-1) & torch.isfinite(r_dot).all(-1)
    out = torch.full(r.shape[:-1] + (3,), math.nan, dtype=r.dtype, device=r.device)
    out[ok] = system.body_velocity(r[ok], r_dot[ok]).to(r.dtype)
    return out
