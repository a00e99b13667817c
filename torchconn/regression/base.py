"""The regression stage's base: :class:`Regression` (``fit(traj, cycle, pool=...) -> model``),
which :class:`~torchconn.regression.tube.TubeRegression` and
:class:`~torchconn.regression.noise_aware.NoiseAwareRegression` implement, and the check of
the bin count that every regression and the estimator apply."""

from __future__ import annotations

import abc

from .._options import Options
from ..phase.limit_cycle import LimitCycle
from ..trajectory import Trajectory
from .model import LocalConnectionModel

__all__ = ["Regression", "check_bin_count"]


def check_bin_count(n_bins: int, n_samples: int, where: str) -> None:
    """Refuse more phase bins than the recording's ``n_samples`` samples (``ValueError``
    naming ``where``): every bin needs samples of its own, and the bins' series grow as
    ``n_bins²``."""
    if n_bins > n_samples:
        raise ValueError(
            f"{where}: n_bins = {n_bins} is more than the {n_samples} samples of the recording: "
            "every phase bin needs samples of its own; use fewer bins (regression__n_bins; "
            "torchconn-fit --n-bins, estimator.regression.n_bins)")


class Regression(Options, abc.ABC):
    """Base of the estimator's regression stage: ``fit(traj, cycle, pool=...) -> model``."""

    @abc.abstractmethod
    def fit(self, traj: Trajectory, cycle: LimitCycle, *, pool: bool = False
            ) -> LocalConnectionModel:
        """The local model of a prepared trajectory (``smoothed`` and ``phase`` set) around
        ``cycle``: batch dims ``...`` of ``traj``, or none when ``pool``."""
