"""Simulate: batched Stratonovich rollouts of the shape SDE and the motion-capture observation model.

- :func:`simulate` (:mod:`~torchconn.simulation.rollout`) -- noisy recordings of a system
  executing a gait, batched over cells (noise levels × trials), seeded per cell.
- :func:`observe` (:mod:`~torchconn.simulation.observe`) -- Gaussian marker noise and drop-outs.
"""

from .observe import observe
from .rollout import POWER_DEFINITION, cell_generators, simulate

__all__ = ["simulate", "observe", "cell_generators", "POWER_DEFINITION"]
