"""Input and output: trajectory files (the documented CSV format, lossless NPZ).

See :mod:`~torchconn.io.trajectory_files` and ``docs/conventions.md`` (section "Trajectory files").
"""

from .trajectory_files import count_cycles, load_npz, read_csv, save_npz, write_csv

__all__ = ["read_csv", "write_csv", "save_npz", "load_npz", "count_cycles"]
