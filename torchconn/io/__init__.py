"""Input and output: trajectory files (the documented CSV format, lossless NPZ) and tracking
files (:mod:`~torchconn.io.tracking`).

See :mod:`~torchconn.io.trajectory_files` and ``docs/conventions.md`` (section "Trajectory files").
"""

from . import tracking  # noqa: F401  # sets the conversion behind Trajectory.from_movement
from .trajectory_files import count_cycles, load_npz, read_csv, save_npz, write_csv

__all__ = ["read_csv", "write_csv", "save_npz", "load_npz", "count_cycles"]
