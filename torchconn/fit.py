"""``torchconn-fit DATA… [--links N] --out DIR``: fit your recordings (CSV or tracking files).

Also runs as ``python -m torchconn.fit``. Reads trajectory CSV files (the format of
docs/conventions.md, section "Trajectory file format"), or tracking files (SLEAP, DeepLabCut,
WCON, point arrays; docs/tracking.md) converted on the fly with the options of
``torchconn-convert``; applies known conditions (``--known ambient_flow:u_x=…``); prints the
checks before fitting (:mod:`torchconn.io.preflight`); estimates phase and limit cycle, fits the
local connection (and the metric, when a ``power`` column is present) with all trials pooled
into one model, and writes ``DIR/model.npz``, ``DIR/connection.csv`` (one row per phase on a
uniform grid: ``phase, r1…rd, A_x_i, A_y_i, A_theta_i, dA_<k>_<i>_<j>[, M_<i>_<j>,
M_gamma_dot_<i>, power_on_cycle]``, then each estimate's standard error ``<column>_se``, see
:func:`connection_table`) and PNG plots (unless ``--no-figures``):
``held_out_velocity.png`` (recorded body velocity against the model's prediction and the
phase average on the last cycles, fitted without them), and with 95% confidence bands the
connection (``ConnectionEstimator.model_``), the limit cycle and the metric. Where the
forecasting model differs from the connection (a short recording, whose complexity was
chosen by held-out error: a ridge on ``Â``, or components predicted by the phase average or
the connection alone), that model
(``ConnectionEstimator.forecast_model_``, what ``predict`` uses and the printed held-out R² is
of) goes to ``DIR/forecast_model.npz``, and the printout says which is which. ``M_gamma_dot``
(``M̂γ̇``) and ``power_on_cycle`` (``γ̇ᵀM̂γ̇``) are what the gait itself identifies; the full
``M̂`` is only as good as the recording's off-cycle excitation (see the bands in ``metric.png``).
``DIR/fit.json`` records the settings of every estimator stage, the data (and conversion)
summary, the checks, the gait (frequency in Hz, :func:`gait_summary`), the units of its
numbers and of the table's columns (:data:`UNITS`) and the versions. Every estimator
setting is reachable through ``--config`` (an ``[estimator]`` table with stage sub-tables, read by
:func:`~torchconn.regression.estimator.estimator_from_settings`) and
``--set estimator.<stage>.<field>=value``. The outputs replace ``DIR`` whole once all are
written (:class:`~torchconn._output.OutputFolder`): never half a fit, nor a mix of two. Exit
codes: 0 done, 2 bad input or an unusable output folder (one line says what to fix), 1 an
internal error.
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path

import torch

from ._cli import InputError, resolve_device, run_command, set_threads
from ._output import OutputFolder, write_bytes_atomic, write_table
from ._provenance import write_sidecar
from .cli.common import add_common, add_config, config_tables, informer
from .cli.conversion import (
    add_conversion_arguments,
    add_links,
    check_conversion_table,
    conversion_flags,
    conversion_settings,
    load_recordings,
    report_checks,
    resolve_links,
    warn_unused_conversion,
)
from .fit_report import fit_report
from .io.preflight import CYCLE_RULES, CycleRule, preflight
from .io.trajectory_files import read_csv
from .known import changes_data, parse_known, relative_to_known
from .physics.systems.swimmer import NLinkSwimmer
from .regression.defaults import pooled_estimator
from .regression.estimator import ConnectionEstimator, estimator_settings
from .regression.model import ROWS, LocalConnectionModel
from .regression.reference import FAMILIES
from .regression.selection import COMPONENTS, PoorHeldOutSkillWarning, nested_list

__all__ = ["connection_table", "write_connection_csv", "gait_summary", "UNITS", "main"]

PROG = "torchconn-fit"
#: where ``fit`` writes the forecasting model when it differs from the connection (model.npz)
FORECAST_FILE = "forecast_model.npz"
#: the fit's report: its summary in words, tables and figures, one self-contained HTML file
REPORT_FILE = "report.html"


#: rows of connection.csv (``--grid``, :func:`connection_table`'s ``n_points``)
GRID = 100


def connection_table(model: LocalConnectionModel, n_points: int = GRID):
    """Columns and rows of ``connection.csv`` for an unbatched model, on a uniform phase grid
    (computed from a CPU copy of the model).

    Columns: ``phase`` (rad), the limit cycle ``r1…rd`` (rad), ``A_<k>_<i>`` (``k`` in x, y:
    body lengths per rad; theta: rad per rad), ``dA_<k>_<i>_<j>`` (per rad), and with a metric
    ``M_<i>_<j>``, ``M_gamma_dot_<i>``, ``power_on_cycle`` (power units). Then, for each of
    these estimates, its standard error ``<column>_se``: the per-bin standard errors of
    :attr:`LocalConnectionModel.bins` (whose ±1.96 SE are the 95% bands of the plots),
    interpolated linearly in phase (periodically) between the bin centres.
    """
    if model.batch_shape:
        raise ValueError(f"connection_table needs one model, got batch {tuple(model.batch_shape)}")
    model = model.to("cpu")
    d = model.shape_dim
    phi = torch.arange(n_points, dtype=torch.float64, device=model.device) * (2 * math.pi / n_points)
    bins = model.bins
    cols = ["phase"] + [f"r{i + 1}" for i in range(d)]
    blocks = [phi[:, None], model.gamma_at(phi)]
    # (column names, values on the grid, per-bin standard errors) of each estimate
    estimates = [([f"A_{k}_{i + 1}" for k in ROWS for i in range(d)],
                  model.connection(phi), bins.A_se),
                 ([f"dA_{k}_{i + 1}_{j + 1}" for k in ROWS for i in range(d) for j in range(d)],
                  model.connection_jacobian(phi), bins.dA_se)]
    if model.M is not None:
        estimates += [([f"M_{i + 1}_{j + 1}" for i in range(d) for j in range(d)],
                       model.metric(phi), bins.M_se),
                      # the parts of M̂ the gait itself identifies, beside the full M̂
                      ([f"M_gamma_dot_{i + 1}" for i in range(d)], model.metric_gamma_dot(phi),
                       bins.M_gamma_dot_se),
                      (["power_on_cycle"], model.power_on_cycle(phi), bins.power_on_cycle_se)]
    for names, values, _ in estimates:
        cols += names
        blocks.append(values.reshape(n_points, -1))
    for names, _, se in estimates:
        if se is not None:
            cols += [f"{name}_se" for name in names]
            blocks.append(_between_bins(bins.phase, se, phi).reshape(n_points, -1))
    return cols, torch.cat(blocks, -1).tolist()


def _between_bins(centres: torch.Tensor, values: torch.Tensor, phase: torch.Tensor
                  ) -> torch.Tensor:
    """``values`` ``(M, ...)`` given at the bin centres ``(M,)`` (rad), interpolated linearly
    and periodically (period 2π) to ``phase`` ``(P,)``; ``(P, ...)``."""
    order = torch.argsort(centres)
    c, v = centres[order], values[order]
    c = torch.cat([c[-1:] - 2 * math.pi, c, c[:1] + 2 * math.pi])
    v = torch.cat([v[-1:], v, v[:1]])
    x = torch.remainder(phase, 2 * math.pi)
    j = torch.searchsorted(c, x, right=True).clamp(1, len(c) - 1)
    w = ((x - c[j - 1]) / (c[j] - c[j - 1])).reshape(-1, *[1] * (v.ndim - 1))
    return v[j - 1] + w * (v[j] - v[j - 1])


def write_connection_csv(model: LocalConnectionModel, path: Path | str, n_points: int = GRID
                         ) -> Path:
    """Write :func:`connection_table` to ``path`` (CSV with a header row), atomically."""
    return write_table(path, *connection_table(model, n_points))


#: the units of fit.json's numbers and of connection.csv's columns (``*`` any index; ``t``
#: in seconds, as ``torchconn-convert`` writes it: docs/conventions.md, "Units")
UNITS = {
    "t, dt, period_s": "s", "gait_frequency_hz": "Hz (gait cycles per second)",
    "x, y": "body lengths", "theta, r*, phase": "rad", "phase_rate": "rad/s",
    "v_x, v_y": "body lengths/s", "omega": "rad/s",
    "A_x_*, A_y_*": "body lengths/rad", "A_theta_*": "rad/rad",
    "dA_x_*, dA_y_*": "body lengths/rad^2", "dA_theta_*": "1/rad",
    "M_*": "power units s^2/rad^2", "M_gamma_dot_*": "power units s/rad",
    "power_on_cycle": "power units", "*_se": "those of the column it is the standard error of",
    "R2": "1 (fraction of the velocity's variance explained)",
}


def gait_summary(model: LocalConnectionModel) -> dict:
    """The gait of an unbatched model: its phase rate (rad/s), frequency (Hz) and period
    (s), from the phase estimated on the recording's time base (``t``, seconds)."""
    rate = float(model.phase_rate)
    return {"phase_rate": rate, "frequency_hz": rate / (2 * math.pi),
            "period_s": 2 * math.pi / rate}


#: most rows of connection.csv (``--grid``): a phase step of 6e-5 rad, far finer than any fit
_MAX_GRID = 100_000

#: shortcut flags -> the (stage, field) they set
_FLAGS = {"n_bins": ("regression", "n_bins"), "fourier_order": ("regression", "fourier_order"),
          "window": ("regression", "window"), "phase_order": ("phaser", "order")}

#: the estimator's stage names: ``--set regression.kernel=box`` means ``estimator.regression…``
_STAGE_KEYS = ("smoother", "phaser", "cycle", "regression", "pool", "complexity",
               "held_out_folds", "prior")


def _phase_order(text: str) -> int | str:
    """``--phase-order``: ``auto`` or an integer."""
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer or 'auto', got {text!r}") from None


def build_estimator(args, table: dict | None) -> ConnectionEstimator:
    """The estimator of ``fit``: :func:`~torchconn.regression.defaults.pooled_estimator` (the
    API's defaults, trials pooled), then the ``[estimator]`` table (nested per stage, see
    :func:`estimator_from_settings`), then the shortcut flags."""
    table = dict(table or {})
    if args.complexity is not None:
        table["complexity"] = args.complexity
    if args.folds is not None:
        table["held_out_folds"] = args.folds
    if args.prior is not None:
        table["prior"] = None if args.prior == "none" else args.prior
    if args.regression is not None:
        table["regression"] = {**table.get("regression", {}), "method": args.regression}
    if args.metric is not None:  # auto: fit the metric when there is a power column
        table["metric"] = {**table.get("metric", {}),
                           "enabled": {"auto": None, "yes": True, "no": False}[args.metric]}
    for flag, (stage, field) in _FLAGS.items():
        v = getattr(args, flag)
        if v is not None:
            table[stage] = {**table.get(stage, {}), field: v}
    try:
        estimator = pooled_estimator(table)
    except ValueError as err:
        raise InputError(f"estimator options: {err}") from None
    if not estimator.pool:
        raise InputError("estimator.pool = false: torchconn-fit writes one model for all the "
                         "trials it reads (pooled); for one model per trial run it on each "
                         "file, or use ConnectionEstimator(pool=False) in Python")
    return estimator


def _parser() -> argparse.ArgumentParser:
    """The argument parser of ``torchconn-fit``."""
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Fit one local connection model (and the metric, when the files have a "
        "power column) to your recorded trials, pooled, and write DIR/model.npz, "
        "DIR/connection.csv (one row per phase), PNG plots with 95% bands and DIR/fit.json. "
        "Reads trajectory CSVs or tracking files. The estimator is ConnectionEstimator's "
        "defaults with the trials pooled (in Python: "
        "torchconn.regression.defaults.pooled_estimator(), the same numbers). "
        "Also runs as python -m torchconn.fit.",
    )
    p.add_argument("data", nargs="+", type=Path,
                   help="trajectory CSV files: columns t, x, y, theta, r1..rd[, power][, trial], "
                   'one trial per file or several with a trial column (format: '
                   'docs/conventions.md, section "Trajectory file format"); or tracking files '
                   "(SLEAP, DeepLabCut, WCON, points: docs/tracking.md)")
    add_links(p)
    p.add_argument("--out", type=Path, required=True, help="output directory")
    add_config(p, "TOML file with an [estimator] table (stage sub-tables [estimator.phaser], "
               "[estimator.regression], ...) and a [convert] table",
               "override a setting, e.g. --set estimator.regression.ridge=1e-6 or, for a "
               "stage, the short form --set regression.kernel=box (stages: smoother, phaser, "
               "cycle, regression; repeatable)")
    default = pooled_estimator()  # the defaults the help names: the API's, trials pooled
    p.add_argument("--n-bins", type=int, help="phase bins (estimator.regression.n_bins, "
                   f"default {default.regression.n_bins})")
    p.add_argument("--fourier-order", type=int,
                   help="Fourier order in phase (estimator.regression.fourier_order, default "
                   f"{default.regression.fourier_order})")
    p.add_argument("--window", type=float,
                   help="bin half-width in bin spacings (default: sized from the data)")
    p.add_argument("--phase-order", type=_phase_order, metavar="K|auto",
                   help="Phaser correction order (estimator.phaser.order): an integer, or "
                   "'auto' (default) to choose it from the data")
    p.add_argument("--regression", choices=("noise_aware", "tube"),
                   help="noise_aware (default): regress on raw differences with the "
                   "motion-capture noise removed, shrunk towards the smoothed fit where the data "
                   "cannot support the correction; tube: on Kalman-smoothed velocities "
                   "(torchconn 0.1's method)")
    p.add_argument("--complexity", choices=("auto", "fixed", "cv"),
                   help="auto (default): --n-bins and --fourier-order as given unless the model "
                   "then predicts held-out cycles worse than their phase-averaged velocity, "
                   "then as cv; fixed: as given; cv: bins, Fourier order and ridge chosen by "
                   "held-out error over blocks of whole cycles (estimator.complexity)")
    p.add_argument("--folds", type=int,
                   help="blocks of whole cycles for the held-out check and the complexity "
                   f"choice (estimator.held_out_folds, default {default.held_out_folds}; 0 "
                   "skips the check)")
    p.add_argument("--prior", choices=(*FAMILIES, "none"),
                   help="the physics reference the forecasts may lean on where it predicts "
                   "held-out cycles better, and the baseline reported beside the model: "
                   "swimmer (default), the viscous N-link swimmer with its drag ratio fitted; "
                   "none: no prior (estimator.prior)")
    p.add_argument("--metric", choices=("auto", "yes", "no"),
                   help="estimate the dissipation metric: auto (default) when the files have a "
                   "power column, yes to require one, no never")
    p.add_argument("--known", action="append", default=[], metavar="EFFECT:P=V,...",
                   help="a known condition, e.g. ambient_flow:u_x=0.01,u_y=0 (repeatable): the "
                   "recording is modelled relative to it")
    p.add_argument("--grid", type=int, default=GRID,
                   help=f"rows of connection.csv (>= 2, default {GRID})")
    add_conversion_arguments(p)
    add_common(p)
    return p


def _check_flags(args) -> None:
    """Refuse out-of-range numeric flags (``--links``, ``--grid``, ``--folds``, ``--window``)."""
    if args.links is not None and args.links < 2:
        raise InputError(f"--links must be >= 2, got {args.links}")
    if args.grid < 2:
        raise InputError(f"--grid must be >= 2 (rows of connection.csv), got {args.grid}")
    if args.grid > _MAX_GRID:
        raise InputError(f"--grid must be <= {_MAX_GRID} (rows of connection.csv), got "
                         f"{args.grid}")
    if args.folds is not None and (args.folds < 0 or args.folds == 1):
        raise InputError(f"--folds must be 0 (no held-out check) or >= 2, got {args.folds}")
    if args.window is not None and not (math.isfinite(args.window) and args.window > 0):
        raise InputError(f"--window must be a positive number, got {args.window}")


def _config_tables(args) -> dict:
    """The ``--config`` file with the ``--set`` overrides applied (a stage's short form
    ``regression.kernel=box`` read as ``estimator.regression.kernel``), checked to hold only
    an ``[estimator]`` table and a valid ``[convert]`` table."""
    overrides = [f"estimator.{o}" if o.split(".", 1)[0] in _STAGE_KEYS else o
                 for o in args.overrides]
    tables = config_tables(args.config, overrides)
    unknown = sorted(set(tables) - {"estimator", "convert"})
    if unknown:
        raise InputError(f"unknown config section(s) {unknown}; fit reads [estimator] and "
                         "[convert]")
    if not isinstance(tables.get("estimator", {}), dict):
        raise InputError(f"[estimator] must be a table of estimator settings, got "
                         f"{tables['estimator']!r}")
    check_conversion_table(tables.get("convert"))  # checked even where no file needs it
    return tables


def _swimmer_and_known(args, tables: dict) -> tuple[NLinkSwimmer, list]:
    """The swimmer of ``--links`` in the frame of ``--frame`` (or ``[convert] frame``, else
    the centre link for odd N and the mean-rotation frame for even N), and the ``--known``
    conditions, each checked to change the data (not only the simulator)."""
    frame = args.frame or (tables.get("convert", {}).get("frame")
                           or ("center" if args.links % 2 else "com-mean"))
    swimmer = NLinkSwimmer(args.links, frame=frame)
    known = [parse_known(k, swimmer) for k in args.known]
    for k in known:
        if not changes_data(k):
            raise InputError(f"--known {k.name}: it changes only the simulator, and fit "
                             "estimates the model from the data without one; give it to "
                             "torchconn-discrepancy instead")
    return swimmer, known


def main(argv: list[str] | None = None) -> int:
    """Run ``torchconn-fit`` on ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    args = _parser().parse_args(argv)
    say = informer(args.quiet)

    def body() -> int:
        set_threads(args.threads)
        device = resolve_device(args.device)
        _check_flags(args)
        tables = _config_tables(args)
        given = conversion_flags(args)
        estimator = build_estimator(args, tables.get("estimator"))
        args.links, how = resolve_links(args.links, args.data, args.format)
        if how:
            say(how)

        def conv():  # conversion options matter (and are checked) for tracking files only
            return conversion_settings(args, args.links, tables.get("convert"))

        swimmer, known = _swimmer_and_known(args, tables)
        with OutputFolder(args.out, command=PROG) as folder:
            rec, traj, check = _read_checked(args, conv, given, known, swimmer, estimator, say)
            traj = traj.to(device)  # read and checked on the CPU, moved once
            # the frame of the velocities, for the physics reference
            traj = traj.with_fields(meta={**traj.meta, "frame": swimmer.frame})
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", PoorHeldOutSkillWarning)  # reported below
                est = estimator.fit(traj)
            model = est.model_.to("cpu")  # outputs are written from CPU copies
            # the model predict() uses, where it differs from the connection (short recordings)
            forecast = None if est.forecast_model_ is est.model_ else est.forecast_model_.to("cpu")
            details: list[str] = []
            _report_metric(model, details.append)
            if est.complexity_ is not None:
                _report_complexity(est.complexity_, details.append)
            if forecast is not None:
                _report_forecast(model, details.append)
            if est.held_out_skill_ is not None:
                _report_held_out(est, details.append)
            figures = {} if args.no_figures else _figures(est, model)
            report = fit_report(
                est, title=f"{PROG}: {', '.join(p.name for p in args.data)}",
                n_links=args.links, frame=swimmer.frame,
                frequency_hz=gait_summary(model)["frequency_hz"],
                reference=_reference_words(est.reference_),
                figures=[(png, caption or name) for name, (png, caption) in figures.items()],
                details=details)
            outputs = _write_results(folder.path, args, model, forecast, figures)
            report.write(folder.path / REPORT_FILE)
            outputs.append(REPORT_FILE)
            write_sidecar(folder.path / "fit.json", {
                "command": PROG, "argv": sys.argv[1:] if argv is None else list(argv),
                **_sidecar(args, estimator, est, rec, traj, check, known, model, forecast),
                "outputs": outputs,
                "device": str(device),
            })
            out = folder.commit()
            say("\n".join(report.text()))
            say(f"wrote {', '.join(str(out / o) for o in outputs)} and {out / 'fit.json'}; "
                f"open {out / REPORT_FILE} in a browser for the report with its figures")
            return 0

    return run_command(PROG, body)


def _read_checked(args, conv, given, known, swimmer, estimator, say):
    """Read the recordings (converting tracking files), make them relative to the known
    conditions and print the checks before fitting; returns ``(recordings, trajectory,
    checks)``, or raises :class:`InputError` when the recording is not ready to fit."""
    rec = load_recordings(args.data, fmt=args.format, n_links=args.links,
                          settings=conv, read_csv=read_csv)
    warn_unused_conversion(rec, given)
    traj = relative_to_known(rec.trajectory, known, swimmer)
    # the phase estimator's own minimum (``--set phaser.min_cycles=...``) is the fit's rule
    need = getattr(estimator.phaser, "min_cycles", CYCLE_RULES["fit"].per_trial)
    check = preflight(traj, body_length=rec.body_length,
                      rules={"fit": CycleRule(per_trial=need, total=need)})
    report_checks(check, say, "fit")
    if not check.ready["fit"]:
        raise InputError("the recording is not ready to fit: "
                         + "; ".join(check.problems["fit"]))
    return rec, traj, check


def _figures(est, model) -> dict[str, tuple[bytes, str | None]]:
    """The fit's figures by file name, each rendered once for its file and for the report
    (PNG bytes and caption, :func:`~torchconn.plotting.render_png`): the held-out velocity
    first, then the connection, the limit cycle and the metric (where fitted)."""
    # lazy: the plots import matplotlib, which only a fit that draws figures needs
    from .plotting import render_png
    from .regression import plots

    figures = {"held_out_velocity.png": plots.plot_held_out_velocity(est),
               "connection.png": plots.plot_connection(model),
               "limit_cycle.png": plots.plot_limit_cycle(model, est.trajectory_.smoothed.r,
                                                         est.trajectory_.phase)}
    if model.M is not None:
        figures["metric.png"] = plots.plot_metric(model)
    return {name: render_png(fig) for name, fig in figures.items()}


def _write_results(out: Path, args, model, forecast, figures: dict) -> list[str]:
    """Write ``model.npz``, ``connection.csv``, the forecasting model where it differs and the
    ``figures`` (file name -> (PNG bytes, caption)) into ``out``; returns the names
    written."""
    model.save(out / "model.npz")
    write_connection_csv(model, out / "connection.csv", args.grid)
    outputs = ["model.npz", "connection.csv"]
    if forecast is not None:
        forecast.save(out / FORECAST_FILE)
        outputs.append(FORECAST_FILE)
    for name, (png, _) in figures.items():
        write_bytes_atomic(out / name, png)
        outputs.append(name)
    return outputs


def _sidecar(args, estimator, est, rec, traj, check, known, model, forecast) -> dict:
    """The entries of ``fit.json`` that describe the settings, the data, the checks and the
    fit (``command``, ``argv``, ``outputs`` and ``device`` are added by the caller)."""
    held_out = est.held_out_skill_
    return {
        "settings": {"estimator": estimator_settings(estimator),
                     "convert": rec.reports[0].settings if rec.reports else None},
        "known": [k.to_dict() for k in known],
        "data": {"sources": [str(x) for x in args.data],
                 "n_trials": int(traj.batch_shape.numel()), "n_samples": traj.n_samples,
                 "dt": traj.dt, "trials": traj.meta.get("trials"),
                 "conversion": [r.to_dict() for r in rec.reports]},
        "preflight": check.to_dict(),
        "model": {"window": model.meta.get("window"), "metric": model.M is not None},
        "gait": gait_summary(model),
        "units": UNITS,
        # how the forecasting model (forecast_model.npz) differs from model.npz; None:
        # model.npz is the forecasting model too
        "forecast_model": None if forecast is None else {
            "file": FORECAST_FILE, **model.meta["forecast_model"]},
        "complexity": (None if est.complexity_ is None else
                       {"n_bins": est.complexity_.n_bins,
                        "fourier_order": est.complexity_.fourier_order,
                        "ridge": est.complexity_.ridge,
                        "checked": est.complexity_.checked,
                        "connection_regressed": est.complexity_.connection_regressed,
                        "components": list(COMPONENTS),
                        "phase_averaged": nested_list(est.complexity_.phase_averaged),
                        "connection_only": nested_list(
                            est.complexity_.connection_only)}),
        "held_out_skill": (None if held_out is None
                           else _skill_summary(held_out, est.held_out_folds)),
        # per component the model's held-out R² and its three baselines', on interleaved
        # blocks of cycles and on the last block fitted on the earlier ones
        "held_out": None if held_out is None else {
            "folds": est.held_out_folds,
            "interleaved": _baselines_summary(held_out),
            "forward": (None if est.forward_skill_ is None
                        else _baselines_summary(est.forward_skill_)),
            # per component the forecasts' share of the physics reference (0: the model)
            "prior_weight": (None if est.prior_weight_ is None
                             else est.prior_weight_.tolist())},
        "reference": (None if est.reference_ is None
                      else {**est.reference_.describe(), "n_links": est.reference_.n_links}),
    }


def _report_metric(model, say) -> None:
    """Print the shape noise estimated for the metric and what of it the gait identifies."""
    if model.M is None:
        return
    noise = (model.meta or {}).get("metric_noise_std")
    if noise is not None:
        say("shape noise estimated for the metric (rad): "
            + ", ".join(f"r{i + 1} {w:.2g}" for i, w in enumerate(noise)))
    say("metric: M_gamma_dot and power_on_cycle are identified by the gait itself; "
        "the full M only as far as the data leave the cycle (see the bands in "
        "metric.png)")


def _report_complexity(c, say) -> None:
    """Print the complexity used (given or chosen held out) and which components the
    forecasting model predicts by a baseline (phase average, connection alone)."""
    if not c.checked:
        say(f"complexity as given ({c.n_bins} bins, Fourier order "
            f"{c.fourier_order}, ridge {c.ridge:g}): no held-out check can score it "
            "or a simpler one on this short recording, so "
            f"{', '.join(c.phase_averaged_names())} are predicted by the "
            f"phase-averaged velocity (rows of A, b and dA/dr 0 in {FORECAST_FILE}; "
            "model.npz holds the given complexity's estimates, unchecked)")
    else:
        say(f"complexity chosen by held-out error: {c.n_bins} bins, Fourier order "
            f"{c.fourier_order}, ridge {c.ridge:g}")
    if c.connection_regressed:
        say("no model with the offset terms b and dA/dr can be checked held out on "
            "this recording (too few samples per bin without one block of cycles), "
            "so the connection alone (1 + d regressors per bin) was fitted and "
            "checked instead; model.npz holds it (b and dA/dr not estimated: 0)")
    if c.checked and c.phase_averaged_names():
        say("forecasts predict by the phase-averaged velocity (the shape terms did not "
            "beat it on held-out cycles; their rows of A, b and dA/dr are 0 in "
            f"{FORECAST_FILE}): {', '.join(c.phase_averaged_names())}")
    if c.connection_only_names() and not c.connection_regressed:
        say("forecasts predict by the connection alone (the offset terms did not add "
            "to it on held-out cycles; their rows of b and dA/dr are 0 in "
            f"{FORECAST_FILE}, A is kept): {', '.join(c.connection_only_names())}")
    elif c.connection_only_names():
        say("forecasts predict by the connection alone (it beat the phase-averaged "
            f"velocity on held-out cycles): {', '.join(c.connection_only_names())}")


def _report_forecast(model, say) -> None:
    """Print how ``model.npz`` (the connection) and the forecasting model differ."""
    differs, own = model.meta["forecast_model"], model.meta["settings"]["regression"]
    ridge = differs["A_ridge"]
    # the connection's own setting, not the forecasts' ridge: its complexity may have
    # been chosen with A unpenalised where the forecasts' ridge is 0
    free = own.get("ridge_connection", True) is False
    say("model.npz, connection.csv and the plots: the connection, every row estimated "
        f"({own['n_bins']} bins, Fourier order {own['fourier_order']}, ridge "
        f"{own['ridge']:g}" + (" on b and dA/dr only, A unpenalised: the complexity "
                               "chosen held out with A unpenalised)"
                               if free else ")"))
    how = [f"{differs['n_bins']} bins, Fourier order {differs['fourier_order']}"] + (
        [f"A shrunk by the ridge {ridge:g}"] if ridge else []) + (
        ["rows 0 where named above"]
        if differs["phase_averaged"] or differs["connection_only"] else [])
    say(f"{FORECAST_FILE}: the forecasting model (what ConnectionEstimator.predict "
        "uses, and the held-out R² above): " + ", ".join(how))


def _report_held_out(est, say) -> None:
    """Say how far the forecasts lean on the physics reference (the held-out R² of the model
    and its baselines are the report's table), and warn
    (:class:`PoorHeldOutSkillWarning`) where bins cannot be scored, the model loses to the
    phase average, or nothing has skill."""
    held_out = est.held_out_skill_
    weight = est.prior_weight_
    if weight is not None and bool((weight > 0).any()):
        shrunk = [f"{name} {float(w):.0%}" for name, w in zip(
            COMPONENTS, weight.reshape(-1, 3).amax(0).tolist(), strict=True) if w > 0]
        say("physics prior: the forecasts lean towards the physics reference where it "
            "predicts held-out cycles better (share of the reference: " + ", ".join(shrunk)
            + "); the model's held-out R² are of these forecasts, the connection (Â) is "
            "as estimated")
    if bool(held_out.unscored.any()):
        warnings.warn("some phase bins cannot be fitted when a block of cycles is "
                      "left out: the model has too many coefficients for this recording "
                      "(record more cycles, or use fewer --n-bins)", PoorHeldOutSkillWarning,
                      stacklevel=2)
    elif bool(held_out.worse_than_phase_average.any()):
        warnings.warn("the model predicts held-out cycles worse than the phase-averaged "
                      f"velocity for {held_out.shortfalls()}: its shape terms do not help "
                      "predict those components on this recording ("
                      + ("record more cycles; the complexity was already chosen by held-out "
                         "error)" if est.complexity_ is not None else "try --complexity cv, "
                         "fewer --n-bins, a lower --fourier-order or a wider --window, or "
                         "record more cycles)"), PoorHeldOutSkillWarning, stacklevel=2)
    if bool(held_out.without_skill.any()):
        warnings.warn("neither the model nor the phase-averaged velocity predicts "
                      "held-out cycles better than their mean velocity for "
                      f"{held_out.without_skill_names()}: not predictable from the gait's "
                      "phase and shape on this recording (noise, or a motion the shape "
                      "changes do not drive: a flow, a tether, contact)",
                      PoorHeldOutSkillWarning, stacklevel=2)


def _reference_words(ref) -> str:
    """The physics reference in words, e.g. ``the 5-link viscous swimmer (resistive-force
    theory, center frame), drag ratio 41.2 fitted``."""
    if ref is None:
        return ""
    return (f"the {ref.n_links}-link viscous swimmer (resistive-force theory, {ref.frame} "
            f"frame), {_parameters(ref)} fitted")


def _parameters(ref) -> str:
    """The reference's fitted parameters in words, e.g. ``drag ratio 2.31`` (per trial where
    there are several)."""
    return ", ".join(f"{name.replace('_', ' ')} "
                     + ", ".join(f"{v:.3g}" for v in value.reshape(-1).tolist())
                     for name, value in ref.parameters.items())


def _baselines_summary(skill) -> dict:
    """Per component (v_x, v_y, omega) the R² of the model, the phase average, the physics
    reference and zero (None where not scored): a number for pooled trials, else a nested
    list shaped like the trials."""
    columns = (("model", skill.r2), ("phase_average", skill.r2_phase_average),
               ("physics", skill.r2_physics), ("zero", skill.r2_zero))
    return {name: {key: None if r2 is None else r2[..., k].tolist() for key, r2 in columns}
            for k, name in enumerate(COMPONENTS)}


def _skill_summary(skill, n_folds: int) -> dict:
    """Held-out R² per component (v_x, v_y, omega) of the model and its two baselines."""
    return {"folds": n_folds, "components": ["v_x", "v_y", "omega"],
            "model": skill.r2.reshape(-1).tolist(),
            "phase_average": skill.r2_phase_average.reshape(-1).tolist(),
            "template": skill.r2_template.reshape(-1).tolist(),
            "worse_than_phase_average": skill.worse_than_phase_average.reshape(-1).tolist(),
            "without_skill": skill.without_skill.reshape(-1).tolist()}


if __name__ == "__main__":
    sys.exit(main())
