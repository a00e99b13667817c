"""The sweep runner: the paper's accuracy-versus-noise experiments in one command.

``torchconn-sweep [--config NAME|FILE.toml] [--out DIR] [--set key=value ...]`` (or
``python -m torchconn.sweep``), ``NAME`` a packaged config (``quick``, ``fig4a``, ...).
"""

from .._output import FolderBusy, FolderLock
from .config import DEFAULT_TOML, Experiment, SimulationSettings, SweepConfig, load_config
from .experiment import Cell, ExperimentResult, experiment_cells, run_cell, run_experiment
from .runner import SweepSummary, run_sweep
from .store import ResultStore, read_table

__all__ = [
    "DEFAULT_TOML", "Experiment", "SimulationSettings", "SweepConfig", "load_config",
    "Cell", "ExperimentResult", "experiment_cells", "run_cell", "run_experiment",
    "FolderBusy", "FolderLock", "SweepSummary", "run_sweep", "ResultStore", "read_table",
]
