"""Held-out skill on real tracked recordings: fit the first cycles, predict the rest.

Each file (any format ``torchconn-convert`` reads, or a trajectory CSV) is converted as
``torchconn-convert`` would (``--links``, ``--fps``, ``--keypoints``; one trial), the estimator is
fitted to the first ``--train`` fraction of its samples (default 0.6) and scored on the rest, as
R² per body-velocity component (v_x, v_y, ω) against the observed velocity the way the default
regression sees it (``ConnectionEstimator.score``):

- ``default``: ``ConnectionEstimator()`` as ``torchconn-fit`` runs it (complexity ``"auto"``):
  its forecasting model, ``score().r2``;
- ``connection``: the default's ``model_``, every row as estimated (what a user reads and
  saves), on the same samples;
- ``fixed``: ``ConnectionEstimator(complexity="fixed")`` (48 bins, order 12, no check-driven
  choice);
- ``tube``: ``ConnectionEstimator(regression=TubeRegression(), complexity="fixed")``, torchconn
  0.1's method; its target is the Kalman-smoothed velocity, not the raw interval differences;
- ``phase avg``: the training cycles' phase-averaged velocity (``score()``'s baseline);
- ``template``: the connection's intercept ``ĉ(φ) = Â(γ)γ̇`` on the later samples
  (``score().r2_template``, of ``model_``).

The later cycles are phased by the phase model fitted to the first ones, applied to the whole
recording (its later part kept): ``Phaser.transform`` of the later part alone needs 3 cycles,
and ``--phase-length`` measures why (its error on simulated later records of 1-6 cycles).
The table also gives the cycles fitted and scored, what the fit's held-out check chose, the
warnings and the fit's time (CPU, one thread).

Run by hand::

    python benchmarks/real_recordings.py XMUC02_Trial1_sleap-1.csv --links 5 --fps 60
    python benchmarks/real_recordings.py fish.analysis.csv --links 5 --fps 50 \\
        --keypoints snout,hyoid,pelvic_fin_base,anus,peduncle,dorsal_caudal
    python benchmarks/real_recordings.py --phase-length --seeds 70 71 72

The recordings measured in the README ("Real recordings") are the SLEAP exports shipped with
``fishmechr`` (github.com/tytell/fishmechr, ``data-raw/``, CC BY 4.0); they are not part of
torchconn.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from torchconn import ConnectionEstimator, Phaser, RTSSmoother, TubeRegression
from torchconn.convert import load_recordings
from torchconn.io.tracking import ConversionSettings
from torchconn.io.trajectory_files import count_cycles
from torchconn.regression.selection import COMPONENTS, skill


def later_phase(est: ConnectionEstimator, traj, cut: int) -> torch.Tensor:
    """Phase ``(..., T - cut)`` of the samples from ``cut`` on: the phase model fitted to the
    first ``cut`` samples applied to the whole recording (smoothed as the fit smooths)."""
    whole = est.smoother.smooth(traj)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fit warned of the same channels
        return est.phaser_.transform(whole.smoothed.r)[..., cut:]


def _fit(make, train):
    """The estimator ``make()`` fitted to ``train``, its CPU seconds and the warnings' texts."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        start = time.process_time()
        est = make().fit(train)
        seconds = time.process_time() - start
    return est, seconds, [f"{w.category.__name__}: {w.message}" for w in caught]


def evaluate(traj, train_fraction: float) -> dict:
    """Fit the first ``train_fraction`` of the samples of ``traj`` (one trial), score the rest."""
    cut = int(round(train_fraction * traj.n_samples))
    train, later = traj.slice_time(0, cut), traj.slice_time(cut, traj.n_samples)
    out = {"cycles": (float(count_cycles(train.r).sum()), float(count_cycles(later.r).sum())),
           "samples_per_cycle": traj.n_samples / float(count_cycles(traj.r).sum())}
    est, out["seconds"], out["warnings"] = _fit(ConnectionEstimator, train)
    phase = later_phase(est, traj, cut)
    scored = est.score(later, phase=phase)
    view = skill.regression_view(est.prepare(later, phase), est.regression_,
                                 est.forecast_model_, pool=est.pool)
    delivered = skill.skill(est.model_, est.phase_average_, view)
    out.update(default=scored.r2, connection=delivered.r2, phase_avg=scored.r2_phase_average,
               template=scored.r2_template)
    for name, make in (("fixed", lambda: ConnectionEstimator(complexity="fixed")),
                       ("tube", lambda: ConnectionEstimator(regression=TubeRegression(),
                                                            complexity="fixed"))):
        try:
            other = _fit(make, train)[0]
            out[name] = other.score(later, phase=later_phase(other, traj, cut)).r2
        except ValueError as err:  # too many coefficients for the recording
            out[name] = torch.full((3,), math.nan, dtype=torch.float64)
            out[name + "_error"] = str(err)
    c, held = est.complexity_, est.held_out_skill_
    out["choice"] = _given(held) if c is None else (
        ("the connection alone (no full model scores held out), "
         if getattr(c, "connection_regressed", False)
         else "") + f"{c.n_bins} bins, order {c.fourier_order}, ridge {c.ridge:g}" + "".join(
            f"; {tag}: {', '.join(names)}" for tag, names in
            (("phase avg", c.phase_averaged_names()), ("connection only",
                                                       c.connection_only_names())) if names))
    return out


def _given(held) -> str:
    """What the check said of the given complexity (48 bins, order 12) where it kept it."""
    if held is None:
        return "given (48 bins, order 12), no check"
    if bool(held.unscored.any()):
        return ("given (48 bins, order 12), unchecked: some bins cannot be fitted without a "
                "block, nor could any simpler candidate")
    lost = [n for n, w in zip(COMPONENTS, held.worse_than_phase_average.reshape(-1, 3).any(0)
                              .tolist(), strict=True) if w]
    return "given (48 bins, order 12), " + (
        f"lost to the phase average held out on {', '.join(lost)}" if lost else "check passed")


def report(name: str, out: dict) -> None:
    fitted, scored = out["cycles"]
    print(f"\n{name}: {fitted:.1f} cycles fitted, {scored:.1f} scored, "
          f"{out['samples_per_cycle']:.0f} samples per cycle; fit {out['seconds']:.1f} s CPU")
    print(f"  the check chose: {out['choice']}")
    for w in dict.fromkeys(out["warnings"]):
        print(f"  warned: {w[:200]}")
    print("  R² on the later cycles    " + "  ".join(f"{c:>7}" for c in COMPONENTS))
    for key in ("default", "connection", "fixed", "tube", "phase_avg", "template"):
        r2 = torch.as_tensor(out[key]).reshape(-1)
        print(f"  {key:<25} " + "  ".join(f"{float(v):7.3f}" for v in r2))
        if key + "_error" in out:
            print(f"    ({out[key + '_error'][:160]})")


def phase_length(seeds: list[int]) -> None:
    """RMS phase error of ``Phaser.transform`` on later records of 1-6 cycles (simulated
    5-link waves and a 3-link circle, ω = 0.005, 126 samples per cycle), the phase model
    fitted to 6 earlier cycles, against the simulator's phase (the fit's offset removed): of
    the later record alone, and of the whole recording up to its end with its part kept."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from short_recordings import SAMPLES_PER_CYCLE, recording  # beside this file

    lengths = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0)
    errors = {L: [] for L in lengths}
    whole = {L: [] for L in lengths}  # the record from its start transformed, the part kept
    short = Phaser(min_cycles=0.5)  # the transform's own check lowered, to measure below it
    for seed in seeds:
        for links, kind in ((5, "wave0.7"), (5, "wave2"), (3, "wave0.7")):
            traj = recording(links, kind, 14, seed, 0.005)  # 14 + 4 cycles
            r = RTSSmoother().smooth(traj).smoothed.r
            truth = traj.truth.phase
            cut = 6 * SAMPLES_PER_CYCLE + 1
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fitted = Phaser().fit(r[..., :cut, :])
            fitted = short._fitted_copy(model_=fitted.model_, phase_=fitted.phase_)
            offset = torch.angle(torch.exp(1j * (fitted.phase_ - truth[..., :cut])).mean(-1))
            for L in lengths:
                n = int(L * SAMPLES_PER_CYCLE) + 1
                rms, rms_whole = [], []
                for start in range(cut, traj.n_samples - n + 1, SAMPLES_PER_CYCLE // 2):
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        alone = fitted.transform(r[..., start:start + n, :])
                        kept = fitted.transform(r[..., :start + n, :])[..., start:]
                    for p, out in ((alone, rms), (kept, rms_whole)):
                        d = torch.angle(torch.exp(1j * (p - truth[..., start:start + n]
                                                        - offset[..., None])))
                        out.append(float(d.square().mean().sqrt()))
                errors[L].append(np.mean(rms))
                whole[L].append(np.mean(rms_whole))
    print("later record | RMS phase error (rad; mean, max over recordings) of Phaser.transform"
          " on the record alone | on the whole recording, its part kept")
    for L in lengths:
        print(f"{L:4.1f} cycles  | {np.mean(errors[L]):.3f}, {np.max(errors[L]):.3f}"
              f" | {np.mean(whole[L]):.3f}, {np.max(whole[L]):.3f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("files", nargs="*", type=Path)
    p.add_argument("--links", type=int, default=5)
    p.add_argument("--fps", type=float, default=None)
    p.add_argument("--keypoints", default=None, help="comma-separated, head to tail")
    p.add_argument("--train", type=float, nargs="+", default=[0.6],
                   help="fractions of the samples fitted (the rest is scored)")
    p.add_argument("--phase-length", action="store_true",
                   help="measure Phaser.transform's error against the later record's length")
    p.add_argument("--seeds", type=int, nargs="+", default=[70, 71, 72])
    args = p.parse_args()
    torch.set_num_threads(1)
    if args.phase_length:
        phase_length(args.seeds)
    settings = ConversionSettings(
        n_links=args.links, fps=args.fps,
        keypoints=None if args.keypoints is None else tuple(args.keypoints.split(",")))
    for path in args.files:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the conversion's notes are in its report
            traj = load_recordings([path], n_links=args.links, settings=settings).trajectory
        if traj.batch_shape != (1,):
            raise SystemExit(f"{path}: {traj.batch_shape[0]} trials; this benchmark takes one")
        for fraction in args.train:
            name = f"{path.name}, first {fraction:.0%} fitted"
            try:
                report(name, evaluate(traj, fraction))
            except ValueError as err:  # e.g. too few cycles fitted for the phase
                print(f"\n{name}: cannot be fitted: {err}")


if __name__ == "__main__":
    main()
