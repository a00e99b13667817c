"""The augmented model: a nominal swimmer plus named effects, saved and loaded as JSON.

The discrepancy workflow writes the model it ends with (the nominal swimmer and the accepted
effects with their fitted parameters) so that the rest of torchconn can use it::

    model = load_augmented("out/augmented_model.json")
    model.system            # the swimmer with drag-ratio / link-length effects applied
    model.drift             # the rollout drift hook of its velocity effects (or None)
    traj = model.simulate(gait, eta=0.025, n_cycles=20, seeds=[1, 2])  # all effects on
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from torch import Tensor

from .._provenance import write_json
from ..physics.effects import get_effect
from ..physics.systems.base import LocomotionSystem
from ..physics.systems.swimmer import NLinkSwimmer
from .simulate import EffectDrift, augmented_system, effect_parameters, simulate_with_effects

__all__ = ["AugmentedModel", "load_augmented", "FORMAT"]

FORMAT = "torchconn.discrepancy.AugmentedModel/1"


@dataclass(eq=False)
class AugmentedModel:
    """A nominal swimmer and effects ``{name: (n_params,) tensor}`` (0 = absent).

    Attributes:
        nominal: the nominal :class:`~torchconn.physics.systems.NLinkSwimmer`.
        effects: fitted parameters per effect name.
        meta: provenance (verdict, data files, ...).
    """

    nominal: LocomotionSystem
    effects: dict[str, Tensor] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    @property
    def system(self) -> LocomotionSystem:
        """The swimmer with the system effects (drag ratio, link lengths) applied."""
        return augmented_system(self.nominal, self.effects)

    @property
    def drift(self) -> EffectDrift | None:
        """The :func:`torchconn.simulation.rollout.simulate` drift hook of the velocity effects, or None."""
        d = EffectDrift(self.effects)
        return d if d else None

    def simulate(self, gait, **kwargs):
        """:func:`~torchconn.discrepancy.simulate_with_effects` with this model's effects."""
        return simulate_with_effects(self.nominal, gait, self.effects, **kwargs)

    def to_dict(self) -> dict:
        sys = self.nominal
        if not isinstance(sys, NLinkSwimmer):
            raise TypeError("only NLinkSwimmer nominal models can be saved")
        effects = []
        for name, p in self.effects.items():
            e = get_effect(name)
            specs = e.param_specs(sys)
            effects.append({
                "name": name,
                "description": e.description,
                "parameters": {s.name: float(v) for s, v in zip(specs, p.tolist(), strict=True)},
                "units": {s.name: s.unit for s in specs},
                "physical": {k: float(v) for k, v in e.physical(p.detach(), sys).items()},
            })
        return {
            "format": FORMAT,
            "system": {
                "type": "NLinkSwimmer",
                "n_links": sys.n_links,
                "drag_ratio": float(sys.drag_ratio),
                "frame": sys.frame,
                "link_lengths": sys.link_lengths.detach().tolist(),
                "drag_coefficient": float(sys.drag_coefficient),
            },
            "effects": effects,
            "meta": self.meta,
        }

    @classmethod
    def from_dict(cls, data: dict) -> "AugmentedModel":
        if data.get("format") != FORMAT:
            raise ValueError(f"not an augmented model (format {data.get('format')!r}, expected "
                             f"{FORMAT!r})")
        s = data["system"]
        if s.get("type") != "NLinkSwimmer":
            raise ValueError(f"unsupported system type {s.get('type')!r}")
        nominal = NLinkSwimmer(int(s["n_links"]), drag_ratio=float(s["drag_ratio"]),
                               frame=s["frame"], link_lengths=s["link_lengths"],
                               drag_coefficient=float(s.get("drag_coefficient", 1.0)))
        effects = effect_parameters({e["name"]: e["parameters"] for e in data["effects"]}, nominal)
        return cls(nominal=nominal, effects=effects, meta=data.get("meta", {}))

    def save(self, path: str | Path) -> Path:
        return write_json(path, self.to_dict())

    def __repr__(self) -> str:
        eff = ", ".join(f"{n}={[round(x, 6) for x in p.tolist()]}" for n, p in self.effects.items())
        return f"AugmentedModel({self.nominal!r}; {eff or 'no effects'})"


def load_augmented(path: str | Path) -> AugmentedModel:
    """Read an augmented model written by :meth:`AugmentedModel.save` (``augmented_model.json``)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"cannot read an augmented model from {path}: {err}") from err
    return AugmentedModel.from_dict(data)

