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

:func:`load_config` validates the whole config before any work: unknown keys (listed with the
valid ones and the closest match), types and ranges of every field, ``--set`` paths and
indices, and TOML syntax (with file and line); every problem is an
:class:`~torchconn._cli.InputError` naming the file and the key.
"""

from __future__ import annotations

import copy
import dataclasses
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._cli import InputError, check_keys, did_you_mean, resolve_device
from .._files import read_text
from .._options import check_value
from .._provenance import source_hash
from .._resources import config_names, configs, read_config
from .._version import __version__
from ..cli.common import apply_overrides
from ..regression.estimator import ConnectionEstimator, estimator_from_settings, estimator_settings

__all__ = [
    "SimulationSettings", "Experiment", "SweepConfig", "load_config", "resolve_config",
    "sweep_config_names", "apply_overrides", "DEFAULT_TOML", "SYSTEMS", "NOISE_KINDS",
    "TRIAL_TILE",
]

SYSTEMS = ("3link", "9link")
NOISE_KINDS = ("system", "observation")
PHASES = ("estimated", "true")
#: block sizes are multiples of this: MKL's GEMM computes rows in tiles of 4, and a trial's
#: numbers are bit-identical between blocks only when every block starts on a tile boundary
TRIAL_TILE = 4

#: the sweep ``torchconn-sweep`` runs with no ``--config`` (the packaged ``default.toml``,
#: which documents every field; about 30 s on 2 cores)
DEFAULT_TOML = configs().joinpath("default.toml").read_text(encoding="utf-8")

_TOP = {"name": str, "seed": int, "phase": str, "error_bins": int, "block_trials": int,
        "device": str, "simulation": dict, "estimator": dict, "experiment": list}


def _in_range(key: str, value, tp, low, high=None) -> None:
    """``value`` is a ``tp`` (int or float) in ``[low, high]``, else a ``ValueError``."""
    check_value(key, value, tp, {"ge": low, **({"le": high} if high is not None else {})})


def _folder_name(key: str, value: str) -> None:
    if not value or any(c in value for c in '/\\:*?"<>|\0') or value in (".", ".."):
        raise InputError(f"{key} must be a non-empty name usable as a folder name (no / \\ : * ? "
                         f'" < > |), got {value!r}')


@dataclass(frozen=True, kw_only=True)
class SimulationSettings:
    """Rollout settings (defaults: the paper's, docs/conventions.md): α, η, cycles, sampling,
    fine steps."""

    alpha: float = 0.05
    eta: float = 0.025
    n_cycles: int = 30
    samples_per_cycle: int = 64
    substeps: int = 8

    def __post_init__(self) -> None:
        # > 0: the rollouts start from the stationary law N(0, η²/(2α))
        check_value("alpha", self.alpha, float, {"gt": 0.0})
        _in_range("eta", self.eta, float, 0.0)
        _in_range("n_cycles", self.n_cycles, int, 2, 100_000)
        _in_range("samples_per_cycle", self.samples_per_cycle, int, 8, 100_000)
        _in_range("substeps", self.substeps, int, 2, 1000)
        if self.substeps % 2:
            raise InputError(f"substeps must be even (each sample sits mid-way through its "
                             f"fine steps), got {self.substeps}")


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
            _in_range("levels", v, float, 0.0)
        if len(set(self.levels)) != len(self.levels):
            raise InputError(f"levels must be distinct, got {list(self.levels)}")
        _in_range("trials", self.trials, int, 1, 100_000)
        _in_range("omega", self.omega, float, 0.0)
        _in_range("eta_factor", self.eta_factor, float, 0.0)
        if not self.name:
            object.__setattr__(self, "name", f"{self.system}-{self.noise_kind}")
        _folder_name("name", self.name)


@dataclass(frozen=True, kw_only=True)
class SweepConfig:
    """A whole sweep: experiments, shared simulation and estimator settings, root seed.

    ``estimator`` is the ``[estimator]`` table (see
    :func:`~torchconn.regression.estimator.estimator_from_settings`), or a
    :class:`ConnectionEstimator`; it is validated and stored in full, normalised form, so equal
    estimators written differently (flat 0.1 keys, nested tables) hash alike.
    ``block_trials`` is the number of trials per stored cell (a multiple of
    :data:`TRIAL_TILE`); the results do not depend on it. ``device`` (``cpu``, ``cuda``,
    ``cuda:N``) is where the cells are simulated and fitted; it must be available on this
    machine. CPU and CUDA draw different random numbers from the same seeds, so the device is
    part of what determines the results (and of the cells' fingerprints).
    """

    name: str
    seed: int
    experiments: tuple[Experiment, ...]
    estimator: dict = field(default_factory=dict)
    phase: str = "estimated"
    error_bins: int = 16
    block_trials: int = 20
    device: str = "cpu"
    raw: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        est = self.estimator
        if not isinstance(est, ConnectionEstimator):
            est = estimator_from_settings(est, where="[estimator]")
        object.__setattr__(self, "estimator", estimator_settings(est))
        _folder_name("name", self.name)
        _in_range("seed", self.seed, int, 0, 2**63 - 1)
        if self.phase not in PHASES:
            raise InputError(f"phase must be one of {PHASES}, got {self.phase!r}"
                             + did_you_mean(self.phase, PHASES))
        _in_range("error_bins", self.error_bins, int, 2, 10_000)
        _in_range("block_trials", self.block_trials, int, TRIAL_TILE, 100_000)
        resolve_device(self.device, "device")
        if self.block_trials % TRIAL_TILE:
            raise InputError(f"block_trials must be a multiple of {TRIAL_TILE} (so that results "
                             f"do not depend on it), got {self.block_trials}")
        if not self.experiments:
            raise InputError("the config defines no [[experiment]]")
        names = [e.name for e in self.experiments]
        if len(set(names)) != len(names):
            raise InputError(f"experiment names must be unique, got {names}; give repeated "
                             "systems a distinct name = \"...\"")
        min_cycles = self.estimator["phaser"].get("min_cycles", 0.0)
        for i, e in enumerate(self.experiments):
            sim = e.simulation
            if sim.n_cycles < min_cycles + 1:
                raise InputError(
                    f"experiment {i} ({e.name}): n_cycles = {sim.n_cycles} is too few; the "
                    f"estimator needs at least min_cycles + 1 = {min_cycles + 1:g}")
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
            "estimator": self.estimator,
            "seed": self.seed, "phase": self.phase, "error_bins": self.error_bins,
            "index": [e.name for e in self.experiments].index(experiment.name),
            # the random streams differ between device types (not between GPUs of one type)
            "device": resolve_device(self.device, "device").type,
        }

    def make_estimator(self) -> ConnectionEstimator:
        """A fresh (unfitted) estimator with this sweep's settings."""
        return estimator_from_settings(self.estimator, where="[estimator]")


def _check_type(value, tp, key: str):
    """``value`` checked against the annotation ``tp`` (``tuple[float, ...]`` element-wise),
    floats returned as ``float``."""
    if typing.get_origin(tp) is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(f"{key} must be a list, got {value!r} ({type(value).__name__})")
        return tuple(_check_type(v, typing.get_args(tp)[0], f"{key}[{i}]")
                     for i, v in enumerate(value))
    check_value(key, value, tp)
    floats = tp is float or float in typing.get_args(tp)
    return float(value) if floats and isinstance(value, int) and not isinstance(value, bool) \
        else value


def build_settings(cls, table, where: str, skip: tuple[str, ...] = ()):
    """A frozen settings dataclass ``cls`` from a TOML table: unknown keys, types and the
    class's own range checks reported with ``where`` (e.g. ``"[simulation]"``)."""
    if not isinstance(table, dict):
        raise InputError(f"{where} must be a table of settings, got {table!r}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls) if f.init and f.name not in skip]
    check_keys(table, names, where)
    try:
        values = {k: _check_type(v, hints[k], k) for k, v in table.items()}
        return cls(**values)
    except ValueError as err:
        raise InputError(f"{where} {err}") from None


def _parse(raw: dict[str, Any]) -> SweepConfig:
    raw = copy.deepcopy(raw)
    check_keys(raw, _TOP, "top level")
    for key, tp in _TOP.items():
        if key in raw and tp in (dict, list) and not isinstance(raw[key], tp):
            what = "a [section] table" if tp is dict else "an array of [[experiment]] tables"
            raise InputError(f"{key} must be {what}, got {raw[key]!r}")
    sim = build_settings(SimulationSettings, raw.get("simulation", {}), "[simulation]")
    experiments = []
    for i, exp in enumerate(raw.get("experiment", [])):
        where = f"[[experiment]] {i}"
        if not isinstance(exp, dict):
            raise InputError(f"{where} must be a table, got {exp!r}")
        exp = dict(exp)
        check_keys(exp, [f.name for f in dataclasses.fields(Experiment)], where)
        own = exp.pop("simulation", {})
        if not isinstance(own, dict):
            raise InputError(f"{where} simulation must be a table, got {own!r}")
        sim_exp = build_settings(SimulationSettings, {**dataclasses.asdict(sim), **own},
                                 f"{where} [simulation]")
        for key in ("system", "noise_kind", "levels", "trials"):
            if key not in exp:
                raise InputError(f"{where}: missing required key {key!r}")
        experiments.append(build_settings(Experiment, exp, where, skip=("simulation",)))
        object.__setattr__(experiments[-1], "simulation", sim_exp)
    values = {k: _check_type(raw[k], tp, k) for k, tp in _TOP.items()
              if k in raw and tp not in (dict, list)}
    try:
        return SweepConfig(
            name=values.get("name", "sweep"), seed=values.get("seed", 0),
            experiments=tuple(experiments), estimator=raw.get("estimator", {}),
            phase=values.get("phase", "estimated"), error_bins=values.get("error_bins", 16),
            block_trials=values.get("block_trials", 20), device=values.get("device", "cpu"),
            raw=raw,
        )
    except InputError:
        raise
    except ValueError as err:  # from the estimator's own validation
        raise InputError(str(err)) from None


def sweep_config_names() -> list[str]:
    """Names of the packaged sweep configs (those with an ``[[experiment]]``)."""
    return [n for n in config_names() if "experiment" in read_config(n)]


def resolve_config(config: str | Path) -> tuple[str, str]:
    """The TOML text a ``--config`` value names, and where it came from.

    ``config`` is a path to a TOML file, or the name of a packaged sweep config (``"quick"`` or
    ``"quick.toml"``); an existing file wins over a packaged name.
    """
    path = Path(config)
    if path.is_dir():
        raise InputError(f"config {path} is a folder, expected a TOML file or the name of a "
                         f"packaged config ({', '.join(sweep_config_names())})")
    if path.is_file():
        try:
            return read_text(path, "a TOML file", "config"), str(path)
        except (ValueError, OSError) as err:
            raise InputError(str(err)) from None
    name = str(config)
    stem = name[:-5] if name.endswith(".toml") else name
    if stem not in sweep_config_names():
        raise InputError(
            f"config {name!r} not found: neither a TOML file nor a packaged sweep config"
            f"{did_you_mean(stem, sweep_config_names())}; packaged: "
            f"{', '.join(sweep_config_names())}"
        )
    return configs().joinpath(f"{stem}.toml").read_text(encoding="utf-8"), f"{stem}.toml (packaged)"


def load_config(config: str | Path | None = None, overrides: list[str] = ()) -> SweepConfig:
    """Read and validate a sweep config: a path to a TOML file, the name of a packaged config
    (``"quick"``, ``"fig4a"``, ...), or None for the default sweep (``"default"``).

    Raises:
        InputError: naming the file (and line, for TOML syntax), the key and what was
            expected; ``--set`` problems name the override.
    """
    if config is None:
        text, source = DEFAULT_TOML, "default.toml (packaged)"
    else:
        text, source = resolve_config(config)
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"config {source}: invalid TOML: {err}") from None
    raw = apply_overrides(raw, list(overrides))
    try:
        return _parse(raw)
    except ValueError as err:  # InputError, and the type checks of _check_type
        sets = [o for o in overrides if "=" in o]
        hint = f" (after --set {', '.join(sets)})" if sets else ""
        raise InputError(f"{source}: {err}{hint}") from None
