"""Noise of recorded channels: the measurement noise from the spectrum of their increments
(:mod:`~torchconn.noise.spectrum`) and the velocity filters over intervals of samples with the
noise they carry (:mod:`~torchconn.noise.intervals`). Used by the regression and the discrepancy
workflow alike."""

from .intervals import (
    MAX_INTERVAL_CYCLES,
    VELOCITY_KERNEL,
    VELOCITY_KERNELS,
    IntervalSamples,
    flatten_batch,
    interval_noise_gains,
    interval_samples,
    interval_view,
    interval_weights,
    intervals_by_h,
    noise_ratio,
    overlap_inflation,
    pooled_view,
    take_intervals,
    velocity_interval_for,
)
from .spectrum import (
    KERNEL_CHUNK,
    NoiseEstimate,
    bridge_gaps,
    estimate_noise,
    normal_increments,
    normal_span,
    phase_noise_floor,
)

__all__ = [
    "NoiseEstimate", "estimate_noise", "phase_noise_floor", "normal_increments", "normal_span",
    "bridge_gaps", "KERNEL_CHUNK",
    "VELOCITY_KERNELS", "VELOCITY_KERNEL", "MAX_INTERVAL_CYCLES", "interval_weights",
    "IntervalSamples", "interval_noise_gains", "interval_samples", "overlap_inflation",
    "noise_ratio", "velocity_interval_for", "flatten_batch",
    "intervals_by_h", "take_intervals", "pooled_view", "interval_view",
]
