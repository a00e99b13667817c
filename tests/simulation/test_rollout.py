"""Stochastic rollouts: the noise-free limit, SDE statistics, strong convergence, batching."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from torchconn import AffineConnectionSystem, NLinkSwimmer
from torchconn.physics import se2
from torchconn.physics.gaits import FourierGait, displacement, three_link_gait
from torchconn.simulation.rollout import _heun_offsets, _integrate, cell_generators, simulate

# Two-sided acceptance probability of each statistical check; with fixed seeds the tests are
# deterministic, this only sets how wide the sampling-distribution bands are.
P_FAIL = 1e-4


def circle_gait(radius: float = 1.0) -> FourierGait:
    """``r = radius (cos φ, sin φ)``."""
    return FourierGait(torch.tensor([[0.0, 0.0], [radius, 0.0], [0.0, radius]],
                                    dtype=torch.float64))


def chi2_band(n: int) -> tuple[float, float]:
    """Band for ``Σ z² / n`` of ``n`` i.i.d. standard normals (known zero mean)."""
    return (stats.chi2.ppf(P_FAIL / 2, n) / n, stats.chi2.ppf(1 - P_FAIL / 2, n) / n)


# ---------------------------------------------------------------------------- noise-free limit
def test_noise_free_cycle_matches_gait_displacement():
    system, gait = NLinkSwimmer(3), three_link_gait("extremal")
    ref = displacement(system, gait)
    traj = simulate(system, gait, eta=0.0, n_cycles=3, seeds=[7])
    P = traj.meta["samples_per_cycle"]
    for c in range(2):
        per_cycle = se2.relative(traj.pose[0, c * P], traj.pose[0, (c + 1) * P])
        rel = float(torch.linalg.vector_norm(per_cycle - ref) / torch.linalg.vector_norm(ref))
        assert rel < 1e-4, rel
    # the shape sits on the gait, the phase runs at unit speed, δ stays zero
    torch.testing.assert_close(traj.truth.phase[0], traj.t, rtol=0, atol=1e-12)
    torch.testing.assert_close(traj.r[0], gait(traj.t), rtol=0, atol=1e-12)
    assert traj.truth.delta.abs().max() == 0


def test_noise_free_truth_is_the_interval_mean():
    """xi and r_dot are the means over the centred recording interval; power belongs to the
    sample interval [t_k, t_k+1) (docs/conventions.md), with the metric at the interval's mid-shape.

    xi is compared with Gauss–Legendre quadrature of the smooth integrand; the trapezoid on the
    fine grid is second order, so halving h must quarter the error.
    """
    system, gait = NLinkSwimmer(3), three_link_gait("extremal")
    errors = []
    for substeps in (16, 32):
        traj = simulate(system, gait, eta=0.0, n_cycles=1, samples_per_cycle=16,
                        substeps=substeps, seeds=0, phase0=0.3)
        assert traj.batch_shape == ()
        dt = traj.dt
        nodes, weights = np.polynomial.legendre.leggauss(24)
        nodes = torch.as_tensor(nodes) * dt / 2
        weights = torch.as_tensor(weights) / 2
        phi = 0.3 + traj.t[:, None] + nodes  # (T, q)
        r, v = gait(phi), gait.velocity(phi)
        a, m = system.connection_and_metric(r)
        xi = ((a @ v[..., None])[..., 0] * weights[:, None]).sum(1)
        errors.append(float((traj.truth.xi - xi).abs().max() / xi.abs().max()))
        r_dot = (gait(0.3 + traj.t + dt / 2) - gait(0.3 + traj.t - dt / 2)) / dt
        torch.testing.assert_close(traj.truth.r_dot, r_dot, rtol=0, atol=1e-12)
        # independent of the recording: the gait itself at the sample times
        r_k = gait(0.3 + traj.t)
        v = (r_k[1:] - r_k[:-1]) / dt
        m_k = system.metric((r_k[1:] + r_k[:-1]) / 2)
        power = torch.einsum("ti,tij,tj->t", v, m_k, v)
        torch.testing.assert_close(traj.power[:-1], power, rtol=1e-12, atol=0)
        assert torch.isnan(traj.power[-1])
    xi16, xi32 = errors
    print(f"interval-mean errors: xi {xi16:.2e} -> {xi32:.2e}")
    assert xi32 < 1e-4
    assert 3 < xi16 / xi32 < 5


def test_power_on_sample_interval_constant_metric():
    """The affine toy has a constant M, so on the rough SDE path the recorded power is exactly
    ``v_kᵀ M v_k`` with ``v_k`` the difference of the recorded true shapes; the last row is empty."""
    system = AffineConnectionSystem.random(d=3, seed=4)
    gait = FourierGait(torch.tensor([[0.1, 0.0, -0.2], [1.0, 0.3, 0.0], [0.0, 0.5, 0.8]],
                                    dtype=torch.float64))
    traj = simulate(system, gait, eta=0.3, n_cycles=2, samples_per_cycle=16, seeds=[[3, 4]])
    r = traj.truth.r.numpy()
    v = np.diff(r, axis=-2) / traj.dt
    expected = np.einsum("...i,ij,...j->...", v, system.m.numpy(), v)
    np.testing.assert_allclose(traj.power[..., :-1].numpy(), expected, rtol=1e-13, atol=0)
    assert torch.isnan(traj.power[..., -1]).all() and torch.isfinite(traj.power[..., :-1]).all()
    torch.testing.assert_close(traj.truth.power, traj.power, rtol=0, atol=0, equal_nan=True)


def test_a_rollout_without_power_is_the_same_trajectory():
    system, gait = NLinkSwimmer(3), three_link_gait("extremal")
    full = simulate(system, gait, eta=0.05, n_cycles=2, samples_per_cycle=16, seeds=[[5, 6]])
    bare = simulate(system, gait, eta=0.05, n_cycles=2, samples_per_cycle=16, seeds=[[5, 6]],
                    power=False)
    assert bare.power is None and bare.truth.power is None and bare.meta["power"] is None
    assert full.meta["power"] is not None and torch.isfinite(full.power[..., :-1]).all()
    for name in ("phase", "pose", "r", "xi", "r_dot", "delta"):
        assert torch.equal(getattr(bare.truth, name), getattr(full.truth, name)), name
    assert torch.equal(bare.pose, full.pose) and torch.equal(bare.r, full.r)


# ---------------------------------------------------------------------------- SDE statistics
@pytest.fixture(scope="module")
def ou_run():
    """Many cells of a cheap toy system; fast attraction so the run covers several 1/α."""
    system = AffineConnectionSystem.random(d=2, seed=1)
    eta, alpha = 0.5, 1.0
    seeds = np.random.SeedSequence(2024).generate_state(1000)
    traj = simulate(system, circle_gait(), eta=eta, alpha=alpha, n_cycles=1,
                    samples_per_cycle=32, substeps=4, seeds=seeds, stationary_start=False)
    return traj, eta, alpha


def test_delta_variance_follows_the_ou_law(ou_run):
    traj, eta, alpha = ou_run
    delta = traj.truth.delta  # (N, T, 2)
    n = delta.shape[0] * delta.shape[-1]
    lo, hi = chi2_band(n)
    for k in (3, 10, traj.n_samples - 1):
        s = traj.t[k].item() + traj.dt / 2  # time since the start of the path
        var = eta**2 / (2 * alpha) * (1 - math.exp(-2 * alpha * s))
        ratio = float((delta[:, k] ** 2).mean() / var)
        assert lo < ratio < hi, (k, ratio, lo, hi)


def test_stationary_start_variance():
    eta, alpha = 0.025, 0.05  # the paper's values
    seeds = np.random.SeedSequence(11).generate_state(600)
    traj = simulate(AffineConnectionSystem.random(d=2, seed=1), circle_gait(), eta=eta,
                    alpha=alpha, n_cycles=1, samples_per_cycle=8, substeps=2, seeds=seeds)
    var = eta**2 / (2 * alpha)
    lo, hi = chi2_band(2 * len(seeds))
    for k in (0, traj.n_samples - 1):
        ratio = float((traj.truth.delta[:, k] ** 2).mean() / var)
        assert lo < ratio < hi, (k, ratio)


def test_phase_diffusion(ou_run):
    traj, eta, _ = ou_run
    dev = traj.truth.phase - traj.t  # φ(t) − t, with φ(−Δt/2) = −Δt/2
    n = dev.shape[0]
    lo, hi = chi2_band(n)
    z = stats.norm.ppf(1 - P_FAIL / 2)
    for k in (0, 10, traj.n_samples - 1):
        var = eta**2 * (traj.t[k].item() + traj.dt / 2)
        ratio = float((dev[:, k] ** 2).mean() / var)
        assert lo < ratio < hi, (k, ratio)
        assert abs(float(dev[:, k].mean())) < z * math.sqrt(var / n)


# ---------------------------------------------------------------------------- convergence
def test_strong_convergence_same_brownian_path():
    """Refine the fine step along one Brownian path; fit the slope of log error vs log h."""
    system, gait = NLinkSwimmer(3), three_link_gait("extremal")
    B, d, P, fine = 24, 2, 16, 256
    dt = 2 * math.pi / P
    gen = torch.Generator().manual_seed(5)
    z_fine = torch.randn(B, P * fine, d + 1, generator=gen, dtype=torch.float64)
    kw = dict(eta=torch.full((B,), 0.2, dtype=torch.float64),
              alpha=torch.full((B,), 0.05, dtype=torch.float64),
              phase0=torch.zeros(B, dtype=torch.float64),
              delta0=torch.zeros(B, d, dtype=torch.float64), n_samples=P, dt=dt)

    def run(substeps: int) -> dict:
        m = fine // substeps
        z = z_fine.reshape(B, -1, m, d + 1).sum(2) / math.sqrt(m)  # same path, coarser grid
        pos = [0]

        def noise(n: int) -> torch.Tensor:
            out = z[:, pos[0]:pos[0] + n]
            pos[0] += n
            return out

        return _integrate(system, gait, noise=noise, substeps=substeps, **kw)

    ref = run(fine)
    levels = [2, 4, 8, 16, 32]
    err_pose, err_r = [], []
    for s in levels:
        out = run(s)
        err_pose.append(float((out["pose"] - ref["pose"]).norm(dim=-1).max(-1).values
                              .pow(2).mean().sqrt()))
        err_r.append(float((out["r"] - ref["r"]).abs().max()))
    h = np.array([dt / s for s in levels])
    slope = np.polyfit(np.log(h), np.log(err_pose), 1)[0]
    slope_r = np.polyfit(np.log(h), np.log(err_r), 1)[0]
    print(f"strong errors: pose {np.array(err_pose)}, slope {slope:.2f}; "
          f"shape {np.array(err_r)}, slope {slope_r:.2f}")
    # the pose: order ½ without a Lévy-area term, up to 1 while the drift part dominates
    assert slope > 0.4, (slope, err_pose)
    assert np.all(np.diff(err_pose) < 0)
    # the shape: φ is exact, δ has additive noise, so Heun is strongly first order
    assert slope_r > 0.8, (slope_r, err_r)


def test_block_heun_offsets_are_the_step_by_step_predictor_corrector():
    """The shape offsets of a block, by scan, equal Heun's steps taken one at a time, for
    cells with no, the paper's and a strong attraction (odd block length included)."""
    gen = torch.Generator().manual_seed(2)
    B, K, d, h = 3, 37, 4, 2 * math.pi / 64 / 8
    alpha = torch.tensor([[0.0], [0.05], [40.0]], dtype=torch.float64)
    delta0 = torch.randn(B, d, generator=gen, dtype=torch.float64)
    dw = 0.3 * math.sqrt(h) * torch.randn(B, K, d, generator=gen, dtype=torch.float64)
    ah = alpha * h
    fast = _heun_offsets(delta0, dw, 1 - ah + 0.5 * ah * ah, 1 - 0.5 * ah)
    delta, slow = delta0, []
    for n in range(K):
        pred = delta - alpha * delta * h + dw[:, n]
        delta = delta + 0.5 * (-alpha * delta - alpha * pred) * h + dw[:, n]
        slow.append(delta)
    torch.testing.assert_close(fast, torch.stack(slow, 1), rtol=0, atol=1e-14)


# ---------------------------------------------------------------------------- batching, seeds
def test_cell_result_independent_of_batch():
    system, gait = NLinkSwimmer(3), three_link_gait()
    seeds = np.array([[11, 12, 13], [21, 22, 23]])
    eta = torch.tensor([[0.025], [0.05]], dtype=torch.float64)
    big = simulate(system, gait, eta=eta, n_cycles=2, seeds=seeds)
    assert big.batch_shape == (2, 3)
    alone = simulate(system, gait, eta=0.05, n_cycles=2, seeds=22)
    for name in ("pose", "r", "power"):
        torch.testing.assert_close(getattr(big, name)[1, 1], getattr(alone, name),
                                   rtol=0, atol=1e-12, equal_nan=True)
    for name in ("phase", "xi", "r_dot", "delta"):
        torch.testing.assert_close(getattr(big.truth, name)[1, 1], getattr(alone.truth, name),
                                   rtol=0, atol=1e-12)
    # same seed, other noise level: the same standard normals (common random numbers)
    other = simulate(system, gait, eta=0.025, n_cycles=2, seeds=[12])
    torch.testing.assert_close(big.truth.phase[0, 1], other.truth.phase[0], rtol=0, atol=1e-12)


def test_seed_sequences_and_reproducibility():
    system = AffineConnectionSystem.random(d=2, seed=0)
    spawned = np.random.SeedSequence(3).spawn(2)
    a = simulate(system, circle_gait(), eta=0.1, n_cycles=1, samples_per_cycle=8, seeds=spawned)
    b = simulate(system, circle_gait(), eta=0.1, n_cycles=1, samples_per_cycle=8,
                 seeds=np.random.SeedSequence(3).spawn(2))
    torch.testing.assert_close(a.pose, b.pose, rtol=0, atol=0)
    assert not torch.allclose(a.pose[0], a.pose[1])
    gens, shape = cell_generators([[1, 2]])
    assert shape == (1, 2) and len(gens) == 2
    assert a.meta["eta"] == 0.1 and a.meta["batch_shape"] == [2]


def test_drift_hook_world_frame_flow():
    """A uniform world-frame flow u, passed as body velocity Ad_{g⁻¹} u, carries the body along."""
    system = AffineConnectionSystem(torch.zeros(3, 2), torch.zeros(3, 2, 2))  # A ≡ 0
    u = torch.tensor([0.3, -0.1], dtype=torch.float64)
    spin = 0.2

    def flow(pose, t):
        c, s = torch.cos(pose[..., 2]), torch.sin(pose[..., 2])
        vx, vy = c * u[0] + s * u[1], -s * u[0] + c * u[1]
        return torch.stack([vx, vy, torch.full_like(vx, spin)], -1)

    errors = []
    for substeps in (8, 16):
        traj = simulate(system, circle_gait(), eta=0.0, n_cycles=1, samples_per_cycle=16,
                        substeps=substeps, seeds=[[1, 2]], drift=flow)
        assert traj.batch_shape == (1, 2)
        s = traj.t + traj.dt / 2
        expected = torch.stack([u[0] * s, u[1] * s, spin * s], -1)
        errors.append(float((traj.pose[0, 1] - expected).abs().max()))
        torch.testing.assert_close(traj.truth.xi[..., 2],
                                   torch.full_like(traj.truth.xi[..., 2], spin))
    print(f"drift errors {errors}")
    assert errors[1] < 1e-4
    assert 3 < errors[0] / errors[1] < 5  # Heun is second order for a smooth drift


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(substeps=3), "substeps must be even"),
        (dict(eta=torch.zeros(3)), "eta must be a float or a tensor broadcastable"),
        (dict(eta=-0.1), "eta must be >= 0"),
        (dict(seeds=[0.5, 1.5]), "seeds must be an integer array"),
        (dict(seeds=[-1]), "non-negative"),
        (dict(alpha=0.0), "stationary_start needs alpha > 0"),
        (dict(n_cycles=0), "n_cycles must be an integer >= 1"),
    ],
)
def test_bad_arguments(kwargs, match):
    args = dict(eta=0.01, n_cycles=1, samples_per_cycle=8, seeds=[0, 1])
    args.update(kwargs)
    with pytest.raises((ValueError, TypeError), match=match):
        simulate(AffineConnectionSystem.random(d=2), circle_gait(), **args)


def test_gait_dimension_mismatch():
    with pytest.raises(ValueError, match="gait has 2 joints but the system has 8"):
        simulate(NLinkSwimmer(9), circle_gait(), eta=0.0, seeds=[0])
