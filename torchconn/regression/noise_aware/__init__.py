"""Noise-aware connection regression: filtered raw differences with an errors-in-variables fix.

The smoothed regression (:func:`~torchconn.regression.connection_regression` on a Kalman
smoother's output) smooths the noisy pose channels, which carry the target ``ξ``, harder than
the shape channels, which carry the regressors ``δ̇``; that removes the body's response to the
very shape jitter that identifies ``A`` and shrinks ``Â`` towards 0 under motion-capture noise.
Here target and regressors see the same linear filter over ``h`` samples and nothing else is
smoothed (:mod:`torchconn.noise.intervals`). The noise's expected contribution to each bin's
normal matrix is subtracted (:mod:`.eiv`); the per-channel noise is estimated from the data
(:mod:`torchconn.noise.spectrum`); a pooled fit chooses the interval and the bins' width by an
estimate of ``Â``'s mean squared error after its bias correction (:mod:`.bias`); where the data
are too few for the correction to pay, the estimate falls back towards the smoothed
regression's (:mod:`.shrink`). The stage itself is :class:`NoiseAwareRegression`
(:mod:`.regression`).
"""

from .bias import bin_bias_correction, derivative_bias_allowance, derivative_bias_correction
from .eiv import eiv_correction, eiv_row_correction, noise_aware_regression
from .regression import NoiseAwareRegression, predictions_only
from .shrink import blend_fits, offset_gain, offsets_at

__all__ = ["NoiseAwareRegression", "predictions_only", "noise_aware_regression", "eiv_correction",
           "eiv_row_correction", "blend_fits", "offset_gain", "offsets_at",
           "bin_bias_correction", "derivative_bias_correction", "derivative_bias_allowance"]
