"""The fitted local model: A, ∂A/∂r and M around a limit cycle, as Fourier series in phase.

A :class:`LocalConnectionModel` is what :class:`~torchconn.regression.estimator.ConnectionEstimator`
produces. It holds the limit cycle ``γ(φ)`` and Fourier series in phase of every regression
term of eq. ``advanceddatadriven`` -- ``c(φ) ≈ A γ̇``, ``b(φ) ≈ ∂A/∂r γ̇``, ``A(φ)``,
``∂A/∂r(φ)`` -- and, when power was recorded, of the metric ``M(φ)``. It predicts the body
velocity of any sample in the tube,

    ξ ≈ c(φ) + b(φ) δ + A(φ) δ̇ + ∂A/∂r(φ) (δ̇ ⊗ δ),   δ = r − γ(φ),  δ̇ = ṙ − γ̇(φ),

and keeps the per-bin estimates with their standard errors for confidence bands. Leading
batch dims ``...`` (noise levels × trials) are those of the data it was fitted to.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .. import _checks
from .._output import savez
from ..phase.fourier import FourierSeries
from .diagnostics import RegressionDiagnostics
from .gait_prediction import GaitPrediction, predict_gait

__all__ = ["LocalConnectionModel", "BinEstimates", "ROWS"]

#: the rows of the connection ``A`` (body-velocity components ``v_x, v_y, ω``) as the
#: columns of tables name them (``A_x_1``, ``dA_theta_2_1``, ...)
ROWS = ("x", "y", "theta")


@dataclass(frozen=True)
class BinEstimates:
    """Per-bin regression estimates and standard errors.

    Attributes:
        phase: ``(M,)`` bin-centre phases.
        gamma, gamma_dot: ``(..., M, d)`` limit cycle and its phase derivative at the centres.
        c, b, A, dA: ``(..., M, 3)``, ``(..., M, 3, d)``, ``(..., M, 3, d)``, ``(..., M, 3, d, d)``.
        c_se, b_se, A_se, dA_se: their standard errors (same shapes).
        n_samples: ``(..., M)`` samples used per bin.
        M, M_se: ``(..., M, d, d)`` metric estimates and standard errors, or None. The full
            ``M̂`` is only as good as the off-cycle excitation of the data: directions of the
            shape velocity the recording rarely visits get wide errors.
        M_gamma_dot, M_gamma_dot_se: ``(..., M, d)`` ``M̂γ̇`` on the cycle and its standard error
            (identified by the gait itself), or None.
        power_on_cycle, power_on_cycle_se: ``(..., M)`` ``γ̇ᵀM̂γ̇`` and its standard error, or None.
        M_bias: ``(..., M, d, d)`` the model's bias allowed for in ``M_se`` (and in the other
            metric standard errors; :func:`~torchconn.regression.metric.tied_metric_regression`'s
            ``order_bias``): one systematic error shared by the entries and bins, not independent
            scatter; None where not estimated.
        M_change_factor: ``(..., M, d, d, R)`` a factor of the part of ``M_se``'s variance that
            is the sampling noise of that bias estimate (``order_bias``):
            its covariance across entries and bins is ``Σ_r F[..., r] ⊗ F[..., r]``; None
            where that noise is not in ``M_se``.
        dM: ``(..., M, d, d, d)`` the metric's shape derivative ``∂M̂_ij/∂r_k`` at
            ``[..., i, j, k]`` (the tied model's ``∂M/∂r(φ)``), or None.
        M_offset_bias: ``(..., M, d, d)`` the tube's second-order bias of ``M̂`` (``M̂`` absorbs
            ``½∂²M/∂r² : E[δδᵀ]``), estimated as the change of ``M̂`` when that term is fitted
            too (without ``TiedMetric.second_order``): not in ``M_se``; nearby-gait draws
            add it as one error shared by entries and bins. None where not estimated.
        M_sampling_factor: ``(..., M, d, d, R)`` a factor of the part of ``M_se``'s variance
            that is the fit's own sampling noise (the tied model's cluster-robust covariance),
            across entries and bins: each cycle's share of the error evaluated at the bins
            (``R ≤`` cycles); None where not estimated (the paper's per-bin model, models
            saved by older versions): then that noise is drawn entry by entry.
        A_sampling_factor: ``(..., M, 3, d, R)`` a factor of ``Â``'s sampling covariance across
            entries and bins, ``Σ_r F[..., r] ⊗ F[..., r]`` with the diagonal ``A_se²``: each
            whole cycle's share of the error (``R ≤`` cycles;
            :func:`~torchconn.regression.noise_aware.sampling_factor`). Nearby-gait draws take
            ``Â`` from it: the displacement integrates ``Âγ̇``, known better than the entries
            one by one. None where not estimated (unpooled fits, ``TubeRegression``, models
            saved by older versions): ``Â`` is drawn entry by entry.
        A_bias_allowance: ``(..., M, 3, d)`` an allowance for the bias of ``Â``: the tube's
            second order (``Â`` absorbs ``½∂²A/∂r² : E[δδᵀ]``,
            :func:`~torchconn.regression.noise_aware.offset_bias`) and the sampling
            interval's (:func:`~torchconn.regression.noise_aware.bias.interval_bias`), summed: not
            in ``A_se``; nearby-gait draws add it as one error shared by entries and bins.
            None where not estimated (recordings with detected measurement noise, unpooled
            fits).
        dA_correlation: ``(..., M, 3, d², d²)`` the correlation of each bin and row's tied
            ``∂Â/∂r`` entries (``vec`` row-major), from the tie
            (:func:`~torchconn.regression.tie_connection_derivative`'s ``correlation``).
            Nearby-gait draws take ``∂Â/∂r`` with it: the displacement's first-order term
            contracts it with the gait's velocity, which the tie pins through ``b̂``. None
            where not estimated (unpooled fits, ``TubeRegression``, older models): drawn
            entry by entry.
    """

    phase: Tensor
    gamma: Tensor
    gamma_dot: Tensor
    c: Tensor
    b: Tensor
    A: Tensor
    dA: Tensor
    c_se: Tensor
    b_se: Tensor
    A_se: Tensor
    dA_se: Tensor
    n_samples: Tensor
    M: Tensor | None = None
    M_se: Tensor | None = None
    M_gamma_dot: Tensor | None = None
    M_gamma_dot_se: Tensor | None = None
    power_on_cycle: Tensor | None = None
    power_on_cycle_se: Tensor | None = None
    M_bias: Tensor | None = None
    M_change_factor: Tensor | None = None
    M_sampling_factor: Tensor | None = None
    dM: Tensor | None = None
    M_offset_bias: Tensor | None = None
    A_sampling_factor: Tensor | None = None
    A_bias_allowance: Tensor | None = None
    dA_correlation: Tensor | None = None


@dataclass(frozen=True)
class LocalConnectionModel:
    """Fourier-in-phase local model of a connection (and metric) around a gait.

    Attributes:
        gamma: limit cycle ``γ(φ)``, value shape ``(d,)``.
        phase_rate: ``(...)`` mean phase velocity ``φ̇`` in rad per unit of ``t`` (rad/s for
            recorded data: 2π times the gait frequency in Hz; 1 on the simulations' clock, one
            cycle per 2π, docs/conventions.md "Units"); on the cycle ``ṙ = φ̇ dγ/dφ``.
        c, b, A, dA: Fourier series of the regression terms, value shapes ``(3,)``,
            ``(3, d)``, ``(3, d)``, ``(3, d, d)`` (``dA[..., k, i, j] = ∂A^k_i/∂r_j``).
        M: Fourier series of the metric ``(d, d)``, or None when no power was recorded.
        dM: Fourier series of its shape derivative ``∂M̂/∂r`` ``(d, d, d)`` (``[i, j, k] =
            ∂M_ij/∂r_k``), or None (no power, the paper's metric model, no derivative term).
            A nearby gait's cost uses ``M̂`` on the cycle; this term's change of it enters the
            cost's standard error (:func:`~torchconn.regression.gait_prediction.predict_gait`).
        bins: the per-bin estimates the series were fitted to.
        meta: settings and provenance (JSON-serialisable); :attr:`diagnostics` reads the
            regression's choices from it.
        dA_fit: where ``dA`` is the tied estimate of ``∂Â/∂r`` (NoiseAwareRegression), the
            regression's own ``δ̇⊗δ`` coefficient, fitted beside ``c, b, A``: :meth:`predict`
            uses it (with the tied one in its place the predictions lose that consistency,
            10-60 % further off on the 9-link), while ``dA`` is the estimate of the
            Jacobian that :meth:`connection_jacobian`, the bands and nearby gaits use. None:
            ``dA`` serves both.
    """

    gamma: FourierSeries
    phase_rate: Tensor
    c: FourierSeries
    b: FourierSeries
    A: FourierSeries
    dA: FourierSeries
    bins: BinEstimates
    M: FourierSeries | None = None
    meta: dict | None = None
    dA_fit: FourierSeries | None = None
    dM: FourierSeries | None = None

    @property
    def diagnostics(self) -> RegressionDiagnostics:
        """What the regression chose while fitting (window, intercept order, velocity
        interval, noise level, blend weights), as recorded in :attr:`meta`."""
        return RegressionDiagnostics.from_meta(self.meta)

    @property
    def shape_dim(self) -> int:
        return self.gamma.value_shape[-1]

    @property
    def batch_shape(self) -> torch.Size:
        return self.gamma.batch_shape

    @property
    def device(self) -> torch.device:
        """The device of the model's tensors (that of the data it was fitted to)."""
        return self.gamma.coeffs.device

    def to(self, device: torch.device | str) -> "LocalConnectionModel":
        """The same model with every tensor on ``device`` (e.g. ``"cpu"`` to write it out)."""
        def move(x):
            if isinstance(x, FourierSeries):
                return FourierSeries(x.coeffs.to(device), x.value_ndim)
            return x if x is None else x.to(device)

        bins = {f.name: move(getattr(self.bins, f.name)) for f in fields(self.bins)}
        return LocalConnectionModel(
            gamma=move(self.gamma), phase_rate=move(self.phase_rate), c=move(self.c),
            b=move(self.b), A=move(self.A), dA=move(self.dA), bins=BinEstimates(**bins),
            M=move(self.M), meta=self.meta, dA_fit=move(self.dA_fit), dM=move(self.dM),
        )

    # ------------------------------------------------------------------ evaluation
    def gamma_at(self, phase: Tensor) -> Tensor:
        """``γ(φ)``: phase ``(..., P)`` -> ``(..., P, d)``."""
        return self.gamma(phase)

    def gamma_dot_at(self, phase: Tensor) -> Tensor:
        """``γ̇ = φ̇ dγ/dφ``, the shape velocity on the cycle: ``(..., P)`` -> ``(..., P, d)``."""
        return self.phase_rate[..., None, None] * self.gamma.derivative()(phase)

    def offsets(self, phase: Tensor, r: Tensor, r_dot: Tensor) -> tuple[Tensor, Tensor]:
        """``δ = r − γ(φ)`` and ``δ̇ = ṙ − γ̇(φ)`` for samples ``(..., P, d)``."""
        return r - self.gamma_at(phase), r_dot - self.gamma_dot_at(phase)

    def connection(self, phase: Tensor) -> Tensor:
        """``Â(γ(φ))``: ``(..., P)`` -> ``(..., P, 3, d)``."""
        return self.A(phase)

    def connection_jacobian(self, phase: Tensor) -> Tensor:
        """``∂Â/∂r(γ(φ))``: ``(..., P)`` -> ``(..., P, 3, d, d)``."""
        return self.dA(phase)

    def metric(self, phase: Tensor) -> Tensor:
        """``M̂(γ(φ))``: ``(..., P)`` -> ``(..., P, d, d)``."""
        if self.M is None:
            raise ValueError("this model has no metric: fit it to data with a power channel")
        return self.M(phase)

    def metric_at(self, phase: Tensor, delta: Tensor) -> Tensor:
        """``M̂(γ(φ) + δ)`` to first order, ``M̂(φ) + ∂M̂/∂r(φ) δ`` (``M̂(φ)`` alone without
        ``dM``): phase ``(..., P)``, offsets ``δ (..., P, d)`` -> ``(..., P, d, d)``."""
        m = self.metric(phase)
        if self.dM is None:
            return m
        return m + torch.einsum("...ijk,...k->...ij", self.dM(phase), delta)

    def metric_gamma_dot(self, phase: Tensor) -> Tensor:
        """``M̂γ̇`` on the cycle, the part of ``M̂`` the gait itself identifies:
        ``(..., P)`` -> ``(..., P, d)``."""
        return (self.metric(phase) @ self.gamma_dot_at(phase).unsqueeze(-1)).squeeze(-1)

    def power_on_cycle(self, phase: Tensor) -> Tensor:
        """Power dissipated on the cycle, ``γ̇ᵀM̂γ̇``: ``(..., P)`` -> ``(..., P)``."""
        return (self.gamma_dot_at(phase) * self.metric_gamma_dot(phase)).sum(-1)

    def predict(self, phase: Tensor, r: Tensor, r_dot: Tensor) -> Tensor:
        """Body velocity of samples in the tube (eq. ``advanceddatadriven``).

        Args:
            phase: ``(..., P)``; r, r_dot: ``(..., P, d)``; batch dims broadcast with the model's.
        Returns:
            ``(..., P, 3)``.
        """
        self._check_samples(phase, r, r_dot)
        delta, delta_dot = self.offsets(phase, r, r_dot)
        return (
            self.c(phase)
            + _apply(self.b(phase), delta)
            + _apply(self.A(phase), delta_dot)
            + torch.einsum("...kij,...i,...j->...k", self.prediction_dA(phase), delta_dot,
                           delta)
        )

    @property
    def prediction_dA(self) -> FourierSeries:
        """The series of the ``δ̇⊗δ`` coefficient :meth:`predict` uses: ``dA_fit`` where
        ``∂Â/∂r`` was tied, else ``dA``."""
        return self.dA if self.dA_fit is None else self.dA_fit

    def predict_power(self, phase: Tensor, r: Tensor, r_dot: Tensor) -> Tensor:
        """Power ``ṙᵀ M̂(φ) ṙ``: ``(..., P)``."""
        self._check_samples(phase, r, r_dot)
        return torch.einsum("...i,...ij,...j->...", r_dot, self.metric(phase), r_dot)

    def evaluate_gait(self, gait, **options) -> GaitPrediction:
        """Displacement, cost and efficiency per cycle of a *nearby* gait, from this model alone.

        First-order model ``A(γ') ≈ Â(φ) + ∂Â/∂r(φ) δ`` around the fitted cycle, integrated
        over one cycle like :func:`torchconn.physics.gaits.evaluate` (the reference on a known
        system), with standard errors from the per-bin standard errors and the gait's distance
        from the data in tube radii (warns, then refuses, past it). See
        :func:`torchconn.regression.gait_prediction.predict_gait` for ``options``.

        Returns:
            a :class:`~torchconn.regression.gait_prediction.GaitPrediction`, batch dims ``...``.
        """
        return predict_gait(self, gait, **options)

    def _check_samples(self, phase: Tensor, r: Tensor, r_dot: Tensor) -> None:
        d = self.shape_dim
        _checks.phase_samples(phase, r, r_dot, d=d, same_batch=True,
                              why=f" for a model of a {d}-joint system")

    def __getitem__(self, index) -> "LocalConnectionModel":
        """Select batch elements (e.g. one trial's model): ``model[level, trial]``."""
        if not isinstance(index, tuple):
            index = (index,)

        def pick(x):
            if isinstance(x, FourierSeries):
                return FourierSeries(x.coeffs[index], x.value_ndim)
            return x

        bins = {f.name: getattr(self.bins, f.name) for f in fields(self.bins)}
        bins = {k: (v if v is None or k == "phase" else v[index]) for k, v in bins.items()}
        return LocalConnectionModel(
            gamma=pick(self.gamma), phase_rate=self.phase_rate[index], c=pick(self.c),
            b=pick(self.b), A=pick(self.A), dA=pick(self.dA), bins=BinEstimates(**bins),
            M=pick(self.M), meta=self.meta, dA_fit=pick(self.dA_fit), dM=pick(self.dM),
        )

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> Path:
        """Write the model to a ``.npz`` file (lossless), atomically; like ``numpy.savez``,
        adds ``.npz`` to a name without it. Returns the path written."""
        arrays = {}
        for name in _SERIES:
            series = getattr(self, name)
            if series is not None:
                arrays[f"series_{name}"] = series.coeffs.detach().cpu().numpy()
                arrays[f"ndim_{name}"] = np.array(series.value_ndim)
        for f in fields(self.bins):
            value = getattr(self.bins, f.name)
            if value is not None:
                arrays[f"bins_{f.name}"] = value.detach().cpu().numpy()
        arrays["phase_rate"] = self.phase_rate.detach().cpu().numpy()
        arrays["meta"] = np.array(json.dumps(self.meta or {}, default=str))
        return savez(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> "LocalConnectionModel":
        """Read a model written by :meth:`save`."""
        with np.load(Path(path)) as data:
            arrays = {k: data[k] for k in data.files}
        series = {}
        for name in _SERIES:
            if f"series_{name}" in arrays:
                series[name] = FourierSeries(
                    torch.from_numpy(arrays[f"series_{name}"]), int(arrays[f"ndim_{name}"])
                )
        bins = {
            f.name: torch.from_numpy(arrays[f"bins_{f.name}"]) if f"bins_{f.name}" in arrays
            else None
            for f in fields(BinEstimates)
        }
        return cls(
            gamma=series["gamma"], phase_rate=torch.from_numpy(arrays["phase_rate"]),
            c=series["c"], b=series["b"], A=series["A"],
            dA=series["dA"], M=series.get("M"), bins=BinEstimates(**bins),
            meta=json.loads(str(arrays["meta"])), dA_fit=series.get("dA_fit"),
            dM=series.get("dM"),
        )


#: the series a model file holds (``M``, ``dA_fit`` and ``dM`` where present)
_SERIES = ("gamma", "c", "b", "A", "dA", "M", "dA_fit", "dM")


def _apply(matrix: Tensor, vector: Tensor) -> Tensor:
    """``(..., k, i) @ (..., i) -> (..., k)``."""
    return (matrix @ vector.unsqueeze(-1)).squeeze(-1)
