"""The next gait in a form a robot can execute: joint angles over time, Fourier coefficients."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from .._output import atomic_file, write_bytes_atomic
from ..physics.gaits.gait import FourierGait

__all__ = ["gait_table", "write_gait"]


def gait_table(gait: FourierGait, samples_per_cycle: int = 64, period: float = 2 * math.pi):
    """One cycle sampled uniformly: ``(samples_per_cycle, 1 + d)`` array ``[t, r1 … rd]``."""
    if not isinstance(samples_per_cycle, int) or samples_per_cycle < 4:
        raise ValueError(f"samples_per_cycle must be an integer >= 4, got {samples_per_cycle!r}")
    phi = torch.arange(samples_per_cycle, dtype=torch.float64) * (2 * math.pi / samples_per_cycle)
    r = gait(phi).detach().cpu().numpy()
    t = phi.numpy() * (period / (2 * math.pi))
    return np.column_stack([t, r])


def write_gait(gait: FourierGait, stem: str | Path, *, samples_per_cycle: int = 64,
               period: float = 2 * math.pi, extra: dict | None = None) -> dict[str, Path]:
    """Write ``STEM.csv`` (``t, r1 … rd`` over one cycle) and ``STEM.json`` (the Fourier
    coefficients ``[a0, a1, b1, …]`` per joint, the period and ``extra``); returns both paths.

    ``r_j(t) = a0_j + Σ_k a_kj cos(k ω t) + b_kj sin(k ω t)``, ``ω = 2π / period``.
    """
    stem = Path(stem)
    table = gait_table(gait, samples_per_cycle, period)
    d = table.shape[1] - 1
    csv = stem.with_suffix(".csv")
    with atomic_file(csv, "w") as fh:
        np.savetxt(fh, table, delimiter=",", fmt="%.10g",
                   header="t," + ",".join(f"r{j + 1}" for j in range(d)), comments="")
    spec = {
        "form": "r_j(t) = a0_j + sum_k a_kj cos(k w t) + b_kj sin(k w t), w = 2 pi / period",
        "period": period,
        "joints": d,
        "rows": ["a0"] + [f"{ab}{k}" for k in range(1, gait.order + 1) for ab in "ab"],
        "fourier_coefficients": gait.coeffs.detach().cpu().tolist(),
    } | (extra or {})
    js = stem.with_suffix(".json")
    write_bytes_atomic(js, json.dumps(spec, indent=2).encode())
    return {"csv": csv, "json": js}
