"""The motion-capture observation model: noise level, drop-outs, seeding."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from torchconn import AffineConnectionSystem, Trajectory
from torchconn.physics.gaits import FourierGait
from torchconn.simulation.observe import observe
from torchconn.simulation.rollout import cell_generators, simulate

P_FAIL = 1e-4


@pytest.fixture(scope="module")
def traj() -> Trajectory:
    gait = FourierGait(torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64))
    return simulate(AffineConnectionSystem.random(d=2, seed=3), gait, eta=0.05, n_cycles=2,
                    samples_per_cycle=50, substeps=2, seeds=np.arange(8).reshape(2, 4))


def test_noise_has_the_requested_std(traj):
    omega = torch.tensor([[0.01], [0.2]], dtype=torch.float64)  # one level per batch row
    obs = observe(traj, omega, seeds=np.arange(100, 108).reshape(2, 4))
    noise = torch.cat([obs.pose - traj.pose, obs.r - traj.r], -1)  # (2, 4, T, 5)
    n = noise[0].numel()
    lo = stats.chi2.ppf(P_FAIL / 2, n) / n
    hi = stats.chi2.ppf(1 - P_FAIL / 2, n) / n
    z = stats.norm.ppf(1 - P_FAIL / 2)
    for level in range(2):
        w = float(omega[level, 0])
        ratio = float((noise[level] ** 2).mean()) / w**2
        print(f"omega {w}: variance ratio {ratio:.4f} (band {lo:.4f}..{hi:.4f})")
        assert lo < ratio < hi
        assert abs(float(noise[level].mean())) < z * w / math.sqrt(n)
        # every channel (x, y, θ, r1, r2) gets the same std
        per_channel = noise[level].reshape(-1, 5).pow(2).mean(0) / w**2
        m = noise[level].reshape(-1, 5).shape[0]
        assert ((per_channel > stats.chi2.ppf(P_FAIL / 2, m) / m)
                & (per_channel < stats.chi2.ppf(1 - P_FAIL / 2, m) / m)).all()
    # power is a separate channel and is not perturbed; the truth is kept as it was
    torch.testing.assert_close(obs.power, traj.power, rtol=0, atol=0, equal_nan=True)
    assert obs.truth is traj.truth
    assert obs.meta["omega"] == [[0.01], [0.2]] and obs.meta["dropout"] == 0.0
    assert obs.meta["observe_seeds"] == np.arange(100, 108).reshape(2, 4).tolist()


def test_dropout_blanks_whole_rows_at_the_requested_rate(traj):
    rate = 0.2
    obs = observe(traj, 0.01, dropout=rate, seeds=np.arange(8).reshape(2, 4))
    lost = torch.isnan(obs.r[..., 0])
    # whole rows: pose, r and power are lost together, and only there
    assert torch.equal(torch.isnan(obs.pose).any(-1), lost)
    assert torch.equal(torch.isnan(obs.pose).all(-1), lost)
    assert torch.equal(torch.isnan(obs.r).all(-1), lost)
    # (the last row's power is empty anyway: its interval ends after the recording)
    assert torch.equal(torch.isnan(obs.power[..., :-1]), lost[..., :-1])
    assert torch.isnan(obs.power[..., -1]).all()
    n = lost.numel()
    lo, hi = stats.binom.ppf([P_FAIL / 2, 1 - P_FAIL / 2], n, rate) / n
    frac = float(lost.double().mean())
    print(f"drop-out fraction {frac:.4f} for rate {rate} (band {lo:.4f}..{hi:.4f})")
    assert lo <= frac <= hi
    # the noise on kept samples is the same as without drop-outs (normals are drawn first)
    plain = observe(traj, 0.01, seeds=np.arange(8).reshape(2, 4))
    torch.testing.assert_close(obs.r[~lost], plain.r[~lost], rtol=0, atol=0)


def test_cells_independent_of_batch_and_of_rollout_noise(traj):
    whole = observe(traj, 0.1, seeds=np.arange(50, 58).reshape(2, 4))
    alone = observe(traj[1, 2], 0.1, seeds=56)
    torch.testing.assert_close(whole.pose[1, 2], alone.pose, rtol=0, atol=1e-15)
    torch.testing.assert_close(whole.r[1, 2], alone.r, rtol=0, atol=1e-15)
    # the same seeds as the rollout draw from another stream, not the SDE's normals again
    obs_gens, _ = cell_generators([3], "observe")
    sim_gens, _ = cell_generators([3], "rollout")
    a = torch.randn(20, generator=obs_gens[0], dtype=torch.float64)
    b = torch.randn(20, generator=sim_gens[0], dtype=torch.float64)
    assert not torch.allclose(a, b)


def test_zero_noise_is_identity(traj):
    obs = observe(traj, 0.0, seeds=np.zeros((2, 4), dtype=np.int64))
    torch.testing.assert_close(obs.pose, traj.pose, rtol=0, atol=0)
    torch.testing.assert_close(obs.r, traj.r, rtol=0, atol=0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(omega=0.1, seeds=[0, 1]), "seeds must have the trajectory's batch shape"),
        (dict(omega=-0.1, seeds=np.zeros((2, 4), dtype=int)), "omega must be finite and >= 0"),
        (dict(omega=torch.ones(3), seeds=np.zeros((2, 4), dtype=int)), "broadcastable"),
        (dict(omega=0.1, dropout=1.0, seeds=np.zeros((2, 4), dtype=int)), "dropout must be"),
    ],
)
def test_bad_arguments(traj, kwargs, match):
    with pytest.raises(ValueError, match=match):
        observe(traj, **kwargs)
