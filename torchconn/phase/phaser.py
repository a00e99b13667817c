"""Phase estimation for noisy oscillator data: the Phaser algorithm, batched.

Phaser (Revzen & Guckenheimer 2008, Phys. Rev. E 78, 051907) turns a multichannel
record of an oscillator into a phase that advances uniformly in time on average:

1. each channel is centred and scaled, and its *protophase* is the angle of its analytic
   signal (FFT-based Hilbert transform along time);
2. each protophase ``θ`` is corrected to ``ψ = θ + P(θ)`` so that it advances uniformly:
   samples taken uniformly in time have protophase density ``ρ(θ) ∝ 1/θ̇``, and a phase
   with ``ψ̇`` constant has ``dψ/dθ = 2π ρ(θ)``; with ``S_k = <e^{-ikθ}>`` averaged over
   the record this integrates to ``P(θ) = Σ_{k≤K} 2 Re(S_k e^{ikθ} / (ik))``
   (:func:`correction_series`);
   The order ``K`` is fixed, or chosen per channel by cross-validation over blocks of whole
   cycles (:func:`correction_order`);
3. the corrected channel phases, which differ by constant offsets, are combined: the leading
   eigenvector of the Hermitian ``C x C`` coherence matrix of their unit phasors ``e^{iψ_c}``
   aligns them, and each is weighed by its phase signal-to-noise ratio (the inverse variance of
   its phase noise, from the rank-one structure ``|R_ab| = ρ_a ρ_b`` of the coherences) or,
   as in torchconn 0.1, by the eigenvector itself (which ignores how noisy a channel is).
   Channels winding at a multiple of the others' rate (harmonics) are left out;
4. the combined phase is corrected once more as in 2;
5. a Poincaré-section offset fixes phase 0 (see :func:`estimate_phase`).

Two refinements over a plain implementation matter at the 1e-3 rad level. Averages (channel
means, the ``S_k``) are taken over a whole number of cycles, since a trailing partial cycle
biases them by ``O(1/cycles)``. And because an FFT Hilbert transform treats the record as
periodic, which makes it wrong by ~0.1-1 rad within a cycle of either end, a first pass
measures the period and the second pass appends a periodic continuation of the cycle that
leads from the record's end back into its start, so the transform sees no seam.
Step 3 is a variant of Phaser's PCA step (which projects ``(cos ψ_c, sin ψ_c)`` on two real
principal components); it needs no choice of sign or rotation direction.
"""

from __future__ import annotations

import abc
import copy
import math
import warnings
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from .. import _checks, _linalg
from .._options import Options, option
from ..cycles import block_masks, cycle_blocks, whole_cycle_weights
from ..io.preflight import CYCLE_RULES, MIN_PERIODICITY, periodicity
from .fourier import FourierSeries, fit_fourier, fourier_design
from .smoothing import unwrap

__all__ = [
    "PhaseEstimator",
    "Phaser",
    "PhaseModel",
    "analytic_signal",
    "protophase",
    "correction_series",
    "correction_order",
    "held_out_order",
    "highest_order",
    "estimate_phase",
    "hilbert_phase_pc1",
    "circular_rms",
    "PhaseAmbiguityWarning",
]

# channels whose standard deviation is below this fraction of their magnitude are constant
_CONST_TOL = 1e-10


def analytic_signal(x: Tensor, dim: int = -1) -> Tensor:
    """Analytic signal ``x + i H[x]`` along ``dim`` via the FFT (complex, same shape)."""
    n = x.shape[dim]
    h = torch.zeros(n, dtype=x.dtype, device=x.device)
    h[0] = 1.0
    h[1 : (n + 1) // 2] = 2.0
    if n % 2 == 0:
        h[n // 2] = 1.0
    shape = [1] * x.ndim
    shape[dim] = n
    return torch.fft.ifft(torch.fft.fft(x, dim=dim) * h.reshape(shape), dim=dim)


def protophase(x: Tensor) -> Tensor:
    """Wrapped Hilbert protophase of every channel of ``x (..., T, C)`` -> ``(..., T, C)``."""
    z = x - x.mean(-2, keepdim=True)
    return torch.angle(analytic_signal(z, dim=-2))


def correction_series(theta: Tensor, order: int, weights: Tensor | None = None) -> FourierSeries:
    """Phaser's series correction ``P`` with ``θ + P(θ)`` advancing uniformly on average.

    Args:
        theta: protophases ``(..., T)`` (wrapped or not) of samples taken uniformly in time.
        order: number of harmonics ``K`` kept (0 gives no correction).
        weights: optional ``(..., T)`` sample weights for the averages ``S_k = <e^{-ikθ}>``.
            Averaging over a whole number of cycles (see
            :func:`~torchconn.cycles.whole_cycle_weights`) avoids the ``O(1 / cycles)`` bias a
            trailing partial cycle puts into every ``S_k``.

    Returns:
        scalar :class:`~torchconn.phase.fourier.FourierSeries` of order ``K``, batch ``(...)``.
    """
    if weights is None:
        weights = torch.ones_like(theta)
    w = weights / weights.sum(-1, keepdim=True)
    # [1, c_1, s_1, ...] = <cos kθ>, <sin kθ>: the design matrix averaged over the record
    cs = (w[..., None, :] @ fourier_design(theta, order))[..., 0, :]
    # dψ/dθ - 1 = 2 Σ (c_k cos kθ + s_k sin kθ), a zero-mean series; P is its antiderivative
    rate = torch.cat([torch.zeros_like(cs[..., :1]), 2 * cs[..., 1:]], -1)
    return FourierSeries(rate, 0).integral()


def correction_order(theta: Tensor, weights: Tensor, max_order: int | Tensor,
                     folds: int = 5) -> Tensor:
    """Correction order chosen by cross-validation over blocks of whole cycles.

    The correction of order ``K`` is ``P_K(θ) = Σ_{k≤K} 2 Re(S_k e^{ikθ} / (ik))`` with
    ``S_k = <e^{-ikθ}>`` (:func:`correction_series`), so its mean square error against the
    correction of the underlying oscillation is ``Σ_{k≤K} 2 |Ŝ_k − S_k|² / k² + Σ_{k>K} 2 |S_k|² / k²``:
    :func:`held_out_order` of the values 1 with harmonic weights ``2 / k²``.

    Args:
        theta: protophases ``(..., T)`` (wrapped or not) of samples taken uniformly in time.
        weights: ``(..., T)`` whole-cycle weights (:func:`~torchconn.cycles.whole_cycle_weights`
            of the unwrapped protophase); blocks are formed from the cycles they cover.
        max_order: largest order considered (``>= 1``): an integer, or ``(...)`` integers, one
            per batch element.
        folds: number of blocks; a record with fewer whole cycles has one cycle per block
            (``>= 2`` cycles needed to hold any out).

    Returns:
        ``(...)`` int64 orders in ``[1, max_order]``.
    """
    limit = torch.as_tensor(max_order, device=theta.device)
    if limit.is_floating_point() or bool((limit < 1).any()):
        raise ValueError(f"correction_order: max_order must be integers >= 1, got {max_order}")
    k = torch.arange(1, int(limit.max()) + 1, dtype=theta.dtype, device=theta.device)
    return held_out_order(unwrap(theta), weights, None, limit, folds=folds,
                          harmonic_weights=2 / k.square(), lowest=1)


def held_out_order(theta: Tensor, weights: Tensor, values: Tensor | None,
                   max_order: int | Tensor, *, folds: int = 5,
                   harmonic_weights: Tensor | None = None, lowest: int = 0,
                   n_pooled: int = 0) -> Tensor:
    """The order of a Fourier series in phase of ``values`` with the least held-out error over
    blocks of whole cycles.

    The series of order ``K`` has the harmonics ``S_k = <v e^{-ikθ}>`` (weighted means over the
    samples), so its mean square error against the underlying periodic function is
    ``Σ_{k≤K} c_k |Ŝ_k − S_k|² + Σ_{k>K} c_k |S_k|²`` (``c_k`` the harmonic weights). The
    record's whole cycles are split into ``folds`` contiguous blocks; for each block the ``S_k``
    of the other blocks (``Ŝ_k``) are scored against the block's own (``S'_k``, an unbiased and
    independent estimate of ``S_k``): ``|Ŝ_k|² − 2 Re(Ŝ_k conj S'_k)`` estimates
    ``|Ŝ_k − S_k|² − |S_k|²`` without bias, so the block-weighted sum over ``k ≤ K`` is the
    held-out mean square error of the order-``K`` series up to a constant. The order with the
    smallest is chosen (the lowest on ties): harmonics the data resolve are kept, harmonics
    that only fit the noise are not. Deterministic (no random folds); each batch element on its
    own.

    Args:
        theta: unwrapped phases ``(..., T)`` of samples taken uniformly in time.
        weights: ``(..., T)`` whole-cycle weights
            (:func:`~torchconn.cycles.whole_cycle_weights`); 0 drops a sample (e.g. NaN values).
        values: ``(..., T, C)`` channels whose errors add up, or None for the values 1.
        max_order: largest order considered: an integer or ``(...)`` integers.
        folds: number of blocks (a record with fewer whole cycles has one cycle per block).
        harmonic_weights: ``(K,)`` weights ``c_k`` of harmonics ``lowest … max_order`` (None: 1).
        lowest: the lowest harmonic scored (0 scores the mean as well; the lowest order
            returned).
        n_pooled: the first ``n_pooled`` batch dims are one recording (trials of one model):
            their held-out errors add up and they get one order.

    Returns:
        ``(...)`` int64 orders in ``[lowest, max_order]`` (without the pooled dims).
    """
    limit = torch.as_tensor(max_order, device=theta.device)
    blocks = block_masks(cycle_blocks(theta, folds, span="centred"), folds)
    wb = weights[..., :, None] * blocks.to(weights)  # (..., T, F)
    k = torch.arange(lowest, int(limit.max()) + 1, dtype=theta.dtype, device=theta.device)
    e = torch.polar(torch.ones_like(theta[..., None] * k), -theta[..., None] * k)  # (..., T, K)
    if values is None:
        sums = (wb.mT.to(e.dtype) @ e).unsqueeze(-1)  # (..., F, K, 1): Σ_t w e^{-ikθ} per block
    else:
        v = torch.where(weights[..., None] > 0, values, 0.0)
        sums = torch.einsum("...tf,...tk,...tc->...fkc", wb.to(e.dtype), e, v.to(e.dtype))
    count = wb.sum(-2)[..., None, None]  # (..., F, 1, 1)
    tiny = torch.finfo(count.dtype).tiny
    held = sums / count.clamp_min(tiny)
    rest = ((sums.sum(-3, keepdim=True) - sums)
            / (count.sum(-3, keepdim=True) - count).clamp_min(tiny))
    gain = (rest.abs().square() - 2 * (rest * held.conj()).real).sum(-1)  # (..., F, K)
    if harmonic_weights is not None:
        gain = gain * harmonic_weights
    score = (count[..., 0] * gain.cumsum(-1)).sum(-2)  # (..., K)
    if n_pooled:
        score = score.sum(tuple(range(n_pooled)))
    score = torch.where(k <= limit[..., None], score, torch.full_like(score, math.inf))
    return score.argmin(-1) + lowest


def circular_rms(estimate: Tensor, truth: Tensor, dim: int = -1) -> Tensor:
    """RMS of the wrapped difference ``estimate - truth`` after removing its circular mean.

    The natural error of a phase estimate, which is only defined up to a constant offset.
    Shapes broadcast; the mean is taken over ``dim``.
    """
    d = estimate - truth
    off = torch.angle(torch.exp(1j * d).mean(dim, keepdim=True))
    w = torch.remainder(d - off + math.pi, 2 * math.pi) - math.pi
    return w.pow(2).mean(dim).sqrt()


def hilbert_phase_pc1(x: Tensor) -> Tensor:
    """Naive baseline: unwrapped Hilbert phase of the first principal component.

    Args:
        x: ``(..., T, C)``.

    Returns:
        ``(..., T)`` unwrapped phase (no correction, no edge treatment, arbitrary offset).
    """
    _check_x(x, "hilbert_phase_pc1")
    xc = x - x.mean(-2, keepdim=True)
    _, vec = _linalg.eigh(xc.mT @ xc, "the shape channels' covariance")
    pc1 = (xc @ vec[..., -1:])[..., 0]
    return unwrap(torch.angle(analytic_signal(pc1, dim=-1)))


@dataclass(frozen=True, eq=False)
class PhaseModel:
    """What Phaser learns from a recording, batched over ``...``; reusable on new recordings.

    Attributes:
        mean: ``(..., C)`` channel centres (averaged over whole cycles).
        scale: ``(..., C)`` channel standard deviations.
        channel_correction: series correction of each channel's protophase, batch ``(..., C)``:
            ``ψ_c = θ_c + P_c(θ_c)`` (step 2).
        weights: ``(..., C)`` complex combination of the channels' phasors ``e^{iψ_c}`` (step 3):
            its angles align the channels (the leading eigenvector of their coherence matrix),
            its magnitudes weigh them (summing to 1; 0 for a channel left out).
        correction: series correction of the combined phase, batch ``(...)`` (step 4).
        offset: ``(...)`` Poincaré-section offset subtracted last: where phase 0 is (step 5).
        coherence: ``(..., C)`` each channel's estimated phase coherence ``ρ_c = |<e^{iε_c}>|``
            (1: no phase noise ``ε_c``; 0 for a channel left out), from which ``weighting="snr"``
            weighs it.
        channel_order: ``(..., C)`` int64 order of each channel's correction (the series are
            stored at the largest order, with the harmonics above it zero).
        order: ``(...)`` int64 order of the combined phase's correction.
    """

    mean: Tensor
    scale: Tensor
    channel_correction: FourierSeries
    weights: Tensor
    correction: FourierSeries
    offset: Tensor
    coherence: Tensor
    channel_order: Tensor
    order: Tensor

    @property
    def batch_shape(self) -> torch.Size:
        return self.offset.shape


# trailing (non-batch) dims of each PhaseModel field's tensor
_MODEL_TRAILING = {"mean": 1, "scale": 1, "channel_correction": 2, "weights": 1, "correction": 1,
                   "offset": 0, "coherence": 1, "channel_order": 1, "order": 0}


def _map_model(model: PhaseModel, fn) -> PhaseModel:
    """Apply ``fn(tensor, n_trailing)`` to every tensor of ``model`` (series: their coeffs)."""
    out = {}
    for name, trailing in _MODEL_TRAILING.items():
        value = getattr(model, name)
        if isinstance(value, FourierSeries):
            out[name] = FourierSeries(fn(value.coeffs, trailing), value.value_ndim)
        else:
            out[name] = fn(value, trailing)
    return PhaseModel(**out)


class PhaseEstimator(Options, abc.ABC):
    """Base of the estimator's phase stage, in scikit-learn manners but immutable.

    ``fitted = estimator.fit(x)`` returns a fitted *copy* (the option object itself stays
    unfitted, so it can be shared and cloned) carrying ``model_`` (what was learned) and
    ``phase_`` (the phase of the training record, ``(..., T)``); ``fitted.transform(x_new)``
    reuses ``model_`` on new recordings of the same system.
    """

    @abc.abstractmethod
    def fit(self, x: Tensor) -> PhaseEstimator:
        """Learn a phase model from ``x (..., T, C)``; returns a fitted copy."""

    @abc.abstractmethod
    def transform(self, x: Tensor) -> Tensor:
        """Phase ``(..., T)`` of ``x (..., T, C)`` under the fitted model."""

    def _fitted_copy(self, **attributes) -> PhaseEstimator:
        fitted = copy.copy(self)
        for name, value in attributes.items():
            object.__setattr__(fitted, name, value)  # fitted state: not an option field
        return fitted

    def _check_fitted(self) -> None:
        if not hasattr(self, "model_"):
            raise RuntimeError(
                f"this {type(self).__name__} is not fitted: use fitted = phaser.fit(x) and then "
                "fitted.transform(x_new) (fit returns a fitted copy; the options stay unfitted)"
            )


@dataclass(frozen=True, kw_only=True)
class Phaser(PhaseEstimator):
    """Revzen's Phaser (this module's algorithm) as the estimator's phase stage.

    Attributes:
        order: harmonics in each series correction: ``"auto"`` chooses them per channel and
            trial by cross-validation over blocks of whole cycles (:func:`correction_order`,
            at most ``max_order``); an integer fixes them (2-4 robust; high orders fit the noise).
        max_order: the largest order ``"auto"`` considers (also capped at
            :func:`highest_order` of the samples per cycle, above which an explicit order is
            refused).
        min_cycles: fewest cycles a trial must cover (default: the ``fit`` rule of
            :data:`torchconn.io.preflight.CYCLE_RULES`).
        section_channel: the channel whose upward crossing of its mean defines phase 0.

    Each record is extended by its periodic continuation before the Hilbert transform, and the
    channels' corrected phases are combined with weights by their phase signal-to-noise ratio
    (:func:`estimate_phase`'s ``periodic_padding=True``, ``weighting="snr"``). Against
    torchconn 0.1's phase (order 3, ``"coherence"`` weights) on simulated 3-, 5- and 9-link
    swimmers at five noise levels and on synthetic cases (``benchmarks/phase_accuracy.py``,
    seeds not used to set them) the defaults were no worse on any, 26 % better on the 9-link
    reference gait, 71 % with one good channel among noisy ones.

    ``fit(x)`` and ``transform(x)`` take ``x (..., T, C)`` (e.g. smoothed shapes). NaN rows
    before a trial's first or after its last finite row are padding (trials of unequal length
    on one grid): each trial is then phased over its own span, NaN outside it. NaN inside a
    span is an error (smooth drop-outs first).
    """

    order: int | Literal["auto"] = option("auto", ge=0)
    max_order: int = option(12, ge=1)
    min_cycles: float = option(CYCLE_RULES["fit"].per_trial, gt=0)
    section_channel: int = 0

    def fit(self, x: Tensor) -> Phaser:
        """Phaser fitted to ``x (..., T, C)``: a copy with ``model_`` (:class:`PhaseModel`,
        batch ``(...)``) and ``phase_`` (``(..., T)``, equal to :func:`estimate_phase`)."""
        _check_x(x, "Phaser.fit")
        if not x.is_floating_point():
            x = x.to(torch.get_default_dtype())
        spans = _spans(x)
        if spans is None:
            model, phase = _fit(x, self, "Phaser.fit")
        else:
            # unequal lengths: one fit per trial on its own span, models stacked
            flat = x.reshape(-1, *x.shape[-2:])
            phase = torch.full(flat.shape[:-1], float("nan"), dtype=x.dtype, device=x.device)
            models = []
            for k, (lo, hi) in enumerate(spans):
                m, phase[k, lo:hi] = _fit(flat[k, lo:hi], self, "Phaser.fit")
                models.append(m)
            batch = x.shape[:-2]
            model = PhaseModel(**{
                name: _stack([getattr(m, name) for m in models], batch)
                for name in _MODEL_TRAILING
            })
            phase = phase.reshape(x.shape[:-1])
        return self._fitted_copy(model_=model, phase_=phase)

    def transform(self, x: Tensor) -> Tensor:
        """Phase ``(..., T)`` of new recordings ``x (..., T, C)`` under the fitted model.

        The channels are centred, scaled, corrected, combined and offset exactly as in the fit
        (same phase origin); only the Hilbert transform and its periodic padding come from the
        new data. ``x``'s batch dims broadcast against the model's. On the training record it
        reproduces ``phase_``.
        """
        self._check_fitted()
        _check_x(x, "Phaser.transform")
        if not x.is_floating_point():
            x = x.to(torch.get_default_dtype())
        model = self.model_
        if _spans(x) is None:
            return _transform(model, x, self, "Phaser.transform")
        batch = _checks.broadcast_shapes(x.shape[:-2], model.batch_shape)
        flat = x.expand(batch + x.shape[-2:]).reshape(-1, *x.shape[-2:])
        per = _map_model(model, lambda t, n: t.expand(batch + t.shape[t.ndim - n:])
                         .reshape((-1,) + t.shape[t.ndim - n:]))
        phase = torch.full(flat.shape[:-1], float("nan"), dtype=x.dtype, device=x.device)
        for k, (lo, hi) in enumerate(_spans(flat)):
            one = _map_model(per, lambda t, n, k=k: t[k])
            phase[k, lo:hi] = _transform(one, flat[k, lo:hi], self, "Phaser.transform")
        return phase.reshape(batch + x.shape[-2:-1])


def _stack(values: list, batch: torch.Size):
    """Stack per-trial (unbatched) tensors or series into batch ``batch``; series of different
    orders (each trial's own) are zero-padded to the highest."""
    if isinstance(values[0], FourierSeries):
        order = max(v.order for v in values)
        c = torch.stack([v.padded(order).coeffs for v in values])
        return FourierSeries(c.reshape(batch + c.shape[1:]), values[0].value_ndim)
    t = torch.stack(values)
    return t.reshape(batch + t.shape[1:])


def _spans(x: Tensor) -> list[tuple[int, int]] | None:
    """None when every row of ``x (..., T, C)`` is finite; else each batch element's
    ``(first, last + 1)`` finite row, batch flattened (padding of unequal-length trials)."""
    rows = torch.isfinite(x).all(-1)  # (..., T)
    if bool(rows.all()):
        return None
    flat = rows.reshape(-1, rows.shape[-1])
    spans = []
    for k in range(flat.shape[0]):
        idx = torch.nonzero(flat[k]).flatten()
        if idx.numel() == 0:
            raise ValueError(
                f"Phaser: batch element {k} (flattened) of x has no row without NaN; smooth "
                "drop-outs first (torchconn.phase.smoothing.rts_smooth predicts through them)"
            )
        spans.append((int(idx[0]), int(idx[-1]) + 1))
    return spans


def estimate_phase(
    x: Tensor,
    *,
    order: int | Literal["auto"] = "auto",
    max_order: int = 12,
    min_cycles: float = 3.0,
    section_channel: int = 0,
    periodic_padding: bool = True,
    weighting: Literal["snr", "coherence"] = "snr",
) -> Tensor:
    """Phaser phase estimate of a multichannel oscillator record.

    Args:
        x: ``(..., T, C)`` samples, uniform in time, ``C >= 1`` channels (e.g. shapes ``r``),
            no NaNs (smooth/fill drop-outs first, e.g. with :func:`torchconn.phase.smoothing.rts_smooth`).
        order: harmonics in each series correction. 2-4 is robust; high orders fit the noise
            in the protophase (see tests). ``"auto"`` chooses them from the data (see
            :class:`Phaser`), at most ``max_order``.
        max_order: the largest order ``"auto"`` considers.
        min_cycles: fewest cycles accepted; fewer make the correction unreliable.
        section_channel: channel that defines phase 0 (below).
        periodic_padding: extend the record by its periodic continuation before the Hilbert
            transform (reduces end effects); False gives the plain FFT transform.
        weighting: how channels are weighted when combined, ``"snr"`` or ``"coherence"`` (see
            :class:`Phaser`).

    Phase 0 (the Poincaré section): the offset is chosen so that the first-harmonic component
    of channel ``section_channel`` is ``A sin(φ)`` with ``A > 0``, i.e. it crosses its mean
    upwards at ``φ = 0 (mod 2π)``. For a near-sinusoidal channel this is where the centred
    signal crosses zero upwards, and it is the same place on the cycle in every trial.

    :class:`Phaser` does the same as an estimator stage whose fitted model can be reused on
    new recordings.

    Returns:
        ``(..., T)`` unwrapped phase in radians, increasing on average by 2π per cycle.

    Raises:
        ValueError: wrong shape; NaN anywhere (a channel that is all NaN is named); a constant
            channel (named); fewer than ``min_cycles`` cycles; a section channel without a
            first harmonic.
    """
    _check_x(x, "estimate_phase")
    if order != "auto":
        order = _checks.integer(order, "order", fn="estimate_phase")
    if not x.is_floating_point():
        x = x.to(torch.get_default_dtype())
    if weighting not in ("snr", "coherence"):
        raise ValueError(f"estimate_phase: weighting must be 'snr' or 'coherence', got "
                         f"{weighting!r}")
    if not isinstance(periodic_padding, bool):
        raise TypeError(f"estimate_phase: periodic_padding must be True or False, got "
                        f"{periodic_padding!r}")
    options = Phaser(order=order, max_order=max_order, min_cycles=min_cycles,
                     section_channel=section_channel)
    return _fit(x, options, "estimate_phase", padding=periodic_padding,
                weighting=weighting)[1]


def highest_order(samples_per_cycle: Tensor | float) -> Tensor:
    """The highest correction order a record sampled ``samples_per_cycle`` times per cycle
    resolves: the largest ``K`` whose ``2K + 1`` harmonic coefficients fit in one cycle's
    samples (``2K + 1 <= samples_per_cycle``; ``(...)`` int64, 0 below 3 samples per cycle).
    An explicit ``order`` above it is refused and ``"auto"`` considers none above it, both on
    the samples per cycle of the lowest-order pass (:func:`_first_pass`)."""
    per_cycle = torch.as_tensor(samples_per_cycle)
    return torch.floor((per_cycle - 1) / 2).clamp_min(0).long()


def _first_pass(x: Tensor, o, fn: str, weighting: str = "snr") -> tuple[Tensor, Tensor]:
    """Pass 1 on the plainly centred record: the phase ``(..., T)`` at ``o.order`` (the lowest,
    1, for ``"auto"``) that measures the period, and the samples per cycle ``(...)`` counted
    at order 1 (checked against ``min_cycles`` and the order, :func:`highest_order`)."""
    C = x.shape[-1]
    if not -C <= o.section_channel < C:
        raise ValueError(
            f"{fn}: section_channel={o.section_channel} is out of range for C={C} channels"
        )
    _check_values(x, fn)
    z = (x - x.mean(-2, keepdim=True)) / x.std(-2, keepdim=True)
    with warnings.catch_warnings():
        # this pass only counts cycles: the fit's own pass warns of the channels it leaves out
        # (the user saw each warning twice, with different ratios), and a transform was warned
        # of them by its fit
        warnings.simplefilter("ignore", PhaseAmbiguityWarning)
        # the cycles are counted at the lowest order, whatever the order asked for: the count
        # that decides whether an order is too high is not made with that order
        counted = _phaser(z, 1, None, weighting)[1]
        phase = counted if o.order in ("auto", 1) else _phaser(z, o.order, None, weighting)[1]
    span = counted[..., -1] - counted[..., 0]
    cycles = span / (2 * math.pi)
    if bool((cycles < o.min_cycles).any()):
        where = torch.nonzero(cycles < o.min_cycles)[0].tolist()
        advice = ("the phase correction needs several cycles -- record longer trials"
                  if fn != "Phaser.transform" else
                  "the Hilbert transform of so short a record is unreliable (RMS 0.18 rad at 2 "
                  "cycles against 0.08 at 3: benchmarks/real_recordings.py --phase-length); to "
                  "phase the later cycles of a recording, transform the whole recording and "
                  "keep their part (0.09 rad at any length): transform(r)[..., start:], then "
                  "score(later, phase=...)")
        raise ValueError(
            f"{fn}: x covers only about {float(cycles.min()):.1f} cycles (batch index "
            f"{tuple(where)}), fewer than min_cycles={o.min_cycles}; {advice}"
        )
    per_cycle = (x.shape[-2] - 1) / cycles
    lowest = 1 if o.order == "auto" else o.order
    if bool((highest_order(per_cycle) < lowest).any()):
        fewest = float(per_cycle.min())
        if o.order == "auto":
            raise ValueError(
                f"{fn}: x has only ~{fewest:.1f} samples per cycle; the phase needs at least 3 "
                "(the correction's lowest order, 1, has 3 coefficients per cycle): record at a "
                "higher frame rate"
            )
        raise ValueError(
            f"{fn}: order={o.order} is too high for ~{fewest:.0f} samples per cycle (order K "
            f"has 2K + 1 coefficients per cycle and needs as many samples; at most order "
            f"{int(highest_order(per_cycle).min())} here); use a small order such as 3, or "
            "order='auto'"
        )
    return phase, per_cycle


def _order(o, per_cycle: Tensor):
    """The order argument of :func:`_phaser`: ``o.order``, or for ``"auto"`` the largest order
    considered in each batch element (``(...)``): ``o.max_order`` capped at the
    :func:`highest_order` of the element's samples per cycle ``per_cycle (...)``."""
    if o.order != "auto":
        return o.order
    return ("auto", highest_order(per_cycle).clamp(max=o.max_order))


def _fit(x: Tensor, o, fn: str, *, padding: bool = True, weighting: str = "snr"
         ) -> tuple[PhaseModel, Tensor]:
    """The whole algorithm on ``x (..., T, C)`` (no NaN): the model and the phase ``(..., T)``;
    ``padding``, ``weighting``: :func:`estimate_phase`'s ``periodic_padding``, ``weighting``."""
    # pass 1 counts cycles and finds the period; pass 2 re-centres each channel on a whole
    # number of cycles (a partial cycle biases the mean by O(1/cycles)) and pads periodically
    phase, per_cycle = _first_pass(x, o, fn, weighting)
    w = whole_cycle_weights(phase)[..., None]
    mean = (w * x).sum(-2) / w.sum(-2)
    scale = x.std(-2)
    z = (x - mean[..., None, :]) / scale[..., None, :]
    period = _period(phase) if padding else None
    fitted, phase = _phaser(z, _order(o, per_cycle), period, weighting)

    # Poincaré section: rotate so the section channel's fundamental is A sin(φ), A > 0
    fund = fit_fourier(phase, z[..., o.section_channel], 1).coeffs  # (..., 3): a0, a1, b1
    amp = torch.hypot(fund[..., 1], fund[..., 2])
    if bool((amp < 0.1).any()):
        raise ValueError(
            f"{fn}: channel {o.section_channel} has almost no first harmonic (amplitude "
            f"{float(amp.min()):.2g} of its std), so it cannot define phase 0; pass another "
            "section_channel"
        )
    offset = torch.atan2(-fund[..., 1], fund[..., 2])
    model = PhaseModel(mean=mean, scale=scale, offset=offset, **fitted)
    return model, phase - offset[..., None]


def _transform(model: PhaseModel, x: Tensor, o, fn: str) -> Tensor:
    """Phase ``(..., T)`` of ``x (..., T, C)`` (no NaN) under a fitted ``model``."""
    if model.mean.shape[-1] != x.shape[-1]:
        raise ValueError(f"{fn}: the phase model was fitted to {model.mean.shape[-1]} channels, "
                         f"x has {x.shape[-1]}")
    first = _first_pass(x, o, fn)[0]
    period = _period(first)
    z = (x - model.mean[..., None, :]) / model.scale[..., None, :]
    theta = _protophases(z, period)
    combined = _combine(theta + model.channel_correction(theta), model.weights)
    return combined + model.correction(combined) - model.offset[..., None]


def _protophases(z: Tensor, period: Tensor | None) -> Tensor:
    """Step 1: wrapped Hilbert protophases ``(..., C, T)`` of ``z (..., T, C)``, the record
    padded by its periodic continuation when ``period`` (samples, ``(...)``) is given."""
    T = z.shape[-2]
    if period is None:
        theta = torch.angle(analytic_signal(z, dim=-2))
    else:
        theta = torch.angle(analytic_signal(_periodic_pad(z, period), dim=-2)[..., :T, :])
    return theta.mT


def _combine(psi: Tensor, weights: Tensor) -> Tensor:
    """Step 3's combination of channel phases ``psi (..., C, T)`` -> unwrapped ``(..., T)``."""
    u = torch.polar(torch.ones_like(psi), psi).mT  # (..., T, C) unit phasors
    return unwrap(torch.angle((u @ weights[..., None])[..., 0]))


def _phaser(z: Tensor, order, period: Tensor | None, weighting: str) -> tuple[dict, Tensor]:
    """Phaser steps 1-4 on centred, scaled ``z (..., T, C)``.

    ``order`` is an integer, or ``("auto", K_max)`` to choose each correction's order in
    ``[1, K_max]`` (:func:`correction_order`). Returns the fitted :class:`PhaseModel` fields
    (all but ``mean``, ``scale``, ``offset``) and the unwrapped phase ``(..., T)``.
    """
    T = z.shape[-2]
    theta = _protophases(z, period)
    w = whole_cycle_weights(unwrap(theta))
    channel_correction, channel_order = _correction(theta, order, w)
    psi = theta + channel_correction(theta)
    # a channel whose protophase winds k >= 2 times per cycle of the others carries a harmonic
    # of the oscillation (xy, x² − y² of a circle), or mostly noise: its phasor e^{ikφ} is
    # incoherent with e^{iφ} and would pull the combination, so it gets no weight
    fundamental = _fundamental_channels(theta, z)  # (..., C) bool
    u = torch.polar(fundamental[..., None].to(psi), psi).mT  # (..., T, C) phasors, 0 if excluded
    # u_c ≈ e^{iφ} a_c with |a_c| = 1: the coherence R = uᴴu/T ≈ conj(a) aᵀ, whose top
    # eigenvector v ∝ conj(a) aligns the channels, so u v ∝ e^{iφ}
    R = u.mH @ u / T
    _, vec = _linalg.eigh(R, "the channels' phase coherence matrix")
    weights = vec[..., -1]
    coherence = _channel_coherence(R, fundamental)
    if weighting == "snr":
        # u_c = e^{i(φ + ε_c)} a_c with independent phase noise ε_c of variance v_c: the
        # combination with the least variance weighs each aligned phasor by 1 / v_c, and for
        # wrapped-normal noise ρ_c = exp(−v_c / 2)
        mag = 1 / _phase_noise_variance(u, R, weights.abs(), fundamental, unwrap(theta))
        weights = weights.sgn() * (mag / mag.sum(-1, keepdim=True))
    else:
        weights = weights / weights.abs().sum(-1, keepdim=True)
    combined = _combine(psi, weights)
    w = whole_cycle_weights(combined)
    correction, combined_order = _correction(combined, order, w)
    fitted = dict(channel_correction=channel_correction, weights=weights, correction=correction,
                  coherence=coherence, channel_order=channel_order, order=combined_order)
    return fitted, combined + correction(combined)


#: a channel's phase-noise variance is floored at this fraction of the noisiest channel's, so
#: one channel that looks noise-free cannot take all the weight from estimation noise alone
_MIN_VARIANCE = 1e-3
#: blocks of whole cycles over which the spread of the channels' phase-noise estimates is taken
_BLOCKS = 5
#: the channels' log phase-noise variances keep their deviations from the mean in full only
#: where their spread is many times this factor times its sampling variance (smaller factors
#: let equal-noise channels get unequal weights)
_SHRINK = 8.0


def _phase_noise_variance(u: Tensor, R: Tensor, prior: Tensor, keep: Tensor,
                          theta: Tensor) -> Tensor:
    """Each channel's phase-noise variance ``(..., C)`` for the SNR weights, ``inf`` for a
    channel left out (``keep (..., C)`` False), shrunk towards the variances ``∝ 1 / prior``
    that the ``prior (..., C)`` weights imply (the coherence eigenvector's) by as much as the
    channels' differences are within estimation noise.

    ``v_c = −2 log ρ_c`` from the coherence matrix ``R (..., C, C)`` of the phasors
    ``u (..., T, C)`` (:func:`_log_coherence`), floored at :data:`_MIN_VARIANCE` of the
    largest. Slow noise (a swimmer's joint noise decorrelates over cycles) leaves few
    independent samples in a record, so channels of equal noise can differ by chance, and
    weighing by that is worse than equal weights. Empirical Bayes in ``log v``: the same
    estimate on :data:`_BLOCKS` blocks of whole cycles of the unwrapped protophases
    ``theta (..., C, T)`` gives each channel's sampling variance ``s²_c`` (between-block
    variance / blocks); the deviations ``d_c`` of ``log v_c`` from the prior's (up to a common
    constant) are scaled by ``B = max(0, 1 − c mean s² / their observed variance)``, ``c`` =
    :data:`_SHRINK`. With ``B = 0`` (no evidence that the channels differ, or fewer than three
    kept channels) the weights are the prior's.
    """
    # blocks of whole cycles along the channels' mean unwrapped protophase
    rough = (theta - theta[..., :1]).mul(keep[..., None]).sum(-2) / keep.sum(-1, keepdim=True)
    block = block_masks(cycle_blocks(rough, _BLOCKS, span="centred"), _BLOCKS).to(u.real.dtype)
    count = block.sum(-2)  # (..., F)
    Rb = (u.mH[..., None, :, :] * block.mT[..., :, None, :]) @ u[..., None, :, :]
    Rb = Rb / count.clamp_min(1)[..., None, None]  # (..., F, C, C)
    log_vb = _log_variance(-2 * _log_coherence(Rb, keep[..., None, :]), keep[..., None, :])
    log_v = _log_variance(-2 * _log_coherence(R, keep), keep)
    # shrink towards the variances the prior weights imply (v ∝ 1 / weight)
    tiny = torch.finfo(log_v.dtype).tiny
    target = torch.where(keep, -prior.clamp_min(tiny).log(), torch.zeros_like(log_v))
    d, db = log_v - target, log_vb - target[..., None, :]
    m = keep.to(log_v)
    center = (d * m).sum(-1, keepdim=True) / m.sum(-1, keepdim=True).clamp_min(1)
    v = (target + center + _shrink(d, db, keep, count) * (d - center)).exp()
    return torch.where(keep, v, torch.full_like(v, math.inf))


def _shrink(x: Tensor, xb: Tensor, keep: Tensor, count: Tensor) -> Tensor:
    """Shrinkage factor ``B (..., 1)`` of channel estimates ``x (..., C)`` from their values on
    blocks ``xb (..., F, C)`` (``count (..., F)`` samples each; empty blocks are ignored)."""
    used = (count > 0)[..., None]  # (..., F, 1)
    nb = used.sum(-2).clamp_min(2)  # (..., 1)
    mb = (xb * used).sum(-2) / nb
    s2 = ((xb - mb[..., None, :]).square() * used).sum(-2) / (nb - 1) / nb  # (..., C)
    m = keep.to(x)
    k = m.sum(-1, keepdim=True).clamp_min(1)
    center = (x * m).sum(-1, keepdim=True) / k
    spread = ((x - center).square() * m).sum(-1, keepdim=True) / (k - 1).clamp_min(1)
    noise = (s2 * m).sum(-1, keepdim=True) / k
    shrink = (1 - _SHRINK * noise / spread.clamp_min(torch.finfo(x.dtype).tiny)).clamp(0.0, 1.0)
    return torch.where(k >= 3, shrink, torch.zeros_like(shrink))


def _log_variance(v: Tensor, keep: Tensor) -> Tensor:
    """``log v (..., C)`` of kept channels' variances ``v`` floored at :data:`_MIN_VARIANCE`
    times the largest (estimation noise can make a small one 0 or negative); 0 elsewhere."""
    v = torch.where(keep, v, torch.zeros_like(v))
    v = torch.maximum(v, _MIN_VARIANCE * v.amax(-1, keepdim=True))
    v = v.clamp_min(torch.finfo(v.dtype).tiny)
    return torch.where(keep, v.log(), torch.zeros_like(v))


def _correction(theta: Tensor, order, w: Tensor) -> tuple[FourierSeries, Tensor]:
    """The series correction of protophases ``theta (..., T)`` with its order ``(...)``:
    ``order`` fixed, or ``("auto", K_max)`` chosen by :func:`correction_order`."""
    if isinstance(order, tuple):
        limit = order[1].reshape(order[1].shape + (1,) * (theta.ndim - 1 - order[1].ndim))
        limit = limit.expand(theta.shape[:-1])  # per batch element, the same for its channels
        chosen = correction_order(theta, w, limit)
        return correction_series(theta, int(limit.max()), w).truncated(chosen), chosen
    series = correction_series(theta, order, w)
    return series, torch.full(theta.shape[:-1], order, dtype=torch.long, device=theta.device)


def _channel_coherence(R: Tensor, keep: Tensor) -> Tensor:
    """Each channel's phase coherence ``ρ_c (..., C)`` (:func:`_log_coherence`, at most 1; 0
    for a channel left out)."""
    log_rho = _log_coherence(R, keep).clamp(max=0.0)
    return torch.where(keep, log_rho.exp(), torch.zeros_like(log_rho))


def _log_coherence(R: Tensor, keep: Tensor) -> Tensor:
    """Each channel's ``log ρ_c (..., C)`` from the coherence matrix ``R (..., C, C)`` of the
    aligned-up-to-a-constant phasors: with independent phase noise ``|R_ab| = ρ_a ρ_b``
    (``a ≠ b``), fitted by least squares over the pairs of kept channels (``keep (..., C)``
    bool); unconstrained, so estimation noise can make it positive. Needs three kept channels;
    with fewer every kept channel gets the coherence of the pair (or 1 alone). Left-out
    channels get 0."""
    C = R.shape[-1]
    L = R.abs().clamp(1e-12, 1.0).log()
    m = keep.to(L)
    pair = m[..., :, None] * m[..., None, :] * (1 - torch.eye(C, dtype=L.dtype, device=L.device))
    deg = pair.sum(-1)
    # normal equations of min Σ_{a≠b kept} (L_ab − l_a − l_b)²: (diag(deg) + pair) l = Σ_b pair L
    A = torch.diag_embed(torch.where(deg > 0, deg, torch.ones_like(deg))) + pair
    rhs = (pair * L).sum(-1)
    many = keep.sum(-1, keepdim=True) >= 3
    eye = torch.eye(C, dtype=L.dtype, device=L.device)
    log_rho = _linalg.solve(torch.where(many[..., None], A, eye),
                            torch.where(many, rhs, 0)[..., None], "the channels' coherence fit")[..., 0]
    # two kept channels: |R_ab| = ρ² with ρ shared; one: ρ = 1
    pair_mean = (pair * L).sum((-2, -1)) / pair.sum((-2, -1)).clamp_min(1) / 2
    return torch.where(keep & many, log_rho, torch.where(keep, pair_mean[..., None], 0.0))


#: a channel winding at least this many times faster than the slowest is not a fundamental
_HARMONIC_RATIO = 1.5


def _fundamental_channels(theta: Tensor, z: Tensor) -> Tensor:
    """``(..., C)`` True for channels whose protophase ``theta (..., C, T)`` winds about as often
    as the slowest *periodic* channel of ``z (..., T, C)`` (less than :data:`_HARMONIC_RATIO`
    times as often, and not that many times less); warns when some do not.

    A channel is periodic where it winds at least twice and its
    :func:`~torchconn.io.preflight.periodicity` at the period its own winding gives reaches
    :data:`~torchconn.io.preflight.MIN_PERIODICITY` (where no channel is, all count).
    Faster channels carry a harmonic of the gait (xy, x² − y² of a circle); slower ones are
    dominated by drift or noise, as the head joints of a tracked zebrafish whose tail beats at
    9 samples per cycle (wound 3-7 times while the tail beat 15-25 times, periodicity
    −0.2-0.0 against the tail's 0.3-0.6). Either way their combination with the gait's
    channels would be ambiguous; taking the slowest channel of all as the reference let such a
    drifting channel define the phase and leave the gait's channels out."""
    turns = (unwrap(theta)[..., -1] - unwrap(theta)[..., 0]).abs() / (2 * math.pi)
    # the autocorrelation at the period means little unless the record holds two of them
    periodic = (periodicity(z.mT.unsqueeze(-1), turns) >= MIN_PERIODICITY) & (turns >= 2)
    periodic = periodic | ~periodic.any(-1, keepdim=True)
    reference = torch.where(periodic, turns.clamp_min(0.5), math.inf).amin(-1, keepdim=True)
    faster = turns >= _HARMONIC_RATIO * reference
    slower = turns * _HARMONIC_RATIO <= reference
    keep = ~(faster | slower)
    ratio = turns / reference
    for mask, factor, what in (
            (faster, ratio, "as often as the slowest periodic channel (a harmonic of the gait, "
                            "or noise)"),
            (slower, 1 / ratio, "less often than the slowest periodic channel (drift or noise)")):
        if bool(mask.any()):
            warnings.warn(
                f"Phaser: {int(mask.sum())} channel(s) wind {float(factor[mask].min()):.1f}-"
                f"{float(factor[mask].max()):.1f}x {what}; combining them with the others "
                "would be ambiguous, so they are left out of the phase",
                PhaseAmbiguityWarning, stacklevel=4)
    return keep


class PhaseAmbiguityWarning(UserWarning):
    """Some channels wind at a multiple of the gait's rate, or far below it, and were left out
    of the phase."""


def _period(phase: Tensor) -> Tensor:
    """Period in samples from the least-squares slope of ``phase (..., T)`` over its central
    80 % (the plain transform's phase is least reliable within a cycle of either end)."""
    T = phase.shape[-1]
    lo, hi = T // 10, T - T // 10
    t = torch.arange(lo, hi, dtype=phase.dtype, device=phase.device)
    t = t - t.mean()
    p = phase[..., lo:hi]
    slope = (p * t).sum(-1) / (t * t).sum()
    return 2 * math.pi / slope


def _periodic_pad(z: Tensor, period: Tensor) -> Tensor:
    """Append a periodic continuation that leads the record's end back into its start.

    ``z (..., T, C)``, ``period (...)`` in samples -> ``(..., 2T, C)``. Appended sample
    ``T + s`` (``s < L = T``) shows the cycle at virtual time ``τ(s) = T + s + δ h(s / L)``,
    where the smooth step ``h(u) = u - sin(2πu) / 2π`` (slope 0 at both ends) absorbs the
    ``|δ| <= P/2`` that makes ``τ(L)`` a whole number of periods: the padded signal then has
    continuous phase and frequency at the record's end and at the FFT's wrap-around to its
    start. The value at ``τ`` is read one or more periods earlier in the record, cross-fading
    (raised cosine) from the last cycles to the first, so each join looks like data from
    neighbouring cycles.
    """
    T = z.shape[-2]
    P = period.clamp(2.0, (T - 1) / 3.0)[..., None]
    # as long as the record (>= 3 periods): a length set by the data alone, not by the batch,
    # keeps each batch element's result independent of the others
    L = T
    s = torch.arange(L, dtype=z.dtype, device=z.device)
    u = s / L
    delta = torch.round((T + L) / P) * P - (T + L)
    tau = T + s + delta * (u - torch.sin(2 * math.pi * u) / (2 * math.pi))
    pos_end = tau - torch.ceil((tau - (T - 1)) / P) * P  # latest copy inside the record
    pos_start = tau - torch.floor(tau / P) * P  # copy in the first period
    w = 0.5 - 0.5 * torch.cos(math.pi * (s + 1) / (L + 1))
    ext = (1 - w[:, None]) * _interp(z, pos_end) + w[:, None] * _interp(z, pos_start)
    return torch.cat([z, ext], dim=-2)


def _interp(z: Tensor, pos: Tensor) -> Tensor:
    """Linear interpolation of ``z (..., T, C)`` at fractional sample positions ``(..., L)``."""
    T, C = z.shape[-2:]
    pos = pos.clamp(0, T - 1)
    i0 = pos.floor().long().clamp(max=T - 2)
    f = (pos - i0)[..., None]
    g0 = z.gather(-2, i0[..., None].expand(*i0.shape, C))
    g1 = z.gather(-2, (i0 + 1)[..., None].expand(*i0.shape, C))
    return g0 + f * (g1 - g0)


def _check_x(x: Tensor, fn: str) -> None:
    _checks.tensor(
        x, "x", "(..., T, C) with T >= 4 samples along axis -2 and C >= 1 channels along axis -1",
        fn=fn, valid=lambda t: t.ndim >= 2 and t.shape[-1] >= 1 and t.shape[-2] >= 4,
    )


def _check_values(x: Tensor, fn: str) -> None:
    nan = torch.isnan(x)
    if bool(nan.any()):
        allnan = nan.all(-2)
        if bool(allnan.any()):
            where = _checks.first_index(allnan)
            raise ValueError(
                f"{fn}: channel {where[-1]} of x (batch index {where[:-1]}) is "
                "NaN at every sample; drop that channel"
            )
        raise ValueError(
            f"{fn}: x contains {int(nan.sum())} NaN samples; fill or smooth drop-outs "
            "first (torchconn.phase.smoothing.rts_smooth predicts through them)"
        )
    _checks.finite(x, "x", fn=fn)
    std = x.std(-2)
    flat = std <= _CONST_TOL * x.abs().amax(-2)
    if bool(flat.any()):
        where = _checks.first_index(flat)
        raise ValueError(
            f"{fn}: channel {where[-1]} of x (batch index {where[:-1]}; joint angle "
            f"r{where[-1] + 1} when x holds a recording's shapes) is constant and carries no "
            "phase: every channel must oscillate with the gait; drop it, or check the "
            "recording's column (a placeholder, or a joint that was not tracked)"
        )
