"""Sweep configuration: TOML files (packaged by name, or any path), with overrides.

A sweep is a list of experiments; each runs one system under one kind of noise at several
levels, several trials per level:

- ``noise_kind = "system"``: levels are factors of η (the SDE's noise), observation noise
  fixed at the experiment's ``omega``;
- ``noise_kind = "observation"``: levels are values of ω (motion-capture noise std), η fixed
  at ``eta_factor · η``.

Every field is documented in the packaged ``default.toml`` (the repository's
``configs/default.toml``, the sweep run with no config). The configs that ship with torchconn
(``default``, ``quick``, ``fig3``, ``fig4a``, ``fig4b``) are named by their stem; a path names
any other TOML file.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._provenance import source_hash
from .._resources import config_names, configs, read_config
from ..regression.estimator import ConnectionEstimator, estimator_from_settings, estimator_settings

__all__ = [
    "SimulationSettings", "Experiment", "SweepConfig", "load_config", "resolve_config",
    "sweep_config_names",
    "apply_overrides",
    "DEFAULT_TOML", "SYSTEMS", "NOISE_KINDS",
]

SYSTEMS = ("3link", "9link")
NOISE_KINDS = ("system", "observation")

#: the sweep ``torchconn-sweep`` runs with no ``--config`` (the packaged ``default.toml``,
#: which documents every field; about 80 s on 2 cores)
DEFAULT_TOML = configs().joinpath("default.toml").read_text(encoding="utf-8")


@dataclass(frozen=True, kw_only=True)
class SimulationSettings:
    """Rollout settings (defaults: the paper's, docs/conventions.md): α, η, cycles, sampling,
    fine steps."""

    alpha: float = 0.05
    eta: float = 0.025
    n_cycles: int = 30
    samples_per_cycle: int = 64
    substeps: int = 8


@dataclass(frozen=True, kw_only=True)
class Experiment:
    """One system under one kind of noise at several levels (see the module docstring)."""

    system: str
    noise_kind: str
    levels: tuple[float, ...]
    trials: int
    omega: float = 0.0
    eta_factor: float = 1.0
    traces: bool = False
    simulation: SimulationSettings = SimulationSettings()
    name: str = ""

    def __post_init__(self) -> None:
        if self.system not in SYSTEMS:
            raise ValueError(f"experiment system must be one of {SYSTEMS}, got {self.system!r}")
        if self.noise_kind not in NOISE_KINDS:
            raise ValueError(
                f"experiment noise_kind must be one of {NOISE_KINDS}, got {self.noise_kind!r}"
            )
        if not self.levels or any(v < 0 for v in self.levels):
            raise ValueError(f"experiment levels must be non-empty and >= 0, got {self.levels}")
        if self.trials < 1:
            raise ValueError(f"experiment trials must be >= 1, got {self.trials}")
        if not self.name:
            object.__setattr__(self, "name", f"{self.system}-{self.noise_kind}")


@dataclass(frozen=True, kw_only=True)
class SweepConfig:
    """A whole sweep: experiments, shared simulation and estimator settings, root seed.

    ``estimator`` is the ``[estimator]`` table (see
    :func:`~torchconn.regression.estimator.estimator_from_settings`), or a
    :class:`ConnectionEstimator`; it is validated and stored in full, normalised form, so equal
    estimators written differently (flat 0.1 keys, nested tables) hash alike.
    """

    name: str
    seed: int
    experiments: tuple[Experiment, ...]
    estimator: dict = field(default_factory=dict)
    phase: str = "estimated"
    error_bins: int = 16
    raw: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        est = self.estimator
        if not isinstance(est, ConnectionEstimator):
            est = estimator_from_settings(est, where="[estimator]")
        object.__setattr__(self, "estimator", estimator_settings(est))
        if self.phase not in ("estimated", "true"):
            raise ValueError(f"phase must be 'estimated' (Phaser) or 'true', got {self.phase!r}")
        names = [e.name for e in self.experiments]
        if len(set(names)) != len(names):
            raise ValueError(f"experiment names must be unique, got {names}")

    def fingerprint(self, experiment: Experiment) -> str:
        """Hash of everything that determines an experiment's results (for resuming safely),
        the package's source code included."""
        payload = {
            "source": source_hash(),
            "experiment": dataclasses.asdict(experiment),
            "estimator": self.estimator,
            "seed": self.seed, "phase": self.phase, "error_bins": self.error_bins,
            "index": [e.name for e in self.experiments].index(experiment.name),
        }
        text = json.dumps(payload, sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def make_estimator(self) -> ConnectionEstimator:
        """A fresh (unfitted) estimator with this sweep's settings."""
        return estimator_from_settings(self.estimator, where="[estimator]")


def _parse(raw: dict[str, Any]) -> SweepConfig:
    raw = copy.deepcopy(raw)
    known = {"name", "seed", "phase", "error_bins", "simulation", "estimator", "experiment"}
    unknown = set(raw) - known
    if unknown:
        raise ValueError(f"unknown top-level config keys {sorted(unknown)}; known: {sorted(known)}")
    sim = SimulationSettings(**raw.get("simulation", {}))
    experiments = []
    for i, exp in enumerate(raw.get("experiment", [])):
        exp = dict(exp)
        sim_exp = dataclasses.replace(sim, **exp.pop("simulation", {}))
        try:
            experiments.append(
                Experiment(levels=tuple(float(v) for v in exp.pop("levels", ())),
                           simulation=sim_exp, **exp)
            )
        except TypeError as err:
            raise ValueError(f"experiment {i}: {err}") from None
    if not experiments:
        raise ValueError("the config defines no [[experiment]]")
    return SweepConfig(
        name=raw.get("name", "sweep"), seed=int(raw.get("seed", 0)),
        experiments=tuple(experiments), estimator=raw.get("estimator", {}),
        phase=raw.get("phase", "estimated"), error_bins=int(raw.get("error_bins", 16)), raw=raw,
    )


def apply_overrides(raw: dict, overrides: list[str]) -> dict:
    """Apply ``key.path=value`` overrides (value parsed as TOML, else a string).

    ``experiment.trials=2`` sets a key in every experiment; ``experiment.1.trials=2`` in one.
    """
    raw = copy.deepcopy(raw)
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"override {item!r} must look like section.key=value")
        path, text = item.split("=", 1)
        try:
            value = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            value = text
        keys = path.strip().split(".")
        targets = [raw]
        for key in keys[:-1]:
            nxt = []
            for t in targets:
                if isinstance(t, list):
                    nxt.extend([t[int(key)]] if key.isdigit() else [x.setdefault(key, {}) for x in t])
                else:
                    nxt.append(t.setdefault(key, {}))
            targets = nxt
        for t in targets:
            for tt in (t if isinstance(t, list) else [t]):
                tt[keys[-1]] = value
    return raw


def sweep_config_names() -> list[str]:
    """Names of the packaged sweep configs (those with an ``[[experiment]]``)."""
    return [n for n in config_names() if "experiment" in read_config(n)]


def resolve_config(config: str | Path) -> tuple[str, str]:
    """The TOML text a ``--config`` value names, and where it came from.

    ``config`` is a path to a TOML file, or the name of a packaged sweep config (``"quick"`` or
    ``"quick.toml"``); an existing file wins over a packaged name.
    """
    path = Path(config)
    if path.is_file():
        return path.read_text(encoding="utf-8"), str(path)
    name = str(config)
    stem = name[:-5] if name.endswith(".toml") else name
    if stem not in sweep_config_names():
        raise FileNotFoundError(
            f"config {name!r} is neither a TOML file nor a packaged sweep config; packaged: "
            f"{', '.join(sweep_config_names())}"
        )
    return configs().joinpath(f"{stem}.toml").read_text(encoding="utf-8"), f"{stem}.toml (packaged)"


def load_config(config: str | Path | None = None, overrides: list[str] = ()) -> SweepConfig:
    """Read a sweep config: a path to a TOML file, the name of a packaged config
    (``"quick"``, ``"fig4a"``, ...), or None for the default sweep (``"default"``)."""
    if config is None:
        text, source = DEFAULT_TOML, "default.toml (packaged)"
    else:
        text, source = resolve_config(config)
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"config {source} is not valid TOML: {err}") from None
    return _parse(apply_overrides(raw, list(overrides)))
