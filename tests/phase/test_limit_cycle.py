"""Limit-cycle fit: exactness, the matched filter's gain, offsets, phase rate, errors."""

from __future__ import annotations

import math

import pytest
import torch

from torchconn.phase.fourier import FourierSeries
from torchconn.phase.limit_cycle import LimitCycle, fit_limit_cycle, phase_rate
from torchconn.phase.smoothing import rts_smooth, smooth_trajectory
from torchconn.physics.gaits import reference_gait

from .common import swimmer_trials

DT = torch.float64
SPC = 60
STEP = 2 * math.pi / SPC
GRID = torch.linspace(0, 2 * math.pi, 401, dtype=DT)[:-1]


def _cycle(scale=1.0):
    """A 2-D gait with odd harmonics 1, 3, 5 (like the reference 3-link gait)."""
    c = torch.zeros(11, 2, dtype=DT)
    c[0] = torch.tensor([0.1, -0.2])
    c[1, 0], c[2, 1] = 1.0, 0.7
    c[5, 0], c[6, 1] = 0.1, 0.2
    c[9, 0], c[10, 1] = -0.03, 0.02
    return FourierSeries(scale * c, 1)


def _phases(trials, cycles, eta, gen):
    dW = torch.randn(trials, int(cycles * SPC), generator=gen, dtype=DT) * math.sqrt(STEP)
    return torch.cumsum(STEP + eta * dW, -1)


def _ou(shape, alpha, eta, gen):
    a = math.exp(-alpha * STEP)
    kicks = eta * math.sqrt((1 - a * a) / (2 * alpha)) * torch.randn(shape, generator=gen, dtype=DT)
    out, d = [], torch.zeros_like(kicks[..., 0, :])
    for k in range(shape[-2]):
        d = a * d + kicks[..., k, :]
        out.append(d)
    return torch.stack(out, -2)


def _err(series, truth):
    """RMS over phase of the difference of two cycles, per batch element."""
    return (series(GRID) - truth(GRID)).pow(2).sum(-1).mean(-1).sqrt()


def test_noise_free_cycle_is_exact():
    gamma = _cycle()
    phi = torch.arange(7 * SPC + 13, dtype=DT) * STEP * 1.01 + 0.4
    lc = fit_limit_cycle(phi, gamma(phi), gamma.derivative()(phi), order=5)
    assert isinstance(lc, LimitCycle)
    for s in (lc.gamma, lc.gamma0):
        assert torch.allclose(s.coeffs, gamma.coeffs, atol=1e-10)
    assert torch.allclose(lc.omega.coeffs, gamma.derivative().coeffs, atol=1e-10)
    assert torch.allclose(lc.gamma_dot_at(GRID), gamma.derivative()(GRID), atol=1e-10)
    assert lc.gamma_at(GRID).shape == (400, 2) and lc.gamma0_weight.shape == (5, 2)


def test_self_consistent_cycle_beats_direct_fit():
    # the matched filter's premise: r and r_dot observed with independent noise (the paper's
    # "separate noisy datasets"); the paper's phase and shape noise plus observation noise.
    # Measured over 16 trials: RMS error 0.0059 (gamma) vs 0.0075 (gamma0), better in 16/16.
    gen = torch.Generator().manual_seed(0)
    gamma = _cycle()
    phi = _phases(16, 30, 0.025, gen)
    r = (
        gamma(phi)
        + _ou(phi.shape + (2,), 0.5, 0.025, gen)
        + 0.05 * torch.randn(*phi.shape, 2, generator=gen, dtype=DT)
    )
    r_dot = gamma.derivative()(phi) + 0.1 * torch.randn(*phi.shape, 2, generator=gen, dtype=DT)
    lc = fit_limit_cycle(phi, r, r_dot, order=5)
    e, e0 = _err(lc.gamma, gamma), _err(lc.gamma0, gamma)
    assert (e < e0).float().mean() >= 0.75
    assert e.mean() < 0.9 * e0.mean()
    # integration divides harmonic k's velocity noise by k: high harmonics lean on omega
    w = lc.gamma0_weight.mean(0)  # (K, d)
    assert (w.diff(dim=0) < 0).all()


def test_with_smoothed_velocities_no_worse_than_direct_fit():
    # when r_dot is the smoother's derivative of the same noisy r, the two fits share their
    # errors and the combination gains nothing, but must not hurt either (measured ratio 1.00)
    gen = torch.Generator().manual_seed(1)
    gamma = _cycle()
    phi = _phases(8, 30, 0.025, gen)
    r = (
        gamma(phi)
        + _ou(phi.shape + (2,), 0.05, 0.025, gen)
        + 0.01 * torch.randn(*phi.shape, 2, generator=gen, dtype=DT)
    )
    rs, rds = rts_smooth(r, STEP)
    lc = fit_limit_cycle(phi, rs, rds, order=5)
    assert _err(lc.gamma, gamma).mean() < 1.1 * _err(lc.gamma0, gamma).mean()


def test_offsets_and_phase_rate():
    # a gait run at 2 cycles per 2π time units: with dt the fit finds the phase rate 2
    gen = torch.Generator().manual_seed(2)
    gamma = _cycle()
    t = torch.arange(10 * SPC, dtype=DT) * STEP / 2
    phi = 2 * t + 0.3
    delta = 0.05 * torch.randn(len(t), 2, generator=gen, dtype=DT)
    r = gamma(phi) + delta
    r_dot = 2 * gamma.derivative()(phi)
    lc = fit_limit_cycle(phi, r, r_dot, order=5, dt=STEP / 2)
    assert abs(lc.phase_rate.item() - 2.0) < 1e-10
    assert abs(phase_rate(phi, STEP / 2).item() - 2.0) < 1e-10
    assert torch.allclose(lc.omega.coeffs, gamma.derivative().coeffs, atol=1e-10)
    d, d_dot = lc.offsets(phi, r, r_dot)
    # the offsets are the noise, up to the cycle's own (small) estimation error
    assert (d - delta).abs().max() < 0.03 and d_dot.abs().max() < 0.03
    assert torch.allclose(d, r - lc.gamma_at(phi))


def test_batch_elements_get_their_own_cycle():
    small, big = _cycle(0.5), _cycle(2.0)
    phi = torch.arange(5 * SPC, dtype=DT) * STEP
    r = torch.stack([small(phi), big(phi)])
    r_dot = torch.stack([small.derivative()(phi), big.derivative()(phi)])
    lc = fit_limit_cycle(phi.expand(2, -1), r, r_dot)
    assert torch.allclose(lc.gamma.coeffs[0], small.coeffs, atol=1e-10)
    assert torch.allclose(lc.gamma.coeffs[1], big.coeffs, atol=1e-10)
    assert lc.gamma_at(GRID).shape == (2, 400, 2)
    d, d_dot = lc.offsets(phi.expand(2, -1), r, r_dot)
    assert d.abs().max() < 1e-10 and d_dot.abs().max() < 1e-10


def test_nan_samples_are_ignored():
    gamma = _cycle()
    phi = torch.arange(5 * SPC, dtype=DT) * STEP
    r, r_dot = gamma(phi), gamma.derivative()(phi)
    r[::7, 1] = float("nan")
    r_dot[3::11, 0] = float("nan")
    lc = fit_limit_cycle(phi, r, r_dot)
    assert torch.allclose(lc.gamma.coeffs, gamma.coeffs, atol=1e-10)


def test_errors_are_clear():
    phi = torch.arange(100, dtype=DT) * STEP
    r = torch.zeros(100, 2, dtype=DT)
    with pytest.raises(ValueError, match=r"r must have shape \(\.\.\., T=100, d\)"):
        fit_limit_cycle(phi, r[:90], r[:90])
    with pytest.raises(ValueError, match="r_dot must have the same shape as r"):
        fit_limit_cycle(phi, r, r[:, :1])
    with pytest.raises(ValueError, match="at least 21 samples"):
        fit_limit_cycle(phi[:15], r[:15], r[:15], order=10)


def _harmonic_error(series, ref_fn):
    """RMS distance to the reference gait over phase, constant offset removed: a trial's mean
    shape wanders with the slow OU offset δ, which no cycle fit can or should remove."""
    phi = torch.linspace(0, 2 * math.pi, 257, dtype=torch.float64)[:-1]
    e = series(phi) - ref_fn(phi)
    return (e - e.mean(-2, keepdim=True)).pow(2).mean((-1, -2)).sqrt()


@pytest.mark.parametrize("omega", [0.05, 0.1])
def test_self_consistent_cycle_beats_gamma0_with_an_independent_velocity_channel(omega):
    # the paper's claim holds when the velocity data carry their own noise (e.g. encoder
    # rates beside camera angles): the matched filter then averages two independent estimates
    traj = swimmer_trials("3link", 3, omega=omega, seed=11, n_cycles=30)
    gen = torch.Generator().manual_seed(5)
    v = traj.truth.r_dot + 3 * omega * torch.randn(traj.truth.r_dot.shape, generator=gen,
                                                   dtype=torch.float64)
    cycle = fit_limit_cycle(traj.truth.phase, traj.r, v, order=8, dt=traj.dt)
    ref = reference_gait("3link")
    err, err0 = _harmonic_error(cycle.gamma, ref), _harmonic_error(cycle.gamma0, ref)
    print(f"omega {omega}: gamma {err.mean():.5f} vs gamma0 {err0.mean():.5f}")
    assert err.mean() < 0.9 * err0.mean()
    assert (err < err0).float().mean() >= 2 / 3


def test_self_consistent_cycle_with_smoothed_velocities_is_no_worse_than_gamma0():
    # with r_dot from smoothing the same r the two estimates share their errors (and the
    # smoother damps high harmonics), so the filter cannot gain much: a measured finding
    traj = swimmer_trials("3link", 3, omega=0.05, seed=11, n_cycles=30)
    sm = smooth_trajectory(traj.pose, traj.r, traj.dt)
    cycle = fit_limit_cycle(traj.truth.phase, traj.r, sm.r_dot, order=8, dt=traj.dt)
    ref = reference_gait("3link")
    err, err0 = _harmonic_error(cycle.gamma, ref), _harmonic_error(cycle.gamma0, ref)
    print(f"smoothed velocities: gamma {err.mean():.5f} vs gamma0 {err0.mean():.5f}")
    assert err.mean() < 1.15 * err0.mean()
