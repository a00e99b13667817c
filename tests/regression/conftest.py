"""Recordings shared by the regression tests."""

import pytest

from torchconn import ConnectionEstimator, SelfConsistentCycle

from .common import WAVE_SPC, wave_recording


@pytest.fixture(scope="module")
def eight():
    """Two trials of the 5-link, 8 cycles each, ω = 0.005, prepared (smoothed and phased)."""
    traj = ConnectionEstimator().prepare(wave_recording(8, n_trials=2))
    return traj, SelfConsistentCycle().fit(traj), SelfConsistentCycle().fit(traj, pool=True)


@pytest.fixture(scope="module")
def short():
    """One trial of the 5-link, 4 cycles, ω = 0.005: the default complexity overfits it."""
    return wave_recording(4, seed=3)


@pytest.fixture(scope="module")
def short_and_later():
    """One trial of the 5-link, ω = 0.005: 4 cycles to fit and the next 4 to score."""
    traj = wave_recording(8, seed=SHORT_SEED).with_fields(power=None)
    cut = 4 * WAVE_SPC + 1
    return traj.slice_time(0, cut), traj.slice_time(cut, traj.n_samples)


SHORT_SEED = 7  # v_y falls back to the phase average, v_x and ω keep the connection alone
