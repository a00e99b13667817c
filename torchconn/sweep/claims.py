"""The paper's claims, checked on a sweep's tables (one row per claim, numbers as evidence).

Every test compares models on the same trials. A claim whose data the sweep lacks is reported
with ``holds = "n/a"``; a claim that fails is reported as failing, with its numbers.
"""

from __future__ import annotations

import warnings
from collections import defaultdict

import numpy as np
from scipy import stats

__all__ = ["CLAIMS", "check_claims"]

CLAIMS = {
    "a": "the data-driven model has zero mean error at every phase; the analytic model does not",
    "b": "for the 9-link the data-driven error is lower than the analytic one, more so than for "
         "the 3-link",
    "c": "as system noise grows the analytic model degrades faster; the data-driven one is worse "
         "at low noise and better at high noise",
    "d": "under observation noise the error against ground truth grows more slowly than the "
         "error against the observed data",
}

#: significance level of the per-bin mean-error tests of claim (a)
ALPHA = 0.01


def _table(rows, columns):
    return [dict(zip(columns, r, strict=False)) for r in rows]


def _rms(results, **where) -> dict[float, np.ndarray]:
    """Per level: the metric over trials, for rows matching ``where``."""
    out = defaultdict(list)
    for r in results:
        if all(r[k] == v for k, v in where.items()):
            out[r["level"]].append(r["value"])
    return {lvl: np.asarray(v) for lvl, v in sorted(out.items())}


def _nearest(levels, target):
    levels = list(levels)
    return levels[int(np.argmin([abs(lv - target) for lv in levels]))] if levels else None


def _claim_a(results, phase_errors, experiments):
    parts, verdicts = [], []
    for exp in experiments:
        if exp.noise_kind != "system" or exp.trials < 3:
            continue
        level = _nearest(exp.levels, 1.0)
        frac, net = {}, {}
        for model in ("data_driven", "analytic"):
            by_bin = defaultdict(list)
            for r in phase_errors:
                if (r["experiment"], r["level"], r["model"]) == (exp.name, level, model):
                    by_bin[(r["component"], r["phase"])].append(r["mean"])
            if by_bin:
                # (bins, trials), NaN-padded should a trial lack a bin; two-sided t-test per bin
                n = max(len(v) for v in by_bin.values())
                m = np.array([v + [np.nan] * (n - len(v)) for v in by_bin.values()])
                p = _ttest_pvalues(m)
                frac[model] = float(np.mean(p < ALPHA))
            else:
                frac[model] = float("nan")
            x_means = [np.mean(v) for (c, _), v in by_bin.items() if c == "x"]
            net[model] = (float(np.mean(x_means)), float(np.sqrt(np.mean(np.square(x_means)))))
        ok = frac["data_driven"] <= 0.1 and frac["analytic"] >= 0.25
        verdicts.append(ok)
        parts.append(f"{exp.name} at {level:g}x eta: bins with mean error != 0 (p<{ALPHA}, "
                     f"{exp.trials} trials): data-driven {frac['data_driven']:.0%}, "
                     f"analytic {frac['analytic']:.0%}; x mean error over phase (net, RMS over "
                     f"bins): data-driven {net['data_driven'][0]:.2g}, {net['data_driven'][1]:.2g}; "
                     f"analytic {net['analytic'][0]:.2g}, {net['analytic'][1]:.2g}")
    return verdicts, parts


def _ttest_pvalues(m: np.ndarray) -> np.ndarray:
    """Two-sided p-values of one-sample t-tests of mean 0 along the last axis of ``m (..., n)``
    (NaN: missing). Rows without spread get p = 0 if their mean is non-zero, else NaN (never
    significant); scipy's warning about them is silenced."""
    with warnings.catch_warnings(), np.errstate(divide="ignore", invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        res = stats.ttest_1samp(m, 0.0, axis=-1, nan_policy="omit")
    return np.asarray(res.pvalue, dtype=float)


def _unit_noise_errors(results, exp):
    """Per-trial x RMS errors ``(data_driven, analytic)`` at the level closest to η."""
    level = _nearest(exp.levels, 1.0)
    common = dict(experiment=exp.name, component="x", metric="rms_vs_ground_truth")
    dd = _rms(results, model="data_driven", **common)[level]
    an = _rms(results, model="analytic", **common)[level]
    return level, dd, an


def _bootstrap_ratios(dd, an, n=2000, seed=0):
    """Ratios of mean errors ``mean(dd)/mean(an)`` over ``n`` resamples of the trials."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(dd), size=(n, len(dd)))
    return dd[idx].mean(1) / an[idx].mean(1)


def _claim_b(results, experiments):
    sys_exps = {e.system: e for e in experiments if e.noise_kind == "system"}
    if "9link" not in sys_exps:
        return [], []
    l9, dd9, an9 = _unit_noise_errors(results, sys_exps["9link"])
    boot9 = _bootstrap_ratios(dd9, an9)
    p9 = float(np.mean(boot9 < 1))
    parts = [f"9-link at {l9:g}x eta, x RMS vs ground truth: data-driven {dd9.mean():.3g}, "
             f"analytic {an9.mean():.3g} (ratio {dd9.mean() / an9.mean():.2f}; lower in "
             f"{p9:.0%} of bootstrap resamples of the trials)"]
    verdicts = [p9 >= 0.95]
    if "3link" in sys_exps:
        l3, dd3, an3 = _unit_noise_errors(results, sys_exps["3link"])
        boot3 = _bootstrap_ratios(dd3, an3, seed=1)
        p_more = float(np.mean(boot9 < boot3))
        parts.append(f"3-link at {l3:g}x eta: data-driven {dd3.mean():.3g}, analytic "
                     f"{an3.mean():.3g} (ratio {dd3.mean() / an3.mean():.2f}); the 9-link ratio "
                     f"is the lower in {p_more:.0%} of resamples (holds at >= 95%)")
        verdicts.append(p_more >= 0.95)
    return verdicts, parts


def _slope(levels, values, log=True):
    x, y = np.asarray(levels, float), np.asarray(values, float)
    if log:
        keep = x > 0
        x, y = np.log(x[keep]), np.log(y[keep])
    return float(np.polyfit(x, y, 1)[0]) if len(x) >= 2 else float("nan")


def _claim_c(results, experiments):
    verdicts, parts = [], []
    for exp in experiments:
        if exp.noise_kind != "system" or exp.system != "9link" or len(exp.levels) < 3:
            continue
        common = dict(experiment=exp.name, component="x", metric="rms_vs_ground_truth")
        dd = {k: v.mean() for k, v in _rms(results, model="data_driven", **common).items()}
        an = {k: v.mean() for k, v in _rms(results, model="analytic", **common).items()}
        lv = sorted(dd)
        s_dd, s_an = _slope(lv, [dd[x] for x in lv]), _slope(lv, [an[x] for x in lv])
        lo, hi = lv[0], lv[-1]
        ok = s_an > s_dd and dd[lo] > an[lo] and dd[hi] < an[hi]
        verdicts.append(ok)
        parts.append(
            f"{exp.name}: log-log slope of x RMS vs noise: analytic {s_an:.2f}, data-driven "
            f"{s_dd:.2f}; at {lo:g}x: data-driven {dd[lo]:.3g} vs analytic {an[lo]:.3g}; at "
            f"{hi:g}x: data-driven {dd[hi]:.3g} vs analytic {an[hi]:.3g}"
        )
    return verdicts, parts


def _claim_d(results, experiments):
    verdicts, parts = [], []
    for exp in experiments:
        if exp.noise_kind != "observation" or len(exp.levels) < 2:
            continue
        common = dict(experiment=exp.name, component="x", model="data_driven")
        vs_truth = {k: v.mean() for k, v in
                    _rms(results, metric="rms_vs_ground_truth", **common).items()}
        vs_obs = {k: v.mean() for k, v in _rms(results, metric="rms_vs_observed", **common).items()}
        lv = sorted(vs_truth)
        s_t = _slope(lv, [vs_truth[x] for x in lv], log=False)
        s_o = _slope(lv, [vs_obs[x] for x in lv], log=False)
        verdicts.append(s_t < s_o)
        parts.append(
            f"{exp.name}: growth of data-driven x RMS per unit omega: vs ground truth {s_t:.3g}, "
            f"vs observed {s_o:.3g} (omega {lv[0]:g}..{lv[-1]:g}: vs truth "
            f"{vs_truth[lv[0]]:.3g}->{vs_truth[lv[-1]]:.3g}, vs observed "
            f"{vs_obs[lv[0]]:.3g}->{vs_obs[lv[-1]]:.3g})"
        )
    return verdicts, parts


def check_claims(results_rows, phase_rows, experiments, result_columns, phase_columns):
    """Rows ``(claim, holds, evidence)`` for the claims in :data:`CLAIMS`."""
    results = _table(results_rows, result_columns)
    phase_errors = _table(phase_rows, phase_columns)
    found = {
        "a": _claim_a(results, phase_errors, experiments),
        "b": _claim_b(results, experiments),
        "c": _claim_c(results, experiments),
        "d": _claim_d(results, experiments),
    }
    rows = []
    for key, text in CLAIMS.items():
        verdicts, parts = found[key]
        holds = "n/a" if not verdicts else bool(all(verdicts))
        evidence = "; ".join(parts) if parts else "the sweep has no experiment that tests this"
        rows.append((f"({key}) {text}", holds, evidence))
    return rows
