"""OnlineConnection: the connection's bin regressions updated cycle by cycle equal a batch fit
of the same samples (numpy lstsq on the stacked design, and the package's own solver), with
forgetting the batch fit with weights λ^age, and its confidence grows with the cycles."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from torchconn import NLinkSwimmer, simulate
from torchconn.phase.fourier import FourierSeries
from torchconn.regression import (
    LocalConnectionModel,
    TubeRegression,
    assign_bins,
    connection_regression,
)
from torchconn.regression.online import OnlineConnection

from .common import circle_gait, fit_pooled

F64 = torch.float64
M, WINDOW, ORDER = 16, 1.5, 5
N_CYCLES, SPC = 12, 64


@pytest.fixture(scope="module")
def recording():
    """Two trials of the 3-link, clean (true phase, shapes and body velocities)."""
    gait = circle_gait()
    traj = simulate(NLinkSwimmer(3), gait, eta=0.025, n_cycles=N_CYCLES, samples_per_cycle=SPC,
                    seeds=np.arange(2))
    truth = traj.truth
    start = truth.phase[..., :1]
    cycle = torch.floor((truth.phase - start) / (2 * math.pi)).long().clamp(0, N_CYCLES - 1)
    return gait.coeffs, truth.phase, truth.r, truth.r_dot, truth.xi, cycle


def cycle_samples(recording, c):
    """The samples of cycle ``c`` of every trial, the others NaN (missing)."""
    _, phase, r, r_dot, xi, cycle = recording
    keep = cycle == c
    return (torch.where(keep, phase, torch.nan),
            *(torch.where(keep.unsqueeze(-1), x, torch.nan) for x in (r, r_dot, xi)))


def numpy_fit(gamma_m, gamma_dot_m, phase, r, r_dot, xi, weight):
    """Per-bin weighted least squares by numpy lstsq on the stacked design ``[1, δ, δ̇, δ̇⊗δ]``
    (``(M, P, 3)``): bins of half-width ``WINDOW`` spacings with tricube weights, times the
    samples' own ``weight``; samples flattened ``(N,)``."""
    phase, r, r_dot, xi, weight = (np.asarray(x) for x in (phase, r, r_dot, xi, weight))
    spacing = 2 * np.pi / M
    out = []
    for m in range(M):
        dist = np.abs((phase - m * spacing + np.pi) % (2 * np.pi) - np.pi) / (WINDOW * spacing)
        w = np.where(dist < 1, (1 - np.clip(dist, 0, 1) ** 3) ** 3, 0.0) * weight
        delta = r - np.asarray(gamma_m[m])
        delta_dot = r_dot - np.asarray(gamma_dot_m[m])
        cross = (delta_dot[:, :, None] * delta[:, None, :]).reshape(len(phase), -1)
        x = np.concatenate([np.ones((len(phase), 1)), delta, delta_dot, cross], 1)
        sw = np.sqrt(w)[:, None]
        out.append(np.linalg.lstsq(x * sw, xi * sw, rcond=None)[0])
    return np.stack(out)


def assert_close_per_bin(got, want, rtol):
    """``‖got − want‖ ≤ rtol ‖want‖`` in every bin (``(..., M, P, K)``)."""
    got, want = np.asarray(got), np.asarray(want)
    err = np.linalg.norm((got - want).reshape(got.shape[:-2] + (-1,)), axis=-1)
    size = np.linalg.norm(want.reshape(want.shape[:-2] + (-1,)), axis=-1)
    assert np.all(err <= rtol * size), float((err / size).max())


def online_for(recording, **kw):
    coeffs = recording[0]
    return OnlineConnection(FourierSeries(coeffs, 1), 1.0, n_bins=M, window=WINDOW,
                            kernel="tricube", fourier_order=ORDER, **kw)


def test_cycle_by_cycle_equals_batch_lstsq_per_trial(recording):
    coeffs, phase, r, r_dot, xi, _ = recording
    # statistics batched over the two trials: one cycle each, both trials at once
    gamma = FourierSeries(coeffs.expand(2, -1, -1), 1)
    online = OnlineConnection(gamma, torch.ones(2), n_bins=M, window=WINDOW, kernel="tricube",
                              fourier_order=ORDER)
    for c in range(N_CYCLES):
        online.update(*cycle_samples(recording, c))
    assert online.cycles == N_CYCLES
    fit = online.fit()
    assert fit.coef.shape == (2, M, 9, 3)
    for trial in range(2):
        want = numpy_fit(online.gamma_m[trial], online.gamma_dot_m[trial], phase[trial],
                         r[trial], r_dot[trial], xi[trial], np.ones(phase.shape[-1]))
        assert_close_per_bin(fit.coef[trial], want, 1e-8)


def test_pooled_trials_equal_the_batch_solver(recording):
    """Trials pooled (a leading dim of the samples): coefficients and standard errors equal
    connection_regression on every sample at once."""
    _, phase, r, r_dot, xi, _ = recording
    online = online_for(recording)
    for c in range(N_CYCLES):
        online.update(*cycle_samples(recording, c))
    bins = assign_bins(phase.reshape(-1), M, window=WINDOW, kernel="tricube")
    batch = connection_regression(r.reshape(-1, 2), r_dot.reshape(-1, 2), xi.reshape(-1, 3),
                                  bins, online.gamma_m, online.gamma_dot_m)
    fit = online.fit()
    assert_close_per_bin(fit.coef, batch.coef, 1e-8)
    assert_close_per_bin(fit.se_coef, batch.se_coef, 1e-6)
    torch.testing.assert_close(fit.n_samples, batch.n_samples)
    want = numpy_fit(online.gamma_m, online.gamma_dot_m, phase.reshape(-1), r.reshape(-1, 2),
                     r_dot.reshape(-1, 2), xi.reshape(-1, 3), np.ones(phase.numel()))
    assert_close_per_bin(fit.coef, want, 1e-8)


def test_forgetting_equals_batch_with_geometric_weights(recording):
    _, phase, r, r_dot, xi, cycle = recording
    lam = 0.7
    online = online_for(recording, forgetting=lam)
    for c in range(N_CYCLES):
        conf = online.update(*cycle_samples(recording, c))
        assert conf.forgetting == lam
    age = (N_CYCLES - 1 - cycle).to(F64)
    want = numpy_fit(online.gamma_m, online.gamma_dot_m, phase.reshape(-1), r.reshape(-1, 2),
                     r_dot.reshape(-1, 2), xi.reshape(-1, 3), (lam ** age).reshape(-1))
    assert_close_per_bin(online.fit().coef, want, 1e-8)
    # and it differs from forgetting nothing by far more than that
    plain = numpy_fit(online.gamma_m, online.gamma_dot_m, phase.reshape(-1), r.reshape(-1, 2),
                      r_dot.reshape(-1, 2), xi.reshape(-1, 3), np.ones(phase.numel()))
    err = np.linalg.norm(online.fit().coef.numpy() - plain) / np.linalg.norm(plain)
    assert err > 1e-4


def test_per_update_forgetting_overrides_the_default(recording):
    """λ given per update: cycle c's weight is the product of the λ of every later update."""
    _, phase, r, r_dot, xi, cycle = recording
    lams = [1.0] + [0.6 + 0.03 * c for c in range(1, N_CYCLES)]
    online = online_for(recording)
    for c in range(N_CYCLES):
        online.update(*cycle_samples(recording, c), forgetting=lams[c])
    later = np.array([np.prod(lams[c + 1:]) for c in range(N_CYCLES)])
    weight = later[cycle.numpy()].reshape(-1)
    want = numpy_fit(online.gamma_m, online.gamma_dot_m, phase.reshape(-1), r.reshape(-1, 2),
                     r_dot.reshape(-1, 2), xi.reshape(-1, 3), weight)
    assert_close_per_bin(online.fit().coef, want, 1e-8)


def test_confidence_grows_with_the_cycles(recording):
    online = online_for(recording)
    history = [online.update(*cycle_samples(recording, c)) for c in range(N_CYCLES)]
    assert online.confidence() is history[-1] and online.history == history
    # nothing to predict the first cycle with
    assert bool(history[0].r2.isnan().all())
    r2 = torch.stack([h.score for h in history[1:]])
    assert bool((r2 > 0.99).all())
    assert float(r2[0]) < float(r2[-4:].mean())  # the first prediction is the worst
    # ∂Â/∂r's relative standard error falls as 1/√cycles
    rel = torch.stack([h.dA_relative_se for h in history]).numpy()
    n = np.arange(1, N_CYCLES + 1)
    slope = np.polyfit(np.log(n), np.log(rel), 1)[0]
    assert -0.65 < slope < -0.35, slope
    assert [int(h.fitted_bins) for h in history] == [M] * N_CYCLES


def test_model_predicts_like_the_bins(recording):
    _, phase, r, r_dot, xi, _ = recording
    online = online_for(recording)
    with pytest.raises(ValueError, match="cannot be fitted yet after 0 cycle"):
        online.model()
    for c in range(N_CYCLES):
        online.update(*cycle_samples(recording, c))
    model = online.model()
    assert isinstance(model, LocalConnectionModel) and model.batch_shape == ()
    assert model.dA_fit is not None  # tied; the direct estimate predicts
    assert online.model(tie=False).dA_fit is None
    pred = model.predict(phase, r, r_dot)
    rel = ((pred - xi).square().mean() / xi.var(dim=(-2, -3)).sum()).sqrt()
    assert float(rel) < 0.05
    # the tube the samples covered, per joint
    delta = r - online.gamma(phase)
    torch.testing.assert_close(torch.tensor(model.meta["tube_rms"], dtype=F64),
                               delta.square().mean((0, 1)).sqrt())


def test_from_model_takes_the_fit_settings():
    traj = simulate(NLinkSwimmer(3), circle_gait(), eta=0.025, n_cycles=6,
                    samples_per_cycle=SPC, seeds=np.arange(2))
    model = fit_pooled(traj, TubeRegression, n_bins=M, fourier_order=ORDER, window=WINDOW,
                       intercept_order=None).model_
    online = OnlineConnection.from_model(model)
    assert (online.n_bins, online.window, online.fourier_order) == (M, WINDOW, ORDER)
    torch.testing.assert_close(online.gamma_m, model.bins.gamma)
    with pytest.raises(ValueError, match="window"):
        OnlineConnection.from_model(dataclasses.replace(model, meta={}))
    assert OnlineConnection.from_model(dataclasses.replace(model, meta={}), window=2.0).window == 2


def test_bad_input_names_the_argument(recording):
    coeffs = recording[0]
    with pytest.raises(ValueError, match="forgetting"):
        online_for(recording, forgetting=1.5)
    online = online_for(recording)
    phase, r, r_dot, xi = cycle_samples(recording, 0)
    with pytest.raises(ValueError, match="forgetting"):
        online.update(phase, r, r_dot, xi, forgetting=0.0)
    with pytest.raises(ValueError, match="xi"):
        online.update(phase, r, r_dot, xi[..., :2])
    for weight in (0.0, -1.0, math.inf):
        with pytest.raises(ValueError, match="weight"):
            online.update(phase, r, r_dot, xi, weight=weight)
    batched = OnlineConnection(FourierSeries(coeffs.expand(3, -1, -1), 1), 1.0, n_bins=M,
                               fourier_order=ORDER)
    with pytest.raises(ValueError, match="phase of shape"):
        batched.update(phase, r, r_dot, xi)
    with pytest.raises(TypeError, match="gamma"):
        OnlineConnection(coeffs, 1.0)
    with pytest.raises(TypeError, match="LocalConnectionModel"):
        OnlineConnection.from_model(coeffs)
    assert online.cycles == 0 and not online.history  # nothing half-added


def test_docstring_example_runs():
    import doctest

    from torchconn.regression import online

    assert doctest.testmod(online).failed == 0
