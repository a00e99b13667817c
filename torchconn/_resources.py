"""The configs that ship with torchconn, read with :mod:`importlib.resources`.

The repository keeps its TOML configs in the top-level ``configs/`` folder; installed (wheel or
editable) that folder is the package ``torchconn.configs`` (``pyproject.toml`` maps it), so the
same files are found from any working directory. In an uninstalled source checkout (the
repository on ``PYTHONPATH``) there is no ``torchconn.configs`` package, and the checkout's
``configs/`` beside ``torchconn/`` is read instead.
"""

from __future__ import annotations

import tomllib
from importlib import resources
from importlib.resources.abc import Traversable

__all__ = ["configs", "config_names", "read_config"]


def configs() -> Traversable:
    """The folder of packaged configs."""
    try:
        return resources.files("torchconn.configs")
    except ModuleNotFoundError:  # a source checkout that was never installed
        return resources.files("torchconn").parent / "configs"  # type: ignore[attr-defined]


def config_names() -> list[str]:
    """Names (file stems) of the packaged ``.toml`` configs, sorted."""
    return sorted(f.name[:-5] for f in configs().iterdir() if f.name.endswith(".toml"))


def read_config(name: str) -> dict:
    """Parse the packaged config ``name`` (``"gaits"``, ``"quick"``, ...; ``.toml`` optional)."""
    stem = name[:-5] if name.endswith(".toml") else name
    if stem not in config_names():
        raise FileNotFoundError(
            f"no packaged config {name!r}; packaged: {', '.join(config_names())}"
        )
    return tomllib.loads(configs().joinpath(f"{stem}.toml").read_text(encoding="utf-8"))
