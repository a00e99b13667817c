"""Forward-in-time skill on real and simulated short recordings: the model against its baselines.

Real recordings (section 1). Each file is converted as ``torchconn-convert`` would (one
trial) and split forward in time:

- ``first 60%``: the estimator is fitted to the first 60 % of the samples and scores the rest;
- ``last 60%`` (backcast): fitted to the last 60 %, scores the first 40 %;
- ``later cycles``: fitted to the first ``k`` cycles, scores the rest, for ``k = 3, 4, ...``
  while at least 2 cycles remain (``--min-left``); the table gives the mean over ``k``.

The cycles are counted on the whole recording's phase (``Phaser`` fitted to the whole record).
The scored part is smoothed with the whole record and phased by the fitted phase model
applied to the whole record (``real_recordings.later_phase``), so that a split has no edge of
its own. Every predictor is scored as ``R²`` per component (``v_x``, ``v_y``, ``ω``) on the
samples and against the target the default regression sees
(:func:`~torchconn.regression.selection.skill.regression_view`), as
:meth:`~torchconn.ConnectionEstimator.score` does:

- ``torchconn``: the forecasting model, ``est.score(...).r2``;
- ``phase avg``: the training part's phase-averaged velocity (``score().r2_phase_average``);
- ``RFT k=2``: ``NLinkSwimmer(N, drag_ratio=2).body_velocity(r, ṙ)``, nothing fitted;
- ``RFT fit k``: the swimmer with its drag ratio fitted to the training part
  (:func:`~torchconn.regression.reference.fit_reference`), ``PhysicsReference.predict``;
- ``zero``: no motion.

Beside them: the fit's own held-out ``R²`` (``est.held_out_skill_.r2``) and its difference from
the forward ``torchconn`` row (issue 33's target: within 0.1).

Simulated recordings (section 2). ``NLinkSwimmer`` 3-link (``reference_gait("3link")``) and
5-link (a travelling wave of 0.7 rad, a circle in each joint pair), ``--cycles`` fitted at
``--samples-per-cycle``, motion-capture noise ``ω`` (``observe``), ``--seeds``; each
recording runs ``--test-cycles`` further cycles that are scored as the real ones are. ``Â``'s
relative RMS error on the fitted cycle against ``NLinkSwimmer(N).connection(γ̂(φ))``
(``accuracy.connection_errors``) is given for the default ``est.model_`` and for the fitted
physics reference's connection on the same cycle (``PhysicsReference.local_model(est.model_)``),
median over seeds.

Every fit is ``ConnectionEstimator()`` but for ``Phaser(min_cycles=2.5)``, which only lowers the
phase's refusal: a part of exactly 3 cycles often phases to 2.9 cycles, which the default
refuses.

Each section ends with one line per recording and split (per configuration when simulated):
the delivered forecast's ``R²`` against ``max(phase avg, RFT fit k)`` per component, and
``PASS`` where it is at least that minus 0.02 on every component and above 0 on ``ω`` (issue
33's target), else ``FAIL``.

Run by hand (about 4 minutes on a loaded 2-core machine, one thread; ``--quick`` about 1)::

    python benchmarks/forward_splits.py --data DIR
    python benchmarks/forward_splits.py --data DIR --quick
    python benchmarks/forward_splits.py rec.csv:links=5:fps=60 \\
        fish.analysis.csv:links=5:fps=50:keypoints=snout,hyoid,pelvic_fin_base,anus,peduncle,dorsal_caudal
    python benchmarks/forward_splits.py --no-real --links 3 --cycles 3 4 --seeds 0 1

``--data DIR`` takes every file in ``DIR`` it knows how to convert: the SLEAP-tracked
prickleback ``XMUC02_Trial1_sleap-1.csv`` (5 links, 60 fps) and the zebrafish in a flow tank
``*fish_01-*RPM*.analysis.csv`` (5 links, 50 fps, keypoints snout, hyoid, pelvic_fin_base,
anus, peduncle, dorsal_caudal), the SLEAP exports of ``fishmechr`` (github.com/tytell/fishmechr,
``data-raw/``, CC BY 4.0); they are not part of torchconn.
"""

from __future__ import annotations

import argparse
import fnmatch
import math
import statistics
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch
from accuracy import connection_errors  # beside this file
from short_recordings import recording  # beside this file

from torchconn import ConnectionEstimator, NLinkSwimmer, Phaser
from torchconn.convert import load_recordings
from torchconn.cycles import cycle_number
from torchconn.io.tracking import ConversionSettings
from torchconn.regression.reference import default_frame, fit_reference
from torchconn.regression.selection import COMPONENTS, skill

PREDICTORS = ("torchconn", "phase avg", "RFT k=2", "RFT fit k", "zero")
FISH_KEYPOINTS = "snout,hyoid,pelvic_fin_base,anus,peduncle,dorsal_caudal"
#: the files ``--data`` knows how to convert: name pattern -> conversion flags
KNOWN_FILES = {
    "XMUC02_*sleap*.csv": {"links": "5", "fps": "60"},
    "*fish_01-*RPM*.analysis.csv": {"links": "5", "fps": "50", "keypoints": FISH_KEYPOINTS},
}
MARGIN = 0.02  # issue 33: R² >= max(phase avg, physics) - MARGIN
SIM_CONFIGS = ((3, "reference"), (5, "wave0.7"))


# ------------------------------------------------------------------------------ scoring
@dataclass
class Split:
    """The R² ``(3,)`` of every predictor on one forward split, the fit's held-out R²
    ``(3,)``, the fitted drag ratio and the fit's cycles."""

    r2: dict[str, torch.Tensor]
    held_out: torch.Tensor
    drag_ratio: float
    cycles: tuple[float, float]
    extra: dict = field(default_factory=dict)


def _r2(pred: torch.Tensor, y: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """``(3,)`` R² of ``pred`` against ``y`` (both ``(N, 3)``) over the samples ``ok``, the
    total sum of squares about the scored samples' mean (as ``Skill``)."""
    y, pred = y[ok], pred[ok]
    sst = (y - y.mean(0)).square().sum(0)
    return 1 - (y - pred).square().sum(0) / sst


def _flat(x: torch.Tensor, k: int) -> torch.Tensor:
    """``(..., N, k)`` -> ``(B·N, k)``."""
    return x.reshape(-1, k)


def score_split(est: ConnectionEstimator, scored, n_links: int) -> Split:
    """Every predictor on ``scored`` (prepared: smoothed and phased), trained as ``est``."""
    reg, model = est.regression_, est.forecast_model_
    d = n_links - 1
    s = est.score(scored)
    view = skill.regression_view(scored, reg, model, pool=est.pool, flatten=False)
    phase, r = view.phase.reshape(-1), _flat(view.r, d)
    r_dot, y = _flat(view.r_dot, d), _flat(view.xi, 3)
    ok = (torch.isfinite(phase) & torch.isfinite(r).all(-1) & torch.isfinite(r_dot).all(-1)
          & torch.isfinite(y).all(-1))
    train = skill.regression_view(est.trajectory_, reg, model, pool=est.pool, flatten=False)
    ref = fit_reference(train.r, train.r_dot, train.xi, pool=True)
    plain = NLinkSwimmer(n_links, drag_ratio=2.0, frame=default_frame(n_links))
    safe_r, safe_rd = torch.where(ok[:, None], r, 0.0), torch.where(ok[:, None], r_dot, 0.0)
    r2 = {"torchconn": s.r2.reshape(-1), "phase avg": s.r2_phase_average.reshape(-1),
          "RFT k=2": _r2(plain.body_velocity(safe_r, safe_rd).to(y.dtype), y, ok),
          "RFT fit k": _r2(ref.predict(safe_r, safe_rd), y, ok),
          "zero": _r2(torch.zeros_like(y), y, ok)}
    # the same R² as score() on the same samples, recomputed here
    shape = view.phase.shape
    mine = _r2(_flat(model.predict(torch.where(ok, phase, 0.0).reshape(shape),
                                   safe_r.reshape(shape + (d,)),
                                   safe_rd.reshape(shape + (d,))), 3), y, ok)
    if not torch.allclose(mine, r2["torchconn"], atol=1e-6, equal_nan=True):
        print(f"  note: R² recomputed {mine.tolist()} differs from score() "
              f"{r2['torchconn'].tolist()}", file=sys.stderr)
    held = est.held_out_skill_
    return Split(r2, (torch.full((3,), math.nan, dtype=torch.float64) if held is None
                      else held.r2.reshape(-1, 3)[0]),
                 float(ref.parameters["drag_ratio"]), (0.0, 0.0), {"reference": ref})


def _estimator() -> ConnectionEstimator:
    """The default estimator but for ``Phaser(min_cycles=2.5)`` (the phase's check only)."""
    return ConnectionEstimator(phaser=Phaser(min_cycles=2.5))


def _quiet_fit(make, train):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return make().fit(train)


def split_at(traj, whole, est_maker, start: int, stop: int, n_links: int, total_phase):
    """Fit ``traj[start:stop]``, score the rest (the other side, one contiguous part)."""
    T = traj.n_samples
    est = _quiet_fit(est_maker, traj.slice_time(start, stop))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fit warned of the same channels
        phase = est.phaser_.transform(whole.smoothed.r)
    lo, hi = (stop, T) if start == 0 else (0, start)
    scored = whole.slice_time(lo, hi).with_fields(phase=phase[..., lo:hi])
    out = score_split(est, scored, n_links)
    n = (total_phase[..., start:stop], total_phase[..., lo:hi])
    out.cycles = tuple(float((p.nan_to_num(-math.inf).amax() - p.nan_to_num(math.inf).amin())
                             / (2 * math.pi)) for p in n)
    return out


# --------------------------------------------------------------------------- printing
def _row(name: str, values: torch.Tensor, width: int = 14) -> str:
    return f"  {name:<{width}} " + "  ".join(f"{float(v):7.3f}" for v in values)


def _verdict(forecast: torch.Tensor, best: torch.Tensor) -> str:
    ok = bool(((forecast >= best - MARGIN) | ~torch.isfinite(best)).all()) and float(
        forecast[2]) > 0
    return "PASS" if ok else "FAIL"


def _summary_line(label: str, forecast: torch.Tensor, phase_avg: torch.Tensor,
                  physics: torch.Tensor) -> str:
    best = torch.maximum(phase_avg, physics)
    parts = "  ".join(f"{c} {float(f):6.3f} vs {float(b):6.3f}"
                      for c, f, b in zip(COMPONENTS, forecast, best, strict=True))
    return f"  {label:<44} {parts}   {_verdict(forecast, best)}"


def print_split(title: str, result: Split | list[Split]) -> dict[str, torch.Tensor]:
    """Print one split's table (a list: the mean over the splits); returns the R² shown."""
    many = isinstance(result, list)
    splits = result if many else [result]
    r2 = {k: torch.stack([s.r2[k] for s in splits]).mean(0) for k in PREDICTORS}
    held = torch.stack([s.held_out for s in splits]).nanmean(0)  # NaN: no held-out score
    n_held = sum(bool(torch.isfinite(s.held_out).all()) for s in splits)
    ks = [s.drag_ratio for s in splits]
    fitted = [s.cycles[0] for s in splits]
    scored = [s.cycles[1] for s in splits]
    cyc = (f"{min(fitted):.1f}-{max(fitted):.1f} cycles fitted, mean of {len(splits)}"
           if many else f"{fitted[0]:.1f} cycles fitted, {scored[0]:.1f} scored")
    print(f" {title}: {cyc}; fitted k {statistics.median(ks):.2f}"
          + (" (median)" if many else ""))
    print(f"  {'R²':<14} " + "  ".join(f"{c:>7}" for c in COMPONENTS))
    for k in PREDICTORS:
        print(_row(k, r2[k]))
    print(_row("fit's held-out", held) + (f"   (mean of the {n_held} scored)"
                                           if many and n_held < len(splits) else ""))
    both = [s.held_out - s.r2["torchconn"] for s in splits]
    print(_row("held-out - fwd", torch.stack(both).nanmean(0)))
    return r2


# ----------------------------------------------------------------------- real recordings
def parse_spec(spec: str, defaults: dict) -> tuple[Path, dict]:
    """``PATH[:key=value...]`` -> the path and its conversion flags (links, fps, keypoints)."""
    path, *pairs = spec.split(":")
    flags = dict(defaults)
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or key not in ("links", "fps", "keypoints"):
            raise SystemExit(f"{spec}: expected PATH:links=N:fps=F:keypoints=a,b,..., got "
                             f"{pair!r}")
        flags[key] = value
    return Path(path), flags


def known_files(folder: Path) -> list[tuple[Path, dict]]:
    """Every file in ``folder`` matching :data:`KNOWN_FILES`, with its flags."""
    out = []
    for path in sorted(folder.iterdir()):
        for pattern, flags in KNOWN_FILES.items():
            if fnmatch.fnmatch(path.name, pattern):
                out.append((path, dict(flags)))
                break
    return out


def load(path: Path, flags: dict):
    links = int(flags.get("links", 5))
    fps = None if flags.get("fps") in (None, "") else float(flags["fps"])
    keypoints = flags.get("keypoints")
    settings = ConversionSettings(
        n_links=links, fps=fps,
        keypoints=None if not keypoints else tuple(keypoints.split(",")))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the conversion's notes are in its report
        traj = load_recordings([path], n_links=links, settings=settings).trajectory
    if traj.batch_shape != (1,):
        raise SystemExit(f"{path}: {traj.batch_shape[0]} trials; this benchmark takes one")
    return traj, links


def real_recording(path: Path, flags: dict, args, summary: list[str]) -> None:
    traj, links = load(path, flags)
    T = traj.n_samples
    make = _estimator
    whole = make().smoother.smooth(traj)
    missing = float(torch.isnan(traj.r).any(-1).float().mean())
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            total_phase = Phaser().fit(whole.smoothed.r).phase_
    except ValueError as err:
        print(f"\n{path.name}: {T} samples, {missing:.0%} of frames missing; the whole record "
              f"cannot be phased: {str(err)[:160]}")
        summary.append(f"  {path.name[:28]:<44} not phased")
        return
    n_total = float((total_phase.nan_to_num(-math.inf).amax()
                     - total_phase.nan_to_num(math.inf).amin()) / (2 * math.pi))
    start = time.perf_counter()
    print(f"\n{path.name}: {T} samples, {n_total:.1f} cycles (whole record's phase), "
          f"{T / n_total:.0f} samples per cycle, "
          f"{missing:.0%} of frames missing")
    cut = int(round(args.train * T))
    splits = (("first 60%", 0, cut), ("last 60%", T - cut, T))
    for title, lo, hi in splits:
        title = title.replace("60", f"{args.train:.0%}".rstrip("%"))
        try:
            s = split_at(traj, whole, make, lo, hi, links, total_phase)
        except ValueError as err:
            print(f" {title}: cannot be fitted: {str(err)[:160]}")
            summary.append(f"  {path.name[:28] + ', ' + title:<44} not fitted")
            continue
        r2 = print_split(title, s)
        summary.append(_summary_line(f"{path.name[:28]}, {title}", r2["torchconn"],
                                     r2["phase avg"], r2["RFT fit k"]))
    cyc = cycle_number(total_phase, origin="first")  # (1, T)
    later, refused = [], []
    k = 3
    while n_total - k >= args.min_left:
        stop = int(torch.nonzero(cyc[0] >= k)[0])
        try:
            later.append(split_at(traj, whole, make, 0, stop, links, total_phase))
        except ValueError as err:
            refused.append(k)
            print(f"  k = {k}: cannot be fitted: {str(err)[:160]}")
        k += args.k_step
    title = "later cycles"
    if later:
        r2 = print_split(f"{title} (k = 3..{k - args.k_step} by {args.k_step})", later)
        summary.append(_summary_line(f"{path.name[:28]}, {title} (mean)", r2["torchconn"],
                                     r2["phase avg"], r2["RFT fit k"]))
    if refused:
        print(f"  not fitted for k = {refused}")
    if not later:
        print(f" {title}: none fitted")
    print(f"  ({time.perf_counter() - start:.0f} s)")


# ------------------------------------------------------------------- simulated recordings
def simulated(n_links: int, kind: str, n_cycles: int, spc: int, omega: float, seed: int,
              test_cycles: int) -> dict:
    traj = recording(n_links, kind, n_cycles, seed, omega, spc, test_cycles)
    cut = n_cycles * spc + 1
    make = _estimator
    whole = make().smoother.smooth(traj)
    est = _quiet_fit(make, traj.slice_time(0, cut))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        phase = est.phaser_.transform(whole.smoothed.r)
    scored = whole.slice_time(cut, traj.n_samples).with_fields(phase=phase[..., cut:])
    out = score_split(est, scored, n_links)
    ref = out.extra["reference"]
    err_model = float(connection_errors(est.model_, n_links)["A"].mean())
    err_ref = float(connection_errors(ref.local_model(est.model_), n_links)["A"].mean())
    return {"split": out, "A_model": err_model, "A_ref": err_ref}


def simulated_section(args, summary: list[str]) -> None:
    print(f"\n=== 2. Simulated recordings: n cycles fitted, the next {args.test_cycles} "
          f"scored; seeds {args.seeds}; medians over seeds")
    print(f"{'links':>5} {'gait':>9} {'n':>3} {'spc':>4} {'omega':>6} | "
          f"{'|Â-A| model_':>12} {'ref(k fit)':>10} {'better':>7} | "
          + " | ".join(f"{p:^23}" for p in ("torchconn", "phase avg", "RFT k=2",
                                              "RFT fit k"))
          + " | held-out - fwd        | k fit  s")
    for n_links, kind in SIM_CONFIGS:
        if n_links not in args.links:
            continue
        for spc in args.samples_per_cycle:
            for omega in args.omega:
                for n in args.cycles:
                    start = time.perf_counter()
                    runs, refused, why = [], 0, ""
                    for seed in args.seeds:
                        try:
                            runs.append(simulated(n_links, kind, n, spc, omega, seed,
                                                  args.test_cycles))
                        except ValueError as err:
                            refused += 1
                            why = str(err)[:120]
                    label = f"{n_links}-link {kind}, {n} cyc, {spc}/cyc, omega {omega:g}"
                    if not runs:
                        print(f"{n_links:>5} {kind:>9} {n:>3} {spc:>4} {omega:>6g} | "
                              f"not fitted ({refused} seeds): {why}")
                        summary.append(f"  {label:<44} not fitted")
                        continue

                    def med(key, runs=runs):
                        return torch.stack([r["split"].r2[key] for r in runs]).median(0).values
                    a_m = statistics.median(r["A_model"] for r in runs)
                    a_r = statistics.median(r["A_ref"] for r in runs)
                    held = torch.stack([r["split"].held_out - r["split"].r2["torchconn"]
                                        for r in runs]).median(0).values
                    k = statistics.median(r["split"].drag_ratio for r in runs)
                    print(f"{n_links:>5} {kind:>9} {n:>3} {spc:>4} {omega:>6g} | "
                          f"{a_m:12.3f} {a_r:10.3f} {'model_' if a_m < a_r else 'ref':>7} | "
                          + " | ".join(" ".join(f"{float(v):7.3f}" for v in med(p))
                                       for p in PREDICTORS[:4])
                          + " | " + " ".join(f"{float(v):6.3f}" for v in held)
                          + f" | {k:5.2f} {time.perf_counter() - start:3.0f}"
                          + (f"  ({refused} seeds not fitted: {why})" if refused else ""),
                          flush=True)
                    summary.append(_summary_line(label, med("torchconn"), med("phase avg"),
                                                 med("RFT fit k")))


# ---------------------------------------------------------------------------------- main
def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("files", nargs="*", help="PATH[:links=N][:fps=F][:keypoints=a,b,...]")
    p.add_argument("--data", type=Path, help="take every file in this folder it knows")
    p.add_argument("--train", type=float, default=0.6, help="fraction fitted (first/last)")
    p.add_argument("--min-left", type=float, default=2.0,
                   help="later cycles: at least this many cycles scored")
    p.add_argument("--k-step", type=int, default=1, help="later cycles: k = 3, 3 + step, ...")
    p.add_argument("--no-real", action="store_true")
    p.add_argument("--no-sim", action="store_true")
    p.add_argument("--links", type=int, nargs="+", default=[3, 5])
    p.add_argument("--cycles", type=int, nargs="+", default=[3, 4, 6, 8, 10])
    p.add_argument("--samples-per-cycle", type=int, nargs="+", default=[16, 32])
    p.add_argument("--omega", type=float, nargs="+", default=[0.0, 0.005])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--test-cycles", type=int, default=4)
    p.add_argument("--quick", action="store_true",
                   help="later cycles every 4th k; simulated 3, 6, 10 cycles at 16 per "
                        "cycle, omega 0.005, seeds 0 1")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    if args.quick:
        args.k_step, args.cycles, args.samples_per_cycle = 4, [3, 6, 10], [16]
        args.omega, args.seeds = [0.005], [0, 1]
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    summary_real: list[str] = []
    if not args.no_real:
        specs = [parse_spec(f, {}) for f in args.files]
        if args.data is not None:
            specs += known_files(args.data)
        if not specs:
            raise SystemExit("no recordings: give files or --data DIR (or --no-real)")
        print("=== 1. Real recordings: forward splits; R² per component on the scored part "
              "(phase and smoothing on the whole record)")
        for path, flags in specs:
            real_recording(path, flags, args, summary_real)
        print("\nsummary (real): the forecast's R² vs max(phase avg, RFT fit k); PASS: "
              f">= max - {MARGIN} on every component and > 0 on omega")
        print("\n".join(summary_real))
    summary_sim: list[str] = []
    if not args.no_sim:
        simulated_section(args, summary_sim)
        print("\nsummary (simulated): the forecast's R² vs max(phase avg, RFT fit k), medians "
              f"over seeds; PASS: >= max - {MARGIN} on every component and > 0 on omega")
        print("\n".join(summary_sim))
    print(f"\n{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
