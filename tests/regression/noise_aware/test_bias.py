"""Bias corrections of the noise-aware fit: the bins' and filter's bias, the offsets' bias and
the allowance for what is left."""

import dataclasses
import math

import numpy as np
import torch

from torchconn import (
    NLinkSwimmer,
    simulate,
)
from torchconn.noise import (
    interval_samples,
)
from torchconn.regression.binning import assign_bins
from torchconn.regression.connection import connection_regression
from torchconn.regression.noise_aware.bias import offset_bias

from ..common import DT_SAMPLES, a_error_and_scale, deliver_corrected_alone, fit_pooled

F64 = torch.float64


def test_bias_correction_removes_the_bins_and_filters_bias_on_a_curved_gait(monkeypatch):
    # Noise-free 3-link reference gait with the interval and bins that ω = 0.002 needs
    # (h = 8, windows of 2 spacings): A changes fast along this gait, so the bins' phase
    # window and the velocity filter average it and the uncorrected Â is off by ~3 %. The
    # pooled choice scores a corrected candidate as V + λ‖B‖², i.e. it takes the bias left
    # after the correction to be at most √λ times the correction B applied; against the exact
    # connection at the bin centres that bound must hold, and the correction must remove most
    # of the bias along the fitted cycle.
    import torchconn.regression.noise_aware.regression as na
    from torchconn.physics.gaits import reference_gait
    from torchconn.regression.noise_aware.bias import RESIDUAL_BIAS_FRACTION

    seeds = np.arange(4) + 700
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=30,
                    samples_per_cycle=DT_SAMPLES, seeds=seeds)
    deliver_corrected_alone(monkeypatch)  # the correction's own Â, not shrunk
    fits = {True: fit_pooled(traj, velocity_interval=8, window=2.0)}
    # uncorrected: the same single candidate (interval and window given) left as fitted
    monkeypatch.setattr(na, "bin_bias_correction", lambda fit, *args, **kwargs: (fit, 0.0))
    fits[False] = fit_pooled(traj, velocity_interval=8, window=2.0)
    err = {bc: a_error_and_scale(est)[0] for bc, est in fits.items()}
    assert err[False] > 0.02, err  # the bias is there (the test can fail)
    assert err[True] < 0.5 * err[False], err
    bins = fits[True].model_.bins
    a_true = NLinkSwimmer(3).connection(bins.gamma)
    residual = float((bins.A - a_true).norm())
    applied = float((bins.A - fits[False].model_.bins.A).norm())
    assert residual <= math.sqrt(RESIDUAL_BIAS_FRACTION) * applied, (residual, applied)


def test_offset_bias_is_the_first_order_fits_error_on_a_second_order_connection():
    """On body velocities made exactly of the first-order terms plus ``δ⊗δ`` and ``δ̇⊗δ⊗δ``
    (a connection with a second derivative, noise-free), the extended fit is exact, so
    ``offset_bias`` is the first-order fit's error in ``Â`` (closed form: that fit minus the
    true ``A``), not small here (the offsets' cube has a mean: the tube is not symmetric
    about the cycle), and its variance is not positive (the extended fit has no residual:
    there is no noise for the allowance to stand out of)."""
    g = torch.Generator().manual_seed(8)
    n, d, m = 2400, 2, 4
    phase = torch.rand(n, generator=g, dtype=F64) * 2 * math.pi
    r = 0.3 * torch.randn(n, d, generator=g, dtype=F64) + 0.2 * torch.rand(n, 1, generator=g,
                                                                            dtype=F64)
    r_dot = torch.randn(n, d, generator=g, dtype=F64)
    c, b, a = (torch.randn(3, *shape, generator=g, dtype=F64) for shape in ((), (d,), (d,)))
    da = torch.randn(3, d, d, generator=g, dtype=F64)
    hess = torch.randn(3, d, 3, generator=g, dtype=F64)  # on δ̇_k δ_i δ_j, i ≤ j
    quad = torch.randn(3, 3, generator=g, dtype=F64)  # on δ_i δ_j, i ≤ j
    iu, ju = torch.triu_indices(d, d)
    square = r[:, iu] * r[:, ju]  # (n, 3)
    xi = (c + r @ b.T + r_dot @ a.T + torch.einsum("kij,ni,nj->nk", da, r_dot, r)
          + torch.einsum("kiq,ni,nq->nk", hess, r_dot, square) + square @ quad.T)
    iv = interval_samples(torch.zeros(n + 1, 3, dtype=F64), torch.zeros(n + 1, d, dtype=F64),
                          torch.zeros(n + 1, dtype=F64), 0.1, 1)
    iv = dataclasses.replace(iv, phase=phase, r=r, r_dot=r_dot, xi=xi)
    bins = assign_bins(phase, m, window=1.0, kernel="tricube")
    zero = torch.zeros(m, d, dtype=F64)
    bias, var = offset_bias(iv, bins, zero, zero)
    first = connection_regression(r, r_dot, xi, bins, zero, zero)
    closed = first.A - a
    torch.testing.assert_close(bias, closed, rtol=1e-7, atol=1e-9)
    assert float(closed.abs().max()) > 0.05
    assert float(var.max()) <= 1e-20
    # of another estimate of Â (as a delivered one, moved from the plain fit): its own error,
    # E − A, with the same variance
    moved = first.A + 0.1 * torch.randn(first.A.shape, generator=g, dtype=F64)
    bias_moved, var_moved = offset_bias(iv, bins, zero, zero, estimate=moved)
    torch.testing.assert_close(bias_moved, moved - a, rtol=1e-7, atol=1e-9)
    assert torch.equal(var_moved, var)


def test_clean_bias_allowance_is_that_of_the_delivered_a(clean30, monkeypatch):
    """A clean pooled fit's allowance is the bias of the ``Â`` it delivers (which the bins' bias
    correction has moved from the plain fit), not of the plain fit: ``offset_bias`` is asked
    for the delivered ``Â``'s change, and the allowance is the resolved sum of the two parts."""
    from torchconn.regression.noise_aware import bias, regression

    seen = {}

    def spy(name):
        original = getattr(regression, name)

        def wrapped(*args, **kw):
            seen[name] = (args, kw, original(*args, **kw))
            return seen[name][2]
        monkeypatch.setattr(regression, name, wrapped)

    spy("offset_bias")
    spy("interval_bias")
    model = fit_pooled(clean30).model_
    args, kw, (tube, tube_var) = seen["offset_bias"]
    _, _, (step, step_var) = seen["interval_bias"]
    assert torch.equal(kw["estimate"], model.bins.A)
    # the plain fit's change differs from it by the plain fit's move, which is not 0
    plain_tube, plain_var = bias.offset_bias(*args, **{**kw, "estimate": None})
    samples, bins, gamma_m, gamma_dot_m = args
    plain = connection_regression(samples.r, samples.r_dot, samples.xi, bins, gamma_m,
                                  gamma_dot_m)
    moved = plain.A - model.bins.A
    torch.testing.assert_close(plain_tube - tube, moved, rtol=1e-9, atol=1e-15)
    assert torch.equal(plain_var, tube_var)
    assert float(moved.abs().max()) > 0.05 * float(tube.abs().max())
    expected = bias.resolved_bias(torch.nan_to_num(tube) + torch.nan_to_num(step),
                                  torch.nan_to_num(tube_var) + torch.nan_to_num(step_var))
    assert torch.equal(model.bins.A_bias_allowance, expected)
