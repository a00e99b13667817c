"""Phase: smoothing, phase estimation (Phaser), the limit cycle and Fourier series in phase.

- :mod:`~torchconn.phase.smoothing` -- batched Kalman/RTS smoother, body velocities.
- :mod:`~torchconn.phase.phaser` -- Revzen's Phaser: a phase that advances uniformly in time.
- :mod:`~torchconn.phase.limit_cycle` -- the self-consistent cycle ``γ(φ)`` and phase rate.
- :mod:`~torchconn.phase.fourier` -- Fourier series in phase for scalars to 3-tensors.
"""

from .fourier import FourierSeries, fit_fourier, fourier_design
from .limit_cycle import CycleEstimator, LimitCycle, SelfConsistentCycle, fit_limit_cycle, phase_rate
from .phaser import (
    PhaseAmbiguityWarning,
    PhaseEstimator,
    PhaseModel,
    Phaser,
    analytic_signal,
    circular_rms,
    correction_order,
    correction_series,
    estimate_phase,
    held_out_order,
    hilbert_phase_pc1,
    protophase,
)
from .smoothing import (
    RTSSmoother,
    Smoother,
    body_velocity,
    noise_parameters,
    rts_smooth,
    smooth_trajectory,
    unwrap,
)

__all__ = [
    "Smoother", "RTSSmoother", "PhaseEstimator", "Phaser", "PhaseModel",
    "CycleEstimator", "SelfConsistentCycle",
    "FourierSeries", "fit_fourier", "fourier_design",
    "LimitCycle", "fit_limit_cycle", "phase_rate",
    "analytic_signal", "protophase", "correction_series", "correction_order",
    "held_out_order", "PhaseAmbiguityWarning",
    "estimate_phase", "hilbert_phase_pc1", "circular_rms",
    "rts_smooth", "unwrap", "body_velocity", "smooth_trajectory", "noise_parameters",
]
