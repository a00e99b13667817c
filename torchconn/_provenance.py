"""Provenance shared by every command: versions, a hash of the code, seeds, the JSON sidecar.

Every command that writes results (``torchconn-sweep``'s ``run.json``, ``torchconn-discrepancy``'s
``report.json``, ``torchconn-fit``'s sidecar) writes it through :func:`write_sidecar`, so each
carries the same ``versions`` and ``source_hash`` and is written atomically
(:func:`torchconn._output.write_bytes_atomic`), so a crash never leaves a half-written JSON.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import platform
from collections.abc import Mapping
from importlib import metadata, resources
from pathlib import Path

import numpy as np
import torch

from ._output import write_bytes_atomic
from ._version import __version__

__all__ = ["versions", "source_hash", "spawn_seeds", "jsonable", "write_json", "write_sidecar"]


def versions() -> dict[str, str]:
    """Versions of torchconn, Python and the libraries that determine its numbers (scipy's
    and matplotlib's from their installed metadata: a command that uses neither loads
    neither)."""
    return {"torchconn": __version__, "python": platform.python_version(),
            "torch": torch.__version__, "numpy": np.__version__,
            "scipy": metadata.version("scipy"), "matplotlib": metadata.version("matplotlib")}


@functools.cache
def source_hash() -> str:
    """SHA-256 (16 hex digits) of the package's Python sources, paths included.

    Changes whenever any ``.py`` file of the installed (or checked-out) package changes, so a
    result fingerprinted with it is never reused by different code.
    """
    h = hashlib.sha256()

    def walk(node, prefix: str) -> None:
        for child in sorted(node.iterdir(), key=lambda c: c.name):
            rel = f"{prefix}{child.name}"
            if child.is_dir():
                if child.name != "__pycache__":
                    walk(child, rel + "/")
            elif child.name.endswith(".py"):
                h.update(rel.encode() + b"\0" + child.read_bytes() + b"\0")

    walk(resources.files("torchconn"), "")
    return h.hexdigest()[:16]


def spawn_seeds(root: int, shape: tuple[int, ...], key: tuple[int, ...] = ()) -> np.ndarray:
    """Independent seeds of the given shape derived from one root seed.

    Cell ``idx`` gets ``SeedSequence(root, spawn_key=key + idx)``: keyed by position, so a
    cell's seed does not depend on which other cells run, in which order, or on which worker.

    Returns:
        object array ``shape`` of non-negative Python ints (< 2**63).
    """
    seeds = np.empty(shape, dtype=object)
    for idx in np.ndindex(*shape):
        ss = np.random.SeedSequence(root, spawn_key=tuple(key) + idx)
        seeds[idx] = int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1))
    return seeds


def jsonable(x):
    """``x`` with tensors and arrays as lists, mapping keys as strings, non-finite floats as
    ``None`` (JSON has no NaN); anything else unknown as its ``str``."""
    if isinstance(x, Mapping):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if hasattr(x, "detach"):  # a torch.Tensor
        x = x.detach().cpu()
    if hasattr(x, "tolist"):  # tensors, arrays and NumPy scalars
        return jsonable(x.tolist())
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if x is None or isinstance(x, (str, int, bool)):
        return x
    return str(x)


def write_json(path: str | Path, obj) -> Path:
    """Write ``jsonable(obj)`` to ``path`` atomically
    (:func:`~torchconn._output.write_bytes_atomic`)."""
    text = json.dumps(jsonable(obj), indent=2, allow_nan=False)
    return write_bytes_atomic(path, (text + "\n").encode())


def write_sidecar(path: str | Path, fields: Mapping) -> Path:
    """A command's JSON sidecar: ``fields`` (config, seeds, results ...) plus ``versions`` and
    ``source_hash``, written atomically by :func:`write_json`."""
    return write_json(path, {**fields, "versions": versions(), "source_hash": source_hash()})
