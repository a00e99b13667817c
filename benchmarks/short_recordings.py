"""Held-out skill on short real-like recordings: the default estimator against its baselines.

Short recordings like tracked fish: one trial of 3-6 gait cycles, 4 joints (5-link), motion-
capture noise ω = 0.005 on x, y, θ and every r_i (the paper's SDE, α = 0.05, η = 0.025,
126 samples per cycle). The estimator is fitted to the first ``n`` cycles and scored on the
next 4 cycles of the same trial (phased by the fitted phaser), as R² per body-velocity
component against the observed velocity the way the default regression sees it (raw interval
differences of the noisy poses for ``NoiseAwareRegression``):

- ``fixed``: the default regression at a fixed complexity (48 bins, Fourier order 12, no ridge);
- ``default``: ``ConnectionEstimator()`` -- complexity ``"auto"``: chosen by held-out error
  over blocks of whole training cycles when the fixed one loses to the phase average there,
  each component predicted by the full model, by the connection alone (``ĉ + Âδ̇``,
  ``choice`` ends in ``/A:x,y`` for v_x and v_y) or by the phase average (``/pa:x,y``; such a
  component ties it exactly), whichever clearly wins held out (``complexity._choose_terms``);
  ``unchecked``: no candidate could be scored held out; ``alone``: no full model could, and
  the connection alone was regressed and checked instead (``complexity.select_connection_alone``);
- ``phase avg``: the training cycles' phase-averaged velocity, ``score()``'s baseline: of the
  model's Fourier order (12 unless the complexity was re-chosen);
- ``pa h-o``: a stronger phase average, each component of the order (up to 12) with the least
  error on held-out blocks of the training cycles (``skill.phase_average_orders``): a series
  of the model's order overfits 3-6 cycles;
- ``template``: the default model on the cycle, ``Â(γ)γ̇``;
- ``exact A``: the swimmer's exact connection applied to the same noisy shapes and shape
  velocities the regression sees -- what a perfect estimate of ``A`` would score against this
  target.

The summary also counts losses against the model-order phase average, the components whose
shape terms are kept, the mean R² per component, and ``Â`` against the swimmer's (relative
RMS on the fitted cycle and the best scale factor, ``accuracy.connection_errors``) as
delivered (``A`` at the end of a row: ``est.model_``, every row estimated, ``Â`` unpenalised)
and of the forecasting model (``forecast``: ``est.forecast_model_``, the chosen ridge on ``Â``
and rows 0 where a component is phase-averaged; ``est.model_`` before the two were told
apart). The R² columns are the forecasting model's (``score()``).

``--no-ridge-connection`` fits with ``NoiseAwareRegression(ridge_connection=False)`` (the
chosen ridge leaves ``Â`` unpenalised); ``--z``, ``--margin``, ``--offset-z`` and
``--every-cycle`` (a model with shape terms must also beat the phase average on every scored
held-out cycle) measure other settings of the check's rules (``complexity._choose_terms``).
``--fallback-cycles N`` sets ``torchconn.cycles.FALLBACK_CYCLES`` (recordings of up to ``N`` cycles
presume the simpler model, ``torchconn.cycles.few_cycles``), and ``--complexity cv`` fits the default
column with ``ConnectionEstimator(complexity="cv")`` (the complexity chosen on every recording,
not only where the given one loses held out).

Only ``Phaser(min_cycles=2.5)`` differs from the defaults: a recording of exactly 3 cycles
often phases to 2.9-3.0 and the default Phaser (3 cycles) refuses it.

Run by hand (about a minute per 20 rows on a loaded 2-core machine)::

    python benchmarks/short_recordings.py                       # seeds 10-14, 5-link, 3 gaits
    python benchmarks/short_recordings.py --links 9 3 --gaits wave0.7 --seeds 10 11
    python benchmarks/short_recordings.py --cost                # cost of the held-out check
    python benchmarks/short_recordings.py --samples-per-cycle 10 --cycles 7 8 10 12 \
        --test-cycles 6 --skip-fixed                            # video rates
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from functools import partial

import numpy as np
import torch
from accuracy import connection_errors  # beside this file

from torchconn import (
    ConnectionEstimator,
    NLinkSwimmer,
    NoiseAwareRegression,
    Phaser,
    TubeRegression,
    observe,
    simulate,
)
from torchconn import cycles as cycle_rules
from torchconn.physics.gaits import FourierGait, reference_gait
from torchconn.regression.selection import complexity, skill

SAMPLES_PER_CYCLE = 126  # Δt ≈ 0.05
TEST_CYCLES = 4
COMPONENTS = ("v_x", "v_y", "omega")


def gait(n_links: int, kind: str) -> FourierGait:
    """``wave<ρ>``: a travelling wave of amplitude ρ rad (3-link: a circle); ``wave2``: a wave
    of 0.6 rad plus a second harmonic of 0.25 rad (a figure-eight-like, non-circular loop);
    ``reference``: the stored reference gait (3- and 9-link)."""
    d = n_links - 1
    if kind == "reference":
        return reference_gait(f"{n_links}link")
    i = torch.arange(d, dtype=torch.float64)
    lag = 2 * math.pi * i / max(d, 4) if d > 2 else torch.tensor([0.0, math.pi / 2])
    radius = 0.6 if kind == "wave2" else float(kind.removeprefix("wave"))
    coeffs = torch.zeros(5 if kind == "wave2" else 3, d, dtype=torch.float64)
    coeffs[1], coeffs[2] = radius * torch.cos(lag), radius * torch.sin(lag)
    if kind == "wave2":
        coeffs[3], coeffs[4] = 0.25 * torch.cos(2 * lag), 0.25 * torch.sin(2 * lag)
    return FourierGait(coeffs)


def recording(n_links: int, kind: str, n_cycles: int, seed: int, omega: float,
              samples_per_cycle: int = SAMPLES_PER_CYCLE, test_cycles: int = TEST_CYCLES):
    """``n_cycles + test_cycles`` cycles of one trial; below 126 samples per cycle the
    simulator's fine step stays about the 126-sample one's (more substeps per sample)."""
    seeds = np.array([seed])
    substeps = max(8, 2 * math.ceil(4 * SAMPLES_PER_CYCLE / samples_per_cycle))
    clean = simulate(NLinkSwimmer(n_links), gait(n_links, kind), eta=0.025,
                     n_cycles=n_cycles + test_cycles, samples_per_cycle=samples_per_cycle,
                     substeps=substeps, seeds=seeds)
    # tracked recordings carry no power channel (and the metric needs more cycles)
    return observe(clean, omega, seeds=seeds).with_fields(power=None)


def _exact_r2(est: ConnectionEstimator, test, n_links: int) -> torch.Tensor:
    """R² of the exact connection on the test recording, on the samples and against the
    target the fitted regression sees (:func:`~torchconn.regression.skill.regression_view`:
    raw interval differences for the noise-aware regression, the smoothed velocities for
    ``TubeRegression``), phase-free."""
    view = skill.regression_view(est.prepare(test), est.regression_, est.forecast_model_,
                                 pool=False, flatten=False)
    pred = (NLinkSwimmer(n_links).connection(view.r) @ view.r_dot.unsqueeze(-1)).squeeze(-1)
    y = view.xi
    sst = (y - y.nanmean(-2, keepdim=True)).square().nansum(-2)
    return (1 - (y - pred).square().nansum(-2) / sst).reshape(-1)


def _order12_r2(est: ConnectionEstimator, test) -> torch.Tensor:
    """R² on the test recording of the training cycles' phase average of the model's Fourier
    order (12 unless the complexity was re-chosen) for every component: ``score()``'s
    baseline."""
    reg, model = est.regression_, est.forecast_model_
    base = skill.phase_average(skill.regression_view(est.trajectory_, reg, model, pool=False),
                               reg.fourier_order)
    # phased by the fitted phaser, as score() does
    view = skill.regression_view(est._prepare_new(test, None), reg, model, pool=False)
    return skill.skill(model, base, view).r2_phase_average.reshape(-1)


def _held_out_order_r2(est: ConnectionEstimator, test) -> torch.Tensor:
    """R² on the test recording of the training cycles' phase average with each component's
    order chosen on held-out blocks (:func:`~torchconn.regression.skill.phase_average_orders`,
    up to order 12), on the samples and target :meth:`ConnectionEstimator.score` uses."""
    reg, model = est.regression_, est.forecast_model_
    unflat = skill.regression_view(est.trajectory_, reg, model, pool=False, flatten=False)
    top = max(reg.fourier_order, complexity.COMPLEXITY_GRID[-1][1])
    orders = skill.phase_average_orders(unflat, top, pool=False)
    base = skill.phase_average(skill.regression_view(est.trajectory_, reg, model, pool=False),
                               top, orders)
    # phased by the fitted phaser, as score() does
    view = skill.regression_view(est._prepare_new(test, None), reg, model, pool=False)
    return skill.skill(model, base, view).r2_phase_average.reshape(-1)


def run_one(n_links: int, kind: str, n_cycles: int, seed: int, omega: float,
            with_fixed: bool = True, ridge_connection: bool = True,
            samples_per_cycle: int = SAMPLES_PER_CYCLE, test_cycles: int = TEST_CYCLES,
            complexity: str = "auto") -> dict:
    traj = recording(n_links, kind, n_cycles, seed, omega, samples_per_cycle, test_cycles)
    cut = n_cycles * samples_per_cycle + 1
    train, test = traj.slice_time(0, cut), traj.slice_time(cut, traj.n_samples)
    phaser = Phaser(min_cycles=2.5)
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out["fixed"] = torch.full((3,), math.nan, dtype=torch.float64)
        if with_fixed:
            try:
                fixed = ConnectionEstimator(phaser=phaser, complexity="fixed").fit(train)
                out["fixed"] = fixed.score(test).r2.reshape(-1)
            except ValueError:
                pass  # cannot be fitted: NaN
        start = time.perf_counter()
        est = ConnectionEstimator(
            phaser=phaser, complexity=complexity,
            regression=NoiseAwareRegression(ridge_connection=ridge_connection)).fit(train)
        out["seconds"] = time.perf_counter() - start
        s = est.score(test)
    c = est.complexity_
    out.update(default=s.r2.reshape(-1), phase_avg=s.r2_phase_average.reshape(-1),
               template=s.r2_template.reshape(-1), exact=_exact_r2(est, test, n_links),
               pa_ho=_held_out_order_r2(est, test), pa12=_order12_r2(est, test))
    # Â as delivered (model_: every row estimated, Â unpenalised) and of the forecasting
    # model (forecast_model_: the chosen ridge on Â, rows 0 where a component is
    # phase-averaged; what model_ was before they were told apart)
    for key, model in (("A", est.model_), ("A_fc", est.forecast_model_)):
        err = connection_errors(model, n_links)
        out[key + "_err"], out[key + "_scale"] = float(err["A"].mean()), float(err["scale"].mean())
    out["kept"] = 3 if c is None else int(3 - torch.as_tensor(c.phase_averaged).sum())
    held = est.held_out_skill_
    unchecked = bool(held.unscored.any()) and (c is None or not c.checked)
    alone = getattr(c, "connection_regressed", False)  # (older versions lack it)
    out["choice"] = ("unchecked" if unchecked and c is None else "fixed" if c is None
                     else ("unchecked" if unchecked else "alone" if alone else "")
                     + f"{c.n_bins}/{c.fourier_order}/{c.ridge:g}") + (
        "" if c is None else "".join(
        f"/{tag}:" + ",".join(n.removeprefix("v_")[0] for n in names)
        for tag, names in (("pa", c.phase_averaged_names()), ("A", c.connection_only_names()))
        if names))
    out["warned"] = bool(held.worse_than_phase_average.any() | held.unscored.any()) or bool(
        c is not None and (c.phase_averaged_names() or c.connection_only_names()))  # both warn
    return out


def _fmt(x, marks=None) -> str:
    marks = [False] * len(x) if marks is None else marks.tolist()
    return " ".join(f"{float(v):6.3f}" + ("*" if m else " ")
                    for v, m in zip(x, marks, strict=True))


def _best_of_3(fn) -> float:
    times = []
    for _ in range(3):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return min(times)


def table(args) -> int:
    print(f"train n cycles, test the next {args.test_cycles} ({args.samples_per_cycle} samples "
          f"per cycle); R² per component "
          f"({', '.join(COMPONENTS)}); default < phase avg (where phase avg > 0) marked *")
    print(f"{'links':>5} {'gait':>9} {'n':>2} {'seed':>4} | {'fixed':^20} | {'default':^20} | "
          f"{'phase avg':^20} | {'pa h-o':^20} | {'template':^20} | {'exact A':^20} | "
          "choice     warn  s/fit")
    wins, ties, losses = ([[] for _ in COMPONENTS] for _ in range(3))
    ho_losses = [[] for _ in COMPONENTS]  # against the held-out-order phase average
    o12_losses = [[] for _ in COMPONENTS]  # against the model-order phase average
    kept, n_rec, r2_sum = 0, 0, torch.zeros(3, dtype=torch.float64)
    a_sums = dict.fromkeys(("A_err", "A_scale", "A_fc_err", "A_fc_scale"), 0.0)
    refused = unchecked = 0
    for n_links in args.links:
        for kind in args.gaits:
            if kind == "reference" and n_links not in (3, 9):
                continue
            for n in args.cycles:
                for seed in args.seeds:
                    try:
                        r = run_one(n_links, kind, n, seed, args.omega, not args.skip_fixed,
                                    not args.no_ridge_connection,
                                    args.samples_per_cycle, args.test_cycles,
                                    args.complexity)
                    except ValueError as err:  # the default refuses the recording
                        print(f"{n_links:>5} {kind:>9} {n:>2} {seed:>4} | not fitted: "
                              f"{str(err)[:100]}", flush=True)
                        refused += 1
                        continue
                    pa = r["phase_avg"]
                    bad = (r["default"] < pa) & (pa > 0)
                    for k in range(len(COMPONENTS)):
                        if pa[k] > 0:
                            gap = float(r["default"][k] - pa[k])
                            (wins if gap > 0 else ties if gap == 0 else losses)[k].append(gap)
                        ho = float(r["default"][k] - r["pa_ho"][k])
                        if r["pa_ho"][k] > 0 and ho < 0:
                            ho_losses[k].append(-ho)
                        o12 = float(r["default"][k] - r["pa12"][k])
                        if r["pa12"][k] > 0 and o12 < 0:
                            o12_losses[k].append(-o12)
                    kept += r["kept"]
                    unchecked += r["choice"].startswith("unchecked")
                    n_rec += 1
                    r2_sum += r["default"]
                    for key in a_sums:
                        a_sums[key] += r[key]

                    print(f"{n_links:>5} {kind:>9} {n:>2} {seed:>4} | {_fmt(r['fixed'])}| "
                          f"{_fmt(r['default'], bad)}| {_fmt(pa)}| {_fmt(r['pa_ho'])}| "
                          f"{_fmt(r['template'])}| "
                          f"{_fmt(r['exact'])}| {r['choice']:10s} {'yes' if r['warned'] else 'no':4s}"
                          f" {r['seconds']:5.2f} A {r['A_err']:.1%} "
                          f"x{r['A_scale']:.2f} forecast {r['A_fc_err']:.1%} "
                          f"x{r['A_fc_scale']:.2f}", flush=True)
    print("default against the phase average, where its R² > 0 (tie: the component is "
          "predicted by the phase average, R² equal)")
    print(f"{'component':>9} {'wins':>5} {'ties':>5} {'losses':>6} {'median shortfall':>17} "
          f"{'max shortfall':>14} {'median gain':>12}")
    for k, name in enumerate(COMPONENTS):
        short = [-g for g in losses[k]]
        print(f"{name:>9} {len(wins[k]):5d} {len(ties[k]):5d} {len(losses[k]):6d} "
              f"{np.median(short) if short else 0:17.4f} {max(short, default=0):14.4f} "
              f"{np.median(wins[k]) if wins[k] else 0:12.4f}")
    n_loss = sum(map(len, losses))
    n_all = n_loss + sum(map(len, wins)) + sum(map(len, ties))
    print(f"default worse than the phase average in {n_loss} of {n_all} components with a "
          f"phase-average R² > 0; {refused} recording(s) refused by the default fit; "
          f"{unchecked} of {n_rec} unchecked (no candidate could be scored held out)")
    short = [g for k in ho_losses for g in k]
    print(f"default worse than the held-out-order phase average ('pa h-o', where its R² > 0) "
          f"in {len(short)} components (v_x / v_y / ω: "
          f"{' / '.join(str(len(k)) for k in ho_losses)}; largest {max(short, default=0):.4f}, "
          f"median {np.median(short) if short else 0:.4f})")
    short = [g for k in o12_losses for g in k]
    print(f"default worse than the model-order phase average (where its R² > 0) in {len(short)} "
          f"components (v_x / v_y / ω: {' / '.join(str(len(k)) for k in o12_losses)}; "
          f"largest {max(short, default=0):.4f}); shape terms kept (not phase-averaged) in "
          f"{kept} of {3 * n_rec}; mean R² v_x / v_y / ω "
          + " / ".join(f"{float(v) / max(n_rec, 1):.4f}" for v in r2_sum))
    mean = {key: v / max(n_rec, 1) for key, v in a_sums.items()}
    print(f"Â against the swimmer's, relative RMS on the fitted cycle (mean, at mean scale): "
          f"as delivered (model_) {mean['A_err']:.1%} at {mean['A_scale']:.2f}; the "
          f"forecasting model's (forecast_model_: ridge on Â, rows 0 where phase-averaged) "
          f"{mean['A_fc_err']:.1%} at {mean['A_fc_scale']:.2f}")
    return 0


def _fit_for_cost(traj, reg, pool, folds):
    return ConnectionEstimator(regression=reg, pool=pool, complexity="fixed",
                               held_out_folds=folds).fit(traj)


def cost(args) -> int:
    """Time of a fit without and with the held-out check, and of the refitting check."""
    torch.manual_seed(0)
    cases = [
        ("5-link, 1 trial x 6 cycles, 126/cycle", 5, "wave0.7", 6, 1, 126, False),
        ("3-link, 4 x 30 pooled, 126/cycle", 3, "wave0.9", 30, 4, 126, True),
        ("9-link, 4 x 30 pooled, 126/cycle", 9, "reference", 30, 4, 126, True),
        ("9-link, 20 x 30 per trial, 64/cycle (a sweep cell)", 9, "reference", 30, 20, 64,
         False),
    ]
    print("CPU seconds (best of 3); ratio = extra time of the check / fit without it")
    for name, n_links, kind, n_cycles, n_trials, spc, pool in cases:
        seeds = np.arange(n_trials)
        traj = observe(simulate(NLinkSwimmer(n_links), gait(n_links, kind), eta=0.025,
                                n_cycles=n_cycles, samples_per_cycle=spc, seeds=seeds),
                       0.005, seeds=seeds)

        reg = TubeRegression()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            plain = _best_of_3(partial(_fit_for_cost, traj, reg, pool, 0))
            checked = _best_of_3(partial(_fit_for_cost, traj, reg, pool, 3))
            est = _fit_for_cost(traj, reg, pool, 0)
            refit = _best_of_3(partial(skill.cross_validate, est.trajectory_, est.limit_cycle_,
                                       reg, pool=pool, refit=True))
        print(f"{name:52s} fit {plain:6.2f}  with check {checked:6.2f} "
              f"(+{(checked - plain) / plain:5.0%})  refitting check {refit:6.2f} "
              f"({refit / plain:4.0%} of a fit)", flush=True)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--links", type=int, nargs="+", default=[5])
    p.add_argument("--gaits", nargs="+", default=["wave0.7", "wave0.9", "wave2"])
    p.add_argument("--cycles", type=int, nargs="+", default=[3, 4, 5, 6])
    p.add_argument("--seeds", type=int, nargs="+", default=[10, 11, 12, 13, 14])
    p.add_argument("--omega", type=float, default=0.005)
    p.add_argument("--samples-per-cycle", type=int, default=SAMPLES_PER_CYCLE,
                   help="e.g. 10-16: video rates")
    p.add_argument("--test-cycles", type=int, default=TEST_CYCLES,
                   help="later cycles scored")
    p.add_argument("--cost", action="store_true", help="time the held-out check instead")
    p.add_argument("--skip-fixed", action="store_true", help="leave out the fixed column")
    p.add_argument("--margin", type=float, default=None,
                   help="complexity.FALLBACK_MARGIN to measure (default: the library's)")
    p.add_argument("--z", type=float, default=None,
                   help="complexity.FALLBACK_Z to measure (default: the library's)")
    p.add_argument("--offset-z", type=float, default=None,
                   help="complexity.OFFSET_TERMS_Z to measure (default: the library's)")
    p.add_argument("--no-ridge-connection", action="store_true",
                   help="NoiseAwareRegression(ridge_connection=False): the chosen ridge leaves "
                   "Â's columns unpenalised")
    p.add_argument("--every-cycle", action="store_true",
                   help="measure: a model with shape terms beats the phase average "
                   "(complexity._clearly_better) only if it does on every scored held-out cycle too")
    p.add_argument("--complexity", choices=("auto", "cv"), default="auto",
                   help="measure: the default column's ConnectionEstimator(complexity=...); "
                   "cv: chosen by held-out error on every recording")
    p.add_argument("--fallback-cycles", type=int, default=None,
                   help="measure: torchconn.cycles.FALLBACK_CYCLES (recordings of up to this many cycles "
                   "presume the simpler model; default: the library's)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    if args.every_cycle:
        clearly = complexity._clearly_better

        def every_cycle(gaps):
            diff = gaps[..., 0]  # (..., C, 3), 0 on cycles without scored samples
            return clearly(gaps) & (diff <= 0).all(-2)
        complexity._clearly_better = every_cycle
    if args.margin is not None:
        complexity.FALLBACK_MARGIN = args.margin
    if args.z is not None:
        complexity.FALLBACK_Z = args.z
    if args.offset_z is not None:
        complexity.OFFSET_TERMS_Z = args.offset_z
    if args.fallback_cycles is not None:
        cycle_rules.FALLBACK_CYCLES = args.fallback_cycles
    return cost(args) if args.cost else table(args)


if __name__ == "__main__":
    raise SystemExit(main())
