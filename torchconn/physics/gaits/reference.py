"""The reference gaits (docs/conventions.md, "Reference gaits") and the optimised gaits.

The optimised gaits ship with the package in ``gaits.toml`` (the repository's ``configs/``),
read with :mod:`importlib.resources`; every reader takes a ``path`` to use another file, e.g.
one written by ``python -m torchconn.physics.gaits.optimize --out FILE.toml``.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from ..._files import read_toml
from ..._resources import read_config
from .gait import FourierGait, ModalGait, PolarGait

__all__ = [
    "three_link_gait",
    "nine_link_modes",
    "reference_gait",
    "optimised_gait",
    "load_gaits",
    "THREE_LINK_EXTREMAL",
    "THREE_LINK_EFFICIENT",
]

#: (a1, b1, a3, b3, a5, b5) of the Tam–Hosoi-form 3-link gaits
THREE_LINK_EXTREMAL = (2.017955906441066, 1.353385144748382, 0.013112519773635,
                       0.263823759269392, -0.031456173657342, -0.003626287235861)
THREE_LINK_EFFICIENT = (1.495398722861924, 1.326600886340017, 0.083253854456986,
                        0.089227148110158, -0.034695750579259, -0.044759551791058)

def three_link_gait(kind: str = "extremal") -> FourierGait:
    """The Tam–Hosoi-form 3-link gait: ``r = R45 (a(t'), b(t'))`` with ``t' = −t``.

    ``a = a1 cos t' + a3 cos 3t' + a5 cos 5t'``, ``b = b1 sin t' + b3 sin 3t' + b5 sin 5t'``.
    ``kind`` is ``"extremal"`` (x-displacement extremal) or ``"efficient"``.
    """
    params = {"extremal": THREE_LINK_EXTREMAL, "efficient": THREE_LINK_EFFICIENT}.get(kind)
    if params is None:
        raise ValueError(f"kind must be 'extremal' or 'efficient', got {kind!r}")
    a1, b1, a3, b3, a5, b5 = params
    ab = torch.zeros(11, 2, dtype=torch.float64)
    for k, a, b in ((1, a1, b1), (3, a3, b3), (5, a5, b5)):
        ab[2 * k - 1, 0] = a  # cos k t' = cos k t
        ab[2 * k, 1] = -b  # sin k t' = -sin k t
    r45 = (math.sqrt(2) / 2) * torch.tensor([[1.0, -1.0], [1.0, 1.0]], dtype=torch.float64)
    return FourierGait(ab @ r45.T)


def nine_link_modes(dtype=torch.float64) -> torch.Tensor:
    """The 9-link two-mode basis ``Φ (8, 2)``: ``r_k = a1 sin(2πk/8) + a2 cos(2πk/8)``."""
    k = torch.arange(1, 9, dtype=dtype)
    return torch.stack([torch.sin(2 * math.pi * k / 8), torch.cos(2 * math.pi * k / 8)], -1)


def load_gaits(path: Path | str | None = None) -> dict:
    """The optimised gaits' table: the packaged ``gaits.toml``, or the TOML file ``path``."""
    if path is None:
        return read_config("gaits")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"gaits file {path} not found; write one with "
            "`python -m torchconn.physics.gaits.optimize --out FILE.toml`, or pass path=None "
            "for the gaits that ship with torchconn"
        )
    return read_toml(path, "gaits file")


def optimised_gait(name: str, path: Path | str | None = None) -> PolarGait:
    """An optimised planar gait (e.g. ``"nine_link_x_extremal"``) from the packaged
    ``gaits.toml`` or the file ``path``."""
    table = load_gaits(path)
    if name not in table:
        where = "the packaged gaits.toml" if path is None else str(path)
        raise KeyError(f"no gait {name!r} in {where}; stored: {sorted(table)}")
    entry = table[name]
    return PolarGait([0.0, 0.0], entry["radius_logit"], entry["direction"], entry["max_radius"])


def reference_gait(system: str, path: Path | str | None = None):
    """The reference gait of a system: ``"3link"`` (Tam–Hosoi extremal) or ``"9link"``.

    The 9-link reference is the x-extremal gait in the two-mode plane, found by the gait
    optimiser and stored in the packaged ``gaits.toml`` (or the file ``path``).
    """
    if system in ("3link", "3-link", "three_link"):
        return three_link_gait("extremal")
    if system in ("9link", "9-link", "nine_link"):
        return ModalGait(nine_link_modes(), optimised_gait("nine_link_x_extremal", path))
    raise ValueError(f"system must be '3link' or '9link', got {system!r}")
