"""The Trajectory container: validation, batch indexing, time slicing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchconn import NLinkSwimmer, Trajectory, simulate
from torchconn.physics.gaits import reference_gait
from torchconn.trajectory import pad_trials, span_groups


@pytest.fixture(scope="module")
def traj():
    return simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=4,
                    seeds=np.arange(6).reshape(2, 3))


def test_slice_time_cuts_every_array_consistently(traj):
    part = traj.slice_time(10, 74)
    assert part.batch_shape == traj.batch_shape and part.n_samples == 64
    assert torch.equal(part.t, traj.t[10:74])
    assert torch.equal(part.pose, traj.pose[..., 10:74, :])
    assert torch.equal(part.power, traj.power[..., 10:74])
    assert torch.equal(part.truth.phase, traj.truth.phase[..., 10:74])
    assert torch.equal(part.truth.xi, traj.truth.xi[..., 10:74, :])
    assert part.dt == pytest.approx(traj.dt, rel=1e-12)


def test_batch_indexing_keeps_time(traj):
    one = traj[1, 2]
    assert one.batch_shape == () and torch.equal(one.r, traj.r[1, 2])
    assert torch.equal(one.truth.delta, traj.truth.delta[1, 2])
    with pytest.raises(IndexError, match="batch dims"):
        traj[0, 0, 0]


def test_validation_names_the_field():
    t = torch.arange(10, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"pose must have shape \(10, 3\)"):
        Trajectory(t=t, pose=torch.zeros(9, 3), r=torch.zeros(10, 2))
    with pytest.raises(ValueError, match="uniformly sampled"):
        Trajectory(t=t ** 1.1, pose=torch.zeros(10, 3), r=torch.zeros(10, 2))
    with pytest.raises(ValueError, match="strictly increasing"):
        Trajectory(t=-t, pose=torch.zeros(10, 3), r=torch.zeros(10, 2))


def test_pad_trials_and_span_groups():
    a, b = torch.ones(3, 2), torch.full((5, 2), 2.0)
    x = pad_trials([a, b])
    assert x.shape == (2, 5, 2) and torch.isnan(x[0, 3:]).all() and torch.equal(x[1], b)
    assert pad_trials([a], 4).shape == (1, 4, 2)
    with pytest.raises(ValueError, match="shorter than the longest"):
        pad_trials([a, b], 4)
    with pytest.raises(ValueError, match="trial 1 has shape"):
        pad_trials([a, torch.ones(3, 3)])
    valid = torch.tensor([[0, 1, 1, 0], [1, 1, 1, 1], [0, 1, 1, 0], [0, 0, 0, 0]], dtype=bool)
    groups = {(a, b): rows.tolist() for rows, a, b in span_groups(valid)}
    assert groups == {(1, 3): [0, 2], (0, 4): [1, 3]}
