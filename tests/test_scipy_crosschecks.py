"""Cross-checks against scipy where scipy does the same computation.

- the FFT Hilbert transform against :func:`scipy.signal.hilbert`;
- the order-2 RTS smoother at a fixed noise ratio against the cubic smoothing spline
  :func:`scipy.interpolate.make_smoothing_spline` (the white-acceleration smoother's posterior
  mean *is* that spline with ``λ = R / q``, given a diffuse prior on the initial state), run
  both sequentially and as a parallel scan;
- a Levenberg–Marquardt fit of the discrepancy workflow against
  :func:`scipy.optimize.least_squares` (``method="lm"``);
- the paired t-test of the workflow and the per-bin t-tests of the claims against the
  textbook statistic ``t = mean / (sd / √n)`` with Student's t distribution.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import signal, stats
from scipy.interpolate import make_smoothing_spline
from scipy.optimize import least_squares

from torchconn import NLinkSwimmer
from torchconn.discrepancy import ForwardModel, prepare_measurement, simulate_with_effects
from torchconn.discrepancy.fitting import Problem, fit_effects, paired_gain
from torchconn.phase.phaser import analytic_signal
from torchconn.phase.smoothing import rts_smooth
from torchconn.physics.gaits import reference_gait
from torchconn.sweep.claims import _ttest_pvalues


@pytest.mark.parametrize("n", [63, 64])
def test_analytic_signal_is_scipy_hilbert(n):
    rng = np.random.default_rng(n)
    x = rng.standard_normal((2, 3, n))
    z = analytic_signal(torch.from_numpy(x), dim=-1).numpy()
    np.testing.assert_allclose(z, signal.hilbert(x, axis=-1), rtol=0, atol=1e-12)
    # along another axis, as Phaser uses it (time at -2)
    z = analytic_signal(torch.from_numpy(x.swapaxes(-1, -2)), dim=-2).numpy()
    np.testing.assert_allclose(z, signal.hilbert(x.swapaxes(-1, -2), axis=-2), rtol=0, atol=1e-12)


@pytest.mark.parametrize("algorithm", ["loop", "scan"])
def test_rts_smoother_is_the_cubic_smoothing_spline(algorithm):
    """Order 2 (white acceleration, spectral density q) with measurement variance R minimises
    ``Σ (y_k − f(t_k))² / R + ∫ f''² / q``: the cubic smoothing spline with ``λ = R / q``.

    Exact (to round-off) wherever the initial prior no longer matters: torchconn starts from a
    vague prior (1e4 times the data's variance) rather than a diffuse one, whose pull decays
    within a few correlation lengths of the start; the end of the record is the spline's
    natural boundary in both.
    """
    rng = np.random.default_rng(0)
    T, dt = 400, 0.05
    t = np.arange(T) * dt
    y = np.stack([np.sin(t) + 0.3 * np.cos(2.3 * t), np.cos(0.7 * t) * t / 10], -1)
    y = y + 0.05 * rng.standard_normal(y.shape)
    R = np.array([0.0025, 0.0025])
    q = np.array([1.0, 0.1])  # two noise ratios, one per channel
    val, der = rts_smooth(torch.from_numpy(y), dt, process_noise=torch.from_numpy(q),
                          measurement_noise=torch.from_numpy(R), algorithm=algorithm)
    for c in range(2):
        spline = make_smoothing_spline(t, y[:, c], lam=R[c] / q[c])
        err = np.abs(val[:, c].numpy() - spline(t))
        derr = np.abs(der[:, c].numpy() - spline.derivative()(t))
        assert err[60:].max() < 1e-10 and derr[60:].max() < 1e-9, (err[60:].max(), derr[60:].max())
        assert err[:60].max() < 1e-5  # the vague prior's pull near the start
        # the spline is not the data: this is a real comparison
        assert np.abs(spline(t) - y[:, c]).max() > 0.05


def test_levenberg_marquardt_fit_matches_scipy_least_squares():
    """The workflow's LM (autograd Jacobians, Broyden updates between them) reaches the
    minimum scipy's MINPACK LM finds on the same residual, at its default tolerances."""
    torch.set_num_threads(1)
    swimmer = NLinkSwimmer(3)
    effects = {"time_lag": {"tau": 0.06}, "drag_ratio": {"delta_k": 0.3}}
    traj = simulate_with_effects(swimmer, reference_gait("3link"), effects, eta=0.025,
                                 n_cycles=5, seeds=[2], omega=0.002)
    problem = Problem(ForwardModel(prepare_measurement(traj, swimmer, min_cycles=3), swimmer),
                      n_folds=2)
    names = ["time_lag", "drag_ratio"]
    fit = fit_effects(problem, names)
    _, scale = problem.specs(names)
    ref = least_squares(
        lambda p: problem.evaluate(names, torch.from_numpy(p), jacobian=False)[0].numpy(),
        np.zeros(len(scale)),
        jac=lambda p: problem.evaluate(names, torch.from_numpy(p))[1].numpy(),
        method="lm", x_scale=scale.numpy(), xtol=1e-15, ftol=1e-15, gtol=1e-15,
    )
    assert ref.success
    se = fit.se().numpy()
    assert np.all(np.abs(fit.p.numpy() - ref.x) < 1e-3 * se), (fit.p, ref.x, se)
    assert fit.cost_history[-1] == pytest.approx(2 * ref.cost, rel=1e-8)
    # and the fit found the hidden effects (a real problem, not a trivial one)
    assert abs(ref.x[0] - 0.06) < 4 * se[0] and abs(ref.x[1] - 0.3) < 4 * se[1]


def test_paired_gain_is_the_one_sided_paired_t_test():
    g = torch.Generator().manual_seed(0)
    base = 10 * torch.rand(12, generator=g, dtype=torch.float64)
    new = base - 0.1 - 0.3 * torch.randn(5, 12, generator=g, dtype=torch.float64)
    batch = paired_gain(base, new, n_entries=100.0)
    for i in range(5):
        d = (base - new[i]).numpy()
        t = d.mean() / (d.std(ddof=1) / math.sqrt(d.size))
        one = paired_gain(base, new[i], 100.0)
        for got in (one, {k: v[i] for k, v in batch.items()}):
            assert got["t"] == pytest.approx(t, rel=1e-12)
            assert got["p"] == pytest.approx(stats.t.sf(t, d.size - 1), rel=1e-10)
            assert got["gain"] == pytest.approx(d.sum() / 100.0, rel=1e-12)
    # no spread: the sign of the gain decides
    assert paired_gain(base, base - 1.0, 100.0)["p"] == 0.0
    assert paired_gain(base, base + 1.0, 100.0)["p"] == 1.0
    assert paired_gain(base, base, 100.0) == {"gain": 0.0, "t": 0.0, "p": 0.5}


def test_claim_a_bin_tests_are_two_sided_t_tests():
    rng = np.random.default_rng(3)
    m = rng.standard_normal((500, 7)) * rng.uniform(0.2, 2, (500, 1)) + rng.uniform(-1, 1, (500, 1))
    m[0], m[1] = 0.0, 0.4  # no spread: mean 0 is never significant, a non-zero mean always
    crit = stats.t.ppf(1 - 0.01 / 2, 6)
    with np.errstate(divide="ignore", invalid="ignore"):
        textbook = np.abs(m.mean(1)) > crit * m.std(1, ddof=1) / math.sqrt(7)
    np.testing.assert_array_equal(_ttest_pvalues(m) < 0.01, textbook)
    assert 0.1 < textbook.mean() < 0.9
