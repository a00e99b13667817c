"""Power study of the discrepancy workflow, beside PySINDy on the same datasets.

What can a recording reveal? For every registered effect, at a few magnitudes (factors of the
reference magnitudes in ``configs/discrepancy_power.toml``) and observation-noise levels, this
simulates replicate recordings of the 3-link swimmer at the paper's α and η with the effect
hidden, runs :func:`torchconn.discrepancy.diagnose` blind, and records

- whether it named the right effect (alone), confounded it with a look-alike, named a wrong
  one, said ``none`` or ``unexplained``;
- the relative error of the fitted parameters and whether the 95% intervals cover the truth.

Effect-free datasets (the study's own swimmer at its noise levels, and the ``[clean]`` grid of
link counts, sampling rates, noise levels and drop-out fractions) measure false discoveries,
and datasets with an effect outside the registry measure confident wrong names:
there "correct" means ``unexplained`` (possibly beside a partial
effect), never a clean ``effect``. The unregistered effects: an unmodelled lateral slip
(``ΔA_vy = ε (r2, r1)``), a first-order inertial relaxation of the body velocity
(:func:`~torchconn.discrepancy.simulate.simulate_inertial_relaxation`, which a registered time
lag imitates only with a negative lag), and a lag of the *pose* stream behind the shapes (a
negative ``time_lag``, outside its physical range). Coverage: the fraction of named effects whose
95% intervals (simultaneous over the effect's parameters) contain the truth (every parameter);
``covered_marginal`` the same with per-parameter 95% quantiles, ``covered_noise_only`` with the
standard error alone. On the *same* datasets,
the field's standard tool: a PySINDy sparse regression (STLSQ) of the nominal residual on a
library of the effects' linearised signatures -- the columns of the forward model's Jacobian in
each effect's parameters at zero (absent) -- with its threshold calibrated on the clean datasets
so that its false-positive rate is about zero too. It names the effects whose coefficients
survive.

Writes ``OUT/power.csv`` (tidy: one row per dataset and method), ``OUT/power.json`` (config,
versions, seeds, the summary table) and ``OUT/power.png``; prints the summary table.

    python benchmarks/bench_discrepancy_power.py --out runs/power [--config FILE]
        [--set study.seeds=4] [--effects ambient_flow drag_ratio] [--workers 2]

pysindy is an optional benchmark dependency (``pip install pysindy``); without it the SINDy
columns are skipped with a note.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import torch
from scipy import stats

from torchconn import plotting as style
from torchconn._provenance import write_sidecar
from torchconn.discrepancy import (
    REGISTRY,
    DiscrepancySettings,
    diagnose,
    effect_parameters,
    simulate_with_effects,
)
from torchconn.discrepancy.simulate import LateralSlipSwimmer, simulate_inertial_relaxation
from torchconn.physics.gaits import reference_gait
from torchconn.physics.systems import NLinkSwimmer

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "discrepancy_power.toml"





#: effects outside the registry, by name in the [unregistered] table
UNREGISTERED = ("unregistered_slip", "inertial_relaxation", "pose_lag")


def simulate_case(name, vals, factor, sw, gait, st, seeds, omega, spc=64, dropout=0.0):
    """One dataset: ``(recording, hidden registered effects)``."""
    kw = dict(eta=st["eta"], alpha=st["alpha"], n_cycles=int(st["n_cycles"]), seeds=seeds,
              omega=omega)
    if name == "unregistered_slip":
        return simulate_with_effects(LateralSlipSwimmer(factor * vals), gait, {}, **kw), {}
    if name == "inertial_relaxation":
        return simulate_inertial_relaxation(sw, gait, factor * vals, **kw), {}
    if name == "pose_lag":  # the poses lag the shapes: a negative time_lag
        return simulate_with_effects(sw, gait, {"time_lag": {"tau": -factor * vals}}, **kw), {}
    hidden = {} if vals is None else {name: {k: factor * v for k, v in vals.items()}}
    return simulate_with_effects(sw, gait, hidden, samples_per_cycle=spc, dropout=dropout,
                                 **kw), hidden


def _one_thread() -> None:
    torch.set_num_threads(1)


def run_job(work) -> tuple[dict, object, dict]:
    """Simulate and diagnose one dataset: ``(row, report or None, hidden effects)`` (the report
    is kept only for the SINDy comparison)."""
    (name, vals, factor, omega, rep_i, nl, spc, drop), seq, st, settings, keep = work
    sw = NLinkSwimmer(int(nl)) if nl == 3 else NLinkSwimmer(int(nl), frame="com-mean")
    gait = reference_gait(f"{nl}link")
    seeds = [int(s) for s in seq.generate_state(int(st["trials"]))]
    traj, hidden = simulate_case(name, vals, factor, sw, gait, st, seeds, omega, spc=spc,
                                 dropout=drop)
    cpu = time.process_time()
    report = diagnose(traj, sw, settings)
    cpu = time.process_time() - cpu
    if name in UNREGISTERED:
        res = report.verdict if report.verdict != "effect" else "wrong"
    else:
        res = outcome(report, name) if vals is not None else report.verdict
    row = {"effect": name, "factor": factor, "omega": omega, "replicate": rep_i,
           "n_links": nl, "samples_per_cycle": spc, "dropout": drop,
           "method": "workflow", "outcome": res,
           "named": "+".join(e.name for e in report.effects) or report.verdict,
           "partial": "+".join(e.name for e in report.partial_effects),
           "correct": int(res == "correct" or (vals is None and res == "none")
                          or (name in UNREGISTERED and res == "unexplained")),
           "param_rel_error": math.nan, "covered": math.nan, "covered_noise_only": math.nan,
           "covered_marginal": math.nan, "cpu_seconds": cpu}
    if vals is not None and name not in UNREGISTERED:
        p_true = effect_parameters(hidden, sw)[name].numpy()
        entry = next((e for e in report.effects if e.name == name), None)
        if entry is not None:
            p_hat = np.array(list(entry.fitted.values()))
            row["param_rel_error"] = float(np.linalg.norm(p_hat - p_true)
                                           / np.linalg.norm(p_true))
            truth = {k: float(v) for k, v in REGISTRY[name].physical(
                torch.as_tensor(p_true), sw).items()}
            row["covered"] = int(all(entry.ci[k][0] <= v <= entry.ci[k][1]
                                     for k, v in truth.items()))
            df = max(report.data["n_cycles"] - 1, 1)
            # the interval from the noise alone (before the twin's bias and lack of fit)
            q = float(stats.t.ppf(0.5 + entry.ci_level / 2, df=df))
            row["covered_noise_only"] = int(all(
                abs(entry.parameters[k] - v) <= q * entry.se[k] for k, v in truth.items()))
            # per-parameter (not simultaneous) 95% intervals: the same half-widths with the
            # plain Student-t quantile in place of the Bonferroni-corrected one
            q_sim = float(stats.t.ppf(1 - (1 - entry.ci_level) / (2 * len(truth)), df=df))
            row["covered_marginal"] = int(all(
                abs(entry.parameters[k] - v) <= 0.5 * (entry.ci[k][1] - entry.ci[k][0])
                * q / q_sim for k, v in truth.items()))
    return row, (report if keep else None), hidden


def load_config(path: Path, overrides: list[str]) -> dict:
    with path.open("rb") as fh:
        cfg = tomllib.load(fh)
    for item in overrides:
        k, _, v = item.partition("=")
        node = cfg
        *parents, leaf = k.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = tomllib.loads(f"x = {v}")["x"]
    return cfg


def outcome(report, truth: str) -> str:
    names = [e.name for e in report.effects]
    groups = [set(c.effects) for c in report.confounded_with]
    if report.verdict == "effect":
        if names == [truth]:
            return "confounded" if any(truth in g for g in groups) else "correct"
        if truth in names:
            return "correct+extra"
        if any(truth in g for g in groups):
            return "confounded"
        return "wrong"
    return report.verdict  # "none" or "unexplained"


def sindy_fit(report, names: list[str], threshold: float):
    """STLSQ of the nominal (whitened) residual on the effects' signature columns at zero."""
    import pysindy as ps

    pb = report.fits["problem"]
    rho = report.fits["base"].rho.numpy()
    cols, owner = [], []
    for n in names:
        k = len(REGISTRY[n].param_specs(pb.fm.system))
        _, J = pb.evaluate([n], torch.zeros(k, dtype=torch.float64))
        cols.append(-J.numpy())  # residual ≈ −J p: regress −ρ... i.e. ρ on −J
        owner += [n] * k
    theta = np.concatenate(cols, 1)
    opt = ps.STLSQ(threshold=threshold, alpha=1e-9, normalize_columns=True, max_iter=50)
    opt.fit(theta, rho[:, None])
    coef = opt.coef_[0]
    norms = np.linalg.norm(theta, axis=0)
    return coef, np.array(owner), norms


def ols_normalised_max(report, names: list[str]) -> float:
    """Largest |coefficient × column norm| of a least-squares fit (no threshold) -- SINDy's
    threshold scale on a clean dataset."""
    coef, _, norms = sindy_fit(report, names, 0.0)
    return float(np.max(np.abs(coef * norms)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("runs/discrepancy_power"))
    ap.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--effects", nargs="+", default=None)
    ap.add_argument("--workers", type=int, default=1,
                    help="processes (one thread each); the SINDy comparison needs 1")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = load_config(args.config, args.overrides)
    st = cfg["study"]
    effects = {k: v for k, v in cfg["effects"].items()
               if args.effects is None or k in args.effects}
    try:
        import pysindy  # noqa: F401

        have_sindy = True
    except ImportError:
        have_sindy = False
        print("pysindy is not installed: the SINDy comparison is skipped (pip install pysindy)")
    if have_sindy and args.workers > 1:
        have_sindy = False
        print("the SINDy comparison needs --workers 1: skipped")
    names = list(REGISTRY)
    settings = DiscrepancySettings(compare_terms=False, experiments=False)
    root = np.random.SeedSequence(int(st["root_seed"]))
    clean = cfg.get("clean", {})
    # clean data: the study's own swimmer and rate at its noise levels (SINDy's threshold), and
    # the [clean] grid of link counts, sampling rates, noise levels and drop-out fractions
    jobs = [("clean", None, 0.0, om, i, st["n_links"], 64, 0.0) for om in st["omegas"]
            for i in range(st["clean_seeds"])]
    drops = clean.get("dropouts", [0.0])
    jobs += [("clean", None, 0.0, om, i, nl, spc, drops[i % len(drops)])
             for nl in clean.get("n_links", []) for spc in clean.get("samples_per_cycle", [64])
             for om in clean.get("omegas", st["omegas"]) for i in range(clean.get("seeds", 1))]
    jobs += [(name, vals, f, om, i, st["n_links"], 64, 0.0) for name, vals in effects.items()
             for f in st["factors"] for om in st["omegas"] for i in range(st["seeds"])]
    unreg = cfg.get("unregistered", {})
    jobs += [(name, unreg[name], f, om, i, st["n_links"], 64, 0.0) for name in UNREGISTERED
             if name in unreg and (args.effects is None or name in args.effects)
             for f in st["factors"] for om in st["omegas"] for i in range(st["seeds"])]
    seqs = root.spawn(len(jobs))

    args.out.mkdir(parents=True, exist_ok=True)
    rows, reports, t0 = [], [], time.time()
    work = [(job, seq, st, settings, have_sindy) for job, seq in zip(jobs, seqs, strict=True)]
    if args.workers > 1:  # every job has its own seeds: the same rows in any order
        import concurrent.futures

        pool = concurrent.futures.ProcessPoolExecutor(args.workers, initializer=_one_thread)
        results = pool.map(run_job, work)
    else:
        results = map(run_job, work)
    for j, (row, report, hidden) in enumerate(results):
        rows.append(row)
        if report is not None:
            reports.append((row["effect"], jobs[j][1], row["factor"], row["omega"],
                            row["replicate"], report, hidden))
        print(f"[{j + 1}/{len(jobs)}] {row['effect']:19s} x{row['factor']:<4g} "
              f"omega={row['omega']:<6g} links={row['n_links']} spc={row['samples_per_cycle']:<4d} "
              f"drop={row['dropout']:<4g} -> {row['outcome']:13s} ({row['cpu_seconds']:.1f} s "
              f"CPU; {time.time() - t0:.0f} s)", flush=True)

    if have_sindy:
        # threshold per noise level from the clean datasets
        thresholds = {}
        for om in st["omegas"]:
            clean = [r[5] for r in reports if r[0] == "clean" and r[3] == om
                     and r[5].fits["problem"].fm.system.n_links == st["n_links"]]
            thresholds[om] = cfg["sindy"]["margin"] * max(ols_normalised_max(r, names)
                                                           for r in clean)
        for name, vals, factor, omega, rep_i, report, hidden in reports:
            coef, owner, _ = sindy_fit(report, names, thresholds[omega])
            named = sorted({o for o, c in zip(owner, coef, strict=True) if c != 0.0})
            if vals is None:
                res = "none" if not named else "wrong"
            elif name in UNREGISTERED:  # it cannot say "unexplained": abstaining is its best
                res = "none" if not named else "wrong"
            elif named == [name]:
                res = "correct"
            elif name in named:
                res = "correct+extra"
            else:
                res = "none" if not named else "wrong"
            row = {"effect": name, "factor": factor, "omega": omega, "replicate": rep_i,
                   "n_links": st["n_links"], "samples_per_cycle": 64, "dropout": 0.0,
                   "partial": "",
                   "method": "pysindy", "outcome": res, "named": "+".join(named) or "none",
                   "correct": int(res == "correct" or (vals is None and res == "none")
                                  or (name in UNREGISTERED and res == "none")),
                   "param_rel_error": math.nan, "covered": math.nan,
                   "covered_noise_only": math.nan, "covered_marginal": math.nan,
                   "cpu_seconds": math.nan}
            if vals is not None and name in named:
                p_true = effect_parameters(hidden, NLinkSwimmer(int(st["n_links"])))[name].numpy()
                p_hat = coef[owner == name]
                row["param_rel_error"] = float(np.linalg.norm(p_hat - p_true)
                                               / np.linalg.norm(p_true))
            rows.append(row)

    with (args.out / "power.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    summary = summarise(rows)
    table = format_table(summary)
    print(table)
    clean_table = summarise_clean(rows)
    print(format_clean(clean_table))
    write_sidecar(args.out / "power.json", {
        "config": cfg, "root_seed": st["root_seed"], "pysindy": have_sindy,
        "pysindy_version": _pysindy_version(),
        "sindy_thresholds": thresholds if have_sindy else None,
        "summary": summary, "clean": clean_table, "seconds": time.time() - t0,
    })
    shown = list(effects) + [u for u in UNREGISTERED if any(r["effect"] == u for r in rows)]
    style.save_figure(plot(summary, st, shown), args.out / "power.png")
    print(f"wrote {args.out / 'power.csv'}, power.json, power.png in {time.time() - t0:.0f} s")
    return 0


def _pysindy_version():
    try:
        import pysindy

        return pysindy.__version__
    except ImportError:
        return None


def summarise(rows: list[dict]) -> list[dict]:
    keys = sorted({(r["method"], r["effect"], r["factor"], r["omega"]) for r in rows},
                  key=lambda k: (k[1], k[0], k[3], k[2]))
    # (clean rows of other link counts and sampling rates pool with their noise level)
    out = []
    for method, effect, factor, omega in keys:
        sel = [r for r in rows if (r["method"], r["effect"], r["factor"], r["omega"])
               == (method, effect, factor, omega)]
        err = [r["param_rel_error"] for r in sel if not math.isnan(r["param_rel_error"])]
        cov = [r["covered"] for r in sel if not math.isnan(r["covered"])]
        cov0 = [r["covered_noise_only"] for r in sel if not math.isnan(r["covered_noise_only"])]
        cov_m = [r["covered_marginal"] for r in sel if not math.isnan(r["covered_marginal"])]
        out.append({
            "method": method, "effect": effect, "factor": factor, "omega": omega, "n": len(sel),
            "p_correct": sum(r["correct"] for r in sel) / len(sel),
            "outcomes": {o: sum(r["outcome"] == o for r in sel) for o in
                         sorted({r["outcome"] for r in sel})},
            "median_param_rel_error": float(np.median(err)) if err else math.nan,
            "ci_coverage": float(np.mean(cov)) if cov else math.nan,
            "ci_coverage_noise_only": float(np.mean(cov0)) if cov0 else math.nan,
            "ci_coverage_marginal": float(np.mean(cov_m)) if cov_m else math.nan,
            "n_named": len(cov),
            "median_cpu_seconds": float(np.nanmedian([r["cpu_seconds"] for r in sel])),
        })
    return out


def summarise_clean(rows: list[dict]) -> list[dict]:
    """Clean datasets per link count, sampling rate and noise level: how many, how many
    ``none`` (a named effect is a false discovery, ``unexplained`` a false alarm)."""
    sel = [r for r in rows if r["method"] == "workflow" and r["effect"] == "clean"]
    keys = sorted({(r["n_links"], r["samples_per_cycle"], r["omega"]) for r in sel})
    out = []
    for nl, spc, om in keys:
        g = [r for r in sel if (r["n_links"], r["samples_per_cycle"], r["omega"]) == (nl, spc, om)]
        out.append({"n_links": nl, "samples_per_cycle": spc, "omega": om, "n": len(g),
                    "with_dropouts": sum(r["dropout"] > 0 for r in g),
                    "none": sum(r["outcome"] == "none" for r in g),
                    "named": sum(r["outcome"] not in ("none", "unexplained") for r in g),
                    "unexplained": sum(r["outcome"] == "unexplained" for r in g),
                    "median_cpu_seconds": float(np.median([r["cpu_seconds"] for r in g]))})
    return out


def format_clean(table: list[dict]) -> str:
    lines = ["clean datasets: links  samples/cycle  omega  n (drop-outs)  none  named  "
             "unexplained  CPU s"]
    for t in table:
        lines.append(f"                {t['n_links']:5d}  {t['samples_per_cycle']:13d}  "
                     f"{t['omega']:5g}  {t['n']:2d} ({t['with_dropouts']})        "
                     f"{t['none']:4d}  {t['named']:5d}  {t['unexplained']:11d}  "
                     f"{t['median_cpu_seconds']:5.1f}")
    tot = {k: sum(t[k] for t in table) for k in ("n", "none", "named", "unexplained")}
    lines.append(f"total {tot['n']} clean datasets: none {tot['none']}, named (false discoveries) "
                 f"{tot['named']}, unexplained {tot['unexplained']}")
    return "\n".join(lines)


def format_table(summary: list[dict]) -> str:
    lines = [f"{'effect':14s} {'factor':>6s} {'omega':>7s} {'method':9s} {'P(correct)':>10s} "
             f"{'rel.err':>8s} {'CI cov':>6s} {'(marg.)':>7s} {'(noise)':>7s} {'CPU s':>6s}  "
             "outcomes"]
    for s in summary:
        lines.append(f"{s['effect']:14s} {s['factor']:6g} {s['omega']:7g} {s['method']:9s} "
                     f"{s['p_correct']:10.2f} {s['median_param_rel_error']:8.3f} "
                     f"{s['ci_coverage']:6.2f} {s['ci_coverage_marginal']:7.2f} "
                     f"{s['ci_coverage_noise_only']:7.2f} "
                     f"{s['median_cpu_seconds']:6.1f}  {s['outcomes']}")
    return "\n".join(lines)


@style.styled
def plot(summary: list[dict], st: dict, effects: list[str]):
    """The power study's figure (a Figure): per effect against magnitude, or at one
    magnitude :func:`plot_one_magnitude`."""
    if len(st["factors"]) == 1:
        return plot_one_magnitude(summary, st, effects)

    fig, axes = style.figure_and_grid(None, (3, len(effects)), (2.6 * len(effects), 7.4),
                                      fn="plot")
    for j, effect in enumerate(effects):
        for i, om in enumerate(st["omegas"]):
            for method, ls in (("workflow", "-"), ("pysindy", "--")):
                sel = sorted((s for s in summary if s["effect"] == effect and s["omega"] == om
                              and s["method"] == method), key=lambda s: s["factor"])
                if not sel:
                    continue
                f = [s["factor"] for s in sel]
                axes[0, j].plot(f, [s["p_correct"] for s in sel], ls, marker="o", color=f"C{i}",
                                label=f"{method}, ω={om:g}")
                axes[1, j].plot(f, [s["median_param_rel_error"] for s in sel], ls, marker="o",
                                color=f"C{i}")
                if method == "workflow":
                    axes[2, j].plot(f, [s["ci_coverage"] for s in sel], ls, marker="o",
                                    color=f"C{i}")
        axes[0, j].set_title(effect, fontsize=9)
        axes[0, j].set_ylim(-0.05, 1.05)
        for a in axes[:, j]:
            a.set_xscale("log")
            a.set_xlim(0.7 * min(st["factors"]), 1.4 * max(st["factors"]))
        errs = [s["median_param_rel_error"] for s in summary if s["effect"] == effect]
        if any(e > 0 for e in errs if not math.isnan(e)):
            axes[1, j].set_yscale("log")
        else:
            axes[1, j].text(0.5, 0.5, "no parameters\n(not in the registry)", ha="center",
                            va="center", transform=axes[1, j].transAxes, fontsize=8)
        axes[2, j].axhline(0.95, color="k", lw=0.8, ls=":")
        axes[2, j].set_ylim(-0.05, 1.05)
        axes[2, j].set_xlabel("magnitude (x reference)")
    axes[0, 0].set_ylabel("P(named right effect)\n(unregistered: P(unexplained))")
    axes[2, 0].set_ylabel("95% interval coverage")
    axes[1, 0].set_ylabel("median relative parameter error")
    axes[0, 0].legend(fontsize=6)
    return style.caption(fig, (
        "Per effect (column) against its magnitude: how often the workflow names the right "
        "effect (top), its parameters' median relative error (middle) and its 95% intervals' "
        "coverage (bottom), per observation noise ω (colour), pysindy dashed. Good: the "
        "chance of the right answer rises to 1 with magnitude, and coverage sits at 0.95."))


def plot_one_magnitude(summary: list[dict], st: dict, effects: list[str]):
    """A study at one magnitude (a Figure): bars per effect and noise level -- named right
    (unregistered effects: called unexplained; clean data: none) and 95% interval coverage."""
    shown = ["clean"] + list(effects)
    fig, axes = style.figure_and_grid(None, (2, 1), (1.0 * len(shown) + 2, 5.4),
                                      fn="plot_one_magnitude", sharex=True)
    axes = axes[:, 0]
    width = 0.8 / len(st["omegas"])
    for i, om in enumerate(st["omegas"]):
        rows = {s["effect"]: s for s in summary if s["omega"] == om and s["method"] == "workflow"}
        x = np.arange(len(shown)) + (i - (len(st["omegas"]) - 1) / 2) * width
        axes[0].bar(x, [rows[e]["p_correct"] if e in rows else np.nan for e in shown], width,
                    color=f"C{i}", label=f"ω = {om:g}")
        axes[1].bar(x, [rows[e]["ci_coverage"] if e in rows else np.nan for e in shown], width,
                    color=f"C{i}")
        for xx, e in zip(x, shown, strict=True):
            if e in rows:
                axes[0].text(xx, 0.02, f"n={rows[e]['n']}", ha="center", fontsize=6,
                             rotation=90, color="w")
    axes[0].set_ylabel("P(right answer)\n(clean: none; unregistered:\nunexplained)")
    axes[1].set_ylabel("95% interval coverage\n(named effects)")
    axes[1].axhline(0.95, color="k", lw=0.8, ls=":")
    axes[1].axhline(0.90, color="k", lw=0.8, ls="--")
    for a in axes:
        a.set_ylim(0, 1.05)
    axes[1].set_xticks(np.arange(len(shown)), shown, rotation=30, ha="right", fontsize=8)
    axes[0].legend(fontsize=7, loc="lower right")
    axes[0].set_title(f"{st['n_links']}-link, {st['trials']} trials x {st['n_cycles']} cycles, "
                      f"reference magnitudes x{st['factors'][0]:g}", fontsize=9)
    return style.caption(fig, (
        "Per effect at one magnitude and per observation noise ω: how often the workflow "
        "gives the right answer (top: on clean data, none; for an effect outside the "
        "registry, unexplained) and its 95% intervals' coverage (bottom). Good: bars near 1 "
        "on top and at the dotted 0.95 line below."))


if __name__ == "__main__":
    sys.exit(main())
