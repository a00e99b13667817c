"""The flags and config handling every command shares.

- :func:`add_common` adds ``--version`` (every command) and, for a command that does work,
  ``--quiet``, ``--no-figures``, ``--threads`` and ``--device``. A command that writes no
  figures (``convert``, ``improve propose``) accepts ``--no-figures`` as a no-op (its help
  says so), so that one set of flags can be passed to every command.
- :func:`informer` is the printer of a command's informational lines, silent under
  ``--quiet`` (errors and warnings are printed whatever the flag).
- :func:`add_config` adds ``--config`` and ``--set``; :func:`config_tables` reads them into
  the config's tables, with :func:`apply_overrides` applying ``--set section.key=value``.
"""

from __future__ import annotations

import argparse
import copy
import tomllib
from collections.abc import Callable
from pathlib import Path

from .._cli import InputError, add_device, add_threads
from .._files import read_toml
from .._version import __version__

__all__ = ["add_common", "add_version", "informer", "add_config", "config_tables",
           "apply_overrides"]


def add_version(parser: argparse.ArgumentParser) -> None:
    """``--version``: print ``torchconn X.Y.Z`` and exit."""
    parser.add_argument("--version", action="version", version=f"torchconn {__version__}")


def add_common(parser: argparse.ArgumentParser, *, version: bool = True, figures: bool = True,
               device: bool = True, quiet_help: str = "print no informational lines") -> None:
    """The flags of a command that does work: ``--version`` (unless ``version=False``, for a
    subcommand whose parent has it), ``--quiet`` (``quiet_help``: what it leaves printed
    besides errors and warnings), ``--no-figures`` (``figures=False``: the command writes
    none, and the flag is accepted as a no-op), ``--threads`` and ``--device``
    (``device=False``: the command runs on the CPU only, or has a ``--device`` of its own)."""
    if version:
        add_version(parser)
    parser.add_argument("--quiet", action="store_true",
                        help=f"{quiet_help}; errors and warnings are printed all the same")
    parser.add_argument("--no-figures", action="store_true",
                        help="do not write PNG figures" if figures else
                        "accepted for uniformity; this command writes no figures")
    add_threads(parser)
    if device:
        add_device(parser)


def informer(quiet: bool) -> Callable[..., None]:
    """``print`` for a command's informational lines, or a no-op under ``--quiet``."""
    return (lambda *_, **__: None) if quiet else print


def add_config(parser: argparse.ArgumentParser, config_help: str, set_help: str) -> None:
    """``--config FILE`` (a TOML file of tables) and ``--set KEY=VALUE`` (repeatable, into
    ``args.overrides``)."""
    parser.add_argument("--config", type=Path, help=config_help)
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE", help=set_help)


def config_tables(path: Path | None, overrides: list[str]) -> dict:
    """A TOML config (``[estimator]``, ``[convert]``, ...) with ``--set section.key=value``
    overrides applied (:func:`apply_overrides`)."""
    raw = read_toml(path, "--config") if path is not None else {}
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ValueError(f"--set {item!r} must look like section.key=value, e.g. "
                             "estimator.regression.ridge=1e-6 or convert.max_gap=0.5")
    return apply_overrides(raw, list(overrides))


def apply_overrides(raw: dict, overrides: list[str]) -> dict:
    """Apply ``key.path=value`` overrides (value parsed as TOML, else a string).

    ``experiment.trials=2`` sets a key in every experiment; ``experiment.1.trials=2`` in one.
    A path through a missing index or a non-table is an :class:`InputError`.
    """
    raw = copy.deepcopy(raw)
    for item in overrides:
        where = f"--set {item}"
        if "=" not in item:
            raise InputError(f"{where}: expected section.key=value, e.g. "
                             "--set simulation.n_cycles=10")
        path, text = item.split("=", 1)
        try:
            value = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            value = text
        keys = path.strip().split(".")
        if not all(keys):
            raise InputError(f"{where}: empty key in {path!r}")
        targets = [raw]
        for depth, key in enumerate(keys[:-1]):
            nxt = []
            for t in targets:
                if isinstance(t, list):
                    if key.lstrip("-").isdigit():
                        k = int(key)
                        if not 0 <= k < len(t):
                            raise InputError(
                                f"{where}: index {k} is out of range; the config has {len(t)} "
                                f"[[{keys[depth - 1]}]] table(s), indices 0-{len(t) - 1}")
                        nxt.append(t[k])
                    else:
                        nxt.extend(x.setdefault(key, {}) if isinstance(x, dict) else x
                                   for x in t)
                elif isinstance(t, dict):
                    nxt.append(t.setdefault(key, {}))
                else:
                    raise InputError(f"{where}: {'.'.join(keys[:depth])} is a value, not a table")
            targets = nxt
        for t in targets:
            for tt in (t if isinstance(t, list) else [t]):
                if not isinstance(tt, dict):
                    raise InputError(f"{where}: {'.'.join(keys[:-1])} is a value, not a table")
                tt[keys[-1]] = value
    return raw
