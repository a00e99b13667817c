"""Re-exports imported on first use: a package's ``__init__`` that costs only what it uses.

A package lists its public names and the modules that define them;
:func:`lazy_exports` gives it the module-level ``__getattr__`` and ``__dir__`` (PEP 562) that
import each module when one of its names is first read. ``package.Name``, ``from package
import Name`` and ``from package import *`` work as with eager imports, and so does
``package.sub`` for any submodule ``sub``, imported on first use too.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from importlib import import_module

__all__ = ["lazy_exports"]


def lazy_exports(package: str, exports: dict[str, str]
                 ) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of the package named ``package`` (its
    ``__name__``, already in ``sys.modules``).

    Args:
        package: the package's ``__name__``.
        exports: public name -> the module that defines it, relative to the package (e.g.
            ``{"Trajectory": ".trajectory"}``); the name is read from that module.

    Returns:
        ``(__getattr__, __dir__)``: ``__getattr__(name)`` imports the module of ``name`` (or,
        for any other name, the submodule ``package.name``), stores the value in the
        package's namespace (later reads do not call it again) and returns it; it raises
        :class:`AttributeError` for a name that is neither.
    """
    namespace = vars(sys.modules[package])

    def __getattr__(name: str):
        if name in exports:
            value = getattr(import_module(exports[name], package), name)
        elif name.startswith("__"):  # e.g. __wrapped__, __path__ probes: never a submodule
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        else:
            try:
                value = import_module(f"{package}.{name}")
            except ModuleNotFoundError as err:
                if err.name != f"{package}.{name}":
                    raise  # the submodule exists; something it imports is missing
                raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
