"""The estimator the commands fit recordings with, and how it differs from
:class:`~torchconn.regression.estimator.ConnectionEstimator`'s defaults: in one setting.

``ConnectionEstimator()`` fits one model per trial (``pool=False``): in Python every trial
stays apart unless asked. ``torchconn-fit`` and ``torchconn-improve propose`` write one model
for all the trials they read, so they pool them (:data:`POOLED`); every other setting is
``ConnectionEstimator``'s own default. :func:`pooled_estimator` is that estimator: in Python it
gives the numbers ``torchconn-fit`` gives for the same files (``ConnectionEstimator(pool=True)``
is the same estimator).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from .estimator import ConnectionEstimator, estimator_from_settings

__all__ = ["POOLED", "pooled_estimator"]

#: the one setting in which the commands' estimator differs from ``ConnectionEstimator()``
POOLED: Mapping[str, Any] = MappingProxyType({"pool": True})


def pooled_estimator(settings: Mapping[str, Any] | None = None, *,
                     where: str = "estimator") -> ConnectionEstimator:
    """The estimator of ``torchconn-fit``: ``ConnectionEstimator``'s defaults with
    :data:`POOLED`, then ``settings`` (a nested table as
    :func:`~torchconn.regression.estimator.estimator_from_settings` reads, e.g. a config's
    ``[estimator]``; ``pool`` may be set there too).

    Raises:
        ValueError: as :func:`~torchconn.regression.estimator.estimator_from_settings`,
            naming ``where``.
    """
    return estimator_from_settings({**POOLED, **(settings or {})}, where=where)
