"""The sweep runner: the paper's accuracy-versus-noise experiments in one command.

``torchconn-sweep [--config NAME|FILE.toml] [--out DIR] [--set key=value ...]`` (or
``python -m torchconn.sweep``), ``NAME`` a packaged config (``quick``, ``fig4a``, ...).
"""

from .config import DEFAULT_TOML, Experiment, SimulationSettings, SweepConfig, load_config
from .experiment import ExperimentResult, run_experiment
from .runner import run_sweep
from .store import read_table

__all__ = [
    "DEFAULT_TOML", "Experiment", "SimulationSettings", "SweepConfig", "load_config",
    "ExperimentResult", "run_experiment", "run_sweep", "read_table",
]
