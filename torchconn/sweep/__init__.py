"""The sweep runner: the paper's accuracy-versus-noise experiments in one command.

``torchconn-sweep [--config NAME|FILE.toml] [--out DIR] [--set key=value ...]`` (or
``python -m torchconn.sweep``), ``NAME`` a packaged config (``quick``, ``fig4a``, ...).
"""

from .._lazy import lazy_exports

#: the public names and the modules that define them, imported on first use (the claims
#: load scipy.stats, the figures matplotlib: ``import torchconn.sweep`` loads neither)
_EXPORTS = {
    "DEFAULT_TOML": ".config", "Experiment": ".config", "SimulationSettings": ".config",
    "SweepConfig": ".config", "load_config": ".config",
    "Cell": ".experiment", "ExperimentResult": ".experiment", "experiment_cells": ".experiment",
    "run_cell": ".experiment", "run_experiment": ".experiment",
    "FolderBusy": ".._output", "FolderLock": ".._output",
    "SweepSummary": ".runner", "run_sweep": ".runner",
    "ResultStore": ".store", "read_table": ".store",
}


__all__ = [
    "DEFAULT_TOML", "Experiment", "SimulationSettings", "SweepConfig", "load_config",
    "Cell", "ExperimentResult", "experiment_cells", "run_cell", "run_experiment",
    "FolderBusy", "FolderLock", "SweepSummary", "run_sweep", "ResultStore", "read_table",
]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
