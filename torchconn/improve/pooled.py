"""One local model from every gait recorded, weighted by its distance from the current gait.

A loop that commands its gaits knows their clock: a recording of gait ``γ_j`` is phased by
``φ = φ₀ + t`` (:func:`clock_phase`), smoothed, and kept as its samples ``(φ, r, ṙ, ξ)``
(:class:`GaitRecording`). The model around the current gait ``γ`` is one phase-bin regression
(:class:`~torchconn.regression.OnlineConnection`, design ``[1, δ, δ̇, δ̇⊗δ]``) centred on ``γ``
over *every* recording: recording ``j`` enters with weight ``exp(−½ (D_j / ℓ)²)``, ``D_j`` the
root-mean-square distance between ``γ_j`` and ``γ`` over the cycle (:func:`gait_distance`) and
``ℓ`` the pooling length. Earlier gaits are data off the current cycle, so the fitted tube --
and a trust region in tube radii -- widens as the loop moves, and ``∂Â/∂r`` is identified from
the spread between gaits, not from one gait's noise alone. A new recording of the current gait
is one :meth:`~torchconn.regression.OnlineConnection.update` of the pooled sums; moving to a new
gait re-weights and re-centres them (:meth:`PooledConnection.model`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .._checks import check_value
from ..cycles import cycles_spanned
from ..phase.fourier import FourierSeries, fit_fourier
from ..phase.smoothing import RTSSmoother, Smoother
from ..physics.gaits.gait import FourierGait
from ..regression.gait_prediction import best_shift
from ..regression.model import LocalConnectionModel
from ..regression.online import CycleConfidence, OnlineConnection
from ..trajectory import Trajectory, pool_batch

__all__ = ["GaitRecording", "PooledConnection", "clock_phase", "gait_distance",
           "gait_recording", "aligned_recording"]

#: recordings weighted less than this are left out of the pooled regression
_MIN_WEIGHT = 1e-3


@dataclass(frozen=True)
class GaitRecording:
    """The samples of one recording of a commanded gait, pooled over its trials.

    Attributes:
        gait: the commanded gait ``γ_j`` (its phase is the recording's clock).
        phase: ``(N,)`` the samples' phase (rad, unwrapped); NaN marks a missing sample.
        r, r_dot: ``(N, d)`` smoothed shapes (rad) and shape velocities (rad per unit time).
        xi: ``(N, 3)`` smoothed body velocities ``(v_x, v_y, ω)``.
        cycles: recorded cycles (all trials).
    """

    gait: FourierGait
    phase: Tensor
    r: Tensor
    r_dot: Tensor
    xi: Tensor
    cycles: int


def clock_phase(traj: Trajectory, phase0: float = 0.0) -> Tensor:
    """``(..., T)`` the commanded gait clock ``φ₀ + t`` of every trial of ``traj``."""
    return (phase0 + traj.t).expand(traj.batch_shape + traj.t.shape)


def gait_recording(traj: Trajectory, gait: FourierGait, cycles: int, *,
                   smoother: Smoother | None = None, phase0: float = 0.0) -> GaitRecording:
    """``traj``'s recordings of the commanded ``gait`` (clock ``φ₀ + t``), smoothed by
    ``smoother`` (default :class:`~torchconn.phase.smoothing.RTSSmoother`), trials pooled."""
    sm = (RTSSmoother() if smoother is None else smoother).smooth(traj).smoothed
    phase = clock_phase(traj, phase0)
    return GaitRecording(gait=gait, phase=pool_batch(phase, 0), r=pool_batch(sm.r, 1),
                         r_dot=pool_batch(sm.r_dot, 1), xi=pool_batch(sm.xi, 1), cycles=cycles)


def aligned_recording(traj: Trajectory, centre: FourierSeries) -> GaitRecording:
    """A prepared recording (smoothed, phased by its own phase estimate) of any gait, as
    samples in the phase of the cycle ``centre`` (values ``(d,)``, e.g. a fitted model's
    ``gamma``).

    The recording's own cycle is fitted through its samples at ``centre``'s order, and its
    phase shifted by the offset ``φ₀`` (on a grid of 256) that brings that cycle closest to
    ``centre`` in mean square: its samples get phase ``ψ + φ₀`` and its gait is its cycle in
    that phase. Phase estimates put phase 0 at a section of each recording's own cycle, so two
    recordings of different gaits agree on phase only up to such an offset.

    Raises:
        ValueError: a recording without phase or smoothed state, or too short to fit its cycle.
    """
    if traj.phase is None or traj.smoothed is None:
        raise ValueError("aligned_recording: the recording must be prepared (smoothed and "
                         "phased: ConnectionEstimator.prepare)")
    sm = traj.smoothed
    psi, r = pool_batch(traj.phase, 0), pool_batch(sm.r, 1)
    own = fit_fourier(psi, r, centre.order, value_ndim=1)
    n = 256
    grid = torch.arange(n, dtype=psi.dtype, device=psi.device) * (2 * math.pi / n)
    offset = float(grid[best_shift(centre(grid), own(grid))])
    shifted = fit_fourier(grid, own(grid - offset), centre.order, value_ndim=1)
    cycles = int(round(float(cycles_spanned(traj.phase).sum())))
    return GaitRecording(gait=FourierGait(shifted.coeffs), phase=psi + offset, r=r,
                         r_dot=pool_batch(sm.r_dot, 1), xi=pool_batch(sm.xi, 1), cycles=cycles)


def gait_distance(a: FourierGait, b: FourierGait, n: int = 256) -> float:
    """Root-mean-square over one cycle of ``|a(φ) − b(φ)|`` (rad), at ``n`` phases."""
    phi = torch.arange(n, dtype=a.coeffs.dtype, device=a.coeffs.device) * (2 * math.pi / n)
    return float(torch.linalg.vector_norm(a(phi) - b(phi), dim=-1).square().mean().sqrt())


class PooledConnection:
    """Every recording so far, and the local model they give around any gait.

    Args:
        length: the pooling length ``ℓ`` (rad): a recording ``D`` rad (rms) from the current
            gait is weighted ``exp(−½ (D/ℓ)²)``; None pools every recording alike.
        phase_rate: the mean phase velocity ``φ̇`` of the gaits (rad per unit of the
            recordings' time; 1 on the simulations' clock).
        n_bins, window, kernel, fourier_order, ridge: the phase bins and the series through
            them (:class:`~torchconn.regression.OnlineConnection`).
    """

    def __init__(self, *, length: float | None = 0.5, phase_rate: float = 1.0,
                 n_bins: int = 16, window: float = 1.5, kernel: str = "tricube",
                 fourier_order: int = 5, ridge: float = 1e-6) -> None:
        check_value("PooledConnection: length", length, float | None, {"gt": 0})
        check_value("PooledConnection: phase_rate", phase_rate, float, {"gt": 0})
        self.length, self.phase_rate = length, float(phase_rate)
        self.settings = dict(n_bins=n_bins, window=window, kernel=kernel,
                             fourier_order=fourier_order, ridge=ridge)
        self.recordings: list[GaitRecording] = []
        self._online: OnlineConnection | None = None
        self._centre: FourierGait | None = None
        self._model: LocalConnectionModel | None = None  # model() of the current sums

    def weight(self, recording: GaitRecording, gait: FourierGait) -> float:
        """The weight of ``recording`` in the model around ``gait``."""
        if self.length is None:
            return 1.0
        return math.exp(-0.5 * (gait_distance(recording.gait, gait) / self.length) ** 2)

    def add(self, recording: GaitRecording) -> CycleConfidence | None:
        """Keep ``recording``; when the model is centred on its gait already, add it to the
        sums online and return the recording's :class:`CycleConfidence` (None otherwise)."""
        self.recordings.append(recording)
        self._model = None
        if self._online is None or self._centre is None:
            return None
        return self._update(self._online, recording, self.weight(recording, self._centre))

    @property
    def cycles(self) -> int:
        """Recorded cycles over all recordings."""
        return sum(rec.cycles for rec in self.recordings)

    def online(self, gait: FourierGait) -> OnlineConnection:
        """The pooled regression centred on ``gait`` (re-weighted and re-centred when the
        gait changed since the last call, else the sums kept up to date by :meth:`add`)."""
        if self._centre is None or not torch.equal(self._centre.coeffs, gait.coeffs):
            online = OnlineConnection(FourierSeries(gait.coeffs, 1), self.phase_rate,
                                      **self.settings)
            for rec in self.recordings:
                w = self.weight(rec, gait)
                if w >= _MIN_WEIGHT:
                    self._update(online, rec, w)
            self._online, self._centre, self._model = online, gait, None
        return self._online

    def model(self, gait: FourierGait) -> LocalConnectionModel:
        """The local model around ``gait`` from every recording (see :class:`PooledConnection`);
        kept until a recording is added or the centre moves.

        The bins' standard errors assume independent samples, but a smoothed recording's
        residuals are correlated over several samples; they are scaled per body-velocity
        component by ``√(1 + 2 Σ_k (1 − k/(L+1)) ρ_k)`` (Bartlett weights, ``ρ_k`` the residuals'
        autocorrelation at lag ``k`` ≤ ``L``, a quarter cycle, over the recordings by their
        weights; never below 1), recorded in ``meta["se_inflation"]``.

        Raises:
            ValueError: where a phase bin cannot be fitted yet (too few recordings near
                ``gait``).
        """
        online = self.online(gait)
        if self._model is not None:  # nothing added since, same centre
            return self._model
        model = online.model()
        factor = self._se_inflation(model, gait)
        bins = model.bins
        k = factor.to(bins.c_se)
        scaled = dataclasses.replace(
            bins, c_se=bins.c_se * k, b_se=bins.b_se * k[:, None], A_se=bins.A_se * k[:, None],
            dA_se=bins.dA_se * k[:, None, None])
        self._model = dataclasses.replace(model, bins=scaled,
                                          meta=model.meta | {"se_inflation": factor.tolist()})
        return self._model

    def _se_inflation(self, model: LocalConnectionModel, gait: FourierGait) -> Tensor:
        """``(3,)`` the standard errors' factor for the residuals' autocorrelation."""
        num = den = None
        for rec in self.recordings:
            w = self.weight(rec, gait)
            if w < _MIN_WEIGHT:
                continue
            ok = torch.isfinite(rec.phase) & torch.isfinite(rec.xi).all(-1)
            pred = model.predict(torch.nan_to_num(rec.phase), torch.nan_to_num(rec.r),
                                 torch.nan_to_num(rec.r_dot))
            e = torch.where(ok[:, None], rec.xi - pred, 0.0)  # (N, 3)
            lags = max(1, round(e.shape[0] / max(rec.cycles, 1) / 4))
            products = torch.stack([(e[:-j] * e[j:]).sum(0) if j else e.square().sum(0)
                                    for j in range(lags + 1)])  # (L + 1, 3)
            bartlett = 1 - torch.arange(lags + 1, dtype=e.dtype, device=e.device) / (lags + 1)
            num = w * (bartlett[1:, None] * products[1:]).sum(0) + (0 if num is None else num)
            den = w * products[0] + (0 if den is None else den)
        if num is None:
            return torch.ones(3, dtype=gait.coeffs.dtype, device=gait.coeffs.device)
        return (1 + 2 * num / den).clamp(min=1).sqrt()

    @staticmethod
    def _update(online: OnlineConnection, rec: GaitRecording, weight: float
                ) -> CycleConfidence:
        return online.update(rec.phase, rec.r, rec.r_dot, rec.xi, weight=weight)
