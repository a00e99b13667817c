"""``torchconn-discrepancy DATA.csv [MORE.csv ...] [--links N] --out DIR``.

Also runs as ``python -m torchconn.discrepancy``. Reads the recordings (the format of
docs/conventions.md, section "Trajectory file format"), compares them with the nominal N-link swimmer,
names the missing effect(s) and writes ``DIR/report.html`` (the verdict in words, with the
figures), ``DIR/report.json``, ``DIR/augmented_model.json``,
``DIR/residual_profile.csv`` and the figures; prints a readable summary. The outputs replace
``DIR`` whole once all are written (:class:`~torchconn._output.OutputFolder`). Exit codes: 0
done, 2 bad input or an unusable output folder (one line says what to fix), 1 an internal
error.
Unknown columns are warned about.
"""

from __future__ import annotations

import argparse
import inspect
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

from .._cli import (
    InputError,
    check_center_frame,
    check_keys,
    did_you_mean,
    resolve_device,
    run_command,
    set_threads,
)
from .._files import read_toml
from .._options import check_field
from .._output import OutputFolder
from ..cli.common import add_common, informer
from ..cli.conversion import (
    add_conversion_arguments,
    add_links,
    conversion_flags,
    conversion_settings,
    load_recordings,
    report_checks,
    resolve_links,
    warn_unused_conversion,
)
from ..io.preflight import preflight
from ..io.trajectory_files import read_csv
from ..known import known_system, parse_known, relative_to_known
from ..physics.effects import REGISTRY
from ..physics.systems.swimmer import NLinkSwimmer
from .workflow import DiscrepancySettings, diagnose

PROG = "torchconn-discrepancy"
#: the defaults the flags name: the API's own (DiscrepancySettings, NLinkSwimmer)
_DEFAULTS = DiscrepancySettings()
_DRAG_RATIO = inspect.signature(NLinkSwimmer).parameters["drag_ratio"].default


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Find where a recording and the nominal N-link swimmer disagree, name the "
        "missing physical effect, add it and report the gap before and after. Writes "
        "DIR/report.html, DIR/report.json, DIR/augmented_model.json, "
        "DIR/residual_profile.csv and figures. "
        "Also runs as python -m torchconn.discrepancy.",
    )
    p.add_argument("data", nargs="+", type=Path,
                   help="trajectory CSV file(s): columns t, x, y, theta, r1..rd[, power][, trial] "
                   '(format: docs/conventions.md, section "Trajectory file format"), or tracking '
                   "files (converted as by torchconn-convert, same options)")
    add_links(p)
    p.add_argument("--drag-ratio", type=float, default=_DRAG_RATIO,
                   help=f"nominal lateral/longitudinal drag ratio (default {_DRAG_RATIO:g})")
    p.add_argument("--frame", default=None, choices=("center", "com-mean"),
                   help="body frame of the recorded pose (default: center)")
    p.add_argument("--link-lengths", type=float, nargs="+", default=None,
                   help="nominal link lengths (default: N equal links of total length 1)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--candidates", nargs="+", default=None, choices=sorted(REGISTRY),
                   help="effects to screen (default: all registered)")
    p.add_argument("--config", type=Path, default=None,
                   help="TOML file with a [discrepancy] table of DiscrepancySettings fields")
    p.add_argument("--alpha", type=float, default=None,
                   help=f"significance level (default {_DEFAULTS.alpha:g})")
    p.add_argument("--folds", type=int, default=None,
                   help=f"cross-validation folds (default {_DEFAULTS.n_folds})")
    p.add_argument("--no-terms", action="store_true",
                   help="skip the term-by-term comparison with the Stage 4 local model")
    p.add_argument("--known", action="append", default=[], metavar="EFFECT:P=V,...",
                   help="a condition with known parameters, e.g. ambient_flow:u_x=0.01,u_y=0 "
                   "(repeatable): the recording is modelled with it and it is not screened")
    add_conversion_arguments(p, frame=False)
    add_common(p, quiet_help="print only the verdict line")
    return p


def _settings(args) -> DiscrepancySettings:
    """:class:`DiscrepancySettings` from ``--config``'s ``[discrepancy]`` table, then the flags;
    every value checked (type, range) with the key or flag it came from."""
    values, origin = {}, {}
    if args.config is not None:
        path = args.config
        table = read_toml(path, "--config")
        where = f"--config {path}: [discrepancy]"
        others = sorted(k for k in table if k != "discrepancy" and isinstance(table[k], dict))
        if others:
            raise InputError(f"--config {path}: unknown section(s) "
                             f"{', '.join(f'[{k}]' for k in others)}; discrepancy reads a "
                             "[discrepancy] table of settings")
        section = table.get("discrepancy", table)
        if not isinstance(section, dict):
            raise InputError(f"{where} must be a table of settings, got {section!r}")
        check_keys(section, DiscrepancySettings.__dataclass_fields__, where)
        values.update(section)
        origin.update({k: f"{where} {k}" for k in section})
        if values.get("candidates") is not None:
            c = values["candidates"]
            if not isinstance(c, list) or not all(isinstance(x, str) for x in c):
                raise InputError(f"{where} candidates must be a list of effect names "
                                 f"({', '.join(REGISTRY)}), got {c!r}")
            unknown = [x for x in c if x not in REGISTRY]
            if unknown:
                raise InputError(f"{where} candidates: unknown effect {unknown[0]!r}"
                                 f"{did_you_mean(unknown[0], REGISTRY)}; registered: "
                                 f"{', '.join(REGISTRY)}")
            values["candidates"] = tuple(c)
    for flag, key, value in (("--candidates", "candidates", args.candidates),
                             ("--alpha", "alpha", args.alpha), ("--folds", "n_folds", args.folds),
                             ("--no-terms", "compare_terms", False if args.no_terms else None)):
        if value is not None:
            values[key] = tuple(value) if key == "candidates" else value
            origin[key] = flag
    for key, value in values.items():
        if key != "candidates":
            try:
                check_field(DiscrepancySettings, key, value, origin[key])
            except ValueError as err:
                raise InputError(str(err)) from None
    try:
        return DiscrepancySettings(**values)
    except (TypeError, ValueError) as err:
        raise InputError(f"[discrepancy] settings: {err}") from None


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    say = (lambda *_: None) if args.quiet else (lambda msg: print(f"  {msg}", flush=True))

    def body() -> int:
        set_threads(args.threads)
        device = resolve_device(args.device)
        if args.links is not None and args.links < 2:
            raise InputError(f"--links must be at least 2, got {args.links}")
        args.links, how = resolve_links(args.links, args.data, args.format)
        if how:
            informer(args.quiet)(how)
        if not (math.isfinite(args.drag_ratio) and args.drag_ratio > 0):
            raise InputError(f"--drag-ratio must be a positive number, got {args.drag_ratio}")
        if args.link_lengths is not None and (
                len(args.link_lengths) != args.links
                or not all(math.isfinite(x) and x > 0 for x in args.link_lengths)):
            raise InputError(f"--link-lengths must give {args.links} positive numbers (one per "
                             f"link, --links {args.links}), got {args.link_lengths}")
        frame = args.frame or "center"
        check_center_frame(args.links, frame)
        system = NLinkSwimmer(args.links, drag_ratio=args.drag_ratio, frame=frame,
                              link_lengths=args.link_lengths)
        settings = _settings(args)
        given = conversion_flags(args)
        known = [parse_known(k, system) for k in args.known]
        def conv():  # conversion options matter (and are checked) for tracking files only
            return conversion_settings(args, args.links)

        with OutputFolder(args.out, command=PROG) as folder:
            return diagnose_into(folder, system, settings, known, conv, device, given)

    def diagnose_into(folder: OutputFolder, system, settings, known, conv, device,
                      given) -> int:
        """Read, check and diagnose the recordings; write the outputs into ``folder``, whose
        contents replace ``--out`` when this returns."""
        rec = load_recordings(args.data, fmt=args.format, n_links=args.links,
                              settings=conv, read_csv=read_csv)
        warn_unused_conversion(rec, given)
        traj = relative_to_known(rec.trajectory, known, system)
        system = known_system(system, known)
        if known:
            names = [k.name for k in known]
            pool = settings.candidates if settings.candidates is not None else tuple(REGISTRY)
            settings = replace(settings, candidates=tuple(c for c in pool if c not in names))
        check = preflight(traj, body_length=rec.body_length)
        report_checks(check, informer(args.quiet), "discrepancy")
        if not check.periodic:  # the cycle rule itself is applied by diagnose()
            raise InputError("the recording is not ready for the discrepancy workflow: "
                             + "; ".join(check.problems["discrepancy"]))
        traj = traj.to(device)  # read and checked on the CPU, moved once
        t0 = time.time()
        if not args.quiet:
            print(f"torchconn-discrepancy: {len(args.data)} file(s), {system}")
        report = diagnose(traj, system, settings, log=say)
        paths = report.save(folder.path, figures=not args.no_figures)
        folder.commit()
        paths = {k: folder.final(p) for k, p in paths.items()}
        if args.quiet:
            names = ", ".join(e.name for e in report.effects)
            print(f"verdict: {report.verdict}" + (f" ({names})" if names else ""))
        else:
            print(report.summary())
            print(f"done in {time.time() - t0:.1f} s; wrote " + ", ".join(str(p) for p in
                                                                          paths.values()))
        return 0

    return run_command(PROG, body)


if __name__ == "__main__":
    sys.exit(main())
