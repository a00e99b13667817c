"""What a phase-bin regression chose while fitting, as one stage hands it to the next.

:class:`RegressionDiagnostics` is the typed view of the choices a regression records in its
model's ``meta`` (window, intercept order, velocity interval, noise level, blend weights):
model selection reads these, not the ``meta`` dict. ``meta`` (and ``fit.json``) keep the
same keys and values.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

__all__ = ["RegressionDiagnostics"]


def _frozen(value: Any) -> Any:
    """JSON lists as nested tuples (numbers and None unchanged)."""
    return tuple(_frozen(v) for v in value) if isinstance(value, list | tuple) else value


@dataclass(frozen=True)
class RegressionDiagnostics:
    """The choices a regression's fit made, per batch element ``...`` of the model.

    Values keep the types the fit recorded (numbers, nested tuples shaped like the model's
    batch dims); None where the regression makes no such choice (a
    :class:`~torchconn.regression.tube.TubeRegression` has no velocity interval, noise level or
    blend).

    Attributes:
        window: the bins' half-width in bin spacings: one float for every batch element, or
            ``(...)`` one per element.
        intercept_order: ``(...)`` the Fourier order of the intercept ``ĉ(φ)`` per batch
            element; None: the model's own order.
        velocity_interval: the velocity interval ``h`` in samples of a noise-aware fit: an
            int (pooled) or ``(...)`` per element.
        velocity_kernel: the name of the interval filter; None: not recorded (the noise-aware
            regression's default filter then applies).
        noise_r: the joint-angle noise standard deviation in radians, ``(d,)`` (pooled) or
            ``(..., d)``.
        noise_ratio: the measurement-noise variance of a one-sample difference over the
            process noise's, averaged over the joints: a float (pooled) or ``(...)``.
        corrected_weight: ``(..., 4)`` the weight ``w ∈ [0, 1]`` of the noise-corrected
            estimate in ``β̂_s + w (β̂_c − β̂_s)`` per term ``c, b, A, ∂A/∂r``.
    """

    window: float | tuple | None = None
    intercept_order: tuple | None = None
    velocity_interval: int | tuple | None = None
    velocity_kernel: str | None = None
    noise_r: tuple | None = None
    noise_ratio: float | tuple | None = None
    corrected_weight: tuple | None = None

    @classmethod
    def from_meta(cls, meta: Mapping[str, Any] | None) -> RegressionDiagnostics:
        """The diagnostics a regression recorded in a model's ``meta`` (None or a missing key:
        None)."""
        meta = meta or {}
        return cls(**{name: _frozen(meta.get(name)) for name in _META_KEYS})


#: the ``meta`` keys :class:`RegressionDiagnostics` reads, each its field of that name
_META_KEYS = ("window", "intercept_order", "velocity_interval", "velocity_kernel", "noise_r",
              "noise_ratio", "corrected_weight")
