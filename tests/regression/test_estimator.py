"""The estimator end to end: exact on the toy, convergent on the swimmer, zero mean error."""

from __future__ import annotations

import copy
import dataclasses
import math
import warnings

import numpy as np
import pytest
import torch
from torch import Tensor

from torchconn import AffineConnectionSystem, NLinkSwimmer, TiedMetric, Trajectory
from torchconn.evaluation.models import error_summary, phase_bin_errors, reference_models
from torchconn.io.trajectory_files import read_csv, write_csv
from torchconn.phase.fourier import fit_fourier
from torchconn.phase.limit_cycle import SelfConsistentCycle
from torchconn.physics.gaits import FourierGait, reference_gait
from torchconn.regression.estimator import ConnectionEstimator
from torchconn.regression.model import LocalConnectionModel
from torchconn.regression.noise_aware import NoiseAwareRegression
from torchconn.regression.tube import TubeRegression
from torchconn.simulation.observe import observe
from torchconn.simulation.rollout import simulate
from torchconn.trajectory import SmoothedState

from ..recordings import five_link_a_error

F64 = torch.float64


def _exact_trajectory(system, gait, n_cycles=12, spc=64, amp=0.1, seed=0, batch=(2,)):
    """Noise-free samples off the cycle with exact velocities: r = γ(φ) + δ(t), δ a sum of
    sinusoids at frequencies incommensurate with the gait, ξ = A(r) ṙ exactly."""
    g = torch.Generator().manual_seed(seed)
    d = system.shape_dim
    t = torch.arange(n_cycles * spc, dtype=F64) * (2 * math.pi / spc)
    freqs = torch.tensor([0.13, 0.37, 0.71, 1.618, 2.33], dtype=F64)
    a = amp * torch.randn(batch + (5, d), generator=g, dtype=F64) / math.sqrt(5)
    ph = 2 * math.pi * torch.rand(batch + (5, d), generator=g, dtype=F64)
    arg = freqs[:, None, None] * t + ph[..., None]  # (..., 5, d, T)
    delta = (a[..., None] * torch.sin(arg)).sum(-3).transpose(-1, -2)
    delta_dot = (a[..., None] * freqs[:, None, None] * torch.cos(arg)).sum(-3).transpose(-1, -2)
    phase = t.expand(batch + t.shape)
    r = gait(phase) + delta
    r_dot = gait.velocity(phase) + delta_dot
    xi = system.body_velocity(r, r_dot)
    pose = torch.zeros(batch + (t.shape[0], 3), dtype=F64)  # not used: smoothed state given
    traj = Trajectory(t=t, pose=pose, r=r)
    return traj.with_fields(
        phase=phase,
        smoothed=SmoothedState(pose=pose, pose_dot=pose, r=r, r_dot=r_dot, xi=xi),
    )


def test_toy_connection_is_recovered_exactly_from_noise_free_data():
    toy = AffineConnectionSystem.random(d=2, seed=3)
    coeffs = torch.zeros(5, 2, dtype=F64)
    coeffs[1, 0], coeffs[2, 1], coeffs[3, 0] = 0.8, 0.6, 0.2  # order-2 gait
    gait = FourierGait(coeffs)
    traj = _exact_trajectory(toy, gait)
    est = ConnectionEstimator(
        cycle=SelfConsistentCycle(order=2), metric=TiedMetric(enabled=False),
        regression=TubeRegression(n_bins=16, fourier_order=6, window=1.0),
    ).fit(traj)
    phi = torch.linspace(0, 2 * math.pi, 50, dtype=F64)
    gamma = est.model_.gamma_at(phi)
    # the cycle comes from the data (mean of r at each phase); the connection at that cycle
    # is exact because A is affine, so a first-order model in the tube has no remainder
    assert torch.allclose(est.model_.connection(phi), toy.connection(gamma), atol=1e-8)
    assert torch.allclose(est.model_.connection_jacobian(phi),
                          toy.connection_jacobian(gamma), atol=1e-8)
    xi_hat = est.model_.predict(traj.phase, traj.r, traj.smoothed.r_dot)
    assert torch.allclose(xi_hat, traj.smoothed.xi, atol=1e-8)


def _swimmer_truth_trajectory(n_cycles, seeds):
    """Simulated 3-link trials whose 'smoothed' state is the simulation's truth (no filter)."""
    s = NLinkSwimmer(3)
    tr = simulate(s, reference_gait("3link"), eta=0.025, n_cycles=n_cycles, seeds=seeds)
    g = tr.truth
    sm = SmoothedState(pose=g.pose, pose_dot=g.pose, r=g.r, r_dot=g.r_dot, xi=g.xi)
    return s, tr.with_fields(smoothed=sm, phase=g.phase)


def test_estimates_converge_to_the_simulator_as_data_grows():
    # narrow bins (96, tricube window of one spacing) keep the tube's bias below the
    # statistical error over this range, so the error falls like N^-1/2
    # The metric: M̂γ̇ (what the gait identifies) is below 1 % and still falls (measured
    # 0.58 %, 0.49 %, 0.43 %: towards the floor of the Fourier order in phase); the full M̂
    # levels off at a few per cent (measured 7.6 %, 8.2 %, 8.1 %): its off-cycle directions see
    # only the offsets' small velocities, against which the model's second-order remainder in
    # the offsets does not average out.
    cycles = np.array([40, 80, 160])
    errs = {"A": [], "dA": [], "M_gamma_dot": [], "M": []}
    for n in cycles:
        s, tr = _swimmer_truth_trajectory(int(n), seeds=np.arange(2) + 100)
        est = ConnectionEstimator(
            regression=TubeRegression(n_bins=96, fourier_order=16, window=1.0)).fit(tr)
        b = est.model_.bins
        m_true = s.metric(b.gamma)
        for name, est_v, true_v in (("A", b.A, s.connection(b.gamma)),
                                    ("dA", b.dA, s.connection_jacobian(b.gamma)),
                                    ("M_gamma_dot", b.M_gamma_dot,
                                     (m_true @ b.gamma_dot[..., None])[..., 0]),
                                    ("M", b.M, m_true)):
            errs[name].append(float((est_v - true_v).pow(2).mean().sqrt()
                                    / true_v.pow(2).mean().sqrt()))
    for name, e in errs.items():
        slope = np.polyfit(np.log(cycles), np.log(e), 1)[0]
        print(f"{name}: relative RMS errors {np.round(e, 4)}, slope {slope:.2f}")
        if name in ("A", "dA"):
            assert -0.8 < slope < -0.3, name
    assert errs["A"][-1] < 0.02
    assert np.all(np.diff(errs["M_gamma_dot"]) < 0) and max(errs["M_gamma_dot"]) < 0.01
    assert max(errs["M"]) < 0.1


def test_data_driven_mean_error_per_phase_bin_is_zero_within_its_standard_error():
    s, tr = _swimmer_truth_trajectory(30, seeds=np.arange(8) + 11)
    M = 32
    est = ConnectionEstimator(metric=TiedMetric(enabled=False), regression=TubeRegression(
        n_bins=M, fourier_order=10, window=0.5, kernel="box")).fit(tr)
    b = est.model_.bins
    # each sample predicted by its own bin's regression (eq. advanceddatadriven at γ_m)
    m = torch.round(torch.remainder(tr.phase, 2 * math.pi) / (2 * math.pi / M)).long() % M

    def at(x):  # (trials, M, ...) -> per sample (trials, T, ...)
        idx = m.reshape(m.shape + (1,) * (x.ndim - 2)).expand(m.shape + x.shape[2:])
        return torch.gather(x, 1, idx)

    delta, delta_dot = tr.smoothed.r - at(b.gamma), tr.smoothed.r_dot - at(b.gamma_dot)
    pred = (at(b.c) + (at(b.b) @ delta[..., None])[..., 0] + (at(b.A) @ delta_dot[..., None])[..., 0]
            + torch.einsum("...kij,...i,...j->...k", at(b.dA), delta_dot, delta))
    _, mean, _, se = phase_bin_errors(pred, tr.smoothed.xi, tr.phase, M)
    z = (mean / se).abs()
    print(f"binned model: max |z| {z.max():.2e}")
    assert z.max() < 1e-6  # least squares with an intercept: zero mean residual in every bin

    # the smooth (Fourier in phase) model: its per-bin bias is far below the analytic model's
    p = reference_models(s, est.model_, est.trajectory_)
    bias = {k: phase_bin_errors(p[k], tr.smoothed.xi, tr.phase, M)[1].mean(0).abs().mean(0)
            for k in ("data_driven", "analytic")}
    print(f"mean |bias| per bin: data-driven {bias['data_driven']}, analytic {bias['analytic']}")
    assert bias["data_driven"][0] < 0.5 * bias["analytic"][0]


def test_batched_fit_equals_one_trial_at_a_time():
    s, tr = _swimmer_truth_trajectory(12, seeds=np.arange(2))
    regression = TubeRegression(n_bins=24, fourier_order=6)
    both = ConnectionEstimator(regression=regression).fit(tr).model_
    one = ConnectionEstimator(regression=regression).fit(tr[1]).model_
    phi = torch.linspace(0, 6, 7, dtype=F64)
    assert torch.allclose(both[1].connection(phi), one.connection(phi), atol=1e-10)


def test_model_save_load_round_trip(tmp_path):
    _, tr = _swimmer_truth_trajectory(12, seeds=np.arange(2))
    model = ConnectionEstimator(regression=TubeRegression(n_bins=24, fourier_order=6)).fit(
        tr.with_fields(power=torch.ones(tr.batch_shape + (tr.n_samples,), dtype=F64))).model_
    path = model.save(tmp_path / "m.npz")
    back = LocalConnectionModel.load(path)
    phi = torch.linspace(0, 6, 7, dtype=F64)
    for name in ("gamma", "c", "b", "A", "dA", "M", "dM"):
        assert torch.equal(getattr(model, name).coeffs, getattr(back, name).coeffs)
    for name in ("M_sampling_factor", "M_offset_bias", "dM"):  # the cost's draws
        assert torch.equal(getattr(model.bins, name), getattr(back.bins, name))
    for name in ("connection", "connection_jacobian", "metric", "gamma_at", "gamma_dot_at"):
        torch.testing.assert_close(getattr(model, name)(phi), getattr(back, name)(phi),
                                   rtol=0, atol=1e-15)


def test_bad_settings_and_inputs_raise():
    with pytest.raises(ValueError, match="fourier_order must satisfy"):
        TubeRegression(n_bins=8, fourier_order=4)
    with pytest.raises(ValueError, match=r"TubeRegression.n_bins must be >= 3, got 2"):
        TubeRegression(n_bins=2)
    with pytest.raises(TypeError, match="torchconn.Trajectory"):
        ConnectionEstimator().fit({"r": 1})
    _, tr = _swimmer_truth_trajectory(4, seeds=np.arange(1))
    # a window too narrow for the full model's regressors: refused at the complexity given
    # (complexity="auto" regresses the connection alone there, which it can score)
    with pytest.raises(ValueError, match="samples"):
        ConnectionEstimator(regression=TubeRegression(window=0.5), metric=TiedMetric(enabled=False),
                            complexity="fixed").fit(tr)
    with pytest.raises(RuntimeError, match="not fitted"):
        ConnectionEstimator().predict(tr)
    model = ConnectionEstimator(
        metric=TiedMetric(enabled=False),
        regression=TubeRegression(n_bins=12, fourier_order=4)).fit(tr).model_
    with pytest.raises(ValueError, match="r must have shape"):
        model.predict(tr.phase, torch.zeros(tr.phase.shape + (3,), dtype=F64), tr.r)


def test_trials_of_different_lengths_are_not_extrapolated(tmp_path):
    from torchconn.io.trajectory_files import read_csv
    from torchconn.phase.phaser import estimate_phase
    from torchconn.phase.smoothing import smooth_trajectory

    long = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=16, seeds=[1])
    short = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=10, seeds=[2])
    write_csv(long, tmp_path / "long.csv")
    write_csv(short, tmp_path / "short.csv")
    traj = read_csv([tmp_path / "long.csv", tmp_path / "short.csv"])  # short one NaN-padded
    est = ConnectionEstimator(regression=TubeRegression(n_bins=24, fourier_order=6),
                              metric=TiedMetric(enabled=False), pool=True).fit(traj)
    prepared = est.trajectory_
    n_short = short.n_samples
    assert torch.isnan(prepared.phase[1, n_short:]).all()
    assert torch.isnan(prepared.smoothed.xi[1, n_short:]).all()
    # the short trial's phase is what Phaser gives on its own recording (up to the smoother's
    # noise estimate, which sees the padded batch: far below Phaser's own error of ~0.03 rad)
    alone = estimate_phase(smooth_trajectory(short.pose[0], short.r[0], short.dt).r)
    torch.testing.assert_close(prepared.phase[1, :n_short], alone, rtol=0, atol=1e-3)
    b = est.model_.bins
    s = NLinkSwimmer(3)
    assert (b.A - s.connection(b.gamma)).abs().max() < 0.05


def test_a_gap_the_phase_cannot_cross_is_named():
    """A tracked recording that lost 6 of its 16 cycles in one run (a tracked zebrafish lost
    9.7 of 23): the smoother bridges the gap without the gait's oscillation, the phase stalls
    across it, and the phaser counts one cycle. The error says so and what to do, and the part
    before the gap fits."""
    from torchconn.simulation.observe import observe

    spc = 16
    clean = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=16,
                     samples_per_cycle=spc, seeds=np.array([5]))
    traj = observe(clean, 0.005, seeds=np.array([5])).with_fields(power=None)
    r = traj.r.clone()
    r[..., 8 * spc:14 * spc, :] = math.nan
    gapped = traj.with_fields(r=r)
    with pytest.raises(ValueError, match=r"covers only about 1\.\d cycles.*here trial 0 has a "
                       r"gap of 6\.0 cycles with no samples.*split the recording at its gaps"):
        ConnectionEstimator(complexity="fixed").fit(gapped)
    est = ConnectionEstimator(complexity="fixed").fit(gapped.slice_time(0, 8 * spc))
    assert float(est.trajectory_.phase[..., -1] - est.trajectory_.phase[..., 0]) > 6 * math.pi


def _errors(name, seeds, eta_factor):
    """x RMS error of the default model against the simulator's ``A(r)ṙ`` on the same smoothed
    shapes, and of the same model with its intercept at ``fourier_order``."""
    system = NLinkSwimmer(int(name[0]))
    traj = simulate(system, reference_gait(name), eta=0.025 * eta_factor, alpha=0.05,
                    n_cycles=30, samples_per_cycle=64, substeps=8, seeds=seeds)
    est = ConnectionEstimator(regression=TubeRegression(), complexity="fixed",
                              metric=TiedMetric(enabled=False),
                              held_out_folds=0).fit(traj)
    model = est.model_
    fixed = dataclasses.replace(model, c=fit_fourier(model.bins.phase, model.bins.c, 12,
                                                     value_ndim=1))

    def error(m):
        preds = reference_models(system, m, est.trajectory_)
        return error_summary(preds["data_driven"], preds["ground_truth"])[0][..., 0]

    return model.meta["intercept_order"], error(model), error(fixed)


def test_the_9link_intercept_gets_the_harmonics_its_body_velocity_has():
    """The 9-link reference gait's on-cycle body velocity has harmonics above 12: the chosen
    intercept order is higher and the model's error against the simulator's own body velocity
    (A(r)ṙ on the same smoothed shapes) falls; the 3-link's stays at the given order, so its
    model is the one of order 12."""
    seeds = np.array([[311, 312]])
    orders, err, err_fixed = _errors("9link", seeds, 0.25)
    assert all(k > 12 for k in orders[0])
    assert bool((err < 0.75 * err_fixed).all()), (err, err_fixed)
    orders3, err3, err3_fixed = _errors("3link", seeds, 1.0)
    assert orders3 == [[12, 12]]
    torch.testing.assert_close(err3, err3_fixed, rtol=1e-12, atol=0)


F64 = torch.float64


SPC = 12  # samples per cycle: a video rate


CYCLES = (9, 14, 20)


PHI = torch.linspace(0, 2 * math.pi, 49, dtype=F64)[:-1]


def test_pooled_fit_of_unequal_recordings_is_close_to_the_swimmer(unequal_recordings):
    traj = read_csv(unequal_recordings)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # few samples per cycle, the metric's ∂M/∂r left out
        est = ConnectionEstimator(pool=True).fit(traj)
    model = est.model_
    assert model.batch_shape == ()
    for field in ("A", "b", "dA", "c", "M"):
        assert torch.isfinite(getattr(model, field).coeffs).all(), field
    # measured over seeds 0-9 of these recordings (_files(dir, 10 * s)): 0.15-0.25, median
    # 0.17 (0.17 here); the same trials cut to 9 cycles each (equal lengths, no power) pooled
    # 0.12-0.28: the error of 12 samples per cycle, not of the unequal lengths
    assert float(five_link_a_error(model)) < 0.35
    # the phase models of the trials (different lengths, orders chosen per trial) stacked
    assert est.phaser_.model_.batch_shape == (3,)
    assert torch.isfinite(est.trajectory_.phase[0, 3:CYCLES[0] * SPC]).all()
    assert torch.isnan(est.trajectory_.phase[0, CYCLES[0] * SPC:]).all()
    # predictions where each trial was recorded, none in the padding
    xi = est.predict(traj)
    assert torch.isfinite(xi[1, : CYCLES[1] * SPC]).all()
    assert torch.isnan(xi[1, CYCLES[1] * SPC:]).all()


def test_per_trial_fits_of_unequal_recordings_are_close_to_the_swimmer(unequal_recordings):
    traj = read_csv(unequal_recordings).with_fields(power=None)  # one trial is too short for its metric
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = ConnectionEstimator().fit(traj)
    assert est.model_.batch_shape == (3,)
    # measured 0.15-0.34 over seeds 0-9 at 9-20 cycles (0.15-0.29 here)
    errors = five_link_a_error(est.model_)
    assert torch.isfinite(errors).all() and float(errors.max()) < 0.45


def test_each_trial_is_fitted_in_a_batch_of_unequal_trials_as_alone(unequal_recordings):
    # the batch shares its settings (the bins' window, the complexity: fixed here), nothing
    # else: smoothing, phase, cycle, noise and regression of each trial see only its span
    est = ConnectionEstimator(complexity="fixed", metric=TiedMetric(enabled=False),
                              regression=NoiseAwareRegression(window=8.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        batch = copy.deepcopy(est).fit(read_csv(unequal_recordings))
        alone = [copy.deepcopy(est).fit(read_csv(f)) for f in unequal_recordings]
    for k, one in enumerate(alone):
        n = one.trajectory_.n_samples
        torch.testing.assert_close(batch.trajectory_.phase[k, :n], one.trajectory_.phase[0],
                                   rtol=0, atol=1e-10, equal_nan=True)
        for name in ("connection", "connection_jacobian", "gamma_at"):
            torch.testing.assert_close(getattr(batch.model_, name)(PHI)[k],
                                       getattr(one.model_, name)(PHI)[0], rtol=0, atol=1e-9)


def test_a_trial_with_its_first_samples_lost_keeps_its_metric():
    # a 3-link recording with power, alone and with NaN rows before and after it (its first
    # samples lost, or a later start and an earlier end than the other trials of a grid):
    # the same model. The metric's interval phases were anchored at the first row, 0 for a
    # lost one: M̂γ̇ came out 73 % off the swimmer's (against 9 %) for one lost sample
    seeds = [3]
    traj = observe(simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=12,
                            samples_per_cycle=32, seeds=seeds), 0.01, seeds=seeds)
    traj = traj.with_fields(truth=None)

    def padded(x: Tensor) -> Tensor:
        return torch.cat([torch.full_like(x[:, :5], math.nan), x,
                          torch.full_like(x[:, :40], math.nan)], 1)

    t = torch.arange(traj.n_samples + 45, dtype=F64) * traj.dt
    moved = Trajectory(t=t, pose=padded(traj.pose), r=padded(traj.r), power=padded(traj.power))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = ConnectionEstimator().fit(traj).model_
        b = ConnectionEstimator().fit(moved).model_
    for name in ("connection", "metric_gamma_dot", "gamma_at"):
        x, y = getattr(a, name)(PHI), getattr(b, name)(PHI)
        torch.testing.assert_close(y, x, rtol=0, atol=1e-10 * float(x.abs().max()))
    truth = NLinkSwimmer(3).metric(b.gamma_at(PHI)) @ b.gamma_dot_at(PHI).unsqueeze(-1)
    error = (b.metric_gamma_dot(PHI) - truth.squeeze(-1)).norm() / truth.norm()
    assert float(error) < 0.2
