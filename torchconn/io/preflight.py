"""Checks before fitting: is there enough of a periodic gait, sampled finely enough?

One place for the rules every command reports up front (``convert``, ``fit``,
``discrepancy``): :data:`CYCLE_RULES` says how many gait cycles each command needs, and
:func:`preflight` measures a recording against all of them, plus samples per cycle, gaps,
body-length spread (for converted tracking data) and whether a periodic gait is there at all.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..trajectory import Trajectory
from .trajectory_files import count_cycles, principal_signal

__all__ = ["CycleRule", "CYCLE_RULES", "MIN_SAMPLES_PER_CYCLE", "MIN_PERIODICITY",
           "MAX_LENGTH_SPREAD", "Preflight", "preflight", "periodicity", "min_cycles"]


@dataclass(frozen=True)
class CycleRule:
    """Gait cycles a command needs: in every trial (Phaser's phase estimate needs whole cycles
    in each trial) and in all trials together."""

    per_trial: float
    total: float


#: the one minimum-cycle rule per command
CYCLE_RULES = {
    # the estimator's regressions need a few cycles; Phaser needs 3 per trial
    "fit": CycleRule(per_trial=3.0, total=3.0),
    # cross-validation over blocks of whole cycles (5 folds) needs 10 in all
    "discrepancy": CycleRule(per_trial=3.0, total=10.0),
}
#: fewer samples per cycle than this: velocities and phase bins are coarse, and the error of
#: the fitted connection grows quickly (benchmarks/bench_sampling_rate.py)
MIN_SAMPLES_PER_CYCLE = 16
#: periodicity score below which no periodic gait is found (see :func:`periodicity`)
MIN_PERIODICITY = 0.25
#: (p90 − p10) / median body length above which the tracking is suspect
MAX_LENGTH_SPREAD = 0.10
#: a gap longer than this fraction of a cycle is bridged by the smoother without data
MAX_GAP_CYCLES = 0.25


def periodicity(r: Tensor, cycles: Tensor) -> Tensor:
    """``(...)`` periodicity score of ``r (..., T, d)``: ``(ρ(P) − ρ(P/2)) / 2`` of the leading
    principal component's autocorrelation ρ at the estimated period P and half of it.

    1 for a sinusoid, about 0 for noise or a random walk (ρ(P) ≈ ρ(P/2))."""
    s, valid = principal_signal(r)
    T = r.shape[-2]
    idx = torch.arange(T, device=r.device)
    first = torch.where(valid, idx, T).amin(-1)
    last = torch.where(valid, idx, -1).amax(-1)
    span = (last - first + 1).clamp_min(1).to(r.dtype)  # recorded span, gaps included
    period = (span / cycles.clamp_min(1e-9)).clamp(2, T - 1)

    def rho(lag: Tensor) -> Tensor:
        lag_i = lag.round().long().clamp(1, T - 1)  # (...)
        j = (idx + lag_i[..., None]).clamp(max=T - 1)
        both = valid & valid.gather(-1, j) & (idx + lag_i[..., None] < T)
        a, b = s, s.gather(-1, j)
        num = (a * b * both).sum(-1)
        den = torch.sqrt((a * a * both).sum(-1) * (b * b * both).sum(-1)).clamp_min(1e-300)
        return num / den

    return (rho(period) - rho(period / 2)) / 2


@dataclass(frozen=True)
class Preflight:
    """What :func:`preflight` found, per trial, and its verdict for each command.

    Attributes:
        cycles: gait cycles per trial; ``total_cycles`` their sum.
        samples_per_cycle: per trial.
        periodicity: per trial (see :func:`periodicity`).
        missing_fraction: missing samples per trial (within its recorded span).
        longest_gap: longest run of missing samples per trial, in cycles.
        length_spread: (p90 − p10) / median body length across frames, or None.
        periodic: every trial shows a periodic gait (periodicity ≥ :data:`MIN_PERIODICITY`).
        ready: command -> True when it can run.
        problems: messages that stop a command (command -> list).
        warnings: messages that do not.
        rules: command -> the :class:`CycleRule` it was checked against.
    """

    cycles: tuple[float, ...]
    total_cycles: float
    samples_per_cycle: tuple[float, ...]
    periodicity: tuple[float, ...]
    missing_fraction: tuple[float, ...]
    longest_gap: tuple[float, ...]
    length_spread: float | None
    periodic: bool
    ready: dict
    problems: dict
    warnings: tuple[str, ...]
    rules: dict

    def lines(self, command: str | None = None, *, with_warnings: bool = True) -> list[str]:
        """Readable lines: the measurements, then each command's verdict (or one command's),
        the :attr:`warnings` (``warning: ...``; left out with ``with_warnings=False``, for a
        caller that gives them through :func:`warnings.warn`) and the problems."""
        n = len(self.cycles)
        out = [f"{n} trial(s), {self.total_cycles:.1f} gait cycles in all (per trial "
               f"{_span(self.cycles, '.1f')}), {_span(self.samples_per_cycle, '.0f')} samples "
               f"per cycle, {100 * max(self.missing_fraction):.0f}% samples missing at most"]
        for cmd, rule in self.rules.items():
            if command is not None and cmd != command:
                continue
            verdict = "ok" if self.ready[cmd] else "NOT ENOUGH"
            out.append(f"{cmd} needs {rule.per_trial:g} cycles per trial and {rule.total:g} in "
                       f"all: {verdict}")
        out += [f"warning: {w}" for w in self.warnings] if with_warnings else []
        cmds = [command] if command is not None else list(self.problems)
        for cmd in cmds:
            out += [f"{cmd}: {p}" for p in self.problems.get(cmd, [])]
        return out

    def to_dict(self) -> dict:
        from dataclasses import asdict

        return asdict(self)


def _span(values, fmt: str) -> str:
    lo, hi = min(values), max(values)
    return f"{lo:{fmt}}" if f"{lo:{fmt}}" == f"{hi:{fmt}}" else f"{lo:{fmt}}-{hi:{fmt}}"


def preflight(traj: Trajectory, *, body_length: Tensor | None = None,
              rules: dict[str, CycleRule] | None = None) -> Preflight:
    """Measure a recording against every command's needs.

    Args:
        traj: recorded trials, any batch shape (flattened into trials).
        body_length: ``(F,)`` or ``(..., F)`` body length per frame (from the tracking
            conversion), or None.
        rules: command -> :class:`CycleRule` in place of :data:`CYCLE_RULES`' entry (e.g.
            ``fit``'s from the phase estimator's own ``min_cycles`` when the user set it).
    """
    rules = {**CYCLE_RULES, **(rules or {})}
    unknown = sorted(set(rules) - set(CYCLE_RULES))
    if unknown:
        raise ValueError(f"preflight: unknown command(s) {unknown} in rules; known: "
                         f"{', '.join(CYCLE_RULES)}")
    r = traj.r.reshape(-1, traj.n_samples, traj.shape_dim)
    finite = torch.isfinite(r).all(-1) & torch.isfinite(traj.pose.reshape(-1, traj.n_samples,
                                                                           3)).all(-1)
    idx = torch.arange(r.shape[-2], device=r.device)
    first = torch.where(finite, idx, r.shape[-2]).amin(-1)
    last = torch.where(finite, idx, -1).amax(-1)
    span = (last - first + 1).clamp_min(1)
    cycles = count_cycles(r)
    spc = span.to(r.dtype) / cycles.clamp_min(1e-9)
    per = periodicity(r, cycles)
    within = (idx >= first[:, None]) & (idx <= last[:, None])
    missing = ((~finite) & within).sum(-1).to(r.dtype) / span.to(r.dtype)
    longest = _longest_runs((~finite) & within).to(r.dtype)
    longest_cycles = longest / spc.clamp_min(1e-9)

    warn, problems = [], {cmd: [] for cmd in rules}
    if float(spc.min()) < MIN_SAMPLES_PER_CYCLE:
        warn.append(f"only {float(spc.min()):.0f} samples per gait cycle (fewer than "
                    f"{MIN_SAMPLES_PER_CYCLE}): velocities and phase bins will be coarse; record "
                    "at a higher frame rate if you can")
    if float(longest_cycles.max()) > MAX_GAP_CYCLES:
        k = int(longest_cycles.argmax())
        warn.append(f"trial {k}: a gap of {int(longest[k])} samples ({float(longest_cycles[k]):.2f} "
                    f"cycles); gaps longer than {MAX_GAP_CYCLES:g} cycle are bridged by the "
                    "smoother without data (split the recording there: max_gap / --max-gap)")
    spread = None
    if body_length is not None:
        bl = body_length[torch.isfinite(body_length)]
        if bl.numel() > 2:
            q = torch.quantile(bl, torch.tensor([0.1, 0.5, 0.9], dtype=bl.dtype, device=bl.device))
            spread = float((q[2] - q[0]) / q[1])
            if spread > MAX_LENGTH_SPREAD:
                warn.append(f"the body length varies by {100 * spread:.0f}% across frames (10th to "
                            f"90th percentile): a tracking problem (swapped or misplaced "
                            "keypoints, a body leaving the image plane) is likely")
    for k in range(r.shape[0]):
        if float(per[k]) < MIN_PERIODICITY:
            for cmd in problems:
                problems[cmd].append(f"trial {k}: no periodic gait found (periodicity "
                                     f"{float(per[k]):.2f} < {MIN_PERIODICITY:g}); the shapes do "
                                     "not repeat a cycle")
    total = float(cycles.sum())
    for cmd, rule in rules.items():
        few = [k for k in range(r.shape[0]) if float(cycles[k]) < rule.per_trial]
        if few:
            found = ", ".join(f"{float(cycles[k]):.1f}" for k in few)
            problems[cmd].append(f"trial(s) {', '.join(str(k) for k in few)} hold fewer than "
                                 f"{rule.per_trial:g} cycles ({found})")
        if total < rule.total:
            problems[cmd].append(f"{total:.1f} cycles in all, {rule.total:g} needed")
    return Preflight(
        cycles=tuple(float(c) for c in cycles), total_cycles=total,
        samples_per_cycle=tuple(float(x) for x in spc), periodicity=tuple(float(x) for x in per),
        missing_fraction=tuple(float(x) for x in missing),
        longest_gap=tuple(float(x) for x in longest_cycles), length_spread=spread,
        periodic=bool((per >= MIN_PERIODICITY).all()),
        ready={cmd: not p for cmd, p in problems.items()}, problems=problems,
        warnings=tuple(warn), rules=rules,
    )


def _longest_runs(mask: Tensor) -> Tensor:
    """``(B,)`` longest run of True in each row of ``mask (B, T)``."""
    c = torch.cumsum(mask.long(), -1)
    at_false = torch.where(mask, torch.zeros_like(c), c)
    return (c - torch.cummax(at_false, -1).values).amax(-1)


def min_cycles(command: str) -> CycleRule:
    """The :data:`CYCLE_RULES` entry of a command (``"fit"`` or ``"discrepancy"``)."""
    if command not in CYCLE_RULES:
        raise ValueError(f"unknown command {command!r}; known: {', '.join(CYCLE_RULES)}")
    return CYCLE_RULES[command]

