"""When two candidates explain the data equally well: collinearity and separating experiments.

Two effects are confounded on a data set when the change one of them makes to the residual --
its *signature*, the Jacobian columns of the residual in its parameters on the actual samples --
can be reproduced by the other. :func:`signature_collinearity` measures this for the fitted
effect: the fraction of its fitted signature ``s_a = J_a p̂_a`` (after projecting out the
effects already accepted) that lies in the span of the other's columns, as ``‖P_b s_a‖ / ‖s_a‖``
(1: indistinguishable, 0: orthogonal). Nothing here comes from a fixed list of "known"
confounders: the numbers are computed from the data's own shapes, headings and phases.

To say which experiment would separate a confounded pair, :func:`separating_experiments`
simulates (noise-free) a few alternative recordings built from the gait the data executed --
run backwards, at a larger or smaller amplitude, with a turning offset, or as two trials at
headings 90° apart -- and computes the same collinearity on each; the one with the smallest
collinearity is the recommended experiment.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .. import _linalg
from ..phase.fourier import fit_fourier
from ..physics.gaits import FourierGait
from ..physics.systems.base import LocomotionSystem
from ..simulation.rollout import simulate
from .forward import ForwardModel, Measurement, measurement_from_clean

__all__ = ["signature_collinearity", "principal_cosine", "separating_experiments",
           "data_gait", "EXPERIMENTS"]


def _project_out(X: Tensor, base: Tensor | None) -> Tensor:
    if base is None or base.shape[1] == 0:
        return X
    Q, _ = torch.linalg.qr(base)
    return X - Q @ (Q.T @ X)


def signature_collinearity(J_a: Tensor, p_a: Tensor, J_b: Tensor,
                           base: Tensor | None = None) -> float:
    """``‖P_b s_a‖ / ‖s_a‖`` with ``s_a = J_a p_a``, both after projecting out ``base``.

    Args:
        J_a: ``(n, P_a)`` whitened Jacobian of effect a; p_a: ``(P_a,)`` its fitted values.
        J_b: ``(n, P_b)`` whitened Jacobian of effect b.
        base: ``(n, P_0)`` columns of effects already in the model (or None).
    """
    s = _project_out(J_a @ p_a, base)
    norm = float(s.norm())
    if norm == 0.0:
        return 0.0
    Jb = _project_out(J_b, base)
    Q, R = torch.linalg.qr(Jb)
    keep = torch.diagonal(R).abs() > 1e-10 * float(torch.diagonal(R).abs().max() + 1e-300)
    Q = Q[:, keep]
    return float((Q.T @ s).norm()) / norm


def principal_cosine(J_a: Tensor, J_b: Tensor, base: Tensor | None = None) -> float:
    """Cosine of the smallest principal angle between the two column spaces (after ``base``)."""
    Qa, _ = torch.linalg.qr(_project_out(J_a, base))
    Qb, _ = torch.linalg.qr(_project_out(J_b, base))
    return float(_linalg.svdvals(Qa.T @ Qb, "the effects' overlap matrix").max().clamp(max=1.0))


def data_gait(m: Measurement, order: int = 7) -> FourierGait:
    """The gait the recording executed: a Fourier series in phase through the usable shapes."""
    series = fit_fourier(m.phase[m.mask], m.r[m.mask], order)
    return FourierGait(series.coeffs)


def _scaled(gait: FourierGait, factor: float) -> FourierGait:
    c = gait.coeffs.clone()
    c[1:] = factor * c[1:]
    return FourierGait(c)


def _offset(gait: FourierGait, total: float) -> FourierGait:
    c = gait.coeffs.clone()
    c[0] = c[0] + total / c.shape[1]
    return FourierGait(c)


#: (name, what to do) of the alternative experiments that are simulated
EXPERIMENTS = (
    ("as_recorded", "the recorded gait again (reference)"),
    ("reversed", "run the same gait backwards"),
    ("larger_amplitude", "the same gait at 1.5x its amplitude about its mean shape"),
    ("smaller_amplitude", "the same gait at 0.6x its amplitude"),
    ("turning", "add a constant joint offset (0.5 rad of total curvature) so the swimmer turns"),
    ("two_headings", "record a second trial swimming at 90 degrees to the first"),
)


def _experiment_measurement(name: str, gait: FourierGait, system: LocomotionSystem,
                            m: Measurement, n_cycles: int) -> Measurement:
    spc = max(16, int(round(2 * math.pi / m.dt)))
    g = {"as_recorded": gait, "reversed": gait.reversed(),
         "larger_amplitude": _scaled(gait, 1.5), "smaller_amplitude": _scaled(gait, 0.6),
         "turning": _offset(gait, 0.5), "two_headings": gait}[name]
    # eta = 0 as a tensor on the recording's device: the experiment is simulated there
    traj = simulate(system, g, eta=m.pose.new_zeros(()), n_cycles=n_cycles,
                    samples_per_cycle=spc, substeps=8, seeds=[0], stationary_start=False)
    pose, r, phase = traj.pose, traj.r, traj.truth.phase
    if name == "two_headings":
        c, s = 0.0, 1.0  # rotate the world by 90°
        turned = torch.stack([c * pose[..., 0] - s * pose[..., 1],
                              s * pose[..., 0] + c * pose[..., 1], pose[..., 2] + math.pi / 2], -1)
        pose = torch.cat([pose, turned], 0)
        r = torch.cat([r, r], 0)
        phase = torch.cat([phase, phase], 0)
    kernel = m.kernel[0]
    return measurement_from_clean(traj.t, pose, r, phase, kernel, traj.dt)


def separating_experiments(
    system: LocomotionSystem,
    m: Measurement,
    weight: Tensor,
    evaluate_columns,
    a: str,
    b: str,
    *,
    n_cycles: int = 4,
) -> list[dict]:
    """Collinearity of a confounded pair under alternative (simulated) experiments.

    Args:
        system: the nominal swimmer.
        m: the recorded measurement (gait, sampling and smoothing kernel are taken from it).
        weight: ``(3,)`` whitening weights (1 / noise floor) of the recorded data.
        evaluate_columns: ``(ForwardModel, weight) -> (J_base, J_a, p_a, J_b, p_b)`` evaluating
            the effects' whitened Jacobians at their fitted values on another measurement.
        a, b: the pair.

    Returns:
        one dict per experiment: ``name``, ``description`` and ``collinearity`` (the larger of
        a-in-b and b-in-a), sorted from the most separating.
    """
    gait = data_gait(m)
    out = []
    for name, text in EXPERIMENTS:
        try:
            ms = _experiment_measurement(name, gait, system, m, n_cycles)
            fm = ForwardModel(ms, system)
            J0, Ja, pa, Jb, pb = evaluate_columns(fm, weight)
            col = max(signature_collinearity(Ja, pa, Jb, J0),
                      signature_collinearity(Jb, pb, Ja, J0))
        except (ValueError, RuntimeError) as err:  # an experiment the swimmer cannot run
            out.append({"name": name, "description": text, "collinearity": None,
                        "error": str(err)})
            continue
        out.append({"name": name, "description": text, "collinearity": col})
    ok = [e for e in out if e["collinearity"] is not None]
    rest = [e for e in out if e["collinearity"] is None]
    return sorted(ok, key=lambda e: e["collinearity"]) + rest
