"""Sweep configuration: TOML files in ``configs/`` (or the embedded default), with overrides.

A sweep is a list of experiments; each runs one system under one kind of noise at several
levels, several trials per level:

- ``noise_kind = "system"``: levels are factors of η (the SDE's noise), observation noise
  fixed at the experiment's ``omega``;
- ``noise_kind = "observation"``: levels are values of ω (motion-capture noise std), η fixed
  at ``eta_factor · η``.

Every field is documented in ``configs/quick.toml``. :func:`load_config` validates the whole
config before any work: unknown keys (listed with the valid ones and the closest match),
types and ranges of every field, ``--set`` paths and indices, and TOML syntax (with file and
line); every problem is an :class:`~torchconn._cli.InputError` naming the key.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import __version__
from .._cli import InputError, check_keys, did_you_mean
from .._provenance import source_hash
from ..regression.estimator import EstimatorSettings

__all__ = [
    "SimulationSettings", "Experiment", "SweepConfig", "load_config", "apply_overrides",
    "DEFAULT_TOML", "SYSTEMS", "NOISE_KINDS", "TRIAL_TILE",
]

SYSTEMS = ("3link", "9link")
#: block sizes are multiples of this: MKL's GEMM computes rows in tiles of 4, and a trial's
#: numbers are bit-identical between blocks only when every block starts on a tile boundary
TRIAL_TILE = 4
NOISE_KINDS = ("system", "observation")

#: the sweep `python -m torchconn.sweep` runs with no arguments (about 80 s on 2 cores)
DEFAULT_TOML = """
name = "default"
seed = 20190101
phase = "estimated"
error_bins = 24

[simulation]
alpha = 0.05
eta = 0.025
n_cycles = 30
samples_per_cycle = 64
substeps = 8

[estimator]

[[experiment]]
system = "3link"
noise_kind = "system"
levels = [0.25, 0.5, 1.0, 2.0, 4.0]
trials = 12
traces = true

[[experiment]]
system = "9link"
noise_kind = "system"
levels = [0.25, 0.5, 1.0, 2.0, 4.0]
trials = 12
traces = true

[[experiment]]
system = "9link"
noise_kind = "observation"
levels = [0.0, 0.005, 0.01, 0.02, 0.04]
trials = 12
"""


PHASES = ("estimated", "true")
_TOP = {"name": str, "seed": int, "phase": str, "error_bins": int, "block_trials": int,
        "simulation": dict, "estimator": dict, "experiment": list}


def _at_least(key: str, value, low, high=None) -> None:
    kind = "an integer" if isinstance(low, int) else "a number"
    if high is None:
        high = math.inf
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (
            isinstance(low, int) and not isinstance(value, int)):
        raise InputError(f"{key} must be {kind}, got {value!r} ({type(value).__name__})")
    if not low <= value <= high or (isinstance(value, float) and not math.isfinite(value)):
        rng = f">= {low}" if high == math.inf else f"in [{low}, {high}]"
        raise InputError(f"{key} must be {kind} {rng}, got {value!r}")


def _folder_name(key: str, value: str) -> None:
    if not value or any(c in value for c in '/\\:*?"<>|\0') or value in (".", ".."):
        raise InputError(f"{key} must be a non-empty name usable as a folder name (no / \\ : * ? "
                         f'" < > |), got {value!r}')



@dataclass(frozen=True, kw_only=True)
class SimulationSettings:
    """Rollout settings (CONVENTIONS defaults): α, η, cycles, sampling, fine steps."""

    alpha: float = 0.05
    eta: float = 0.025
    n_cycles: int = 30
    samples_per_cycle: int = 64
    substeps: int = 8

    def __post_init__(self) -> None:
        _at_least("alpha", self.alpha, 0.0)
        _at_least("eta", self.eta, 0.0)
        _at_least("n_cycles", self.n_cycles, 2, 100_000)
        _at_least("samples_per_cycle", self.samples_per_cycle, 8, 100_000)
        _at_least("substeps", self.substeps, 1, 1000)


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
            raise InputError(f"system must be one of {SYSTEMS}, got {self.system!r}"
                             + did_you_mean(self.system, SYSTEMS))
        if self.noise_kind not in NOISE_KINDS:
            raise InputError(f"noise_kind must be one of {NOISE_KINDS}, got {self.noise_kind!r}"
                             + did_you_mean(self.noise_kind, NOISE_KINDS))
        if not self.levels:
            raise InputError("levels must be a non-empty list of numbers >= 0")
        for v in self.levels:
            _at_least("levels", v, 0.0)
        if len(set(self.levels)) != len(self.levels):
            raise InputError(f"levels must be distinct, got {list(self.levels)}")
        _at_least("trials", self.trials, 1, 100_000)
        _at_least("omega", self.omega, 0.0)
        _at_least("eta_factor", self.eta_factor, 0.0)
        if not self.name:
            object.__setattr__(self, "name", f"{self.system}-{self.noise_kind}")
        _folder_name("name", self.name)


@dataclass(frozen=True, kw_only=True)
class SweepConfig:
    """A whole sweep: experiments, shared simulation and estimator settings, root seed.

    ``block_trials`` is the number of trials per stored cell (a multiple of
    :data:`TRIAL_TILE`); the results do not depend on it.
    """

    name: str
    seed: int
    experiments: tuple[Experiment, ...]
    estimator: EstimatorSettings = EstimatorSettings()
    phase: str = "estimated"
    error_bins: int = 16
    block_trials: int = 8
    raw: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        _folder_name("name", self.name)
        _at_least("seed", self.seed, 0, 2**63 - 1)
        if self.phase not in PHASES:
            raise InputError(f"phase must be one of {PHASES}, got {self.phase!r}"
                             + did_you_mean(self.phase, PHASES))
        _at_least("error_bins", self.error_bins, 2, 10_000)
        _at_least("block_trials", self.block_trials, TRIAL_TILE, 100_000)
        if self.block_trials % TRIAL_TILE:
            raise InputError(f"block_trials must be a multiple of {TRIAL_TILE} (so that results "
                             f"do not depend on it), got {self.block_trials}")
        if not self.experiments:
            raise InputError("the config defines no [[experiment]]")
        names = [e.name for e in self.experiments]
        if len(set(names)) != len(names):
            raise InputError(f"experiment names must be unique, got {names}; give repeated "
                             "systems a distinct name = \"...\"")
        for i, e in enumerate(self.experiments):
            sim = e.simulation
            if sim.n_cycles < self.estimator.min_cycles + 1:
                raise InputError(
                    f"experiment {i} ({e.name}): n_cycles = {sim.n_cycles} is too few; the "
                    f"estimator needs at least min_cycles + 1 = {self.estimator.min_cycles + 1:g}")
            if self.error_bins > sim.samples_per_cycle:
                raise InputError(f"error_bins = {self.error_bins} exceeds samples_per_cycle = "
                                 f"{sim.samples_per_cycle} of experiment {i} ({e.name}); some "
                                 "bins would be empty")

    def fingerprint(self, experiment: Experiment) -> dict:
        """Everything that determines an experiment's results (for resuming safely),
        torchconn's version and source code included."""
        return {
            "torchconn": __version__, "source": source_hash(),
            "experiment": dataclasses.asdict(experiment),
            "estimator": dataclasses.asdict(self.estimator),
            "seed": self.seed, "phase": self.phase, "error_bins": self.error_bins,
            "index": [e.name for e in self.experiments].index(experiment.name),
        }


def _check_type(value, tp, key: str):
    """``value`` converted to the annotation ``tp`` (int, float, bool, str, tuple[float, ...],
    ``X | None``), or an :class:`InputError` naming ``key``."""
    args = typing.get_args(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        return _check_type(value, next(a for a in args if a is not type(None)), key)
    if tp is bool:
        ok = isinstance(value, bool)
    elif tp is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif tp is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
        if ok and not math.isfinite(value):
            raise InputError(f"{key} must be a finite number, got {value!r}")
    elif tp is str:
        ok = isinstance(value, str)
    elif typing.get_origin(tp) is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(f"{key} must be a list, got {value!r} ({type(value).__name__})")
        return tuple(_check_type(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
    else:  # pragma: no cover - a field type this validator does not know
        raise TypeError(f"no validation for {key}: {tp}")
    if not ok:
        name = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}[tp]
        raise InputError(f"{key} must be {name}, got {value!r} ({type(value).__name__})")
    return value


def build_settings(cls, table, where: str, skip: tuple[str, ...] = ()):
    """A frozen settings dataclass ``cls`` from a TOML table: unknown keys, types and the
    class's own range checks reported with ``where`` (e.g. ``"[simulation]"``)."""
    if not isinstance(table, dict):
        raise InputError(f"{where} must be a table of settings, got {table!r}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls) if f.init and f.name not in skip]
    check_keys(table, names, where)
    values = {k: _check_type(v, hints[k], f"{where} {k}") for k, v in table.items()}
    try:
        return cls(**values)
    except InputError as err:
        raise InputError(f"{where} {err}") from None
    except ValueError as err:
        raise InputError(f"{where}: {err}") from None


def _parse(raw: dict[str, Any]) -> SweepConfig:
    raw = copy.deepcopy(raw)
    check_keys(raw, _TOP, "top level")
    for key, tp in _TOP.items():
        if key in raw and tp in (dict, list) and not isinstance(raw[key], tp):
            what = "a [section] table" if tp is dict else "an array of [[experiment]] tables"
            raise InputError(f"{key} must be {what}, got {raw[key]!r}")
    sim = build_settings(SimulationSettings, raw.get("simulation", {}), "[simulation]")
    estimator = build_settings(EstimatorSettings, raw.get("estimator", {}), "[estimator]")
    experiments = []
    for i, exp in enumerate(raw.get("experiment", [])):
        where = f"[[experiment]] {i}"
        if not isinstance(exp, dict):
            raise InputError(f"{where} must be a table, got {exp!r}")
        exp = dict(exp)
        own = exp.pop("simulation", {})
        if not isinstance(own, dict):
            raise InputError(f"{where} simulation must be a table, got {own!r}")
        sim_exp = build_settings(SimulationSettings, {**dataclasses.asdict(sim), **own},
                                 f"{where} [simulation]")
        check_keys(exp, [f.name for f in dataclasses.fields(Experiment)], where)
        for key in ("system", "noise_kind", "levels", "trials"):
            if key not in exp:
                raise InputError(f"{where}: missing required key {key!r}")
        experiments.append(build_settings(Experiment, exp, where, skip=("simulation",)))
        object.__setattr__(experiments[-1], "simulation", sim_exp)
    values = {k: _check_type(raw[k], tp, k) for k, tp in _TOP.items()
              if k in raw and tp not in (dict, list)}
    return SweepConfig(
        name=values.get("name", "sweep"), seed=values.get("seed", 0),
        experiments=tuple(experiments), estimator=estimator,
        phase=values.get("phase", "estimated"), error_bins=values.get("error_bins", 16),
        block_trials=values.get("block_trials", 8), raw=raw,
    )


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


def load_config(path: str | Path | None = None, overrides: list[str] = ()) -> SweepConfig:
    """Read and validate a TOML sweep config (the embedded default when ``path`` is None).

    Raises:
        InputError: naming the file (and line, for TOML syntax), the key and what was
            expected; ``--set`` problems name the override.
    """
    if path is None:
        raw = tomllib.loads(DEFAULT_TOML)
        source = "the default config"
    else:
        path = Path(path)
        source = str(path)
        if not path.exists():
            raise InputError(f"config file {path} not found")
        if path.is_dir():
            raise InputError(f"config {path} is a folder; expected a TOML file such as "
                             "configs/quick.toml")
        try:
            raw = tomllib.loads(path.read_bytes().decode("utf-8"))
        except UnicodeDecodeError:
            raise InputError(f"config {path}: not UTF-8 text; TOML files must be UTF-8") \
                from None
        except tomllib.TOMLDecodeError as err:
            raise InputError(f"config {path}: invalid TOML: {err}") from None
        except OSError as err:
            raise InputError(f"config {path}: cannot read it ({err.strerror})") from None
    raw = apply_overrides(raw, list(overrides))
    try:
        return _parse(raw)
    except InputError as err:
        sets = [o for o in overrides if "=" in o]
        hint = f" (after --set {', '.join(sets)})" if sets else ""
        raise InputError(f"{source}: {err}{hint}") from None
