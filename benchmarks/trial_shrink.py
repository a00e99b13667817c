"""Â's harmonic shrink for one model per trial (``NoiseAwareRegression(resolved_harmonics=
"per_trial")``) against the plain series of the same bins (the default for unpooled fits);
``--pooled``: the default pooled shrink, and what it does to the model's predictions.

One model per trial of ``--cycles`` cycles at 64 samples per cycle (the sweep's setting),
recordings as ``accuracy.py``'s (``recording``: trials ``1000 · seed + i``), scored as there:
relative RMS error of ``Â(φ)`` along the fitted cycle against the exact connection. The bins
are fitted once with the option; the plain series is the order-12 least-squares series of those
bins (what the default returns, bit for bit). Prints the mean over all trials and seeds per
cell, plain → shrunk, and how many one-trial fits got worse.

Run by hand (about a minute on one core for the defaults)::

    PYTHONPATH=. python benchmarks/trial_shrink.py --threads 1

``--pooled``: ``--trials`` trials of ``--cycles`` cycles at 126 samples per cycle pooled into one
model (the default ``NoiseAwareRegression()``, whose pooled series of ``Â`` is shrunk,
``resolved_harmonics=True``, one factor per harmonic and row, with ``ĉ`` and ``b̂`` re-estimated
to it, ``refit_offsets=True``), plain → shrunk on the same bins (plain: the plain series of the
bins' ``Â``, ``ĉ`` and ``b̂``), per cell (mean over seeds):

- ``Â``: as above;
- ``disp gait`` / ``disp cycle``: the model's one-cycle net displacement
  (:meth:`~torchconn.regression.model.LocalConnectionModel.evaluate_gait`, ``Â + ∂Â/∂r δ``) on the
  gait the trials were recorded with / on the model's own fitted cycle (``δ = 0``: ``Â`` alone),
  against :func:`torchconn.physics.gaits.evaluate` on the swimmer: ``|Δ(x, y)| / |(x, y)|``;
- ``x train`` / ``x test``: the sweep's error, RMS of the predicted ``v_x`` (``predict`` on the
  smoothed samples: ``ĉ + b̂δ + Âδ̇ + …``) against the swimmer on the noise-free samples
  (:func:`torchconn.evaluation.models.reference_models`), on the training cycles and on
  ``--test-cycles`` later cycles of the same trials (phased by the fitted phaser), mean over
  trials; ``y test`` / ``ω test``: the same for ``v_y`` and ``ω`` on the later cycles;
- ``ΔR²``: held-out R² (``est.score`` on the later cycles, against the observed velocity the
  way the regression sees it), shrunk − plain per component ``v_x, v_y, ω``.

``worse`` counts the seeds where shrunk is worse than plain, for ``disp gait`` and ``x test``.
``--variants`` adds more models to each row (see :data:`VARIANTS`)::

    PYTHONPATH=. python benchmarks/trial_shrink.py --threads 1 --pooled --links 9 \
        --gaits reference circle --seeds 2000 2001 2002 2003
"""
import argparse
import dataclasses
import itertools
import math
import sys
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from accuracy import SAMPLES_PER_CYCLE, connection_errors, gait_for, recording  # noqa: E402

from torchconn import ConnectionEstimator, NLinkSwimmer, NoiseAwareRegression  # noqa: E402
from torchconn.evaluation.models import clean_trajectory, reference_models  # noqa: E402
from torchconn.phase.fourier import fit_fourier  # noqa: E402
from torchconn.physics.gaits import FourierGait, evaluate  # noqa: E402
from torchconn.regression import skill  # noqa: E402
from torchconn.regression.noise_aware import (  # noqa: E402
    _BIAS_HARMONIC_Z,
    _SERIES_SHRINK,
    _harmonic_noise,
)
from torchconn.regression.tube import intercept_series  # noqa: E402


def errors(links: int, gait: str, omega: float, seed: int, trials: int, cycles: int):
    """Â's error ``(trials,)`` per one-trial fit: plain series, shrunk series."""
    traj = recording(links, gait, omega, n_cycles=cycles, seed=seed, n_trials=trials,
                     samples_per_cycle=64)
    est = ConnectionEstimator(pool=False, regression=NoiseAwareRegression(
        metric=False, resolved_harmonics="per_trial"), complexity="fixed", held_out_folds=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(traj)
    shrunk = est.model_
    plain = dataclasses.replace(shrunk, A=fit_fourier(shrunk.bins.phase, shrunk.bins.A,
                                                      shrunk.A.order, value_ndim=2))
    return connection_errors(plain, links)["A"], connection_errors(shrunk, links)["A"]


def _plain(model):
    """``model`` with the plain order-``K`` least-squares series of its bins' ``Â``, and
    ``ĉ``, ``b̂`` as fitted (:func:`_no_refit`)."""
    return dataclasses.replace(_no_refit(model), A=fit_fourier(model.bins.phase, model.bins.A,
                                                               model.A.order, value_ndim=2))


def _no_refit(model):
    """``model`` with the series of its bins' ``ĉ`` and ``b̂`` as fitted, not re-estimated to
    the shrunk ``Â`` (``NoiseAwareRegression(refit_offsets=False)``, the previous default; the
    same series bit for bit)."""
    centres, order = model.bins.phase, model.b.order
    c_order = model.meta.get("intercept_order")
    c_order = None if c_order is None else torch.as_tensor(c_order)
    return dataclasses.replace(
        model, c=intercept_series(centres, model.bins.c, order, c_order),
        b=fit_fourier(centres, model.bins.b, order, value_ndim=2))


def _resolved_kept(est, model):
    model = _no_refit(model)
    """The shrink left off the harmonics that stand out of their noise: factor 1 where the
    plain harmonic's power is at least ``_BIAS_HARMONIC_Z`` (4) times its noise expectation
    (the bias correction's "resolved"), ``1 − 0.5 noise / power`` (the default's) below."""
    plain = _plain(model)
    power, noise = _harmonic_noise(plain.A, model.bins.A_se, model.meta["window"],
                                   est.regression_.kernel)
    factor = (1 - _SERIES_SHRINK * noise / power.clamp_min(1e-300)).clamp(0, 1)
    factor = torch.where(power >= _BIAS_HARMONIC_Z * noise, 1.0, factor)
    factor[0] = 1
    coeff = torch.cat([factor[:1], factor[1:].repeat_interleave(2)])[:, None, None]
    return dataclasses.replace(model, A=dataclasses.replace(plain.A, coeffs=plain.A.coeffs * coeff))


def _per_harmonic(est, model):
    """The shrink before it was per row: one factor ``1 − 0.5 noise / power`` per harmonic,
    power and noise summed over all entries of ``Â``."""
    plain = _plain(model)
    power, noise = _harmonic_noise(plain.A, model.bins.A_se, model.meta["window"],
                                   est.regression_.kernel)  # (K + 1,)
    factor = (1 - _SERIES_SHRINK * noise / power.clamp_min(1e-300)).clamp(0, 1)
    factor[0] = 1
    coeff = torch.cat([factor[:1], factor[1:].repeat_interleave(2)])[:, None, None]
    return dataclasses.replace(plain, A=dataclasses.replace(plain.A, coeffs=plain.A.coeffs * coeff))


def _per_entry(est, model, rows: bool = False):
    """The default's factor ``1 − 0.5 noise / power`` per entry of ``Â`` and harmonic: the
    entry's power ``a_k² + b_k²`` against its share of the harmonic's noise expectation (the
    noise model's, split over the entries as their bins' mean squared standard errors).
    ``rows``: per row of ``Â`` (``x, y, θ``; power and noise summed over the joints)."""
    plain = _plain(model)
    _, noise = _harmonic_noise(plain.A, model.bins.A_se, model.meta["window"],
                               est.regression_.kernel)  # (K + 1,)
    level = model.bins.A_se.square().nanmean(0)  # (3, d)
    noise = noise[:, None, None] * level / level.sum()  # (K + 1, 3, d)
    c = plain.A.coeffs  # (2K + 1, 3, d)
    power = torch.cat([c[:1].square(), c[1::2].square() + c[2::2].square()])
    if rows:
        noise, power = (x.sum(-1, keepdim=True) for x in (noise, power))  # (K + 1, 3, 1)
    factor = (1 - _SERIES_SHRINK * noise / power.clamp_min(1e-300)).clamp(0, 1)
    factor[0] = 1
    coeff = torch.cat([factor[:1], factor[1:].repeat_interleave(2, 0)])
    return dataclasses.replace(plain, A=dataclasses.replace(plain.A, coeffs=c * coeff))


def _refit_cb(est, model):
    """The shrunk ``Â`` with ``ĉ`` and ``b̂`` refitted to it (the guess that the bins' ``Â``
    errors are offset by the jointly fitted ``ĉ`` and ``b̂``; poolshrink's prototype of the
    default ``refit_offsets``, on the model without it): in each of the model's bins
    (hard bins at the centres), the change ``−ΔÂ(φ) δ̇`` the shrink makes to the prediction on
    the samples the regression saw is regressed on ``[1, δ]`` (ordinary least squares), and the
    series of those coefficients are added to ``ĉ`` and ``b̂``."""
    model, plain = _no_refit(model), _plain(model)
    view = skill.regression_view(est.trajectory_, est.regression_, model, pool=True)
    delta, delta_dot = model.offsets(view.phase, view.r, view.r_dot)  # (N, d)
    change = -((model.A(view.phase) - plain.A(view.phase)) @ delta_dot.unsqueeze(-1))[..., 0]
    m = model.bins.phase.shape[-1]
    index = torch.round(view.phase % (2 * math.pi) / (2 * math.pi / m)).long() % m  # (N,)
    x = torch.cat([torch.ones_like(delta[:, :1]), delta], -1)  # (N, 1 + d)
    coef = []
    for b in range(m):
        sel = index == b
        coef.append(torch.linalg.lstsq(x[sel], change[sel]).solution)  # (1 + d, 3)
    coef = torch.stack(coef)  # (M, 1 + d, 3)
    centres = model.bins.phase
    dc = fit_fourier(centres, coef[:, 0], model.c.order, value_ndim=1)
    db = fit_fourier(centres, coef[:, 1:].transpose(-1, -2).contiguous(), model.b.order,
                     value_ndim=2)  # b̂: (3, d)
    return dataclasses.replace(
        model, c=dataclasses.replace(model.c, coeffs=model.c.coeffs + dc.coeffs),
        b=dataclasses.replace(model.b, coeffs=model.b.coeffs + db.coeffs))


#: models beside plain and shrunk that ``--variants`` adds to each row: name -> (fitted
#: estimator, shrunk model) -> model
VARIANTS = {"no_refit": lambda est, model: _no_refit(model),  # the previous default
            "resolved_kept": _resolved_kept, "refit_cb": _refit_cb, "per_entry": _per_entry,
            # the default's shrink, recomputed, without the refit (as no_refit)
            "per_row": lambda est, model: _per_entry(est, model, rows=True),
            "per_harmonic": _per_harmonic,
            "resolved_kept_refit_cb": lambda est, model: _refit_cb(est, _resolved_kept(est, model)),
            "per_entry_refit_cb": lambda est, model: _refit_cb(est, _per_entry(est, model))}


def prediction_errors(est, model, links: int, gait, test, clean_train, clean_test) -> dict:
    """What ``model`` (pooled, fitted by ``est``) predicts, against the swimmer: see the
    module's docstring (``--pooled``); ``R2`` is ``(3,)``, the rest are numbers."""
    system = NLinkSwimmer(links)
    xy = evaluate(system, gait).displacement[:2]
    own = FourierGait(model.gamma.coeffs)
    xy_own = evaluate(system, own).displacement[:2]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d_gait = model.evaluate_gait(gait, n_draws=0).displacement[:2]
        d_own = model.evaluate_gait(own, phase_offset=0.0, n_draws=0).displacement[:2]
    out = {"A": float(connection_errors(model, links)["A"]),
           "disp_gait": float((d_gait - xy).norm() / xy.norm()),
           "disp_cycle": float((d_own - xy_own).norm() / xy_own.norm())}
    fitted = est.model_, est.forecast_model_
    try:  # (score() predicts with forecast_model_: the same object here, complexity "fixed")
        est.model_ = est.forecast_model_ = model
        for key, traj, clean in (("x_train", est.trajectory_, clean_train),
                                 ("x_test", est._prepare_new(test, None), clean_test)):
            preds = reference_models(system, model, traj, clean)
            err = preds["data_driven"] - preds["ground_truth"]  # (trials, T, 3)
            rms = err.square().nanmean(-2).sqrt().mean(0)  # (3,)
            out[key] = float(rms[0])
            if key == "x_test":
                out["y_test"], out["w_test"] = float(rms[1]), float(rms[2])
        out["R2"] = est.score(test).r2.reshape(-1)
    finally:
        est.model_, est.forecast_model_ = fitted
    return out


def pooled(links: int, gait: str, omega: float, seed: int, trials: int, cycles: int,
           test_cycles: int, variants: tuple[str, ...] = ()) -> dict:
    """:func:`prediction_errors` of the plain, the shrunk (the default) and the ``variants``'
    models of one pooled recording, fitted on its first ``cycles`` cycles."""
    traj = recording(links, gait, omega, n_cycles=cycles + test_cycles, seed=seed,
                     n_trials=trials)
    cut = cycles * SAMPLES_PER_CYCLE + 1
    train, test = traj.slice_time(0, cut), traj.slice_time(cut, traj.n_samples)
    est = ConnectionEstimator(pool=True, regression=NoiseAwareRegression(metric=False),
                              complexity="fixed", held_out_folds=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(train)
    shrunk = est.model_
    models = {"plain": _plain(shrunk), "shrunk": shrunk}
    models.update({name: VARIANTS[name](est, shrunk) for name in variants})
    clean_train, clean_test = clean_trajectory(train), clean_trajectory(test)
    return {name: prediction_errors(est, m, links, gait_for(links, gait), test, clean_train,
                                    clean_test) for name, m in models.items()}


def pooled_table(args) -> int:
    names = ["plain", "shrunk", *args.variants]
    keys = ("A", "disp_gait", "disp_cycle", "x_train", "x_test", "y_test", "w_test")
    print(f"pooled {args.trials} x {args.cycles} cycles (+{args.test_cycles} held out), seeds "
          f"{args.seeds}; % for Â and displacement, 1e-4 for x RMS; " + " → ".join(names))
    print("| links | gait | ω | Â | disp gait | disp cycle | x train | x test | y test | ω test "
          "| ΔR² ×1e4 (v_x, v_y, ω) | worse (disp gait, x test) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for links, gait, omega in itertools.product(args.links, args.gaits, args.omega):
        runs = [pooled(links, gait, omega, s, args.trials, args.cycles, args.test_cycles,
                       tuple(args.variants)) for s in args.seeds]
        cols = []
        for key in keys:
            rms = key.endswith(("_train", "_test"))
            unit = 1e4 if rms else 100
            means = [unit * sum(r[n][key] for r in runs) / len(runs) for n in names]
            cols.append(" → ".join(f"{m:.3f}" if rms else f"{m:.2f}" for m in means))
        dr2 = [1e4 * torch.stack([r[n]["R2"] - r["plain"]["R2"] for r in runs]).mean(0)
               for n in names[1:]]
        worse = [f"{sum(r[n][k] > r['plain'][k] for r in runs)}/{len(runs)}"
                 for n in names[1:] for k in ("disp_gait", "x_test")]
        print(f"| {links} | {gait} | {omega:g} | " + " | ".join(cols) + " | "
              + " ; ".join(", ".join(f"{v:+.1f}" for v in x.tolist()) for x in dr2) + " | "
              + " ".join(worse) + " |", flush=True)
        if args.verbose:
            for s, r in zip(args.seeds, runs, strict=True):
                print(f"  seed {s}: " + "; ".join(
                    f"{n}: " + ", ".join(f"{k} {r[n][k]:.4g}" for k in keys)
                    + " R2 " + ",".join(f"{v:.4f}" for v in r[n]["R2"].tolist())
                    for n in names), flush=True)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--links", type=int, nargs="+", default=[3, 5])
    p.add_argument("--gaits", nargs="+", default=["circle", "reference"])
    p.add_argument("--omega", type=float, nargs="+", default=[0.0, 0.002, 0.005, 0.01])
    p.add_argument("--seeds", type=int, nargs="+", default=[3, 4, 7, 8])
    p.add_argument("--trials", type=int, default=4)
    p.add_argument("--cycles", type=int, default=30)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--pooled", action="store_true",
                   help="the default pooled shrink and the model's predictions (see above)")
    p.add_argument("--test-cycles", type=int, default=10,
                   help="--pooled: later cycles of each trial held out for prediction")
    p.add_argument("--variants", choices=list(VARIANTS), nargs="*", default=[],
                   help="--pooled: more models per row (VARIANTS)")
    p.add_argument("--verbose", action="store_true", help="--pooled: every seed's numbers")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.pooled:
        return pooled_table(args)
    print("| links | gait | ω | Â plain → shrunk | fits worse |")
    print("|---|---|---|---|---|")
    for links, gait, omega in itertools.product(args.links, args.gaits, args.omega):
        pairs = [errors(links, gait, omega, s, args.trials, args.cycles) for s in args.seeds]
        plain = torch.cat([a.reshape(-1) for a, _ in pairs])
        shrunk = torch.cat([b.reshape(-1) for _, b in pairs])
        print(f"| {links} | {gait} | {omega:g} | {100 * float(plain.mean()):.2f} → "
              f"{100 * float(shrunk.mean()):.2f} % | {int((shrunk > plain).sum())} of "
              f"{plain.numel()} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
