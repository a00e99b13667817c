"""The truth for a known system: its exact local model around a gait, and the best gait.

:func:`exact_local_model` is what a perfect estimator would return -- ``A(γ(φ))``,
``∂A/∂r(γ(φ))`` and ``M(γ(φ))`` of the simulator, as Fourier series in phase, with zero standard
errors. :func:`ceiling` maximises the simulator's objective over the improvement loop's own
gait family and constraints, the ceiling a data-driven loop is judged against.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .. import _linalg
from ..phase.fourier import FourierSeries, fit_fourier
from ..physics.gaits.evaluate import displacement, evaluate, gauss_phases
from ..physics.gaits.gait import FourierGait, as_gait
from ..physics.systems.base import LocomotionSystem
from ..regression.model import BinEstimates, LocalConnectionModel
from .loop import LoopSettings, circle_gait, gait_order, true_objective
from .propose import OBJECTIVES, objective_value, penalised_objective

__all__ = ["exact_local_model", "Ceiling", "ceiling"]


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


@dataclass(frozen=True)
class Ceiling:
    """The best gait of the loop's gait family with the true connection.

    Attributes:
        gait: a :class:`FourierGait` of ``order`` harmonics per joint.
        value: its objective (:func:`~torchconn.improve.true_objective`, 256 steps per cycle).
        displacement: its displacement per cycle ``(x, y, θ)``, ``(3,)``.
        peak: its largest shape ``max_φ |r(φ)|`` (rad).
        order: the family's Fourier order per joint.
        values: the objective reached from each start, in the order tried.
        evaluations: objective evaluations over all starts.
    """

    gait: FourierGait
    value: float
    displacement: Tensor
    peak: float
    order: int
    values: tuple[float, ...]
    evaluations: int


_CACHE: dict[tuple, Ceiling] = {}


def ceiling(system: LocomotionSystem, objective: str = "displacement",
            settings: LoopSettings | None = None, *,
            peaks: Sequence[float] = (0.5, 1.0, 2.0, 2.8), random_starts: int = 4,
            starts: Sequence[FourierGait] = (), max_iter: int = 300,
            n_steps: int = 128) -> Ceiling:
    """The best ``objective`` per cycle with the true connection, over the loop's own gaits.

    The family is that of :func:`~torchconn.improve.improve` under ``settings`` (default
    :class:`LoopSettings()`): a free Fourier series per joint of the proposals' order
    (:func:`~torchconn.improve.loop.gait_order`), the trust region's joint limit
    ``|r| ≤ shape_bound`` and turning limit ``max_turn``, penalised as the proposals are
    (:func:`~torchconn.improve.propose.penalised_objective`). The simulator's objective
    (:mod:`torchconn.physics.gaits.evaluate`, ``n_steps`` Magnus steps per cycle) is maximised by
    L-BFGS (``max_iter`` evaluations per start) from several starts, and the best by the
    penalised objective at 256 steps is returned. The objective has many local optima (gaits
    with larger higher harmonics enclose more of the shape space), so the starts are: the
    loop's start circles (:func:`~torchconn.improve.circle_gait`, both directions) scaled to
    each peak ``|r|`` in ``peaks`` (rad, at most 0.9 ``shape_bound``); ``random_starts`` gaits
    with random coefficients of every harmonic (a fixed generator), scaled to the largest peak;
    and the gaits in ``starts`` (e.g. the gaits a loop kept, padded or cut to the family's
    order). The value is a lower bound on the family's best. With ``starts=[start gait]``
    alone (``peaks=()``, ``random_starts=0``) it is the optimum a local ascent with the true
    connection reaches from where the loop starts. Deterministic on one device and
    thread count; the result is cached per system (its connection and metric at fixed shapes),
    objective, family and starts.

    Raises:
        ValueError: an unknown objective, non-positive ``peaks``, no start at all.
    """
    s = LoopSettings() if settings is None else settings
    if not isinstance(s, LoopSettings):
        raise TypeError(f"settings must be a LoopSettings, got {type(s).__name__}")
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    peaks = tuple(float(p) for p in peaks)
    if not all(p > 0 for p in peaks):
        raise ValueError(f"peaks must be positive shape radii (rad), got {peaks!r}")
    if not isinstance(random_starts, int) or random_starts < 0:
        raise ValueError(f"random_starts must be a non-negative integer, got {random_starts!r}")
    if random_starts and not peaks:
        raise ValueError("random_starts are scaled to the largest of peaks: give peaks too")
    if not (peaks or starts):
        raise ValueError("no start: give peaks (start circles) or starts (gaits)")
    tr, order = s.trust_region, gait_order(s)
    extra = tuple(_in_family(as_gait(g), order, system.shape_dim) for g in starts)
    key = (_fingerprint(system), objective, order, tr.shape_bound, tr.max_turn, peaks,
           random_starts, tuple(g.numpy().tobytes() for g in extra), max_iter, n_steps)
    if key not in _CACHE:
        _CACHE[key] = _ceiling(system, objective, s, order,
                               _starts(system.shape_dim, order, peaks, random_starts, tr) + extra,
                               max_iter, n_steps)
    return _CACHE[key]


def _in_family(gait: FourierGait, order: int, d: int) -> Tensor:
    """The coefficients ``(2·order + 1, d)`` of ``gait`` padded with zeros or cut to ``order``."""
    if not isinstance(gait, FourierGait) or gait.shape_dim != d:
        raise ValueError(f"starts must be Fourier gaits of {d} joints")
    coeffs = gait.coeffs.detach().to(dtype=torch.float64, device="cpu")[: 2 * order + 1]
    return torch.cat([coeffs, coeffs.new_zeros(2 * order + 1 - coeffs.shape[0], d)])


def _starts(d: int, order: int, peaks: tuple[float, ...], random_starts: int,
            tr) -> tuple[Tensor, ...]:
    """The optimiser's start coefficients ``(2·order + 1, d)``: circles of both directions at
    each peak, then ``random_starts`` random gaits at the largest peak."""
    grid = torch.arange(256, dtype=torch.float64) * (2 * math.pi / 256)
    bound = math.inf if tr.shape_bound is None else 0.9 * tr.shape_bound
    out = []

    def scaled(coeffs: Tensor, peak: float) -> Tensor:
        coeffs = coeffs.clone()
        coeffs[0] = 0
        size = float(torch.linalg.vector_norm(FourierGait(coeffs)(grid), dim=-1).amax())
        return coeffs * (min(peak, bound) / size)

    for peak in peaks:
        for direction in (-1, 1):
            out.append(_in_family(FourierGait(scaled(circle_gait(d, 1.0, direction).coeffs,
                                                     peak)), order, d))
    gen = torch.Generator().manual_seed(0)
    for _ in range(random_starts):
        coeffs = torch.randn(2 * order + 1, d, generator=gen, dtype=torch.float64)
        out.append(scaled(coeffs, max(peaks)))
    return tuple(out)


def _ceiling(system: LocomotionSystem, objective: str, s: LoopSettings, order: int,
             starts: tuple[Tensor, ...], max_iter: int, n_steps: int) -> Ceiling:
    tr = s.trust_region
    _, theta = gauss_phases(n_steps)
    theta = theta.reshape(-1)
    grid = torch.arange(256, dtype=torch.float64) * (2 * math.pi / 256)

    def penalised(gait: FourierGait, steps: int) -> Tensor:
        if objective == "efficiency":
            m = evaluate(system, gait, steps)
            disp, value = m.displacement, m.efficiency
        else:
            disp = displacement(system, gait, steps)
            value = objective_value(objective, disp, None)
        f = penalised_objective(value, disp, gait(theta), objective, tr)
        return f - 1e3 * torch.relu(-_winding_rate(gait.coeffs, theta)).pow(2).mean()

    runs, evaluations = [], 0
    for params in starts:
        params = params.clone()
        evaluations += _maximise(lambda c: penalised(FourierGait(c), n_steps), params, max_iter)
        gait = FourierGait(params)
        runs.append((float(penalised(gait, 256)), gait))
    _, best = max(runs, key=lambda run: run[0])
    return Ceiling(
        gait=best, value=true_objective(system, best, objective),
        displacement=displacement(system, best, 256).detach(),
        peak=float(torch.linalg.vector_norm(best(grid), dim=-1).amax()), order=order,
        values=tuple(true_objective(system, g, objective) for _, g in runs),
        evaluations=evaluations,
    )


def _maximise(fn, params: Tensor, max_iter: int) -> int:
    """Maximise ``fn(params)`` by L-BFGS (strong Wolfe line search) in place, from ``params``;
    the number of evaluations."""
    params.requires_grad_(True)
    opt = torch.optim.LBFGS([params], lr=1, max_iter=max_iter, tolerance_grad=1e-10,
                            tolerance_change=1e-14, history_size=20, line_search_fn="strong_wolfe")
    count = 0

    def closure() -> Tensor:
        nonlocal count
        opt.zero_grad()
        loss = -fn(params)
        loss.backward()
        count += 1
        return loss

    opt.step(closure)
    params.requires_grad_(False)
    return count


def _winding_rate(coeffs: Tensor, phi: Tensor) -> Tensor:
    """``c × dc/dφ (n,)`` at phases ``phi (n,)`` for the coordinates ``c(φ) (n, 2)`` of
    ``r(φ) − a0`` in the basis of the gait's first harmonic ``(a1, b1)`` (coefficients
    ``(2K+1, d)``): non-negative everywhere exactly when the gait, projected on that plane, is
    star-shaped about its mean shape and winds once per period."""
    series = FourierSeries(torch.cat([torch.zeros_like(coeffs[:1]), coeffs[1:]]), value_ndim=1)
    to_plane = _linalg.pinv(coeffs[1:3].T, "the gait's first-harmonic plane")  # (2, d)
    c = series(phi) @ to_plane.T
    v = series.derivative()(phi) @ to_plane.T
    return c[:, 0] * v[:, 1] - c[:, 1] * v[:, 0]


def _fingerprint(system: LocomotionSystem) -> tuple:
    """A key for ``system``'s mechanics: its type, shape dimension and a digest of its
    connection and metric at fixed shapes."""
    d = system.shape_dim
    probe = torch.linspace(-1.0, 1.0, 5 * d, dtype=torch.float64).reshape(5, d)
    probe = probe * torch.linspace(0.3, 1.1, d, dtype=torch.float64)
    with torch.no_grad():
        a, m = system.connection_and_metric(probe)
    digest = hashlib.sha256(a.cpu().numpy().tobytes() + m.cpu().numpy().tobytes()).hexdigest()
    return type(system).__qualname__, d, digest
