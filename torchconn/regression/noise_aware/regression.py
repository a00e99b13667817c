"""The noise-aware regression stage (:class:`NoiseAwareRegression`) and its search of the
velocity interval, filter and bin width.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import ClassVar, Literal

import torch
from torch import Tensor

from ..._options import option
from ...cycles import cycle_index
from ...noise.intervals import (
    MAX_INTERVAL_CYCLES,
    VELOCITY_KERNEL,
    IntervalSamples,
    flatten_batch,
    interval_samples,
    intervals_by_h,
    noise_ratio,
    pooled_view,
    take_intervals,
    velocity_interval_for,
)
from ...noise.spectrum import estimate_noise
from ...phase.limit_cycle import phase_rate
from ...phase.smoothing import unwrap
from ...trajectory import Trajectory
from ..binning import BinIndex, assign_bins, auto_window, auto_windows
from ..connection import ConnectionFit
from ..tied import tie_connection_derivative
from ..tube import TubeRegression
from .bias import (
    RESIDUAL_BIAS_FRACTION,
    OneSampleOffsets,
    bin_bias_correction,
    cycle_series,
    derivative_bias_allowance,
    derivative_bias_correction,
    interval_bias,
    offset_bias,
    one_sample_offsets,
    resolved_bias,
)
from .eiv import flagged_fit, noise_aware_regression, sampling_factor, scatter_fits, take_fit
from .shrink import blend_fits, offset_gain, offsets_at, rescaled_covariance, shrink_series

__all__ = ["NoiseAwareRegression", "predictions_only"]


_PREDICTIONS_ONLY = contextvars.ContextVar("predictions_only", default=False)


@contextlib.contextmanager
def predictions_only() -> Iterator[None]:
    """Within: :class:`NoiseAwareRegression` fits only what its model's predictions use.

    :meth:`~torchconn.regression.model.LocalConnectionModel.predict` uses ``ĉ, b̂, Â`` and the
    regression's own ``δ̇⊗δ`` coefficient, so the work that serves only the estimate of
    ``∂Â/∂r`` and the bands is skipped: the tie of ``∂Â/∂r`` (with the joint covariance of
    ``b̂`` and the direct estimate it weighs them by) and, pooled, ``Â``'s sampling factor and
    bias allowance. The model's ``dA`` is then the direct estimate (``dA_fit`` None,
    ``meta["derivative"]`` says so) and its predictions are the same bit for bit. For callers
    that score predictions alone (the sweep); a model fitted so is not one to read ``∂Â/∂r``
    or bands from.
    """
    token = _PREDICTIONS_ONLY.set(True)
    try:
        yield
    finally:
        _PREDICTIONS_ONLY.reset(token)


#: standard errors the joints' mean noise variance must stand above 0 for
#: :meth:`NoiseAwareRegression.noise_setup` to correct for it
_NOISE_MIN_Z = 2.0


@dataclass(frozen=True)
class _Search:
    """One filter's search of the pooled choice (``NoiseAwareRegression._search``).

    Attributes:
        fit: the chosen candidate's fit; None where no candidate can be fitted, or none beats
            the search's bound.
        view, h, window: its pooled interval samples, interval and bin half-width (with no
            fit: those at the shortest interval tried).
        mse: its estimated MSE, at least its variance (inf with no fit).
        table: ``[h, window, MSE]`` of every candidate that can be fitted, in the order
            tried (those in ``skipped`` with their variance, a lower bound of the MSE).
        skipped: ``[h, window]`` of the candidates whose bias correction was skipped.
    """

    fit: ConnectionFit | None
    view: IntervalSamples
    h: int
    window: float
    mse: float
    table: list
    skipped: list


def _least_score(order: list, lower: dict, score, *, bound: float = math.inf,
                 prune: bool = True) -> tuple:
    """The first candidate in ``order`` of least ``score(key) -> (fit, score)``, scoring as
    few as the lower bounds ``lower[key] <= score`` allow (branch and bound).

    The candidates are scored in increasing bound (ties in ``order``) until the next bound
    exceeds the least score found, or equals it and comes later in ``order``: none of the
    rest can be first of least score. NaN scores count as ``inf``; a candidate must score
    below ``bound`` (on a tie the bound wins). ``prune=False`` scores every candidate, in
    ``order``.

    Returns the chosen key (None where none scores below a finite ``bound``; where every
    score is ``inf``, the first scored) and ``{key: (fit, score)}`` of those scored, in the
    order scored.
    """
    rank = {key: i for i, key in enumerate(order)}
    queue = sorted(order, key=lambda key: lower[key]) if prune else list(order)
    done, best, least = {}, None, (bound, -1)
    for key in queue:
        if prune and (lower[key], rank[key]) > least:
            break
        fit, value = done[key] = score(key)
        if (math.inf if math.isnan(value) else value, rank[key]) < least:
            best, least = key, (value, rank[key])
    if best is None and done and math.isinf(bound):
        best = min(done, key=rank.__getitem__)
    return best, done


#: where no bin width can be fitted at an interval (the pooled reference, or an unpooled
#: element's own), the interval is divided by this (:func:`_shorter_interval`) until one can
_FALLBACK_INTERVAL_DIVISOR = 1.5


#: the pooled fit's candidate bin half-widths (bin spacings)
_CANDIDATE_WINDOWS = (1.0, 2.0, 3.0, 4.0)


#: every pair of these multiples of ``h0`` and the windows above is a candidate, scored ``V +
#: V⁺ + λ‖B‖²`` with ``λ = RESIDUAL_BIAS_FRACTION`` (see ``_chosen_fit``)
_CORRECTED_INTERVAL_MULTIPLES = (1.5, 2.0, 3.0, 4.0, 6.0)


#: unpooled elements (no choice yet) widen their bins with the noise: by this many bin spacings
#: per unit of the noise ratio (see noise_ratio), up to _MAX_NOISE_WINDOW spacings
_WINDOW_PER_NOISE_RATIO = 20.0


_MAX_NOISE_WINDOW = 3.0


@dataclass(frozen=True)
class _Chosen:
    """What the tie of ``∂Â/∂r`` needs of the corrected fit: the bins' half-width (a number,
    or ``(...)`` per unpooled element) and, for a pooled fit, the chosen candidate's interval
    samples, the one-sample offsets its bias correction modelled (None without it), whether
    no measurement noise was detected and the joints' measurement-noise variance ``(d,)`` (pooled) it
    was corrected for (to run its regression again for the joint covariance of ``b̂`` and
    ``∂Â/∂r``, and for ``Â``'s sampling factor, :meth:`NoiseAwareRegression._rerun_chosen`)."""

    windows: float | Tensor
    view: IntervalSamples | None = None
    offsets: OneSampleOffsets | None = None
    noise_free: bool = False
    noise_var: Tensor | None = None


@dataclass(frozen=True, kw_only=True)
class NoiseAwareRegression(TubeRegression):
    """:class:`~torchconn.regression.tube.TubeRegression` with the connection regressed on raw
    interval differences and corrected for the joint angles' measurement noise.

    Body and shape velocities are differences of the recorded poses and joint angles filtered
    alike over ``velocity_interval`` samples (:func:`interval_samples`), so target and
    regressors see the same operation and nothing else is smoothed; each joint's noise is
    estimated from the spectrum of its increments (:func:`estimate_noise`) and removed from
    every bin's normal equations
    (:func:`eiv_correction`). The smoothed state serves the phase and the limit cycle, and
    :class:`TubeRegression`'s smoothed regression is the fallback: where the data cannot tell
    the corrected estimate from the smoothed one (little data, many joints, much noise: the
    correction then removes most of the normal matrix and mostly adds variance), the result
    is shrunk towards the smoothed estimate (:func:`blend_fits`; the weights of the corrected
    estimate are ``model.meta["corrected_weight"]``). The metric is fitted as by
    :class:`TubeRegression`. It is :class:`~torchconn.regression.ConnectionEstimator`'s
    default regression (settings table ``method = "noise_aware"``). Unpooled, a trial's
    noise estimate, interval and windows do not depend on the other trials of the batch, and
    its coefficients only through the solver's rounding, as :class:`TubeRegression`'s (bit for
    bit on the 3-link; to 1e-13 on the 9-link, where MKL's kernels round with the memory
    alignment of the bins' matrices unless ``MKL_CBWR=AUTO`` is set).

    Attributes (besides :class:`TubeRegression`'s):
        velocity_interval: samples the velocity filter spans; None chooses it from the noise
            (:func:`velocity_interval_for`), and a pooled fit then also tries longer ones.
            With ``window=None`` a pooled fit chooses the bins' width too, by the estimated
            error of ``Â`` (``meta["interval_window_scores"]``); unpooled elements widen it
            with the noise. Where the bins cannot all be fitted at the chosen interval, a
            shorter one is taken (``meta["velocity_interval"]`` is the one used); a pooled fit
            on data with missing samples also tries the box filter
            (``meta["velocity_kernel"]``).
        noise_band_low: lowest frequency (cycles per sample) of the noise fit; None: chosen
            per batch element and joint from the data (:func:`estimate_noise`).
        noise_floor: the noise fit's process floor: ``"flat"`` (default), or ``"low_rate"``:
            the fitted cycle's harmonics spread by phase noise (:func:`phase_noise_floor`)
            where the gait's harmonics reach the noise fit's top band (32 or fewer samples per
            cycle; their phase-noise tails fill it and drive the flat floor's ``σ̂²`` below
            0), ``"flat"`` elsewhere, bit for bit. ``"normal"``: the joint increments projected
            out of the fitted cycle's first derivatives at each sample's phase
            (:func:`normal_increments`), which takes out the phase noise and the phase
            estimate's errors, fitted over ``[0.1, 0.5]`` cycles per sample with a flat floor;
            with two joints (the 3-link) ``"flat"`` bit for bit. Either way the test
            for noise of the joints' mean takes their shared phase noise into account
            (:attr:`NoiseEstimate.correlation`, from the fitted cycle).

    The corrected fit is always shrunk towards the smoothed one (:func:`blend_fits`), a
    pooled fit's ``Â`` corrected for the bins' bias (:func:`bin_bias_correction`), ``∂Â/∂r``
    tied (:func:`~torchconn.regression.tie_connection_derivative`; a pooled fit's corrected
    for, or under noise allowing for, the bins' bias, with ``b̂`` and the direct estimate's
    joint covariance in the bands), a pooled fit's series of ``Â`` shrunk harmonic by
    harmonic with ``ĉ, b̂`` re-estimated to it, and a pooled fit keeps ``Â``'s sampling factor
    and, without detected noise, its bias allowance (docs/validation/deleted-options.md lists
    the variants these replaced).
    """

    velocity_interval: int | None = option(None, ge=1)
    noise_band_low: float | None = option(None, gt=0, le=0.45)
    noise_floor: Literal["flat", "low_rate", "normal"] = "flat"
    #: test hook: correct every candidate of the pooled choice instead of branch and bound
    #: (the same choice and fit bit for bit; ``meta["interval_window_scores"]`` then holds
    #: every candidate's MSE)
    _full_search: ClassVar[bool] = False

    def _corrected_fit(self, traj, pool, samples, gamma_m, gamma_dot_m, opts, bins_for):
        """Unpooled batch elements may carry different noise (a sweep's noise levels), so each
        gets its own interval and window; elements sharing both are regressed together (one
        call per distinct pair, not per trial)."""
        d, n_bins = traj.shape_dim, self.n_bins
        var, ratio, h = self.noise_setup(traj, pool, gamma_m)
        if pool:
            fit, view, window, scores, skipped, offsets = self._chosen_fit(
                traj, var, ratio, int(h), gamma_m, gamma_dot_m, opts)
            meta = {"velocity_interval": view.h, "velocity_kernel": view.kernel,
                    "noise_ratio": float(ratio), "noise_r": var.sqrt().tolist(),
                    "interval_window_scores": scores, "interval_window_bounds": skipped}
            return fit, window, meta, _Chosen(window, view, offsets,
                                              noise_free=not bool((var > 0).any()),
                                              noise_var=var)
        # b̂ and ∂Â/∂r's joint covariance, for the tie: only for groups with detected noise
        # (elsewhere the tie takes the two as independent, and scatter_fits leaves it NaN)
        joint = {} if _PREDICTIONS_ONLY.get() else {"joint_covariance": True}
        batch = tuple(traj.batch_shape)
        n, m = math.prod(batch), n_bins
        flat = flatten_batch(traj)
        h_flat, ratio_flat = h.reshape(-1), ratio.reshape(-1)
        windows = self.element_windows(flat.phase, d, ratio_flat)
        groups, inverse = torch.unique(torch.stack([h_flat.to(windows), windows], -1), dim=0,
                                       return_inverse=True)
        g_m = gamma_m.expand(batch + (m, d)).reshape(n, m, d)
        g_dot = gamma_dot_m.expand(batch + (m, d)).reshape(n, m, d)
        var_flat = var.reshape(n, d)
        by_h = intervals_by_h(flat, h_flat, traj.dt)
        parts, h_flat = [], h_flat.clone()
        pending = torch.ones(n, dtype=torch.bool, device=h_flat.device)
        while bool(pending.any()):
            # an element whose bins cannot all be fitted at its chosen interval (too few
            # independent rows for the overlapping filter) tries a shorter one
            # (_shorter_interval); at h = 1, or a given velocity_interval, on_ill_conditioned
            # applies
            keys = torch.stack([h_flat.to(windows), windows], -1)
            groups, inverse = torch.unique(keys[pending], dim=0, return_inverse=True)
            todo = torch.nonzero(pending).flatten()
            for g, (hg, wg) in enumerate(groups.tolist()):
                hg = int(hg)
                idx = todo[inverse == g]
                if hg not in by_h:
                    shorter = torch.tensor([hg], device=h_flat.device)
                    by_h.update(intervals_by_h(flat, shorter, traj.dt))
                iv = take_intervals(by_h[hg], idx)
                bins = assign_bins(iv.phase, n_bins, window=wg, kernel=self.kernel)
                args = (iv, bins, g_m[idx], g_dot[idx], var_flat[idx])
                group_opts = {**opts, **joint} if bool((var_flat[idx] > 0).any()) else opts
                if hg == 1 or self.velocity_interval:  # nothing shorter to try
                    fit = noise_aware_regression(*args, **group_opts)
                    parts.append((idx, self._with_offset_gain(fit, args, opts, pool)))
                    pending[idx] = False
                    continue
                fit, bad = flagged_fit(args, group_opts)
                fit = self._with_offset_gain(fit, args, opts, pool)
                parts.append((idx[~bad], take_fit(fit, ~bad)))
                pending[idx[~bad]] = False
                h_flat[idx[bad]] = _shorter_interval(hg)
        h = h_flat.reshape(batch)
        meta = {"velocity_interval": h.tolist(), "velocity_kernel": VELOCITY_KERNEL,
                "noise_ratio": ratio.tolist(), "noise_r": var.sqrt().tolist(),
                "windows": windows.reshape(batch).tolist()}
        fit = scatter_fits(parts, n, batch)
        if fit.cov_b_dA is not None:  # only under detected noise (NaN: the tie takes the
            # two as independent where none was, as in a clean element of a noisy group)
            clean = ~(var > 0).any(-1).reshape(batch + (1, 1, 1, 1))
            fit = dataclasses.replace(fit, cov_b_dA=fit.cov_b_dA.masked_fill(clean, torch.nan))
        return fit, float(windows.max()), meta, _Chosen(windows.reshape(batch))

    def _chosen_fit(self, traj: Trajectory, var: Tensor, ratio: Tensor, h0: int,
                    gamma_m: Tensor, gamma_dot_m: Tensor, opts: dict):
        """The pooled corrected fit at the velocity interval, bin width and filter of least
        estimated mean squared error of ``Â``.

        Longer intervals and wider bins lower the variance and add bias (they average ``A``
        over more of the cycle). Every candidate's bias (:func:`bin_bias_correction`) is
        estimated and removed, and ``MSE_c ≈ V_c + V⁺_c + λ‖B_c‖²``: ``V`` the summed squared
        standard errors of ``Â`` (calibrated for the rows' overlap by
        :func:`overlap_inflation`), ``V⁺`` the variance the correction adds, ``B_c`` the
        correction applied and ``λ =`` :data:`RESIDUAL_BIAS_FRACTION` the part of its square
        taken to remain (on the 3-link reference gait without noise the correction removed 2/3
        of the bias). The candidates are every pair of the half-widths
        :data:`_CANDIDATE_WINDOWS` (at least the data-size rule's) and the intervals ``h0``
        and ``h0 · _CORRECTED_INTERVAL_MULTIPLES`` (``h0`` the noise rule's,
        :func:`velocity_interval_for`; at most a quarter cycle); the first of least ``MSE`` in
        that order is taken. ``V_c`` comes from the uncorrected fit and ``V⁺``, ``‖B‖²`` are
        ``≥ 0``, so ``V_c`` bounds ``MSE_c`` from below: the candidates are corrected in
        increasing ``V`` until the next ``V`` exceeds the least ``MSE`` found (or equals it
        and comes later in the order), and the rest cannot be chosen (branch and bound; the
        same choice and fit as correcting all, bit for bit).

        ``window`` or ``velocity_interval``, when given, fix theirs. Where no width can be
        fitted at ``h0``, shorter intervals (:func:`_shorter_interval`) are tried first.

        The triangle filter needs all ``h + 1`` samples of an interval, the box only its two
        ends: where missing samples cost the triangle rows the box keeps, the box's search
        (from its own noise rule's interval) runs too and the lower estimated MSE of the two
        is taken (each at least its candidate's variance; on a tie the triangle). The box's
        candidates are then corrected only while their ``V`` is below the triangle's MSE.
        Complete data (no NaN in the poses, shapes or phase) lose no rows to either filter,
        and the rows are not counted.

        Returns the fit, its interval samples (pooled; ``.h`` and ``.kernel`` the chosen
        interval and filter), the window, the candidates' ``[h, window, MSE]`` (a list;
        ``[h, window, MSE, "box"]`` for the box's), the ``[h, window(, "box")]`` of the
        candidates whose correction was skipped (their table entry is ``V``, a lower bound of
        their MSE, and at least the chosen one's) and the one-sample offsets the bias
        correction models.
        """
        kernels = {VELOCITY_KERNEL: int(self.velocity_interval or h0)}
        if VELOCITY_KERNEL != "box" and _has_missing(traj):
            h_box = int(self.velocity_interval or velocity_interval_for(
                ratio, _samples_per_cycle(traj), "box"))
            if _usable_rows(traj, kernels[VELOCITY_KERNEL], VELOCITY_KERNEL) < _usable_rows(
                    traj, kernels[VELOCITY_KERNEL], "box"):
                kernels["box"] = h_box
        offsets = one_sample_offsets(traj, gamma_m)
        found, bound = {}, math.inf
        for k, h in kernels.items():
            # a later filter is taken only where its MSE is below the earlier ones'
            found[k] = self._search(traj, var, k, h, gamma_m, gamma_dot_m, opts, offsets, bound)
            if found[k].fit is not None:
                bound = min(bound, found[k].mse)
        fitted = {k: f for k, f in found.items() if f.fit is not None}
        if not fitted:  # none can be fitted: on_ill_conditioned decides (e.g. raises)
            f = found[VELOCITY_KERNEL]
            fit = noise_aware_regression(f.view, self._bins(f.view, f.window), gamma_m,
                                         gamma_dot_m, var, **opts)
            return fit, f.view, f.window, [], [], offsets
        kernel = min(fitted, key=lambda k: fitted[k].mse)
        best = fitted[kernel]

        def tagged(rows: list, k: str) -> list:
            return [row + ([] if k == VELOCITY_KERNEL else [k]) for row in rows]

        table = [row for k, f in found.items() for row in tagged(f.table, k)]
        skipped = [row for k, f in found.items() for row in tagged(f.skipped, k)]
        return best.fit, best.view, best.window, table, skipped, offsets

    def _search(self, traj: Trajectory, var: Tensor, kernel: str, h0: int, gamma_m: Tensor,
                gamma_dot_m: Tensor, opts: dict, offsets: OneSampleOffsets,
                bound: float = math.inf) -> _Search:
        """:meth:`_chosen_fit`'s search for one filter (:class:`_Search`). ``offsets``: the
        one-sample offsets the bias correction models (:func:`one_sample_offsets`).
        ``bound``: an MSE to beat (another filter's; a candidate whose ``V`` is not below it
        is not corrected, and none beating it gives no fit)."""
        d = traj.shape_dim
        longest = max(2, int(_samples_per_cycle(traj) * MAX_INTERVAL_CYCLES))
        # per candidate (h, window), in the order tried: the variance V of the uncorrected
        # fit (inf: it cannot be fitted) and the score (once corrected)
        views, fits, variances, scores = {}, {}, {}, {}

        def candidate(h: int, w: float | None) -> tuple[int, float]:
            if h not in views:
                views[h] = pooled_view(traj, h, kernel)
            if w is None:  # the narrowest the data allow
                w = auto_window(views[h].phase, self.n_bins, 1 + 2 * d + d * d,
                                 self.samples_per_regressor)
            key = (h, float(w))
            if key in variances:
                return key
            fit, bad = flagged_fit((views[h], self._bins(views[h], key[1]), gamma_m,
                                     gamma_dot_m, var), opts)
            if bool(bad):  # bins too sparse at this width: not a candidate
                variances[key] = scores[key] = math.inf
                return key
            variances[key] = float(fit.se_A.square().nansum())
            fits[key] = fit
            return key

        while True:
            least = candidate(h0, self.window)[1]  # the narrowest window
            widths = [least] if self.window else [max(least, w) for w in _CANDIDATE_WINDOWS]
            first = [candidate(h0, w) for w in widths]
            if any(k in fits for k in first) or h0 == 1 or self.velocity_interval:
                break
            # no width can be fitted at this interval (too few independent rows for the
            # overlapping filter, or rows lost to missing samples)
            h0 = _shorter_interval(h0)
        if not any(k in fits for k in first):
            return _Search(None, views[h0], h0, least, math.inf, [], [])
        intervals = [] if self.velocity_interval else sorted(
            {min(longest, max(1, round(h0 * f)), traj.n_samples - 1)
             for f in _CORRECTED_INTERVAL_MULTIPLES} - {h0})

        def corrected(key: tuple[int, float]) -> tuple[ConnectionFit, float]:
            view = views[key[0]]
            fit, added = bin_bias_correction(
                fits[key], traj, view, self._bins(view, key[1]), gamma_m, gamma_dot_m,
                pool=True, offsets=offsets, **opts)
            bias = float((fit.A - fits[key].A).square().nansum())
            return fit, variances[key] + float(added) + RESIDUAL_BIAS_FRACTION * bias

        # every pair of interval and width
        order = list(dict.fromkeys(first + [candidate(h, w) for h in intervals
                                            for w in widths]))
        best, done = _least_score([k for k in order if k in fits], variances, corrected,
                                  bound=bound, prune=not self._full_search)
        scores.update({k: score for k, (_, score) in done.items()})
        fit = None if best is None else done[best][0]
        # a candidate not corrected (branch and bound) enters the table with its V
        table = [[h, w, scores.get((h, w), v)] for (h, w), v in variances.items()
                 if math.isfinite(scores.get((h, w), v))]
        skipped = [[h, w] for (h, w) in fits if (h, w) not in scores]
        if best is None:  # no candidate beats the bound
            return _Search(None, views[h0], h0, least, math.inf, table, skipped)
        # against another filter's search (another reference) the estimate is taken at least
        # at the candidate's own variance: a squared bias below 0 is the reference's noise
        mse = max(scores[best], variances[best])
        return _Search(fit, views[best[0]], best[0], best[1], mse, table, skipped)

    def _bins(self, view: IntervalSamples, window: float) -> BinIndex:
        """The bins of pooled interval samples ``view`` at half-width ``window``."""
        return assign_bins(view.phase, self.n_bins, window=window, kernel=self.kernel)

    def _connection_fit(self, traj, pool, samples, gamma_m, gamma_dot_m, opts, bins_for):
        """The corrected fit, shrunk towards the smoothed one (:func:`blend_fits`), with
        ``∂Â/∂r`` tied (:meth:`_tied`) and, pooled, ``Â``'s sampling factor
        (``sampling_factor_A``) and, without detected noise, its bias allowance
        (``bias_allowance_A``); within :func:`predictions_only`, the blended fit alone."""
        fit, window, meta, chosen = self._corrected_fit(traj, pool, samples, gamma_m,
                                                        gamma_dot_m, opts, bins_for)
        full = not _PREDICTIONS_ONLY.get()
        # (unpooled elements got their joint covariance with their fits)
        joint = chosen.view is not None and not chosen.noise_free
        rerun = None
        if chosen.view is not None and full:
            fit, rerun = self._rerun_chosen(fit, traj, chosen, gamma_m, gamma_dot_m, opts,
                                            joint)
        if pool:  # (unpooled elements got theirs with their fits)
            fit = self._with_offset_gain(fit, (
                chosen.view, self._bins(chosen.view, chosen.windows), gamma_m, gamma_dot_m,
                chosen.noise_var), opts, pool)
        tube, _, _ = self._smoothed_fit(samples, gamma_m, gamma_dot_m, opts, bins_for)
        fit, weights = blend_fits(tube, fit)
        meta["corrected_weight"] = weights.tolist()
        if not full:
            meta["derivative"] = "direct (predictions only)"
            return dataclasses.replace(fit, cov_b_dA=None), window, meta
        # the direct estimate stays the coefficient the model predicts with (dA_fit)
        tied, meta["derivative"] = self._tied(fit, traj, chosen, gamma_m, gamma_dot_m, opts)
        fit = dataclasses.replace(tied, dA_direct=fit.dA, cov_b_dA=None)
        if rerun is not None and rerun.influence_A is not None:
            # scaled to the standard errors of the Â delivered
            fit = dataclasses.replace(fit, sampling_factor_A=sampling_factor(
                rerun.influence_A, fit.se_A))
        if chosen.view is not None and chosen.noise_free:
            bins = self._bins(chosen.view, chosen.windows)
            # without noise the rerun is the plain first-order fit both parts start from,
            # standard errors too where the rows' overlap does not inflate them (κ = 1)
            plain = rerun if chosen.view.h == 1 or chosen.view.kernel == "box" else None
            # the bias of the Â delivered: the bins' bias correction and the blend have moved
            # it from the plain fit
            tube, tube_var = offset_bias(chosen.view, bins, gamma_m, gamma_dot_m, first=plain,
                                         estimate=fit.A, **opts)
            step, step_var = interval_bias(traj, chosen.view, bins, self.n_bins, chosen.windows,
                                           self.kernel, gamma_m, gamma_dot_m, full=plain,
                                           **opts)
            # one allowance: the two parts summed, shrunk by how far they stand out of noise
            fit = dataclasses.replace(fit, bias_allowance_A=resolved_bias(
                torch.nan_to_num(tube) + torch.nan_to_num(step),
                torch.nan_to_num(tube_var) + torch.nan_to_num(step_var)))
        return fit, window, meta

    def _with_offset_gain(self, fit: ConnectionFit, args: tuple, opts: dict, pool: bool
                          ) -> ConnectionFit:
        """``fit`` (:func:`noise_aware_regression` of ``args``: samples, bins, cycle, noise)
        with its :func:`offset_gain` where ``ĉ, b̂`` will be re-estimated to a shrunk ``Â``
        (pooled)."""
        if not pool:
            return fit
        gain = offset_gain(fit, *args, delta_max=opts["delta_max"],
                           ridge_connection=opts["ridge_connection"])
        return dataclasses.replace(fit, offset_gain=gain)

    def _rerun_chosen(self, fit: ConnectionFit, traj: Trajectory, chosen: _Chosen,
                      gamma_m: Tensor, gamma_dot_m: Tensor, opts: dict, joint: bool
                      ) -> tuple[ConnectionFit, ConnectionFit]:
        """The chosen candidate's regression (a pooled corrected fit) run again for what the
        search did not compute (:func:`noise_aware_regression`): with ``joint``, ``fit`` gets
        ``cov_b_dA``, scaled from that regression's standard errors to ``fit``'s (which the
        bias correction of ``Â`` leaves as they are). Returns it and that regression, with
        ``sampling_factor`` holding each whole cycle's share of the error of ``Â``
        (``influence_A``, ``(M, 3, d, C)``)."""
        bins = self._bins(chosen.view, chosen.windows)
        # an interval's cycle is its first sample's; the trials' cycles follow each other
        cycles = cycle_index(unwrap(traj.phase)[..., :-chosen.view.h], True, origin="first",
                             missing="first", offset="cumulative")
        raw = noise_aware_regression(
            chosen.view, bins, gamma_m, gamma_dot_m, chosen.noise_var,
            joint_covariance=joint, cycles=cycles, **opts)
        if joint:
            fit = dataclasses.replace(fit, cov_b_dA=rescaled_covariance(
                raw.cov_b_dA, (raw.se_b, raw.se_dA), (fit.se_b, fit.se_dA)))
        return fit, raw

    def _tied(self, fit: ConnectionFit, traj: Trajectory, chosen: _Chosen, gamma_m: Tensor,
              gamma_dot_m: Tensor, opts: dict) -> tuple[ConnectionFit, str]:
        """``fit`` with ``∂Â/∂r`` tied (:func:`tie_connection_derivative`, each element at its
        own window) and, for a pooled bias-corrected fit of data without detected measurement
        noise, corrected for the bins' bias (:func:`derivative_bias_correction`). Returns the
        fit and how (for ``meta["derivative"]``).

        Not under noise: the correction's regression of the model's body velocity runs on
        the recorded samples without the errors-in-variables fix (the model target carries
        the regressors' own noise, unlike the recorded target), so its ``∂Â/∂r`` is
        attenuated and the correction carries that into the estimate. Under noise the same
        bias is instead allowed for in the tie's weights and bands
        (:func:`derivative_bias_allowance`)."""
        if chosen.view is not None:
            bins = assign_bins(chosen.view.phase, self.n_bins, window=chosen.windows,
                               kernel=self.kernel)
            if chosen.noise_free:
                run, how = derivative_bias_correction, "tied, bias-corrected"
            else:
                run, how = derivative_bias_allowance, "tied, bias allowed for"
            tied, _ = run(fit, traj, chosen.view, bins, gamma_m, gamma_dot_m,
                          order=self.fourier_order, pool=True, offsets=chosen.offsets, **opts)
            return tied, how
        tied = tie_connection_derivative(fit, gamma_m, gamma_dot_m, self.fourier_order,
                                         window=chosen.windows, kernel=self.kernel)
        return tied, "tied"

    def _a_series(self, centres: Tensor, fit: ConnectionFit, window, pool: bool):
        """``Â``'s series, each harmonic of each row shrunk by how far it stands out of the
        bins' noise when pooled, the fit with ``ĉ, b̂`` re-estimated in each bin with ``Â``
        held at the shrunk series (moved by the shrink's change at the bin's centre,
        :func:`offsets_at`), and the meta entries that record it."""
        series, fit, meta = super()._a_series(centres, fit, window, pool)
        if not pool:
            return series, fit, meta
        shrunk, factor = shrink_series(series, fit.se_A, window, self.kernel)
        meta = {"A_harmonic_factors": (torch.round(factor * 1e4) / 1e4).tolist()}  # (..., K + 1, 3)
        if fit.offset_gain is not None:  # (_with_offset_gain)
            c, b = offsets_at(fit, shrunk(centres) - series(centres))  # (..., M, 3, d)
            fit = dataclasses.replace(fit, c=c, b=b)
            meta["offsets_refit"] = True
        return shrunk, fit, meta

    def _window(self, phase: Tensor, d: int, ratio: float) -> float:
        """Bin half-width: the data-size rule, widened with the noise."""
        return max(auto_window(phase, self.n_bins, 1 + 2 * d + d * d,
                                self.samples_per_regressor),
                   min(1 + _WINDOW_PER_NOISE_RATIO * ratio, _MAX_NOISE_WINDOW))

    def element_windows(self, phase: Tensor, d: int, ratio: Tensor) -> Tensor:
        """Bin half-widths ``(n,)`` of unpooled elements ``phase (n, N)`` with noise ratios
        ``ratio (n,)``: ``window``, or each element's :meth:`_window` (from its own samples
        and noise only), rounded to half bin spacings so that few distinct windows (groups of
        elements regressed together) remain."""
        if self.window:
            widths = torch.full(phase.shape[:1], float(self.window), dtype=torch.float64,
                                device=phase.device)
        else:
            size = auto_windows(phase, self.n_bins, 1 + 2 * d + d * d,
                                 self.samples_per_regressor)
            noise = (1 + _WINDOW_PER_NOISE_RATIO * ratio.to(size)).clamp_max(_MAX_NOISE_WINDOW)
            widths = torch.maximum(size, noise)
        return torch.round(widths * 2) / 2

    def noise_setup(self, traj: Trajectory, pool: bool, gamma_m: Tensor | None = None):
        """Joint-angle noise variance ``(..., d)``, noise ratio and velocity interval ``(...)``
        (``(d,)`` and scalars when ``pool``: the trials share one rig).

        ``gamma_m``: the limit cycle at the bin centres, ``(..., M, d)`` (``(M, d)`` when
        ``pool``); with ``noise_floor="low_rate"`` the noise fit's process floor follows the
        gait's harmonics where they reach the top band (:func:`phase_noise_floor`); with any
        floor it correlates the joints' estimates (their shared phase noise,
        :attr:`NoiseEstimate.correlation`) in the test of their mean for noise. None: a flat
        floor, joints taken as independent.

        Unpooled, each batch element's are its own: its samples per cycle (which set the
        longest interval and place the gait's harmonics) come from its own phase rate and its
        noise band from its own data (:func:`estimate_noise`), so a trial's fit does not depend
        on the trials it shares a batch with (a sweep's cells)."""
        per_trial = 2 * math.pi / (phase_rate(traj.phase, traj.dt) * traj.dt)  # (...)
        per_cycle = per_trial.nanmean() if pool else per_trial
        band = None if self.noise_band_low is None else (self.noise_band_low, 0.5)
        cycle = cycle_series(gamma_m) if gamma_m is not None else None
        # (..., d), each element on its own; the cycle also correlates the joints' estimates
        # (their shared phase noise) for the joint test below, with either floor
        # the normal projection needs the cycle; without one the floor is flat
        floor = "flat" if cycle is None and self.noise_floor == "normal" else self.noise_floor
        noise = estimate_noise(traj.r, band=band, cycle=cycle, floor=floor,
                               samples_per_cycle=None if cycle is None else per_trial,
                               phase=traj.phase if floor == "normal" else None)
        n_pool = traj.phase.ndim - 1 if pool else 0
        # one level for all joints of a trial (or of the pooled trials): they share the rig
        var = noise.pooled_variance(n_pool, channels=True, min_z=_NOISE_MIN_Z)
        q2 = noise.process.square()
        q2 = q2.mean(tuple(range(n_pool))) if n_pool else q2
        ratio = noise_ratio(var, q2)
        if self.velocity_interval:
            h = torch.full(ratio.shape, self.velocity_interval, dtype=torch.long, device=ratio.device)
        else:
            h = velocity_interval_for(ratio, per_cycle)
        return var, ratio, h


def _usable_rows(traj: Trajectory, h: int, kernel: str) -> int:
    """Interval samples of ``traj`` (all trials) with a finite target and regressors."""
    iv = interval_samples(traj.pose, traj.r, traj.phase, traj.dt, h, kernel)
    ok = iv.xi.isfinite().all(-1) & iv.r_dot.isfinite().all(-1) & iv.r.isfinite().all(-1)
    return int((ok & iv.phase.isfinite()).sum())


def _has_missing(traj: Trajectory) -> bool:
    """Whether ``traj``'s poses, shapes or phase miss a sample (NaN). Without, every interval
    of every filter has a finite target and regressors (:func:`_usable_rows` is the same for
    all)."""
    return not all(bool(x.isfinite().all()) for x in (traj.pose, traj.r, traj.phase))


def _shorter_interval(h: int) -> int:
    """The interval tried when the bins cannot be fitted at ``h > 1``: ``h / 1.5`` rounded,
    shorter by at least one sample (16, 11, 7, 5, 3, 2, 1)."""
    return max(1, min(h - 1, round(h / _FALLBACK_INTERVAL_DIVISOR)))


def _samples_per_cycle(traj: Trajectory) -> float:
    """Mean samples per cycle of a phased trajectory."""
    return 2 * math.pi / float(phase_rate(traj.phase, traj.dt).nanmean() * traj.dt)
