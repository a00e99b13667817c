"""The paper's four body-velocity models (Sec. 5.1) and their errors.

For every sample n, with phase φ_n, shape r_n, shape velocity ṙ_n, the fitted cycle
γ_n = γ(φ_n), γ̇_n and offset δ_n = r_n − γ_n:

- ``ground_truth``: ``A(r_n) ṙ_n`` from the simulator (eq. ``groundtruthbodyvel``), on the
  noise-free shapes when the data carry them (a simulation with observation noise), else on
  the recorded ones;
- ``data_driven``: the fitted model's prediction (eq. ``advanceddatadriven``);
- ``analytic``: ``A(γ_n) ṙ_n + ∂A/∂r(γ_n) δ_n ṙ_n`` -- the simulator's first-order Taylor
  model at the same cycle point (eq. ``analyticalbodyvel``; ∂A/∂r by autograd);
- ``template``: ``A(γ_n) γ̇_n`` (eq. ``templatebodyvel``).

The three models use the same (smoothed) recorded ``r_n, ṙ_n`` and the same phase, so they
differ only in the model. Errors are taken against ``ground_truth`` and against the observed
body velocity the way the regression sees it (:func:`observed_view`: for the default
noise-aware regression the raw differences of the recorded poses over the model's velocity
interval, with every model evaluated on the same intervals).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..phase.fourier import FourierSeries, fourier_on_grid
from ..phase.smoothing import smooth_trajectory
from ..physics.systems.base import LocomotionSystem
from ..regression.model import LocalConnectionModel
from ..regression.selection import regression_view
from ..trajectory import Trajectory

__all__ = [
    "MODELS", "COMPONENTS", "reference_models", "models_on", "observed_view",
    "simulator_on_cycle", "clean_trajectory", "error_summary",
    "phase_bin_errors",
]

MODELS = ("ground_truth", "data_driven", "analytic", "template")
COMPONENTS = ("x", "y", "theta")


def reference_models(
    system: LocomotionSystem,
    model: LocalConnectionModel,
    traj: Trajectory,
    clean: Trajectory | None = None,
    *,
    on_cycle: FourierSeries | None = None,
) -> dict[str, Tensor]:
    """Body velocity ``(..., T, 3)`` of each of :data:`MODELS` on a prepared trajectory.

    Args:
        system: the simulator the data came from (the "truth").
        model: a model fitted to ``traj`` (batch dims equal to the trajectory's, or none).
        traj: a trajectory with ``phase`` and ``smoothed`` set.
        clean: the same trials without observation noise, smoothed (``smoothed`` set); the
            ground truth is then the simulator on these shapes.
        on_cycle: :func:`simulator_on_cycle` of ``system`` and ``model``, when already computed.
    """
    if traj.phase is None or traj.smoothed is None:
        raise ValueError("reference_models needs a prepared trajectory (phase and smoothed set)")
    truth_in = None if clean is None else (clean.smoothed.r, clean.smoothed.r_dot)
    return models_on(system, model, traj.phase, traj.smoothed.r, traj.smoothed.r_dot, truth_in,
                     on_cycle=on_cycle)


def models_on(system: LocomotionSystem, model: LocalConnectionModel, phase: Tensor, r: Tensor,
              r_dot: Tensor, truth_in: tuple[Tensor, Tensor] | None = None, *,
              on_cycle: FourierSeries | None = None) -> dict[str, Tensor]:
    """Body velocity ``(..., N, 3)`` of each of :data:`MODELS` on samples ``phase (..., N)``,
    ``r, r_dot (..., N, d)`` (NaN samples give NaN); the ground truth on ``truth_in``
    (noise-free ``r, r_dot``) when given, else on ``r, r_dot``. ``on_cycle``: the simulator
    along the model's cycle (:func:`simulator_on_cycle`), computed here when not given."""
    if system.shape_dim != r.shape[-1]:
        raise ValueError(
            f"system has {system.shape_dim} joints but the trajectory has {r.shape[-1]}"
        )
    missing = torch.isnan(phase) | torch.isnan(r).any(-1) | torch.isnan(r_dot).any(-1)
    if truth_in is not None:
        missing = missing | torch.isnan(truth_in[0]).any(-1) | torch.isnan(truth_in[1]).any(-1)
        truth_in = tuple(torch.where(missing.unsqueeze(-1), 0.0, x) for x in truth_in)
    phase = torch.where(missing, 0.0, phase)
    r, r_dot = (torch.where(missing.unsqueeze(-1), 0.0, x) for x in (r, r_dot))
    gamma, gamma_dot = model.gamma_at(phase), model.gamma_dot_at(phase)
    delta = r - gamma
    if on_cycle is None:
        on_cycle = simulator_on_cycle(system, model)
    terms = on_cycle(phase)  # (..., N, 3, d, 1 + d)
    A_gamma, dA_gamma = terms[..., 0], terms[..., 1:]

    def apply(a: Tensor, v: Tensor) -> Tensor:
        return (a @ v.unsqueeze(-1)).squeeze(-1)

    out = {
        "ground_truth": system.body_velocity(*(truth_in or (r, r_dot))),
        "data_driven": model.predict(phase, r, r_dot),
        "analytic": apply(A_gamma, r_dot)
        + torch.einsum("...kij,...j,...i->...k", dA_gamma, delta, r_dot),
        "template": apply(A_gamma, gamma_dot),
    }
    return {k: torch.where(missing.unsqueeze(-1), torch.nan, v) for k, v in out.items()}


def observed_view(system: LocomotionSystem, traj: Trajectory, regression,
                  model: LocalConnectionModel, clean: Trajectory | None = None, *,
                  on_cycle: FourierSeries | None = None):
    """The observed body velocity the way ``regression`` sees it, and every model of
    :data:`MODELS` on the same samples.

    For a :class:`~torchconn.regression.NoiseAwareRegression` model these are the raw interval
    differences of the recording (``ξ`` over the model's ``h`` samples, against the mid-point
    shapes and mean shape velocities; the ground truth on the same intervals of ``clean``); for
    a :class:`~torchconn.regression.TubeRegression` the Kalman-smoothed velocities.

    Args:
        traj: the prepared trajectory the model was fitted to (one model per batch element).
        clean: its noise-free twin, smoothed (:func:`clean_trajectory`), or None.
        on_cycle: :func:`simulator_on_cycle` of ``system`` and ``model``, when already computed.

    Returns:
        ``(observed (..., N, 3), {model: (..., N, 3)})``, NaN where an element has fewer samples.
    """
    view = regression_view(traj, regression, model, pool=False, flatten=False)
    truth_in = None
    if clean is not None:
        twin = regression_view(clean.with_fields(phase=traj.phase), regression, model,
                               pool=False, flatten=False)
        truth_in = (twin.r, twin.r_dot)
    return view.xi, models_on(system, model, view.phase, view.r, view.r_dot, truth_in,
                              on_cycle=on_cycle)


def simulator_on_cycle(system: LocomotionSystem, model: LocalConnectionModel, *,
                       n_grid: int = 256) -> FourierSeries:
    """The simulator along the model's cycle: ``A(γ(φ))`` and ``∂A/∂r(γ(φ))`` in phase.

    Both are smooth periodic functions of phase, so they are evaluated exactly on ``n_grid``
    equispaced phases per cycle and trigonometrically interpolated (harmonics up to
    ``n_grid/2 − 1``; their coefficients decay exponentially) -- far cheaper than an autograd
    Jacobian at every sample. Computed once, it serves every set of samples of the same model
    (:func:`reference_models`, :func:`observed_view`).

    Returns:
        one :class:`~torchconn.phase.fourier.FourierSeries` with batch dims
        ``model.batch_shape`` and values ``(3, d, 1 + d)``: ``[..., 0]`` is ``A`` and
        ``[..., 1:]`` is ``∂A/∂r`` (``[..., k, i, 1 + j] = ∂A^k_i/∂r_j``).
    """
    dtype, device = model.gamma.coeffs.dtype, model.gamma.coeffs.device
    grid = torch.arange(n_grid, dtype=dtype, device=device) * (2 * math.pi / n_grid)
    gamma = model.gamma_at(grid.expand(model.batch_shape + (n_grid,)))
    terms = torch.cat([system.connection(gamma)[..., None], system.connection_jacobian(gamma)],
                      -1)  # (..., n_grid, 3, d, 1 + d)
    return fourier_on_grid(terms, n_grid // 2 - 1, value_ndim=3)


def clean_trajectory(traj: Trajectory) -> Trajectory:
    """The noise-free recording of a simulated trajectory (its ``truth``), smoothed."""
    if traj.truth is None:
        raise ValueError("clean_trajectory needs a simulated trajectory (truth is None)")
    clean = Trajectory(t=traj.t, pose=traj.truth.pose, r=traj.truth.r, meta=traj.meta)
    return clean.with_fields(smoothed=smooth_trajectory(clean.pose, clean.r, clean.dt))


def error_summary(prediction: Tensor, target: Tensor) -> Tensor:
    """RMS over time of ``prediction − target`` per component: ``(..., T, 3) -> (..., 3)``.

    Samples where either is NaN are left out.
    """
    err = prediction - target
    ok = torch.isfinite(err)
    sq = torch.where(ok, err * err, torch.zeros_like(err))
    return (sq.sum(-2) / ok.sum(-2).clamp_min(1)).sqrt()


def phase_bin_errors(
    prediction: Tensor, target: Tensor, phase: Tensor, n_bins: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Error statistics per phase bin (the paper's Fig. 3C).

    Bins are centred on ``2πm / n_bins`` like the estimator's regression bins, so with the same
    count each error bin is one regression window.

    Args:
        prediction, target: ``(..., T, 3)``; phase: ``(..., T)``.
    Returns:
        ``(centres (n_bins,), mean (..., n_bins, 3), rms (..., n_bins, 3),
        standard error of the mean (..., n_bins, 3))`` -- the standard error treats samples as
        independent; compare means across independent trials for a test.
    """
    err = prediction - target
    width = 2 * math.pi / n_bins
    idx = torch.round(torch.remainder(phase, 2 * math.pi) / width).long() % n_bins
    one_hot = torch.nn.functional.one_hot(idx, n_bins).to(err.dtype)  # (..., T, B)
    ok = torch.isfinite(err).all(-1).to(err.dtype)[..., None] * one_hot
    e0 = torch.nan_to_num(err)
    count = ok.sum(-2)[..., None]  # (..., B, 1)
    mean = (ok.transpose(-1, -2) @ e0) / count.clamp_min(1)
    second = (ok.transpose(-1, -2) @ (e0 * e0)) / count.clamp_min(1)
    var = (second - mean * mean).clamp_min(0) * count / (count - 1).clamp_min(1)
    centres = torch.arange(n_bins, dtype=err.dtype, device=err.device) * width
    return centres, mean, second.sqrt(), (var / count.clamp_min(1)).sqrt()
