"""The connection's phase-bin regressions updated cycle by cycle (recursive least squares).

Every bin's regression of :func:`~torchconn.regression.connection_regression` is the weighted
least-squares fit ``A β = XᵀWy`` with ``A = XᵀWX`` (plus the solver's ridge) of the design
``[1, δ, δ̇, δ̇⊗δ]`` around the bin's point ``γ_m`` of a fixed cycle. Its solution, standard
errors and residuals depend on the data only through the sums ``[X|y]ᵀW[X|y]``, ``XᵀW²X``,
``Σw`` and the sample count, and a new cycle adds its own sums to them.
:class:`OnlineConnection` keeps those sums per batch element and bin, adds one cycle at a
time (optionally forgetting the earlier ones by a factor ``λ``) and solves them on demand: the
same coefficients as a batch fit of every cycle added, with weights ``λ^age``, at the cost of
one ``P x P`` solve per bin, never a pass over the earlier samples.

What stays fixed between batch refits: the cycle ``γ(φ)`` and phase rate the bins are centred
on, the phase of the samples (given with each cycle), the bins (count, window, kernel), the tube
radius ``delta_max`` and the ridge. What the full estimator
(:class:`~torchconn.regression.NoiseAwareRegression` in a
:class:`~torchconn.regression.ConnectionEstimator`) adds and this does not: the estimate of
the phase and the limit cycle from the data, the choice of velocity interval, bin width and
complexity, the measurement-noise (errors-in-variables) correction, the shrinkage towards the
smoothed fit and the bins' bias correction of ``Â``. The tie of ``∂Â/∂r``
(:func:`~torchconn.regression.tie_connection_derivative`) is a function of the per-bin fit and
is applied by :meth:`OnlineConnection.model`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .. import _checks
from ..phase.fourier import FourierSeries, fit_fourier
from . import _wls
from .binning import KERNELS, assign_bins
from .connection import ConnectionFit, design_blocks, fit_from_solution, ridge_exemptions
from .model import BinEstimates, LocalConnectionModel
from .tied import tie_connection_derivative

__all__ = ["OnlineConnection", "CycleConfidence"]

#: outputs of the connection regression: the body velocity ``(v_x, v_y, ω)``
_K = 3


@dataclass(frozen=True)
class CycleConfidence:
    """The confidence in the model at one cycle (:meth:`OnlineConnection.update`).

    Attributes:
        cycle: the cycles added so far, this one included (1 for the first).
        r2: ``(..., 3)`` the predictive ``R²`` of this cycle's body velocity ``(v_x, v_y, ω)``
            under the model *before* the cycle was added: ``1 − Σ w (ξ − ξ̂)² / Σ w (ξ − ξ̄)²``
            over the cycle's samples in every bin that could be fitted before it (``ξ̂`` the
            bin's local model, ``ξ̄`` the cycle's weighted mean, ``w`` the bins' kernel
            weights; a sample counts in every bin whose window holds it). It is an
            out-of-sample check of what the model is for, on data it has not seen, and
            costs nothing beyond the cycle's own sums. NaN where no bin could be fitted
            before the cycle (the first cycles).
        dA_relative_se: ``(...)`` after adding the cycle, the root-sum-square of the standard
            errors of ``∂Â/∂r`` over the bins and entries relative to that of ``∂Â/∂r``
            itself: ``√(tr Cov(∂Â/∂r)) / ‖∂Â/∂r‖``, per bin the direct ``δ̇⊗δ`` coefficient.
            ``∂Â/∂r`` is what a proposal follows, and the weakest-identified term of the
            design: ``r2`` is dominated by the on-cycle velocity ``ĉ`` and nears 1 long
            before ``∂Â/∂r`` is known. NaN until every bin can be fitted.
        fitted_bins: ``(...)`` int64, the bins that can be fitted after adding the cycle.
        forgetting: the factor ``λ`` the earlier cycles' sums were multiplied by.
    """

    cycle: int
    r2: Tensor
    dA_relative_se: Tensor
    fitted_bins: Tensor
    forgetting: float

    @property
    def score(self) -> Tensor:
        """``(...)`` the mean of :attr:`r2` over the three body-velocity components."""
        return self.r2.mean(-1)


@dataclass(frozen=True)
class _Solved:
    """The bins' solution from the sums, ``(..., M, ·)``."""

    coef: Tensor  # (..., M, P, K), NaN in bins that cannot be fitted
    se: Tensor  # (..., M, P, K)
    residual_rms: Tensor  # (..., M, K)
    condition: Tensor  # (..., M)
    fitted: Tensor  # (..., M) bool


class OnlineConnection:
    """Per-bin sufficient statistics of the connection regression, updated one cycle at a time.

    Args:
        gamma: the cycle ``γ(φ)`` the bins are centred on, a Fourier series with values ``(d,)``
            and batch dims ``...`` (a fitted model's ``model.gamma``).
        phase_rate: ``(...)`` (or a number) the mean phase velocity ``φ̇``: the bins' centre
            velocities are ``γ̇_m = φ̇ dγ/dφ(φ_m)``.
        n_bins: phase bins ``M`` (centres ``φ_m = 2πm/M``).
        window: a bin's half-width in bin spacings (``0 < window < M/2``); fixed, as every
            cycle's samples must be binned alike.
        kernel: the bins' weights, one of :data:`~torchconn.regression.KERNELS`.
        delta_max: only samples with ``‖r − γ_m‖ < delta_max`` enter a bin (None: all).
        ridge: the solver's ridge ``λ ≥ 0`` on the unit diagonal of the standardised normal
            matrix (:func:`~torchconn.regression.connection_regression`).
        ridge_connection: the ridge also penalises ``Â``'s columns (False: not).
        fourier_order: order of the series :meth:`model` fits through the bins
            (at most ``(M − 1) / 2``).
        forgetting: the default ``λ`` of :meth:`update`, ``0 < λ ≤ 1`` (1: nothing is
            forgotten).
        min_samples, max_condition: the fewest samples and largest condition number with
            which a bin is fitted (None: the solver's defaults, ``P + 5`` and ``1e12``).

    The statistics have batch dims ``...`` (those of ``gamma``). A cycle's samples may have
    more leading dims (trials): those are pooled into the statistics. Bins that cannot be
    fitted yet (too few samples, rank-deficient) are NaN in :meth:`fit`; :meth:`model` needs
    them all.

    Examples:
        >>> import torch
        >>> from torchconn.phase.fourier import FourierSeries
        >>> coeffs = torch.zeros(3, 2, dtype=torch.float64)
        >>> coeffs[1, 0] = coeffs[2, 1] = 0.5
        >>> online = OnlineConnection(FourierSeries(coeffs, 1), 1.0, n_bins=8, window=1.0,
        ...                           fourier_order=3)
        >>> online.cycles
        0
    """

    def __init__(self, gamma: FourierSeries, phase_rate: Tensor | float, *, n_bins: int = 48,
                 window: float = 1.0, kernel: str = "tricube", delta_max: float | None = None,
                 ridge: float = 0.0, ridge_connection: bool = True, fourier_order: int = 12,
                 forgetting: float = 1.0, min_samples: int | None = None,
                 max_condition: float | None = None) -> None:
        where = "OnlineConnection"
        if not isinstance(gamma, FourierSeries) or gamma.value_ndim != 1:
            raise TypeError(f"{where}: gamma must be a FourierSeries with values (d,) (a "
                            f"fitted model's .gamma), got {type(gamma).__name__}")
        _checks.check_value(f"{where}: n_bins", n_bins, int, {"ge": 3})
        _checks.check_value(f"{where}: window", window, float, {"gt": 0, "lt": n_bins / 2})
        if kernel not in KERNELS:
            raise ValueError(f"{where}: kernel must be one of {KERNELS}, got {kernel!r}")
        _checks.check_value(f"{where}: delta_max", delta_max, float | None, {"gt": 0})
        _checks.check_value(f"{where}: ridge", ridge, float, {"ge": 0})
        if not math.isfinite(ridge):
            raise ValueError(f"{where}: ridge must be finite, got {ridge!r}")
        _checks.check_value(f"{where}: fourier_order", fourier_order, int,
                            {"ge": 0, "le": (n_bins - 1) // 2})
        self.forgetting = _check_forgetting(forgetting, f"{where}: forgetting")
        coeffs = gamma.coeffs
        batch = gamma.batch_shape
        rate = torch.as_tensor(phase_rate, dtype=coeffs.dtype, device=coeffs.device)
        try:
            rate = rate.expand(batch)
        except RuntimeError:
            raise ValueError(f"{where}: phase_rate of shape {tuple(rate.shape)} does not "
                             f"broadcast to gamma's batch {tuple(batch)}") from None
        if not bool(torch.isfinite(rate).all()) or not bool(torch.isfinite(coeffs).all()):
            raise ValueError(f"{where}: gamma and phase_rate must be finite")
        self.gamma, self.phase_rate = gamma, rate
        self.n_bins, self.window, self.kernel = n_bins, float(window), kernel
        self.delta_max, self.ridge, self.ridge_connection = delta_max, float(ridge), ridge_connection
        self.fourier_order = fourier_order
        self.min_samples, self.max_condition = min_samples, max_condition
        d = gamma.value_shape[-1]
        self.shape_dim = d
        self.n_coef = 1 + 2 * d + d * d
        self.centres = torch.arange(n_bins, dtype=coeffs.dtype, device=coeffs.device) * (
            2 * math.pi / n_bins)
        at = self.centres.expand(batch + (n_bins,))
        self.gamma_m = gamma(at)
        self.gamma_dot_m = rate[..., None, None] * gamma.derivative()(at)
        p, c = self.n_coef, self.n_coef + _K
        kw = dict(dtype=coeffs.dtype, device=coeffs.device)
        self.sums = torch.zeros(batch + (n_bins, c, c), **kw)
        self.sums_w2 = torch.zeros(batch + (n_bins, p, p), **kw)
        self.sum_w = torch.zeros(batch + (n_bins,), **kw)
        self.count = torch.zeros(batch + (n_bins,), dtype=torch.int64, device=coeffs.device)
        self._tube_sq = torch.zeros(batch + (d,), **kw)
        self._tube_n = torch.zeros(batch + (d,), **kw)
        self.cycles = 0
        self.history: list[CycleConfidence] = []
        self._solved: _Solved | None = None  # the solution of the current sums

    @classmethod
    def from_model(cls, model: LocalConnectionModel, **settings) -> "OnlineConnection":
        """Statistics centred on a fitted model's cycle, with its regression's bins, tube
        radius, ridge and Fourier order (``model.meta``); ``settings`` override them (keywords
        of :class:`OnlineConnection`; ``window`` is required where the model was binned at
        one width per batch element)."""
        if not isinstance(model, LocalConnectionModel):
            raise TypeError("OnlineConnection.from_model: model must be a LocalConnectionModel "
                            f"(an estimator's model_), got {type(model).__name__}")
        meta = model.meta or {}
        regression = (meta.get("settings") or {}).get("regression") or {}
        own = {k: regression[k] for k in ("n_bins", "kernel", "delta_max", "ridge",
                                          "ridge_connection", "fourier_order") if k in regression}
        window = meta.get("window")
        if isinstance(window, (int, float)) and not isinstance(window, bool):
            own["window"] = float(window)
        elif "window" not in settings:
            raise ValueError("OnlineConnection.from_model: the model records no single bin "
                             f"width (meta['window'] = {window!r}): pass window=...")
        return cls(model.gamma, model.phase_rate, **(own | settings))

    @property
    def batch_shape(self) -> torch.Size:
        return self.gamma.batch_shape

    # ------------------------------------------------------------------ updates
    def update(self, phase: Tensor, r: Tensor, r_dot: Tensor, xi: Tensor, *,
               forgetting: float | None = None, weight: float = 1.0) -> CycleConfidence:
        """Add one cycle's samples; returns (and records in :attr:`history`) its confidence.

        Args:
            phase: ``(*pooled, ..., N)`` the samples' phase (rad) in the cycle's phase
                (the phase :attr:`gamma` is a function of); NaN marks a missing sample.
            r, r_dot: ``(*pooled, ..., N, d)`` shapes (rad) and shape velocities.
            xi: ``(*pooled, ..., N, 3)`` body velocities ``(v_x, v_y, ω)``.
            forgetting: ``λ`` (default: the constructor's): the earlier cycles' sums are
                multiplied by ``λ`` before this cycle's are added (``XᵀW²X`` by ``λ²``), so
                that after ``C`` cycles cycle ``c``'s weights carry ``λ^(C − c)``.
            weight: every sample of this cycle enters with its kernel weight times ``weight``
                (``> 0``): a recording of another gait, counted less the further it lies.

        ``...`` are the statistics' batch dims; leading ``*pooled`` dims (trials) are summed
        into them.

        Raises:
            ValueError: shapes that do not fit, ±inf samples, or ``forgetting`` outside
                ``(0, 1]``.
        """
        fn = "OnlineConnection.update"
        lam = self.forgetting if forgetting is None else _check_forgetting(
            forgetting, f"{fn}: forgetting")
        _checks.check_value(f"{fn}: weight", weight, float, {"gt": 0})
        if not math.isfinite(weight):
            raise ValueError(f"{fn}: weight must be finite, got {weight!r}")
        _checks.tensor(phase, "phase", "(..., N)", fn=fn, floating=True,
                       valid=lambda t: t.ndim >= 1)
        batch = self.batch_shape
        if tuple(phase.shape[phase.ndim - 1 - len(batch):-1]) != tuple(batch):
            raise ValueError(
                f"{fn}: phase of shape {tuple(phase.shape)} does not end in the statistics' "
                f"batch dims {tuple(batch)} + (N,): expected (*pooled, *{tuple(batch)}, N)")
        # the statistics' dtype and device (those of gamma)
        phase = phase.to(self.sums)
        r, r_dot, xi = (x.to(self.sums) if isinstance(x, Tensor) else x for x in (r, r_dot, xi))
        bins = assign_bins(phase, self.n_bins, window=self.window, kernel=self.kernel)
        s = _wls.prepare(fn, r, r_dot, xi, "xi", _K, bins, self.gamma_m, self.gamma_dot_m)
        new, new_w2, new_w, new_n = self._cycle_sums(s)
        r2 = _predictive_r2(self._solution(), new, self.n_coef)
        self.sums = lam * self.sums + weight * new
        self.sums_w2 = lam**2 * self.sums_w2 + weight**2 * new_w2
        self.sum_w = lam * self.sum_w + weight * new_w
        self.count = self.count + new_n
        self._add_tube(phase, r, lam, weight)
        self.cycles += 1
        self._solved = after = self._solve()
        confidence = CycleConfidence(
            cycle=self.cycles, r2=r2, dA_relative_se=_relative_se(after, self.shape_dim),
            fitted_bins=after.fitted.sum(-1), forgetting=lam)
        self.history.append(confidence)
        return confidence

    def confidence(self) -> CycleConfidence:
        """The confidence at the last cycle added (:class:`CycleConfidence`)."""
        if not self.history:
            raise ValueError("OnlineConnection.confidence: no cycle added yet (call update)")
        return self.history[-1]

    def _cycle_sums(self, s: _wls.BinnedSamples):
        """One cycle's ``[X|y]ᵀW[X|y]``, ``XᵀW²X``, ``Σw`` and counts per bin, summed over the
        pooled dims: ``(..., M, C, C)``, ``(..., M, P, P)``, ``(..., M)``, ``(..., M)``."""
        p, c = self.n_coef, self.n_coef + _K
        total = s.rows.shape[0]
        full = s.r.new_zeros((total, c, c))
        g2 = s.r.new_zeros((total, p, p))
        sum_w = s.r.new_zeros(total)
        count = torch.zeros(total, dtype=torch.int64, device=s.r.device)
        if s.rows.shape[1]:
            for sel, xy, w in _wls._design_chunks(s, design_blocks, p, self.delta_max):
                full[sel] = xy.mT @ xy
                xww = xy[..., :p] * w.sqrt().unsqueeze(-1)  # rows scaled by w: XᵀW²X
                g2[sel] = xww.mT @ xww
                sum_w[sel] = _wls._row_sum(w, -1)
                count[sel] = (w > 0).sum(-1)
        pooled = len(s.batch_shape) - len(self.batch_shape)

        def fold(x: Tensor) -> Tensor:
            x = x.reshape(s.batch_shape + (self.n_bins,) + x.shape[1:])
            return x.sum(tuple(range(pooled))) if pooled else x

        return fold(full), fold(g2), fold(sum_w), fold(count)

    def _add_tube(self, phase: Tensor, r: Tensor, lam: float, weight: float) -> None:
        """Add the cycle's squared offsets ``δ = r − γ(φ)`` per joint (NaN samples aside),
        times ``weight``."""
        pooled = phase.ndim - 1 - len(self.batch_shape)
        valid = torch.isfinite(phase).unsqueeze(-1) & torch.isfinite(r)
        delta = r - self.gamma(torch.nan_to_num(phase))
        sq = torch.where(valid, delta.square(), 0.0).sum(-2)
        n = valid.sum(-2).to(sq)
        dims = tuple(range(pooled))
        if pooled:
            sq, n = sq.sum(dims), n.sum(dims)
        self._tube_sq = lam * self._tube_sq + weight * sq
        self._tube_n = lam * self._tube_n + weight * n

    # ------------------------------------------------------------------ solutions
    def _solution(self) -> _Solved:
        """The solution of the current sums (solved once per update)."""
        if self._solved is None:
            self._solved = self._solve()
        return self._solved

    def _solve(self) -> _Solved:
        """Solve every bin's normal equations from the sums (the solver's ridge convention,
        standard errors and fitting limits, :func:`~torchconn.regression._wls.solve`)."""
        p = self.n_coef
        batch = self.sums.shape[:-2]
        flat = self.sums.reshape(-1, p + _K, p + _K)
        gram, rhs = flat[:, :p, :p], flat[:, :p, p:]
        yy = flat[:, p:, p:].diagonal(dim1=-2, dim2=-1)
        g2 = self.sums_w2.reshape(-1, p, p)
        sum_w = self.sum_w.reshape(-1)
        count = self.count.reshape(-1)
        lam = gram.new_full(gram.shape[:1], self.ridge)
        unpen = ridge_exemptions(self.shape_dim, self.ridge_connection, gram.device)
        normal = gram.clone()
        chol, failed, dead, d2 = _wls.ridge_cholesky(normal, lam, unpen)
        scale = torch.where(dead, 1.0, d2.sqrt())
        beta = torch.cholesky_solve(rhs, chol)
        l_inv = _wls._triangular_inverse(chol)
        condition = _wls.condition_bound(normal, l_inv, scale)
        condition = torch.where(failed | (dead.any(-1) & (self.ridge == 0)), torch.inf,
                                condition)
        dof, cov_diag = _wls.sandwich(l_inv.mT @ l_inv, g2, gram, sum_w)
        # RSS = yᵀWy − 2βᵀXᵀWy + βᵀXᵀWXβ, from the sums alone
        rss = (yy - 2 * (beta * rhs).sum(-2) + (beta * (gram @ beta)).sum(-2)).clamp_min(0)
        sigma2 = torch.where(dof.unsqueeze(-1) > 0, rss / dof.unsqueeze(-1), torch.nan)
        se = (cov_diag.clamp(min=0).unsqueeze(-1) * sigma2.unsqueeze(-2)).sqrt()
        ill = _wls.unfittable(count, condition, p, gram.dtype, self.min_samples,
                              self.max_condition)
        bad = ill[:, None, None] | dead.unsqueeze(-1)
        rms = (rss / sum_w.unsqueeze(-1)).sqrt().masked_fill(ill.unsqueeze(-1), torch.nan)

        def shaped(x: Tensor) -> Tensor:
            return x.reshape(batch + x.shape[1:])

        return _Solved(coef=shaped(beta.masked_fill(bad, torch.nan)),
                       se=shaped(se.masked_fill(bad, torch.nan)),
                       residual_rms=shaped(rms), condition=shaped(condition),
                       fitted=shaped(~ill))

    def fit(self) -> ConnectionFit:
        """The per-bin estimates ``(..., M, ·)`` of every cycle added (as
        :func:`~torchconn.regression.connection_regression` returns them): NaN in bins that
        cannot be fitted yet."""
        sol = self._solution()
        ones = torch.ones_like(sol.condition)
        return fit_from_solution(_wls.Solution(
            coef=sol.coef, se=sol.se, n_samples=self.count, residual_rms=sol.residual_rms,
            condition=sol.condition, ridge=ones * self.ridge, eiv_scale=ones), self.shape_dim)

    def model(self, *, tie: bool = True) -> LocalConnectionModel:
        """The local model of every cycle added: the bins' estimates as Fourier series in
        phase (order :attr:`fourier_order`) around :attr:`gamma`.

        Args:
            tie: tie ``∂Â/∂r`` to ``b̂`` and ``dÂ/dφ``
                (:func:`~torchconn.regression.tie_connection_derivative`, as the noise-aware
                regression does; the direct estimate is ``dA_fit``); False: the direct
                ``δ̇⊗δ`` coefficient.

        Raises:
            ValueError: where a bin cannot be fitted yet (add cycles, widen the window).
        """
        fit = self.fit()
        fitted = torch.isfinite(fit.coef).all(-1).all(-1)
        if not bool(fitted.all()):
            missing = int((~fitted).sum())
            need, _ = _wls.fit_limits(self.n_coef, fit.coef.dtype, self.min_samples)
            raise ValueError(
                f"OnlineConnection.model: {missing} of {fitted.numel()} phase bins cannot be "
                f"fitted yet after {self.cycles} cycle(s) (fewest samples in a bin: "
                f"{int(self.count.min())}, a bin needs {need} and a design of full rank): "
                "add cycles (update), or use fewer bins (n_bins=...) or a wider window "
                "(window=...)")
        if tie:
            tied = tie_connection_derivative(fit, self.gamma_m, self.gamma_dot_m,
                                             self.fourier_order, window=self.window,
                                             kernel=self.kernel)
            fit = dataclasses.replace(tied, dA_direct=fit.dA)
        centres, order = self.centres, self.fourier_order

        def series(values: Tensor, ndim: int) -> FourierSeries:
            return fit_fourier(centres, values, order, value_ndim=ndim)

        bins = BinEstimates(
            phase=centres, gamma=self.gamma_m, gamma_dot=self.gamma_dot_m,
            c=fit.c, b=fit.b, A=fit.A, dA=fit.dA, c_se=fit.se_c, b_se=fit.se_b,
            A_se=fit.se_A, dA_se=fit.se_dA, n_samples=fit.n_samples,
            dA_correlation=fit.corr_dA)
        tube = (self._tube_sq / self._tube_n).sqrt()
        settings = {"n_bins": self.n_bins, "window": self.window, "kernel": self.kernel,
                    "delta_max": self.delta_max, "ridge": self.ridge,
                    "ridge_connection": self.ridge_connection,
                    "fourier_order": self.fourier_order, "tie": tie}
        return LocalConnectionModel(
            gamma=self.gamma, phase_rate=self.phase_rate, c=series(fit.c, 1),
            b=series(fit.b, 2), A=series(fit.A, 2), dA=series(fit.dA, 3),
            dA_fit=None if fit.dA_direct is None else series(fit.dA_direct, 3), bins=bins,
            meta={"settings": {"online": settings}, "window": self.window,
                  "cycles": self.cycles, "batch_shape": list(self.batch_shape),
                  "tube_rms": tube.reshape(-1, self.shape_dim).mean(0).tolist()},
        )


def _check_forgetting(value, where: str) -> float:
    _checks.check_value(where, value, float, {"gt": 0, "le": 1})
    return float(value)


def _predictive_r2(before: _Solved, sums: Tensor, p: int) -> Tensor:
    """``R² (..., K)`` of a cycle's sums ``[X|y]ᵀW[X|y] (..., M, P + K, P + K)`` under the
    bins' coefficients ``before``, over the bins fitted before it; NaN where none was."""
    gram, rhs = sums[..., :p, :p], sums[..., :p, p:]
    yy = sums[..., p:, p:].diagonal(dim1=-2, dim2=-1)  # (..., M, K)
    beta = torch.nan_to_num(before.coef)
    sse = yy - 2 * (beta * rhs).sum(-2) + (beta * (gram @ beta)).sum(-2)
    keep = before.fitted.unsqueeze(-1).to(sse)
    sse = (sse * keep).sum(-2)
    # the intercept column is √w: its row of XᵀWX is Σw, of XᵀWy Σwy
    sw = (gram[..., 0, 0].unsqueeze(-1) * keep).sum(-2)
    swy = (rhs[..., 0, :] * keep).sum(-2)
    sst = (yy * keep).sum(-2) - swy.square() / sw
    return torch.where(sst > 0, 1 - sse / sst, torch.nan)


def _relative_se(sol: _Solved, d: int) -> Tensor:
    """``√(Σ se²) / √(Σ coef²)`` of the ``δ̇⊗δ`` coefficients over bins and entries ``(...)``."""
    cross = slice(1 + 2 * d, None)
    se = sol.se[..., cross, :].square().flatten(-3).sum(-1)
    size = sol.coef[..., cross, :].square().flatten(-3).sum(-1)
    return (se / size).sqrt()
