"""Interval samples and their filters: mean velocities over an interval, the filters' noise
gains, the overlap inflation, the interval from a noise gain, and whole cycles of intervals."""

import math

import pytest
import torch

from torchconn.noise import (
    interval_noise_gains,
    interval_samples,
    overlap_inflation,
    velocity_interval_for,
)

F64 = torch.float64


def test_interval_samples_are_mean_velocities_over_the_interval():
    t = torch.arange(20, dtype=F64) * 0.1
    pose = torch.stack([0.3 * t, 0.0 * t, 0.2 * t], -1)  # constant twist-free? turning at 0.2
    r = torch.stack([torch.sin(t), t], -1)
    iv = interval_samples(pose, r, t, 0.1, 3)
    assert torch.allclose(iv.r_dot[:, 1], torch.ones(17, dtype=F64))
    assert torch.allclose(iv.phase, t[:-3] + 0.15)
    assert torch.allclose(iv.xi[:, 2], torch.full((17,), 0.2, dtype=F64))
    with pytest.raises(ValueError, match="velocity interval h"):
        interval_samples(pose, r, t, 0.1, 0)


def test_triangle_filter_noise_gains_and_exact_velocities():
    # white noise through the filter: variances σ² g_r and σ² g_ṙ, uncorrelated (Monte Carlo)
    g = torch.Generator().manual_seed(2)
    h, dt, sigma = 10, 0.05, 0.01
    noise = sigma * torch.randn(400, 60, 1, generator=g, dtype=F64)
    pose = torch.zeros(400, 60, 3, dtype=F64)
    iv = interval_samples(pose, noise, torch.zeros(400, 60, dtype=F64), dt, h)
    assert iv.kernel == "triangle"
    g_r, g_rate = interval_noise_gains(h, dt)
    r, rate = iv.r[:, 25, 0], iv.r_dot[:, 25, 0]
    assert abs(float(r.var()) / (sigma**2 * g_r) - 1) < 0.2
    assert abs(float(rate.var()) / (sigma**2 * g_rate) - 1) < 0.2
    assert abs(float((r * rate).mean())) < 0.15 * (sigma**2 * (g_r * g_rate) ** 0.5)
    # the box's closed form; the triangle's velocity gain is 16/(h+1)³ per Δt² for odd h
    # (h + 1 steps of 4/(h+1)²), below the box's 2/h² from h = 4 on, 0.28 times at h = 24
    assert interval_noise_gains(h, dt, "box") == (0.5, 2 / (h * dt) ** 2)
    for hh in (5, 11, 25):
        assert math.isclose(interval_noise_gains(hh, 1.0)[1], 16 / (hh + 1) ** 3)
    assert interval_noise_gains(24, 1.0)[1] < 0.3 * interval_noise_gains(24, 1.0, "box")[1]
    # a ramp and a constant twist come out exactly
    t = torch.arange(40, dtype=F64) * dt
    ramp = torch.stack([0.7 * t, -0.2 * t], -1)
    twist = torch.tensor([0.3, -0.1, 0.4], dtype=F64)
    from torchconn.physics import se2
    pose = se2.exp(twist * t[:, None])
    iv = interval_samples(pose, ramp, t, dt, h)
    assert torch.allclose(iv.r_dot, torch.tensor([0.7, -0.2], dtype=F64).expand(30, 2))
    assert torch.allclose(iv.r, ramp[:-h] + ramp[h] / 2)
    assert torch.allclose(iv.xi, twist.expand(30, 3))


def test_overlap_inflation_matches_the_variance_of_overlapping_rows():
    # Monte Carlo: y = a·v observed through white position noise, both filtered alike and
    # regressed on all overlapping rows; the slope's variance over repetitions is κ times the
    # one the rows-independent formula gives
    from torchconn.regression.binning import BinIndex

    g = torch.Generator().manual_seed(3)
    reps, T, h, dt = 600, 800, 12, 0.05
    v = torch.randn(reps, T, 1, generator=g, dtype=F64)  # process velocities (noise-free)
    x = torch.cumsum(v * dt, -2)
    pos = 0.5 * x + 0.05 * torch.randn(reps, T, 1, generator=g, dtype=F64)
    pose = torch.cat([pos, torch.zeros(reps, T, 2, dtype=F64)], -1)
    iv = interval_samples(pose, x, torch.zeros(reps, T, dtype=F64), dt, h)
    xs, ys = iv.r_dot[..., 0], iv.xi[..., 0]
    xs, ys = xs - xs.mean(-1, keepdim=True), ys - ys.mean(-1, keepdim=True)
    slope = (xs * ys).sum(-1) / xs.square().sum(-1)
    resid = ys - slope[:, None] * xs
    naive = resid.square().sum(-1) / (xs.shape[-1] - 2) / xs.square().sum(-1)
    n = xs.shape[-1]
    bins = BinIndex(index=torch.arange(n)[None], weight=torch.ones(1, n, dtype=F64),
                    count=torch.tensor([n]), n_bins=1, n_points=n, window=0.5, kernel="box")
    kappa = float(overlap_inflation(bins, h))
    assert kappa > 3  # the correction matters here
    assert abs(float(slope.var() / naive.mean()) / kappa - 1) < 0.2
    assert float(overlap_inflation(bins, h, "box")) == 1.0


def test_velocity_interval_from_the_filters_noise_gain():
    ratio = torch.tensor([0.0, 0.19, 1.1, 5.0, 50.0], dtype=F64)
    # the box: h = ⌈ratio / 0.05⌉ within [1, a quarter cycle]
    assert velocity_interval_for(ratio, 126, "box").tolist() == [1, 4, 22, 31, 31]
    h = velocity_interval_for(ratio, 126)
    assert h.tolist() == sorted(h.tolist()) and h[0] == 1 and h[-1] == 31
    for k in range(1, 4):  # the shortest whose noise part is at most 5 % of the process's
        _, g_rate = interval_noise_gains(int(h[k]), 1.0)
        _, g_short = interval_noise_gains(int(h[k]) - 1, 1.0)
        from torchconn.noise import interval_weights

        def frac(hh, gr, k=k):
            return float(ratio[k]) / 2 * gr / float(interval_weights(hh).square().sum())
        assert frac(int(h[k]), g_rate) <= 0.05 < frac(int(h[k]) - 1, g_short)


