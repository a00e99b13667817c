"""Noise estimation from the spectrum of a recording's shape increments (``estimate_noise``):
white noise told from a random walk, calibrated standard errors, the phase-noise floor and the
normal projection on curved cycles."""

import math

import numpy as np
import pytest
import torch

from torchconn import NLinkSwimmer, observe, simulate
from torchconn.noise import estimate_noise
from torchconn.physics.gaits import FourierGait

from ..recordings import gait_noise
from ..regression.common import noisy_circle_trials, unpooled_trials

F64 = torch.float64


def test_noise_estimate_separates_white_noise_from_a_random_walk():
    # closed form: increments of a random walk (std q) observed with white noise (std s)
    g = torch.Generator().manual_seed(0)
    q = torch.tensor([0.01, 0.01, 0.003], dtype=F64)
    s = torch.tensor([0.0, 0.004, 0.004], dtype=F64)
    walk = torch.cumsum(q * torch.randn(4, 20000, 3, generator=g, dtype=F64), -2)
    x = walk + s * torch.randn(4, 20000, 3, generator=g, dtype=F64)
    est = estimate_noise(x)
    # one record's estimate scatters by ~15 % here (the process noise is 2.5x larger); the
    # four records pooled are within 10 %
    pooled = est.measurement.square().mean(0).sqrt()
    assert torch.allclose(pooled[1:], s[1:], rtol=0.1)
    assert torch.allclose(est.measurement[:, 1:], s[1:].expand(4, 2), rtol=0.3)
    assert float(pooled[0]) < 0.25 * float(s[1])
    # the process floor, where it dominates the increments
    assert torch.allclose(est.process[:, :2], q[:2].expand(4, 2), rtol=0.05)


@pytest.mark.parametrize("omega", [0.0, 0.002, 0.005, 0.01])
def test_noise_estimate_on_swimmer_recordings(omega, clean30):
    traj = noisy_circle_trials(omega, clean=clean30)
    for x in (traj.r, traj.pose):
        est = estimate_noise(x)
        sigma = est.measurement.square().mean(0).sqrt()  # pooled over trials
        if omega == 0:
            assert float(sigma.max()) < 0.001  # near 0 next to the smallest level that matters
            # and not significantly above 0: what the regression corrects for is exactly 0
            assert bool((est.pooled_variance(1) == 0).all())
        else:
            assert torch.allclose(sigma, torch.full_like(sigma, omega), rtol=0.2)
            assert torch.allclose(est.pooled_variance(1).sqrt(), sigma)


def test_noise_estimate_standard_errors_are_calibrated_and_drop_outs_unbiased():
    # closed form: 200 random walks (std q per sample) observed with white noise (std s), some
    # with 5 % of the samples missing; (σ̂² − s²)/SE must scatter like a standard normal
    g = torch.Generator().manual_seed(11)
    n, q, s = 1000, 0.01, 0.004
    walk = torch.cumsum(q * torch.randn(200, n, 2, generator=g, dtype=F64), -2)
    x = walk + s * torch.randn(200, n, 2, generator=g, dtype=F64)
    x[100:][torch.rand(100, n, generator=g) < 0.05] = float("nan")
    est = estimate_noise(x)
    z = (est.variance - s**2) / est.variance_se
    assert abs(float(z[:100].mean())) < 0.3  # complete records; SE of the mean of 200 z: 0.07
    for part in (z[:100], z[100:]):  # complete, with drop-outs
        assert 0.8 < float(part.std()) < 1.25
    # the bridged gaps' increments are not in the expectation: with 5 % of the samples
    # missing σ̂² comes out about 6 % low (measured: 0.94); within 10 %
    assert abs(float(est.variance[100:].mean()) / s**2 - 1) < 0.1
    assert torch.allclose(est.process.square().mean().sqrt(), torch.tensor(q, dtype=F64),
                          rtol=0.02)


def test_noise_estimate_of_a_trial_does_not_depend_on_its_batch():
    g = torch.Generator().manual_seed(2)
    x = torch.cumsum(0.01 * torch.randn(6, 500, 3, generator=g, dtype=F64), -2)
    x = x + 0.003 * torch.randn(6, 500, 3, generator=g, dtype=F64)
    x[2, 40:60] = float("nan")
    x[4, :, 1] = float("nan")  # a lost channel: no estimate, and the others unaffected
    whole, part = estimate_noise(x), estimate_noise(x[2:3])
    assert float(whole.measurement[4, 1]) == 0 and math.isinf(float(whole.variance_se[4, 1]))
    assert torch.equal(estimate_noise(x[4:5, :, [0, 2]]).measurement, whole.measurement[4:5, [0, 2]])
    for name in ("measurement", "process", "variance_se", "band_low"):
        assert torch.equal(getattr(whole, name)[2:3], getattr(part, name))


@pytest.mark.slow
@pytest.mark.parametrize("n_links, gait, per_cycle", [(3, "reference", 300), (5, "circle", 126),
                                                      (9, "reference", 126)])
def test_noise_estimate_across_links_gaits_and_sampling(n_links, gait, per_cycle):
    # the check on seeds the band rule was not set on: 4 trials x 30 cycles of the
    # paper's SDE; the joints' noise pooled over the trials (what the regression corrects for)
    # within 20 % of the simulator's ω for ω >= 0.002, and nothing corrected on clean data
    from torchconn.physics.gaits import reference_gait
    d = n_links - 1
    if gait == "reference":
        g = reference_gait(f"{n_links}link")
    else:  # a travelling wave, as benchmarks/accuracy.py's circle gait
        lag = 2 * math.pi * torch.arange(d, dtype=F64) / max(d, 4)
        coeffs = torch.zeros(3, d, dtype=F64)
        coeffs[1], coeffs[2] = 0.9 * torch.cos(lag), 0.9 * torch.sin(lag)
        g = FourierGait(coeffs)
    seeds = np.arange(4) + 4000
    clean = simulate(NLinkSwimmer(n_links), g, eta=0.025, n_cycles=30,
                     samples_per_cycle=per_cycle, seeds=seeds)
    for omega in (0.0, 0.002, 0.005, 0.01):
        traj = observe(clean, omega, seeds=seeds)
        for est in (estimate_noise(traj.r), gait_noise(traj)):  # without and with the cycle
            rig = est.pooled_variance(1)  # (d,)
            if omega == 0:
                assert float(rig.mean().sqrt()) < 0.001
            else:
                assert abs(float(rig.mean().sqrt()) / omega - 1) < 0.2, (omega, rig.sqrt())


def test_phase_noise_floor_is_the_spectrum_of_a_phase_random_walk():
    # independent computation: Monte Carlo of r = γ(φ) + δ, φ and δ random walks of the same
    # per-sample std q (the paper's SDE), γ = 0.8 cos φ + 0.3 sin 3φ at 16 samples per cycle;
    # the increments' mean multitaper spectrum against q² (1 + ⟨γ'²⟩) times the shape, in bands
    # between the lines where the shape is far from flat
    from torchconn.noise.spectrum import _increment_spectrum, phase_noise_floor
    from torchconn.phase.fourier import FourierSeries

    g = torch.Generator().manual_seed(3)
    per_cycle, n, reps, q = 16.0, 4000, 200, 0.05
    coeffs = torch.zeros(7, 1, dtype=F64)
    coeffs[1, 0], coeffs[6, 0] = 0.8, 0.3
    cycle = FourierSeries(coeffs, value_ndim=1)
    phi = torch.cumsum(2 * math.pi / per_cycle
                       + q * torch.randn(reps, n + 1, generator=g, dtype=F64), -1)
    delta = torch.cumsum(q * torch.randn(reps, n + 1, 1, generator=g, dtype=F64), -2)
    spec = _increment_spectrum(torch.diff(cycle(phi) + delta, dim=-2))
    observed = spec.power.mean(0)[:, 0] / spec.x0[0, :, 0]
    shape = phase_noise_floor(spec.f, cycle, per_cycle, n=n)[:, 0]
    far = q**2 * (1 + 0.8**2 / 2 + 9 * 0.3**2 / 2)  # q² (1 + ⟨γ'²⟩)
    f = spec.f
    off_lines = (f * per_cycle - (f * per_cycle).round()).abs() > 0.2
    for lo, hi, rise in [(0.05, 0.08, 2.5), (0.1, 0.15, 1.5), (0.2, 0.3, 3.0)]:
        band = off_lines & (f >= lo) & (f < hi)
        assert float(shape[band].mean()) > rise  # far from a flat floor here
        assert abs(float(observed[band].mean() / (far * shape[band].mean())) - 1) < 0.04
    top = off_lines & (f >= 0.4)
    assert abs(float(observed[top].mean() / (far * shape[top].mean())) - 1) < 0.04


def test_low_rate_floor_shapes_only_where_the_harmonics_reach_the_top_band():
    # one batch of two records of the same order-8 gait, at 16 and 64 samples per cycle, with
    # measurement noise of std 0.01: the "low_rate" floor gives the 64-per-cycle element the
    # flat floor's estimate, bit for bit; at 16 per cycle the gait's lines fill the top band,
    # the flat floor's fit is thrown off by their tails (σ̂² off by many times the true
    # 1e-4), and the shaped floor finds the true variance within its standard errors
    from torchconn.phase.fourier import FourierSeries

    g = torch.Generator().manual_seed(5)
    n, q = 1200, 0.03
    coeffs = torch.zeros(17, 2, dtype=F64)
    coeffs[1:] = 0.3 * torch.randn(16, 2, generator=g, dtype=F64) / torch.arange(
        1, 9, dtype=F64).repeat_interleave(2)[:, None]  # order 8, falling as 1/k
    cycle = FourierSeries(coeffs, value_ndim=1)
    per_cycle = torch.tensor([16.0, 64.0], dtype=F64)
    phi = torch.cumsum(2 * math.pi / per_cycle[:, None]
                       + q * torch.randn(2, n + 1, generator=g, dtype=F64), -1)
    x = cycle(phi) + torch.cumsum(q * torch.randn(2, n + 1, 2, generator=g, dtype=F64), -2)
    x = x + 0.01 * torch.randn(x.shape, generator=g, dtype=F64)
    est = {floor: estimate_noise(x, cycle=cycle, samples_per_cycle=per_cycle, floor=floor)
           for floor in ("flat", "low_rate")}
    for name in ("variance", "variance_se", "process", "band_low", "correlation"):
        low, flat = (getattr(est[k], name) for k in ("low_rate", "flat"))
        assert torch.equal(low[1], flat[1]), name
    true = 0.01**2
    assert bool(((est["flat"].variance[0] - true).abs() > 20 * true).all()), (
        est["flat"].variance[0])
    low = est["low_rate"]
    assert bool(((low.variance[0] - true).abs() < 4 * low.variance_se[0]).all()), (
        low.variance[0], low.variance_se[0])
    with pytest.raises(ValueError, match="floor must be 'flat', 'low_rate' or 'normal'"):
        estimate_noise(x, cycle=cycle, samples_per_cycle=per_cycle, floor="shaped")


def test_channel_correlation_closed_form_on_a_circle():
    # γ = a (cos φ, sin φ): the increments' covariance q²_0 (I + γ'γ'ᵀ) gives the two joints'
    # σ̂² the correlation ⟨C_12²⟩ / ⟨C_11²⟩ = (a⁴/8) / (1 + a² + 3a⁴/8)
    from torchconn.noise.spectrum import _channel_correlation
    from torchconn.phase.fourier import FourierSeries

    a, q2_0 = 1.3, 2e-4
    coeffs = torch.zeros(3, 2, dtype=F64)
    coeffs[1, 0], coeffs[2, 1] = a, a
    q2 = torch.full((2,), q2_0 * (1 + a**2 / 2), dtype=F64)  # the fitted floor far from lines
    corr = _channel_correlation(FourierSeries(coeffs, value_ndim=1), q2, torch.zeros(2, dtype=F64),
                                torch.ones(2, dtype=torch.bool))
    expected = (a**4 / 8) / (1 + a**2 + 3 * a**4 / 8)
    torch.testing.assert_close(corr, torch.tensor([[1, expected], [expected, 1]], dtype=F64))


def test_channel_correlation_matches_monte_carlo_and_widens_the_joint_test():
    # independent computation: Monte Carlo of two joints r = γ(φ) + δ that share the phase
    # noise (φ and δ random walks of the same per-sample std, the paper's SDE), without
    # measurement noise: the empirical correlation of the two σ̂² over the draws against the
    # model's (the default flat floor), and testing the channels' mean with it narrows the
    # spread of its z against the independent joints' standard error
    from torchconn.phase.fourier import FourierSeries

    g = torch.Generator().manual_seed(11)
    per_cycle, n, reps, q = 32.0, 2000, 400, 0.03
    coeffs = torch.zeros(5, 2, dtype=F64)
    coeffs[1, 0], coeffs[1, 1], coeffs[2, 1], coeffs[4, 0] = 2.5, 2.25, 0.5, 0.3
    cycle = FourierSeries(coeffs, value_ndim=1)
    phi = torch.cumsum(2 * math.pi / per_cycle
                       + q * torch.randn(reps, n + 1, generator=g, dtype=F64), -1)
    delta = torch.cumsum(q * torch.randn(reps, n + 1, 2, generator=g, dtype=F64), -2)
    est = estimate_noise(cycle(phi) + delta, cycle=cycle, samples_per_cycle=per_cycle)
    model = float(est.correlation[:, 0, 1].mean())
    empirical = float(torch.corrcoef(est.variance.T)[0, 1])
    assert model > 0.4  # far from independent joints
    assert abs(empirical - model) < 0.12, (empirical, model)
    mean, se = est.pooled_mean(0, channels=True)
    z = mean[:, 0] / se[:, 0]
    _, se_independent = est.pooled_mean(0, channels=True, correlated=False)
    z_independent = mean[:, 0] / se_independent[:, 0]
    # the shared phase noise widens the mean's standard error: its z spreads less than the
    # independent one's
    assert float(z.std()) < 0.9 * float(z_independent.std()), (z.std(), z_independent.std())


def test_noise_estimate_names_a_bad_cycle():
    from torchconn.phase.fourier import FourierSeries

    x = torch.cumsum(torch.randn(2, 100, 2, generator=torch.Generator().manual_seed(0),
                                 dtype=F64), -2)
    cycle = FourierSeries(torch.zeros(3, 3, dtype=F64), value_ndim=1)  # 3 channels, not 2
    with pytest.raises(ValueError, match="cycle must be a FourierSeries with values"):
        estimate_noise(x, cycle=cycle, samples_per_cycle=20.0)
    with pytest.raises(ValueError, match="needs its samples_per_cycle"):
        estimate_noise(x, cycle=FourierSeries(torch.zeros(3, 2, dtype=F64), value_ndim=1))


def _curved_cycle_recording(omega, n_trials, seed, n_samples=1920, per_cycle=64):
    """``n_trials`` recordings of a non-planar 4-channel cycle (harmonics 1-3 in every
    channel) at ``per_cycle`` samples per cycle: the phase a random walk about ``t`` and the
    offset a random walk in every channel, both of ``η = 0.025`` (the paper's SDE without
    the offset's slow pull), plus white noise ``omega``. Returns the recording, its true
    phase and the cycle."""
    from torchconn.phase.fourier import FourierSeries

    coeffs = torch.tensor([[0.1, -0.2, 0.0, 0.3],
                           [0.8, 0.1, -0.5, 0.2], [0.0, 0.7, 0.3, -0.4],
                           [0.2, -0.3, 0.25, 0.1], [-0.15, 0.1, 0.2, 0.3],
                           [0.05, 0.08, -0.1, 0.06], [0.1, -0.05, 0.04, -0.08]], dtype=F64)
    cycle = FourierSeries(coeffs, value_ndim=1)
    g = torch.Generator().manual_seed(seed)
    dt = 2 * math.pi / per_cycle
    q = 0.025 * math.sqrt(dt)
    t = torch.arange(n_samples, dtype=F64) * dt
    phase = t + torch.cumsum(q * torch.randn(n_trials, n_samples, generator=g, dtype=F64), -1)
    offset = torch.cumsum(q * torch.randn(n_trials, n_samples, 4, generator=g, dtype=F64), -2)
    noise = omega * torch.randn(n_trials, n_samples, 4, generator=g, dtype=F64)
    return cycle(phase) + offset + noise, phase, cycle


def test_normal_projection_estimates_known_white_noise_on_a_curved_cycle():
    # the normal projection's σ̂² against the noise put in, within 3 of its own standard
    # errors (the trials' and channels' mean, channels correlated by the projection), where
    # the flat floor on the same joints is off by more than 4 of its own (0.62 ω²: the phase
    # noise's lines tilt its band; the projection takes them out)
    omega = 0.002
    x, phase, cycle = _curved_cycle_recording(omega, 40, seed=11)
    normal = estimate_noise(x, cycle=cycle, samples_per_cycle=64.0, floor="normal", phase=phase)
    mean, se = normal.pooled_mean(1, channels=True)
    assert abs(float(mean[0]) - omega**2) < 3 * float(se[0]), (float(mean[0]) / omega**2, se)
    flat = estimate_noise(x, cycle=cycle, samples_per_cycle=64.0)
    mean_flat, se_flat = flat.pooled_mean(1, channels=True)
    assert omega**2 - float(mean_flat[0]) > 4 * float(se_flat[0]), (mean_flat, se_flat)
    # honest per-trial standard errors: (σ̂² − ω²)/SE over trials has spread near 1
    m1, s1 = normal.pooled_mean(0, channels=True)
    z = (m1[:, 0] - omega**2) / s1[:, 0]
    assert abs(float(z.mean())) < 0.6 and 0.6 < float(z.std()) < 1.4, (z.mean(), z.std())
    # clean: near 0 (within 3 standard errors, and below a tenth of ω = 0.002 in σ)
    x0, phase0, _ = _curved_cycle_recording(0.0, 40, seed=12)
    clean = estimate_noise(x0, cycle=cycle, samples_per_cycle=64.0, floor="normal", phase=phase0)
    mean0, se0 = clean.pooled_mean(1, channels=True)
    assert abs(float(mean0[0])) < 3 * float(se0[0]), (mean0, se0)
    assert math.sqrt(max(float(mean0[0]), 0.0)) < 0.2 * omega


def test_normal_projection_spectrum_weights_are_exact():
    # white + MA(1) noise projected by a projector that turns along the record: the fit with
    # the projection's weights (P_ii and (P_k P_k+1)_ii) recovers σ² without bias over a fixed
    # band, where the same channels taken as unweighted increments would not
    from torchconn.noise.spectrum import _normal_weights, _project_normal

    omega = 0.01
    x, phase, cycle = _curved_cycle_recording(omega, 60, seed=13)
    u, frame = _project_normal(torch.diff(x, dim=-2), phase, cycle)
    assert frame.shape[-2] == 2  # d = 4: γ', γ'' projected out
    w0, w1 = _normal_weights(frame)
    # the frame is orthonormal where it is defined
    gram = (frame.unsqueeze(-2) * frame.unsqueeze(-3)).sum(-1)
    torch.testing.assert_close(gram, torch.eye(2, dtype=F64).expand_as(gram), atol=1e-12,
                               rtol=0)
    assert float(w0.min()) >= -1e-12 and float(w0.max()) <= 1 + 1e-12
    est = estimate_noise(x, cycle=cycle, samples_per_cycle=64.0, floor="normal", phase=phase,
                         band=(0.05, 0.5))
    mean, se = est.pooled_mean(1, channels=True)
    assert abs(float(mean[0]) / omega**2 - 1) < 3 * float(se[0]) / omega**2, (mean, se)
    assert float(se[0]) / omega**2 < 0.02


def test_normal_projection_with_two_joints_is_the_flat_floor_and_batch_free():
    from torchconn.noise import normal_increments, normal_span

    assert [normal_span(d) for d in (1, 2, 3, 4, 8, 12)] == [0, 0, 1, 2, 4, 4]
    prep, cycle = unpooled_trials([0.0, 0.005])
    gamma = cycle.gamma
    per_cycle = torch.full(prep.phase.shape[:-1], 64.0, dtype=F64)
    flat = estimate_noise(prep.r, cycle=gamma, samples_per_cycle=per_cycle)
    normal = estimate_noise(prep.r, cycle=gamma, samples_per_cycle=per_cycle, floor="normal",
                            phase=prep.phase)
    for name in ("measurement", "process", "variance_se", "variance", "correlation"):
        assert torch.equal(getattr(flat, name), getattr(normal, name)), name
    # d = 2: nothing projected
    assert torch.equal(normal_increments(prep.r, prep.phase, gamma), torch.diff(prep.r, dim=-2))
    # a trial's estimate does not depend on its batch (4 channels)
    x, phase, cycle4 = _curved_cycle_recording(0.003, 5, seed=14, n_samples=999)
    whole = estimate_noise(x, cycle=cycle4, samples_per_cycle=64.0, floor="normal", phase=phase)
    part = estimate_noise(x[2:3], cycle=cycle4, samples_per_cycle=64.0, floor="normal",
                          phase=phase[2:3])
    for name in ("measurement", "process", "variance_se", "variance", "correlation"):
        assert torch.equal(getattr(whole, name)[2:3], getattr(part, name)), name


def test_normal_projection_names_its_missing_inputs():
    x, phase, cycle = _curved_cycle_recording(0.002, 1, seed=15, n_samples=200)
    with pytest.raises(ValueError, match="phase="):
        estimate_noise(x, cycle=cycle, samples_per_cycle=64.0, floor="normal")
    with pytest.raises(ValueError, match="cycle="):
        estimate_noise(x, floor="normal", phase=phase)
    with pytest.raises(ValueError, match=r"phase must be a tensor \(..., T\) = \(1, 200\)"):
        estimate_noise(x, cycle=cycle, samples_per_cycle=64.0, floor="normal", phase=phase[:, 1:])


def test_noise_fit_leaves_out_the_gaits_harmonics_in_the_top_band():
    # closed form: the harmonics k/N (folded at Nyquist) of the harmonics the cycle carries,
    # within the tapers' half bandwidth (K + 1) / (2 (n + 1)), and only at f >= 0.25
    from torchconn.noise.spectrum import _TAPERS, _off_harmonics
    from torchconn.phase.fourier import FourierSeries
    coeffs = torch.zeros(17, 2, dtype=F64)  # order 8; harmonics 1, 3 and 5 carried
    coeffs[1, 0], coeffs[2, 1], coeffs[5, 0], coeffs[9, 1] = 1.0, 1.0, 0.2, 0.02
    cycle, n = FourierSeries(coeffs, value_ndim=1), 199
    f = torch.fft.rfftfreq(400, dtype=F64)
    keep = _off_harmonics(f, cycle, torch.tensor([10.0, 64.0]), n)  # (2, F, 1)
    assert keep.shape == (2, f.numel(), 1)
    assert bool((keep[1] == 1).all())  # 64 per cycle: 5/64 < 0.25, nothing left out
    width = (_TAPERS + 1) / (2 * (n + 1))
    lines = torch.tensor([0.3, 0.5], dtype=F64)  # k = 3, and k = 5 at Nyquist (k = 4 not carried)
    near = ((f[:, None] - lines).abs() <= width).any(-1) & (f >= 0.25)
    assert torch.equal(keep[0, :, 0], (~near).to(F64))
    assert float(keep[0, (f - 0.4).abs().argmin(), 0]) == 1  # 0.4: no line there


def test_one_noise_level_for_all_joints_of_a_trial():
    """``pooled_variance(channels=True)``: the mean of the joints' variances, tested against
    its own standard error as a whole, for every joint; per trial when nothing is pooled."""
    from torchconn.noise import NoiseEstimate

    var = torch.tensor([[4.0, 0.0, 2.0], [0.5, -0.3, 0.1]], dtype=F64)  # (trials, joints)
    se = torch.tensor([[1.0, 1.0, 1.0], [0.2, 0.2, 0.2]], dtype=F64)
    est = NoiseEstimate(measurement=var.clamp_min(0).sqrt(), process=torch.ones_like(var),
                        variance_se=se, variance=var)
    per_trial = est.pooled_variance(0, channels=True)
    # trial 0: mean 2 against se √3/3 = 0.577 -> kept; trial 1: mean 0.1 against 0.115 -> 0
    torch.testing.assert_close(per_trial, torch.tensor([[2.0] * 3, [0.0] * 3], dtype=F64))
    # per joint, trial 1's joint 0 (0.5 > 2 x 0.2) would have been kept on its own
    assert float(est.pooled_variance(0)[1, 0]) == 0.5
    pooled = est.pooled_variance(1, channels=True)  # one rig: mean 1.05, se 0.29
    torch.testing.assert_close(pooled, torch.full((3,), 1.05, dtype=F64))
