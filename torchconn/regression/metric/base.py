"""The estimator's metric stage: the dissipation metric from a recorded power channel."""

from __future__ import annotations

import abc

from torch import Tensor

from ..._options import Options
from ...phase.limit_cycle import LimitCycle
from ...trajectory import Trajectory
from ..model import LocalConnectionModel

__all__ = ["MetricEstimator"]


class MetricEstimator(Options, abc.ABC):
    """Base of the metric stage: ``fit(traj, cycle, pool=...)`` gives a fitted metric that
    :meth:`attach` evaluates on a fitted connection's phase bins.

    ``enabled``: None (the default) fits the metric when the data carry a power channel, True
    requires one (data without it are refused, naming the missing ``power`` column), False
    never fits it.
    """

    enabled: bool | None

    def wanted(self, power: Tensor | None) -> bool:
        """Whether the metric is fitted for data whose power channel is ``power``."""
        return self.enabled is not False and power is not None

    @abc.abstractmethod
    def fit(self, traj: Trajectory, cycle: LimitCycle, *, pool: bool = False):
        """The metric of a prepared trajectory (``smoothed`` and ``phase`` set, a power
        channel) around ``cycle``: batch dims ``...`` of ``traj``, or none when ``pool``."""

    @abc.abstractmethod
    def attach(self, model: LocalConnectionModel, fitted) -> LocalConnectionModel:
        """``model`` (a connection fitted to the same data) with the metric ``fitted``
        evaluated at its phase bins and interpolated by its Fourier order."""
