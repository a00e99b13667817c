"""Old import paths (torchconn 0.1's flat layout) kept importable for one release.

``import torchconn.rollout`` and ``from torchconn.gaits import reference_gait`` keep working:
a meta-path finder maps each old dotted name onto the module that now holds the code and
returns that very module object (so classes and functions are identical, not copies), with a
:class:`DeprecationWarning` naming the new path.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

#: old module (0.1) -> new module; submodules follow their package
MOVED = {
    "torchconn.se2": "torchconn.physics.se2",
    "torchconn.systems": "torchconn.physics.systems",
    "torchconn.gaits": "torchconn.physics.gaits",
    "torchconn.rollout": "torchconn.simulation.rollout",
    "torchconn.observe": "torchconn.simulation.observe",
    "torchconn.smoothing": "torchconn.phase.smoothing",
    "torchconn.limit_cycle": "torchconn.phase.limit_cycle",
    "torchconn.fourier": "torchconn.phase.fourier",
    "torchconn.estimator": "torchconn.regression.estimator",
    "torchconn.model": "torchconn.regression.model",
    "torchconn.plots": "torchconn.regression.plots",
    "torchconn.data": "torchconn.trajectory",
    "torchconn.reference": "torchconn.testing.numpy_swimmer",
}


def new_name(old: str) -> str | None:
    """The current module name for an old dotted name, or None when it did not move."""
    for o in sorted(MOVED, key=len, reverse=True):
        if old == o or old.startswith(o + "."):
            return MOVED[o] + old[len(o):]
    return None


class _AliasLoader(importlib.abc.Loader):
    def __init__(self, target: str):
        self.target = target

    def create_module(self, spec):
        module = importlib.import_module(self.target)
        self._spec = module.__spec__
        return module

    def exec_module(self, module):
        # the target module is already executed; importlib set __spec__ to the alias's spec
        module.__spec__ = self._spec


class _MovedModuleFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        new = new_name(fullname)
        if new is None:
            return None
        warnings.warn(f"{fullname} moved to {new}; the old path goes away in the next release",
                      DeprecationWarning, stacklevel=2)
        module = importlib.import_module(new)
        return importlib.util.spec_from_loader(
            fullname, _AliasLoader(new), is_package=hasattr(module, "__path__"))


def install() -> None:
    if not any(isinstance(f, _MovedModuleFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, _MovedModuleFinder())  # before PathFinder, which would load copies
