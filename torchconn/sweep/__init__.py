"""The sweep runner: the paper's accuracy-versus-noise experiments in one command.

``python -m torchconn.sweep [--config configs/NAME.toml] [--out DIR] [--set key=value ...]``
"""

from .config import DEFAULT_TOML, Experiment, SimulationSettings, SweepConfig, load_config
from .experiment import ExperimentResult, run_experiment
from .runner import run_sweep
from .store import read_table

__all__ = [
    "DEFAULT_TOML", "Experiment", "SimulationSettings", "SweepConfig", "load_config",
    "ExperimentResult", "run_experiment", "run_sweep", "read_table",
]
