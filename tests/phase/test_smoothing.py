"""Kalman/RTS smoothing: derivative accuracy, drop-outs, unwrapping, body velocity, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchconn.phase.smoothing import (
    body_velocity,
    noise_parameters,
    rts_smooth,
    smooth_trajectory,
    unwrap,
)
from torchconn.physics import se2
from torchconn.trajectory import SmoothedState

DT = torch.float64
SPC = 60  # samples per cycle
STEP = 2 * math.pi / SPC


def _signal(t):
    """Two channels with harmonics, and their exact time derivatives."""
    y = torch.stack(
        [torch.sin(t) + 0.3 * torch.cos(2 * t + 0.4), 0.8 * torch.cos(t) - 0.2 * torch.sin(3 * t)],
        -1,
    )
    dy = torch.stack(
        [torch.cos(t) - 0.6 * torch.sin(2 * t + 0.4), -0.8 * torch.sin(t) - 0.6 * torch.cos(3 * t)],
        -1,
    )
    return y, dy


def _noisy(trials=4, cycles=20, sd=0.05, seed=0):
    gen = torch.Generator().manual_seed(seed)
    t = torch.arange(cycles * SPC, dtype=DT) * STEP
    y, dy = _signal(t)
    return y + sd * torch.randn(trials, *y.shape, generator=gen, dtype=DT), y, dy


def _rms(a, b):
    return (a - b).pow(2).mean().sqrt().item()


@pytest.mark.parametrize("order, bound", [(2, 0.3), (3, 0.25)])
def test_derivative_beats_finite_differences(order, bound):
    # 5 % noise at 60 samples per cycle: central differences amplify it by ~1/(sqrt(2) dt);
    # measured ratios are 0.21 (order 2) and 0.15 (order 3) on 8 x 1200 samples.
    y, truth, dtruth = _noisy()
    val, der = rts_smooth(y, STEP, order=order)
    assert val.shape == der.shape == y.shape
    fd = torch.gradient(y, spacing=STEP, dim=-2)[0]
    ratio = _rms(der, dtruth) / _rms(fd, dtruth)
    assert ratio < bound
    assert _rms(val, truth) < 0.6 * 0.05  # values are denoised too


def test_survives_nan_dropouts():
    y, _, dtruth = _noisy(seed=1)
    gen = torch.Generator().manual_seed(2)
    holes = y.clone()
    holes[torch.rand(y.shape, generator=gen) < 0.1] = float("nan")
    _, der_full = rts_smooth(y, STEP)
    val, der = rts_smooth(holes, STEP)
    assert torch.isfinite(val).all() and torch.isfinite(der).all()
    # losing 10 % of the samples costs roughly sqrt(1/0.9) in noise; measured 1.15x
    assert _rms(der, dtruth) < 1.3 * _rms(der_full, dtruth)
    # gaps at the ends are extrapolated (finite, if not accurate far into the gap)
    holes[0, :5, 0] = float("nan")
    holes[1, -7:, 1] = float("nan")
    val, der = rts_smooth(holes, STEP)
    assert torch.isfinite(val).all() and torch.isfinite(der).all()


def test_constant_velocity_is_exact():
    t = torch.arange(200, dtype=DT) * 0.1
    y = torch.stack([1.0 + 2.0 * t, -0.5 * t], -1)
    val, der = rts_smooth(y, 0.1, process_noise=1e-3, measurement_noise=1e-4)
    # the model is exact for a line; what remains is the vague prior's pull (~1e-8)
    assert torch.allclose(val, y, atol=1e-6)
    assert torch.allclose(der, torch.tensor([2.0, -0.5], dtype=DT).expand_as(der), atol=1e-6)


def test_batch_and_channels_are_independent():
    y, _, _ = _noisy(trials=3, cycles=6)
    y = y.reshape(3, 1, *y.shape[-2:]).expand(3, 2, -1, -1).clone()
    y[:, 1] *= 2.0
    val, der = rts_smooth(y, STEP)
    v1, d1 = rts_smooth(y[2, 1, :, 1:], STEP)
    assert torch.allclose(val[2, 1, :, 1:], v1, atol=1e-10)
    assert torch.allclose(der[2, 1, :, 1:], d1, atol=1e-10)
    # the noise estimates are scale-equivariant: scaling a channel scales its output
    assert torch.allclose(der[:, 1], 2 * der[:, 0], atol=1e-8)


def test_explicit_noise_arguments_broadcast():
    y, _, dtruth = _noisy(trials=2, cycles=5)
    val, der = rts_smooth(
        y, STEP, process_noise=torch.tensor([0.1, 0.2], dtype=DT), measurement_noise=0.05**2
    )
    assert torch.isfinite(der).all() and _rms(der, dtruth) < 0.2


def test_unwrap_matches_numpy_and_skips_nans():
    gen = torch.Generator().manual_seed(3)
    true = torch.cumsum(0.8 * torch.randn(2, 300, generator=gen, dtype=DT), -1)
    wrapped = se2.wrap_angle(true)
    assert torch.allclose(unwrap(wrapped), torch.from_numpy(np.unwrap(wrapped.numpy())), atol=1e-12)
    holes = wrapped.clone()
    holes[:, 10:14] = float("nan")
    holes[0, 0] = float("nan")
    out = unwrap(holes)
    finite = torch.isfinite(holes)
    assert torch.equal(torch.isnan(out), ~finite)
    # unwrapping skips the gap: the result equals numpy's unwrap of the finite samples only
    for i in range(2):
        want = np.unwrap(holes[i][finite[i]].numpy())
        assert np.allclose(out[i][finite[i]].numpy(), want, atol=1e-12)
    assert torch.allclose(unwrap(wrapped.mT, dim=0), unwrap(wrapped).mT)


def test_body_velocity_is_g_inverse_g_dot():
    # a smooth pose path; compare xi with log(g_t^{-1} g_{t+h}) / h
    t = torch.linspace(0, 3, 301, dtype=DT)
    pose = torch.stack([torch.cos(t) + t, torch.sin(2 * t), 0.7 * t + 0.3 * torch.sin(t)], -1)
    pose_dot = torch.stack([1 - torch.sin(t), 2 * torch.cos(2 * t), 0.7 + 0.3 * torch.cos(t)], -1)
    xi = body_velocity(pose, pose_dot)
    h = 1e-6
    ahead = torch.stack(
        [torch.cos(t + h) + t + h, torch.sin(2 * (t + h)), 0.7 * (t + h) + 0.3 * torch.sin(t + h)],
        -1,
    )
    fd = se2.log(se2.relative(pose, ahead)) / h
    assert torch.allclose(xi, fd, atol=1e-5)
    # closed form: facing +y and moving along +x is moving to the body's right
    xi0 = body_velocity(
        torch.tensor([0, 0, math.pi / 2], dtype=DT), torch.tensor([1.0, 0, 0.2], dtype=DT)
    )
    assert torch.allclose(xi0, torch.tensor([0.0, -1.0, 0.2], dtype=DT), atol=1e-15)


def test_smooth_trajectory_unwraps_heading():
    gen = torch.Generator().manual_seed(4)
    T = 400
    t = torch.arange(T, dtype=DT) * STEP
    heading = 0.9 * t  # turns several times
    pose = torch.stack([torch.cos(t), 0.1 * t, se2.wrap_angle(heading)], -1)
    r = torch.stack([torch.sin(t), torch.cos(t)], -1)
    pose = pose + 0.01 * torch.randn(2, T, 3, generator=gen, dtype=DT)
    r = r + 0.01 * torch.randn(2, T, 2, generator=gen, dtype=DT)
    pose[0, 50, :] = float("nan")
    out = smooth_trajectory(pose, r, STEP)
    assert isinstance(out, SmoothedState)
    assert out.pose.shape == (2, T, 3) and out.r.shape == (2, T, 2) and out.xi.shape == (2, T, 3)
    assert (out.pose[..., 2] - heading).abs().max() < 0.05  # unwrapped, not jumping by 2π
    assert (out.pose_dot[..., 2] - 0.9).abs().mean() < 0.02
    assert torch.allclose(out.xi, body_velocity(out.pose, out.pose_dot))


def test_errors_are_clear():
    y = torch.randn(2, 50, 3, dtype=DT)
    bad = y.clone()
    bad[1, :, 2] = float("nan")
    with pytest.raises(
        ValueError, match=r"channel 2 of y \(batch index \(1,\)\) has no finite sample"
    ):
        rts_smooth(bad, 0.1)
    with pytest.raises(ValueError, match="order must be 2 or 3"):
        rts_smooth(y, 0.1, order=4)
    with pytest.raises(ValueError, match="dt must be a positive"):
        rts_smooth(y, 0.0)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., T, C\)"):
        rts_smooth(torch.randn(50, dtype=DT), 0.1)
    with pytest.raises(ValueError, match=r"no empty batch dimension, got \(0, 50, 3\)"):
        rts_smooth(torch.zeros(0, 50, 3, dtype=DT), 0.1)
    with pytest.raises(ValueError, match="measurement_noise must be a scalar or broadcast"):
        rts_smooth(y, 0.1, measurement_noise=torch.ones(4, dtype=DT))
    with pytest.raises(ValueError, match=r"pose must have shape \(\.\.\., T, 3\)"):
        smooth_trajectory(torch.zeros(50, 2, dtype=DT), torch.zeros(50, 2, dtype=DT), 0.1)


# ----------------------------------------------------------------- the parallel scan
def _model_inputs(y, order, dt):
    """The rows, model, noise and prior :func:`rts_smooth` hands to its time recursions."""
    from torchconn.phase import smoothing

    yb = y.movedim(-1, -2).reshape(-1, y.shape[-2])
    fb = torch.isfinite(yb)
    F, Q1 = smoothing._model(order, dt, yb.dtype, yb.device)
    q, R = smoothing._default_noise(yb, fb, F, Q1, dt, None, None)
    x0, P0 = smoothing._prior(yb, fb, order, dt)
    return yb, fb, F, Q1, q, R, x0, P0


def _extended_precision_rts(yb, fb, F, Q1, q, R, x0, P0):
    """An independent sequential Kalman filter + RTS smoother in NumPy ``longdouble``
    (64-bit mantissa on x86: ~2000x float64's precision): the reference both float64
    implementations are judged against. Returns the smoothed means ``(B, T, n)``."""
    L = np.longdouble
    F, Q1 = F.numpy().astype(L), Q1.numpy().astype(L)
    out = []
    for b in range(yb.shape[0]):
        Q, r = L(q[b].item()) * Q1, L(R[b].item())
        x, P = x0[b].numpy().astype(L), P0[b].numpy().astype(L)
        xf, Pf = [], []
        for t in range(yb.shape[1]):
            if t > 0:
                x, P = F @ x, F @ P @ F.T + Q
            if fb[b, t]:
                K = P[:, 0] / (P[0, 0] + r)
                x = x + K * (L(yb[b, t].item()) - x[0])
                P = P - np.outer(K, P[0])
                P = (P + P.T) / 2
            xf.append(x)
            Pf.append(P)
        xs = [xf[-1]]
        for t in range(len(xf) - 2, -1, -1):
            Pp = F @ Pf[t] @ F.T + Q
            G = np.linalg.solve(Pp.astype(np.float64), np.eye(len(x))).astype(L)
            G = G @ (2 * np.eye(len(x), dtype=L) - Pp @ G)  # one Newton step: longdouble inverse
            G = Pf[t] @ F.T @ G
            xs.append(xf[t] + G @ (xs[-1] - F @ xf[t]))
        out.append(np.stack(xs[::-1]).astype(np.float64))
    return torch.from_numpy(np.stack(out))


def _rel(a, b):
    """Largest difference relative to each row's and state's largest magnitude: ``(n,)``."""
    return ((a - b).abs().amax(1) / b.abs().amax(1)).amax(0)


def _drifting(seed):
    """3 trials x 2 channels x 601 samples (odd): noisy harmonics, a drift, 10 % drop-outs and
    a gap at the end; the first sample of every channel is recorded."""
    y, _, _ = _noisy(trials=3, cycles=10, seed=seed)
    y = torch.cat([y, y[:, -1:]], 1) + 0.4 * torch.arange(y.shape[1] + 1, dtype=DT)[:, None]
    gen = torch.Generator().manual_seed(seed + 1)
    y[:, 1:][torch.rand(y[:, 1:].shape, generator=gen) < 0.1] = float("nan")
    y[1, -6:, 1] = float("nan")
    return y


@pytest.mark.parametrize("order", [2, 3])
def test_scan_matches_the_loop(order):
    from torchconn.phase import smoothing

    y = _drifting(5)
    inputs = _model_inputs(y, order, STEP)
    loop = smoothing._rts_loop(*inputs)
    scan = smoothing._rts_scan(*inputs)
    assert _rel(scan, loop)[:2].max() < 1e-10, _rel(scan, loop)  # measured 5e-12 .. 4e-11
    # through the public function, and auto with few rows is the scan
    v_loop, d_loop = rts_smooth(y, STEP, order=order, algorithm="loop")
    v_scan, d_scan = rts_smooth(y, STEP, order=order, algorithm="scan")
    assert (v_scan - v_loop).abs().max() < 1e-10 * v_loop.abs().max()
    assert (d_scan - d_loop).abs().max() < 1e-10 * d_loop.abs().max()
    assert torch.equal(rts_smooth(y, STEP, order=order)[1], d_scan)


@pytest.mark.parametrize("order", [2, 3])
def test_scan_is_as_accurate_as_the_loop_after_a_leading_gap(order):
    # a channel whose first samples are missing starts from the vague prior propagated through
    # the gap: the first update cancels ~10 digits in both implementations (differently), so
    # they agree only to ~4e-9; judged against the exact recursion, the scan is as accurate
    from torchconn.phase import smoothing

    y = _drifting(5)
    y[0, :4, 0] = float("nan")
    inputs = _model_inputs(y, order, STEP)
    exact = _extended_precision_rts(*inputs)
    err_scan = _rel(smoothing._rts_scan(*inputs), exact)[:2].max()
    err_loop = _rel(smoothing._rts_loop(*inputs), exact)[:2].max()
    assert err_scan < 1e-7 and err_scan < 1.5 * err_loop, (err_scan, err_loop)


@pytest.mark.parametrize("order", [2, 3])
def test_scan_is_accurate_across_a_long_gap(order):
    # 300 missing samples in mid-record and at one end: the loop's covariance update
    # P - K P[0] cancels after the gap's growth (measured 3e-4 relative for order 3), while the
    # scan's information form stays within ~1e-6 of the extended-precision recursion
    y, _, _ = _noisy(trials=2, cycles=10, seed=7)
    y[:, 100:400] = float("nan")
    y[0, :150, 0] = float("nan")
    from torchconn.phase import smoothing

    inputs = _model_inputs(y, order, STEP)
    exact = _extended_precision_rts(*inputs)
    err_scan = _rel(smoothing._rts_scan(*inputs), exact)[:2].max()
    err_loop = _rel(smoothing._rts_loop(*inputs), exact)[:2].max()
    assert err_scan < 1e-5 and err_scan <= err_loop, (err_scan, err_loop)


@pytest.mark.parametrize("T", [2, 3, 4, 5, 8, 9, 17])
def test_scan_handles_every_length(T):
    y = torch.sin(torch.arange(T, dtype=DT))[None, :, None] + torch.tensor([0.0, 1.0], dtype=DT)
    kw = dict(process_noise=1.0, measurement_noise=0.01)
    for order in (2, 3):
        a = rts_smooth(y.mT, 0.1, order=order, algorithm="loop", **kw)
        b = rts_smooth(y.mT, 0.1, order=order, algorithm="scan", **kw)
        for u, v in zip(a, b, strict=True):
            assert torch.allclose(u, v, rtol=1e-10, atol=1e-10 * v.abs().max().item())


def test_algorithm_is_checked_and_reaches_the_smoother():
    from torchconn.phase.smoothing import RTSSmoother

    y = torch.randn(1, 50, 2, dtype=DT)
    with pytest.raises(ValueError, match="algorithm must be one of 'auto', 'scan', 'loop'"):
        rts_smooth(y, 0.1, algorithm="fft")
    with pytest.raises(ValueError, match="RTSSmoother.algorithm"):
        RTSSmoother(algorithm="fft")
    assert RTSSmoother(algorithm="loop").get_params()["algorithm"] == "loop"


def test_auto_picks_the_faster_algorithm_on_the_cpu():
    from torchconn.phase.smoothing import _SCAN_MAX_ROWS_CPU

    kw = dict(process_noise=1.0, measurement_noise=0.01)
    for order, rows in _SCAN_MAX_ROWS_CPU.items():
        for n, want, gap in ((rows, "scan", True), (rows + 1, "loop", True),
                             (rows + 1, "scan", False)):
            y = torch.randn(n, 12, 1, dtype=DT, generator=torch.Generator().manual_seed(n))
            if gap:  # with drop-outs the scan is faster only for few rows ...
                y[0, 5] = float("nan")
            # ... without, it shares the covariance steps of all samples and is faster for any
            auto = rts_smooth(y, 0.1, order=order, **kw)[1]
            assert torch.equal(auto, rts_smooth(y, 0.1, order=order, algorithm=want, **kw)[1])


@pytest.mark.parametrize("algorithm", ["loop", "scan"])
@pytest.mark.parametrize("order", [2, 3])
def test_float32_is_finite_and_the_float64_result_rounded(algorithm, order):
    # float32 once gave NaN on a constant channel, a singular solve on a noise-free line and
    # derivatives 5-60 % off on simulated recordings (the covariance updates cancel digits);
    # float32 input now runs the recursions in float64 and comes back in float32
    t = torch.arange(10 * SPC, dtype=DT) * STEP
    noisy, _, _ = _noisy(trials=1, cycles=10, sd=0.01, seed=3)
    y = torch.cat([noisy[0], (3 + 0.5 * t)[:, None], torch.full_like(t, 2.0)[:, None],
                   (10 + torch.sin(t))[:, None]], -1)
    y[100:105, 0] = float("nan")
    y32 = y.float()
    v32, d32 = rts_smooth(y32, STEP, order=order, algorithm=algorithm)
    v64, d64 = rts_smooth(y32.double(), STEP, order=order, algorithm=algorithm)
    assert v32.dtype == d32.dtype == torch.float32
    assert bool(torch.isfinite(v32).all()) and bool(torch.isfinite(d32).all())
    eps = torch.finfo(torch.float32).eps
    assert ((v32.double() - v64).abs() <= eps * v64.abs()).all()
    assert ((d32.double() - d64).abs() <= eps * d64.abs()).all()
    # and the float64 result is right: the line's slope, the constant's zero rate
    assert (d64[:, 2] - 0.5).abs().max() < 1e-4 and d64[:, 3].abs().max() < 1e-12


@pytest.mark.parametrize("algorithm", ["loop", "scan"])
@pytest.mark.parametrize("order", [2, 3])
def test_constant_channel_is_smoothed_to_itself(algorithm, order):
    # a locked joint: zero spread used to underflow the prior and the noise floor to NaN
    y = torch.tensor([0.0, 2.0, -1e-30], dtype=DT).expand(200, 3).clone()
    v, d = rts_smooth(y, STEP, order=order, algorithm=algorithm)
    assert (v - y).abs().max() < 1e-13 and d.abs().max() < 1e-13


@pytest.mark.parametrize("order", [2, 3])
def test_scan_without_dropouts_shares_the_covariance_steps_exactly(order):
    # rows measured at every sample compose their (identical) covariance steps once per scan
    # round; that must be the same arithmetic as composing them pair by pair, which the scan
    # does as soon as one row of the batch has a drop-out -- so a row's result does not depend
    # on its batch -- and it must agree with the loop
    y, _, _ = _noisy(trials=3, cycles=10, seed=11)
    y = y + 0.3 * torch.arange(y.shape[1], dtype=DT)[:, None]
    with_gap = y.clone()
    with_gap[2, 50:53, 1] = float("nan")
    alone = rts_smooth(y[:2], STEP, order=order, algorithm="scan")
    beside = rts_smooth(with_gap, STEP, order=order, algorithm="scan")
    loop = rts_smooth(y[:2], STEP, order=order, algorithm="loop")
    for a, b, c in zip(alone, beside, loop, strict=True):
        assert torch.equal(a, b[:2])
        assert (a - c).abs().max() < 1e-10 * c.abs().max()


def test_a_rows_noise_ratio_does_not_depend_on_its_batch():
    # the sweep's results must not depend on how many trials share a cell: torch's scalar-base
    # power (10 ** x) rounded a short tensor's tail elements differently with its length
    gen = torch.Generator().manual_seed(4)
    t = torch.arange(5 * SPC, dtype=DT) * STEP
    amp = 0.5 + torch.rand(23, 1, generator=gen, dtype=DT)
    y = (amp * torch.sin(t + amp) + 0.02 * torch.randn(23, t.numel(), generator=gen,
                                                       dtype=DT)).T[None]  # (1, T, 23)
    q, R = noise_parameters(y, STEP)
    for n in (1, 3, 5, 13, 17, 20):
        q_n, R_n = noise_parameters(y[..., :n], STEP)
        assert torch.equal(q_n, q[..., :n]) and torch.equal(R_n, R[..., :n]), n
