"""The model-free baseline: ascend the observed objective over the gait's Fourier coefficients.

Each iteration records the gait at ``±h`` along every coefficient (central differences, each
evaluation ``trials × cycles`` recorded cycles scored with :func:`measure_cycles`) and takes a
gradient step of fixed length in coefficient space. It sees only the observed displacement per cycle,
like an experimenter tuning a robot by hand; its budget is counted in recorded cycles so it can
be compared with the model-based loop at the same number of cycles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..physics.gaits.gait import FourierGait
from ..physics.systems.base import LocomotionSystem
from ..simulation import simulate
from .measure import measure_cycles

__all__ = ["BaselineStep", "finite_difference_baseline"]


@dataclass(frozen=True)
class BaselineStep:
    """After each gradient step: recorded cycles so far, the gait and its observed objective."""

    cycles_used: int
    gait: FourierGait
    observed: float


def finite_difference_baseline(
    system: LocomotionSystem, start: FourierGait, *, budget: int, trials: int = 4,
    cycles: int = 20, h: float = 0.05, step: float = 0.3, eta: float = 0.025,
    alpha: float = 0.05, objective: str = "displacement", seed: int = 0,
    shape_bound: float | None = math.pi, max_turn: float | None = 0.05,
) -> list[BaselineStep]:
    """Central-difference gradient ascent of the observed objective until ``budget`` cycles.

    Args:
        start: the start gait; its Fourier coefficients (rows ``[a0, a1, b1, …]``) are the
            parameters. budget: recorded cycles allowed; h: difference step (rad);
            step: length of each ascent step in coefficient space (rad);
            shape_bound: after each step the gait is scaled about its mean shape until
            ``|r| ≤ shape_bound`` (the joint limits the loop's proposals respect);
            max_turn: the observed objective is penalised like the loop's proposals when the
            observed rotation per cycle exceeds it (see :class:`TrustRegion`).
    """
    coeffs = start.coeffs.detach().clone()
    n = coeffs.numel()
    per_eval = trials * cycles
    seeds = np.random.SeedSequence(seed)
    used, out = 0, []

    def measure(c: torch.Tensor) -> float:
        nonlocal used
        s = seeds.spawn(1)[0].generate_state(trials, dtype=np.uint32).astype(np.int64)
        traj = simulate(system, FourierGait(c), eta=eta, alpha=alpha, n_cycles=cycles, seeds=s)
        used += per_eval
        m = measure_cycles(traj)
        value = m.objective(objective)[0]
        if max_turn is not None and objective != "turning":
            value -= 1e3 * max(abs(float(m.displacement[2])) - max_turn, 0.0) ** 2
        return value

    while used + (2 * n + 1) * per_eval <= budget:
        grad = torch.zeros_like(coeffs).reshape(-1)
        for i in range(n):  # one recording per perturbed gait: the experiment itself
            e = torch.zeros(n, dtype=coeffs.dtype, device=coeffs.device)
            e[i] = h
            e = e.reshape(coeffs.shape)
            grad[i] = (measure(coeffs + e) - measure(coeffs - e)) / (2 * h)
        norm = float(torch.linalg.vector_norm(grad))
        if norm > 0 and math.isfinite(norm):
            coeffs = coeffs + step * grad.reshape(coeffs.shape) / norm
        if shape_bound is not None:
            phi = torch.linspace(0, 2 * math.pi, 256, dtype=coeffs.dtype, device=coeffs.device)
            peak = float(torch.linalg.vector_norm(FourierGait(coeffs)(phi), dim=-1).max())
            if peak > shape_bound:
                mean_norm = float(torch.linalg.vector_norm(coeffs[0]))
                shrink = max(shape_bound - mean_norm, 0.0) / max(peak - mean_norm, 1e-12)
                coeffs = torch.cat([coeffs[:1], coeffs[1:] * shrink])
        out.append(BaselineStep(used + per_eval, FourierGait(coeffs.clone()), measure(coeffs)))
    return out
