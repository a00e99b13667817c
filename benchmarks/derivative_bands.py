"""Where the tied ``∂Â/∂r``'s bands fall short under noise (3-link, pooled 4 × 30 cycles).

A diagnosis, not a table of the method: for each recording (``accuracy.py``'s, the default
``NoiseAwareRegression``) it prints the bands' ``e²/se²`` (squared error at the bin centres over
squared standard error, summed; 1 = honest), overall and in the rotation row, and splits it:

- ``smooth``: ``e²/se²`` against the true Jacobian averaged over the bins' phase window
  (tricube, the chosen half-width) instead of at the centre, and ``win²`` that average's own
  squared departure from the centre's truth: the phase-smoothing bias of the window;
- ``direct`` / ``b`` / ``slope``: the tied error's part that comes from each source's error
  (the tie is linear in its three sources at fixed weights), over the tied ``se²``;
- ``across``: the direct estimate's across-cycle component ``nᵀ D n`` (``n`` normal to the
  cycle: the one of the 4 entries per bin and row that only the direct estimate holds), its
  squared error over the solver's variance (``cov_b_dA``) and over that plus the modelled bias
  as the bands take it (``+bias``), and the correlation of its error with the modelled bias;
- ``narrower``: the bands with the change of the tied estimate at the window one step narrower
  (same interval) allowed for, ``se² + Δ²``, and ``Δ²``'s size over ``se²``.

The tie's inputs are read by wrapping
:func:`~torchconn.regression.noise_aware.bias.derivative_bias_allowance` (as
:mod:`~torchconn.regression.noise_aware.regression` calls it) for the duration of a fit
(restored after; the estimates are not touched).

Run by hand (seconds per recording)::

    python benchmarks/derivative_bands.py --gait reference --omega 0.01 --seeds 3 4
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import warnings

import torch
from accuracy import recording

from torchconn import ConnectionEstimator, NLinkSwimmer, NoiseAwareRegression
from torchconn.regression.binning import kernel_weight
from torchconn.regression.noise_aware import bias
from torchconn.regression.noise_aware import regression as noise_aware
from torchconn.regression.tied import cycle_tangent, tie_connection_derivative


@contextlib.contextmanager
def tie_inputs():
    """Record the tie's inputs (the fit, its modelled bias, the cycle and bins) of the fits
    run inside, in the dict yielded."""
    seen, original = {}, noise_aware.derivative_bias_allowance

    def wrapped(fit, traj, samples, bins, gamma_m, gamma_dot_m, *, order, **kw):
        tied, bias = original(fit, traj, samples, bins, gamma_m, gamma_dot_m, order=order, **kw)
        seen.update(fit=fit, bias=bias, bins=bins, gamma_m=gamma_m, gamma_dot_m=gamma_dot_m,
                    order=order, tied=tied)
        return tied, bias

    noise_aware.derivative_bias_allowance = wrapped
    try:
        yield seen
    finally:
        noise_aware.derivative_bias_allowance = original


def fit(traj, **options):
    est = ConnectionEstimator(pool=True, regression=NoiseAwareRegression(**options),
                              complexity="fixed", held_out_folds=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(traj)
    return est.model_


def ratio(e: torch.Tensor, v: torch.Tensor) -> float:
    return float(e.square().nansum() / v.nansum())


def window_truth(model, system: NLinkSwimmer, n_points: int = 81) -> torch.Tensor:
    """The true Jacobian averaged over each bin's window (tricube): ``(M, 3, d, d)``."""
    m, w = model.bins.dA.shape[-4], float(model.meta["window"])
    s = torch.linspace(-1, 1, n_points, dtype=torch.float64)
    k = kernel_weight(s.abs(), "tricube")
    phi = (torch.arange(m, dtype=torch.float64)[:, None] * (2 * math.pi / m)
           + s * (w * 2 * math.pi / m))
    jac = system.connection_jacobian(model.gamma_at(phi.reshape(-1)).detach())
    return (jac.unflatten(0, (m, n_points)) * (k / k.sum())[None, :, None, None, None]).sum(1)


def contributions(seen: dict, system: NLinkSwimmer) -> dict:
    """Each source's error carried through the tie (its weights as the fit's), ``(M, 3, d, d)``."""
    fit, (bias_da, bias_b) = seen["fit"], seen["bias"]
    g, gd = seen["gamma_m"], seen["gamma_dot_m"]
    share = bias.RESIDUAL_BIAS_FRACTION
    weighed = dataclasses.replace(
        fit, se_dA=(fit.se_dA.square() + share * bias_da.square()).sqrt(),
        se_b=(fit.se_b.square() + share * bias_b.square()).sqrt(), cov_b_dA=None)
    jac, conn = system.connection_jacobian(g), system.connection(g)
    b_true = torch.einsum("mkij,mi->mkj", jac, gd)
    zero = dict(A=torch.zeros_like(fit.A), b=torch.zeros_like(fit.b), dA=torch.zeros_like(fit.dA))

    def tie(**errors):
        return tie_connection_derivative(
            dataclasses.replace(weighed, **{**zero, **errors}), g, gd, seen["order"],
            window=seen["bins"].window, kernel=seen["bins"].kernel, consistency=False).dA

    return {"direct": tie(dA=fit.dA - jac), "b": tie(b=fit.b - b_true),
            "slope": tie(A=fit.A - conn)}


def across(seen: dict, system: NLinkSwimmer) -> tuple[float, float, float]:
    """The direct estimate's across-cycle component (3-link): ``e²/var`` (solver), ``e²/var``
    (+ the bias as the bands take it) and the correlation of its error with the modelled bias."""
    fit, bias_da, g = seen["fit"], seen["bias"][0], seen["gamma_m"]
    t = cycle_tangent(g)
    n = torch.stack([-t[..., 1], t[..., 0]], -1) / t.norm(dim=-1, keepdim=True)
    nn = (n[:, :, None] * n[:, None, :]).flatten(-2)  # (M, 4): vec(n nᵀ)
    err = ((fit.dA - system.connection_jacobian(g)).flatten(-2) * nn[:, None]).sum(-1)
    var = torch.einsum("ma,mkab,mb->mk", nn, fit.cov_b_dA[..., 2:, 2:], nn)
    share = bias._DIRECT_BIAS_SHARE
    with_bias = var + share * torch.einsum("ma,mka->mk", nn.square(), bias_da.flatten(-2).square())
    modelled = (bias_da.flatten(-2) * nn[:, None]).sum(-1)
    corr = float(torch.nn.functional.cosine_similarity(err.flatten(), modelled.flatten(), 0))
    return ratio(err, var), ratio(err, with_bias), corr


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--gait", default="reference", choices=["circle", "reference"])
    p.add_argument("--omega", type=float, nargs="+", default=[0.01])
    p.add_argument("--seeds", type=int, nargs="+", default=[3, 4])
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    system = NLinkSwimmer(3)
    for omega in args.omega:
        for seed in args.seeds:
            traj = recording(3, args.gait, omega, seed=seed)
            with tie_inputs() as seen:
                model = fit(traj)
            b = model.bins
            se2, err = b.dA_se.square(), b.dA - system.connection_jacobian(b.gamma)
            smooth = window_truth(model, system)
            w, h = float(model.meta["window"]), int(model.meta["velocity_interval"])
            line = (f"{args.gait} ω {omega:g} seed {seed} h {h} w {w:g}: e²/se² "
                    f"{ratio(err, se2):.2f} (rotation {ratio(err[:, 2], se2[:, 2]):.2f}) "
                    f"smooth {ratio(b.dA - smooth, se2):.2f} "
                    f"win² {ratio(smooth - system.connection_jacobian(b.gamma), se2):.2f}")
            if "fit" not in seen:  # no noise detected: the tie was bias-corrected instead
                print(line + " (no noise detected)", flush=True)
                continue
            line += " | " + " ".join(f"{k} {ratio(e, se2):.2f}"
                                     for k, e in contributions(seen, system).items())
            line += " | across {:.2f} +bias {:.2f} corr {:.2f}".format(*across(seen, system))
            if w > 1:
                change = b.dA - fit(traj, window=w - 1, velocity_interval=h).bins.dA
                line += (f" | narrower {ratio(err, se2 + change.square()):.2f} "
                         f"Δ² {ratio(change, se2):.2f}")
            print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
