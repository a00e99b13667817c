"""Better gaits from data: run the improvement loop on a simulator, or propose the next gait
from recordings.

    torchconn-improve simulate --links 3 --rounds 8 --out runs/improve3
    torchconn-improve propose trial1.csv trial2.csv --out next/
    torchconn-improve propose fish.h5 --links 5 --fps 60 --out next/

Also runs as ``python -m torchconn.improve``. ``propose`` reads trajectory CSVs or tracking
files (SLEAP, DeepLabCut, WCON, points), converted on the fly with ``torchconn-convert``'s
options (:mod:`torchconn.cli.conversion`).

Both take ``--device`` (cpu, cuda, cuda:N): the recordings are simulated (or read on the CPU and
moved once) and the models fitted there; the outputs are written from CPU copies. The outputs
replace ``--out`` whole once all are written (:class:`~torchconn._output.OutputFolder`).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import warnings
from pathlib import Path

from .._checks import check_value
from .._cli import InputError, check_center_frame, resolve_device, run_command, set_threads
from .._output import OutputFolder, write_bytes_atomic, write_table
from .._provenance import write_sidecar
from ..cli.common import add_common, add_version, informer
from ..cli.conversion import (
    add_conversion_arguments,
    add_links,
    conversion_flags,
    conversion_settings,
    load_recordings,
    resolve_links,
    warn_unused_conversion,
)
from ..io.trajectory_files import read_csv
from ..physics.gaits.gait import FourierGait
from ..physics.systems import NLinkSwimmer
from ..regression.defaults import pooled_estimator
from ..report import Report
from .export import write_gait
from .loop import LOOP_OBJECTIVES, MIN_CYCLES, LoopSettings, circle_gait, improve
from .measure import measure_cycles
from .pooled import PooledConnection, aligned_recording
from .propose import OBJECTIVES, TrustRegion, propose_gait

PROG = "torchconn-improve"


def _simulate(args, folder: OutputFolder) -> int:
    system = NLinkSwimmer(args.links)
    settings = LoopSettings(
        rounds=args.rounds, trials=args.trials, cycles=args.cycles, omega=args.omega,
        objective=args.objective, trust_region=TrustRegion(scale=args.scale), seed=args.seed,
        device=args.device,
    )
    start = circle_gait(args.links - 1, args.radius)

    say = informer(args.quiet)

    def report(r):
        what = {"start": "the start gait", "proposal": "the proposal",
                "repeat": "the kept gait again",
                "excited": f"the kept gait perturbed by {r.excitation:.3f} rad (excitation: "
                           "the model's ∂A/∂r is not yet known well enough to step)"}[r.kind]
        verdict = "" if r.accepted else " -- worse than the kept gait, rejected"
        step = (f"moving to a proposal predicted {r.predicted:.4f} [{r.predicted_low:.4f}, "
                f"{r.predicted_high:.4f}] (true {r.realised:.4f})" if r.moved else
                "the gain's interval includes 0: recording again")
        say(f"recording {r.index} ({r.cycles_used} cycles so far): {what}, observed "
            f"{r.observed:.4f} ± {r.observed_se:.4f} (true {r.true:.4f}){verdict}; {step}",
            flush=True)

    out = folder.path
    result = improve(system, start, settings, progress=report)
    rows = [r.as_row() for r in result.rounds]
    keys = list(rows[0])
    write_table(out / "rounds.csv", keys, [[row[k] for k in keys] for row in rows])
    write_sidecar(out / "run.json", {
        "command": "simulate", "links": args.links, "start_radius": args.radius,
        "settings": dataclasses.asdict(settings), "start_true": result.start_true,
        "coverage": result.coverage, "rounds": rows,
    })
    write_gait(result.rounds[-1].kept, out / "best_gait")
    write_gait(result.rounds[-1].proposal, out / "next_gait")
    figures = {}
    if not args.no_figures:
        # lazy: .plots and ..plotting import matplotlib, which only a run that draws
        # figures needs
        from ..plotting import render_png
        from .plots import plot_gaits, plot_rounds

        # each figure rendered once, for its file and for the report
        figures = {"gaits.png": render_png(plot_gaits(result, system), dpi=120),
                   "objective.png": render_png(plot_rounds(result), dpi=120)}
    _simulation_report(args, result, figures).write(out / "report.html")
    for name, (png, _) in figures.items():
        write_bytes_atomic(out / name, png)
    out = folder.commit()
    last = result.rounds[-1]
    say(f"start {result.start_true:.4f} -> kept gait {last.kept_true:.4f} after "
        f"{last.cycles_used} cycles; intervals of the proposals moved to covered "
        f"{result.coverage:.0%}; wrote {out}")
    return 0


def _propose(args, folder: OutputFolder) -> int:
    out = folder.path

    def conv():  # conversion options matter (and are checked) for tracking files only
        return conversion_settings(args, args.links)

    # trajectory CSVs (--links checked against their joint columns) or tracking files,
    # converted as by torchconn-convert
    rec = load_recordings(args.data, fmt=args.format, n_links=args.links, settings=conv,
                          read_csv=read_csv)
    warn_unused_conversion(rec, args.conversion_flags)
    if args.earlier and args.objective == "efficiency":
        raise InputError("--objective efficiency needs the metric, which the pooled model of "
                         "--earlier recordings does not estimate: propose from the current "
                         "recordings alone, or use --objective displacement or turning")
    # one recording (one gait) per --earlier file, all read before any fitting
    earlier = {path: load_recordings([path], fmt=args.format, n_links=args.links,
                                     settings=conv, read_csv=read_csv).trajectory
               for path in args.earlier}
    traj = rec.trajectory.to(args.device)  # moved once
    est = pooled_estimator()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = est.fit(traj).model_
    if earlier:
        model = _pooled_model(args, est, earlier)
    prop = propose_gait(model, args.objective, TrustRegion(scale=args.scale))
    meas, meas_se = measure_cycles(traj, period=2 * math.pi / float(model.phase_rate))\
        .objective(args.objective)
    period = 2 * math.pi / float(model.phase_rate)
    lo, hi = prop.gain_interval()
    summary = {
        "objective": args.objective, "observed": meas, "observed_se": meas_se,
        "predicted_gain": prop.gain, "gain_interval_95": [lo, hi],
        "model_current": prop.current, "model_predicted": prop.predicted,
        "trust_radius_rad": prop.radius, "step_rad": prop.step,
    }
    paths = write_gait(prop.gait, out / "next_gait", period=period,
                       extra={"prediction": summary})
    write_sidecar(out / "report.json", {
        "command": "propose", "data": [str(p) for p in args.data], "links": args.links,
        "scale": args.scale, "device": args.device, **summary,
    })
    report = _proposal_report(args, summary)
    report.write(out / "report.html")
    folder.commit()
    paths = {k: folder.final(p) for k, p in paths.items()}
    say = informer(args.quiet)
    say("\n".join(report.text()))
    say(f"wrote {paths['csv']} (joint angles over one cycle), {paths['json']} and "
        f"{folder.final(out / 'report.html')}")
    return 0


def _pooled_model(args, est, earlier: dict):
    """The model around the current recordings' cycle from them and every ``--earlier``
    recording (``{path: trajectory}``, one gait per file), each weighted by its distance from
    the current gait (:class:`~torchconn.improve.pooled.PooledConnection`)."""
    model = est.model_
    pool = PooledConnection(length=args.pool_length, phase_rate=float(model.phase_rate))
    pool.add(aligned_recording(est.trajectory_, model.gamma))
    for path, traj in earlier.items():
        try:
            prepared = est.prepare(traj.to(args.device))
            pool.add(aligned_recording(prepared, model.gamma))
        except ValueError as err:
            raise InputError(f"--earlier {path}: {err}") from None
    try:
        return pool.model(FourierGait(model.gamma.coeffs))
    except ValueError as err:
        raise InputError(f"the recordings near the current gait are too few for one pooled "
                         f"model ({err}); record more cycles of the current gait, or widen "
                         f"--pool-length") from None


def _proposal_report(args, summary: dict) -> Report:
    """``propose``'s report: the current gait as recorded and as the model predicts it, and
    the proposal's predicted gain with its interval, in plain words."""
    name, meas, se = summary["objective"], summary["observed"], summary["observed_se"]
    model_now = summary["model_current"]
    lo, hi = summary["gain_interval_95"]
    off = (model_now - meas) / abs(meas) if meas else math.nan
    report = Report(f"{PROG} propose: {', '.join(Path(p).name for p in args.data)}")
    report.section("The gait you recorded", [
        f"recorded {name}: {meas:.4g} ± {se:.2g} per cycle (mean ± standard error over cycles)",
        f"the model predicts {model_now:.4g} per cycle for it, "
        + (f"{abs(off):.0%} {'above' if off > 0 else 'below'} the measurement"
           if math.isfinite(off) else "where the measurement is 0")
        + ("; treat the predicted gain with that in mind" if abs(off) > 0.1 else ""),
    ])
    report.section("The proposed gait (next_gait.csv)", [
        f"predicted {name}: {summary['model_predicted']:.4g} per cycle, a gain of "
        f"{summary['predicted_gain']:.3g} (95 % interval {lo:.3g} to {hi:.3g})",
        f"a step of {summary['step_rad']:.3g} rad in joint-angle space, within the trust "
        f"radius {summary['trust_radius_rad']:.3g} rad around the recorded gait",
    ])
    report.section("What to do next", [
        "Record the proposed gait for a few cycles, then run propose again with the new "
        "recordings as the current ones and these (and any earlier ones) after --earlier: "
        "one model then holds every gait recorded."
        + (" The interval includes no gain: record more cycles of the current gait first."
           if lo <= 0 else "")])
    return report


def _simulation_report(args, result, figures: dict) -> Report:
    """``simulate``'s report: each round's recorded and predicted objective, and the
    figures (file name -> (PNG bytes, caption))."""
    report = Report(f"{PROG} simulate: {args.links}-link swimmer, {args.objective}")
    last = result.rounds[-1]
    moved = [r for r in result.rounds if r.moved]
    report.section("Outcome", [
        f"start {result.start_true:.4g}, kept gait after {last.cycles_used} recorded cycles "
        f"{last.kept_true:.4g} (true values of the simulator, per cycle, less the turning and "
        "joint-limit penalties)",
        f"the loop moved to {len(moved)} proposals; their 95 % intervals held the realised "
        f"value for {sum(r.covered for r in moved)} of them"])
    report.table("Recordings", ["recording", "cycles so far", "recorded", "observed",
                                "next", "predicted", "realised"],
                 [[r.index, r.cycles_used, r.kind + ("" if r.accepted else " (rejected)"),
                   f"{r.observed:.4g} ± {r.observed_se:.2g}",
                   "proposal" if r.moved else "record again",
                   f"{r.predicted:.4g} [{r.predicted_low:.4g}, {r.predicted_high:.4g}]",
                   f"{r.realised:.4g}"] for r in result.rounds])
    for name, (png, caption) in figures.items():
        report.figure(png, caption or name)
    return report


#: the trust radius (tube radii) the loop may adapt within (LoopSettings.min_scale, max_scale)
_SCALES = (LoopSettings.min_scale, LoopSettings.max_scale)


def _check_flags(args) -> None:
    """Every flag's type and range, before any work (:class:`InputError` naming the flag)."""
    checks = [("--links", args.links, int, {"ge": 3}), ("--scale", args.scale, float, {"gt": 0})]
    if args.command == "propose":
        checks.append(("--pool-length", args.pool_length, float, {"gt": 0}))
    if args.command == "simulate":
        checks += [("--rounds", args.rounds, int, {"ge": 1}),
                   ("--trials", args.trials, int, {"ge": 1}),
                   ("--cycles", args.cycles, int, {"ge": MIN_CYCLES}),
                   ("--radius", args.radius, float, {"gt": 0}),
                   ("--omega", args.omega, float, {"ge": 0}),
                   ("--seed", args.seed, int, {"ge": 0})]
    for flag, value, tp, bounds in checks:
        try:
            check_value(flag, value, tp, bounds)
        except ValueError as err:
            raise InputError(str(err)) from None
    if args.command == "simulate":
        if args.radius >= math.pi:
            raise InputError(f"--radius must be < π (3.1416), got {args.radius:g}: the start "
                             "circle's radius is the joints' amplitude in rad, and beyond ±π "
                             "the links would cross")
        if not _SCALES[0] <= args.scale <= _SCALES[1]:
            raise InputError(f"--scale must lie in [{_SCALES[0]:g}, {_SCALES[1]:g}] (the "
                             f"trust radius the loop adapts within, in tube radii), got "
                             f"{args.scale:g}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog=PROG,
                                description=__doc__.split("\n")[0])
    add_version(p)
    sub = p.add_subparsers(dest="command", required=True)
    sim = sub.add_parser("simulate", help="run the loop on the N-link swimmer simulator")
    sim.add_argument("--links", type=int, default=3)
    defaults = LoopSettings()
    sim.add_argument("--rounds", type=int, default=defaults.rounds,
                     help="recordings (each of --trials x --cycles cycles of one gait)")
    sim.add_argument("--trials", type=int, default=defaults.trials)
    sim.add_argument("--cycles", type=int, default=defaults.cycles,
                     help=f"cycles per trial and recording (at least {MIN_CYCLES})")
    sim.add_argument("--radius", type=float, default=0.5, help="start circle radius (rad)")
    sim.add_argument("--omega", type=float, default=0.0, help="observation noise")
    sim.add_argument("--seed", type=int, default=0)
    rec = sub.add_parser("propose", help="the next gait to try, from recordings")
    rec.add_argument("data", nargs="+", type=Path,
                     help="recordings of the current gait: trajectory CSV files, or tracking "
                     "files (converted as by torchconn-convert, same options but --frame, "
                     "always center, and --scale, the trust radius here: the body length is the "
                     "median chain length)")
    rec.add_argument("--earlier", nargs="+", type=Path, action="extend", default=[],
                     metavar="FILE",
                     help="recordings of earlier gaits (earlier rounds), one gait per file: "
                     "pooled into one model with the current recordings, each weighted by its "
                     "distance from the current gait")
    rec.add_argument("--pool-length", type=float, default=defaults.pool_length,
                     help="with --earlier: a recording D rad (rms) from the current gait is "
                     "weighted exp(-(D/L)^2/2) (default %(default)s rad)")
    add_links(rec)
    # the loop's swimmer is in the center frame; --scale is the trust radius here
    add_conversion_arguments(rec, frame=False, scale=False)
    for q in (sim, rec):
        q.add_argument("--objective", default="displacement",
                       choices=OBJECTIVES if q is rec else LOOP_OBJECTIVES)
        q.add_argument("--scale", type=float, default=3.0, help="trust radius in tube radii")
        q.add_argument("--out", type=Path, required=True)
        add_common(q, version=False, figures=q is sim)  # propose writes none: a no-op
    args = p.parse_args(argv)

    def body() -> int:
        set_threads(args.threads)
        if args.command == "propose":
            args.conversion_flags = conversion_flags(args)
            args.links, how = resolve_links(args.links, args.data, args.format)
            if how:
                informer(args.quiet)(how)
        _check_flags(args)
        check_center_frame(args.links, "center", "the loop's swimmer is in the center frame: "
                           "use an odd --links")
        args.device = str(resolve_device(args.device))
        with OutputFolder(args.out, command=f"{PROG} {args.command}") as folder:
            return (_simulate if args.command == "simulate" else _propose)(args, folder)

    prog = f"{p.prog} {args.command}"
    return run_command(prog, body)


if __name__ == "__main__":
    sys.exit(main())
