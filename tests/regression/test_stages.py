"""The estimator's pluggable stages: defaults equal the previous pipeline, options validate
themselves, scikit-learn parameter protocol, settings tables, Phaser fit/transform."""

import dataclasses
import math
import warnings

import numpy as np
import pytest
import torch

from torchconn import NLinkSwimmer, TiedMetric, observe, simulate
from torchconn.phase.fourier import fit_fourier
from torchconn.phase.limit_cycle import SelfConsistentCycle, fit_limit_cycle
from torchconn.phase.phaser import Phaser, circular_rms, estimate_phase
from torchconn.phase.smoothing import RTSSmoother, Smoother, smooth_trajectory
from torchconn.physics.gaits import reference_gait
from torchconn.regression.binning import assign_bins
from torchconn.regression.connection import connection_regression
from torchconn.regression.estimator import (
    ConnectionEstimator,
    estimator_from_settings,
    estimator_settings,
)
from torchconn.regression.noise_aware import NoiseAwareRegression
from torchconn.regression.tube import TubeRegression
from torchconn.sweep.config import load_config
from torchconn.trajectory import SmoothedState

F64 = torch.float64


@pytest.fixture(scope="module")
def recording():
    """3-link, 2 trials x 10 cycles, motion-capture noise 0.002, with a power channel."""
    seeds = np.arange(2) + 40
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=10, seeds=seeds)
    return observe(traj, 0.002, seeds=seeds)


def _previous_defaults(traj):
    """torchconn 0.1's default fit spelled out with its lower-level functions and its explicit
    default numbers: RTS order 2, Phaser order 3 (>= 3 cycles), cycle order 8, 48 bins, tricube
    windows sized to 2.5 samples per regressor, Fourier order 12."""
    sm = smooth_trajectory(traj.pose, traj.r, traj.dt, order=2)
    phase = estimate_phase(sm.r, order=3, min_cycles=3.0)
    cycle = fit_limit_cycle(phase, traj.r, sm.r_dot, order=8, dt=traj.dt)
    M, K, d = 48, 12, traj.shape_dim
    centres = torch.arange(M, dtype=F64) * (2 * math.pi / M)
    grid = centres.expand(phase.shape[:-1] + (M,))
    gamma_m = cycle.gamma(grid)
    gamma_dot_m = cycle.phase_rate[..., None, None] * cycle.gamma.derivative()(grid)

    def bins(n_regressors):
        per_spacing = phase.shape[-1] / M  # no NaN: every trial has all its samples
        window = min(max(2.5 * n_regressors / (1.2 * per_spacing), 1.0), M / 4)
        return assign_bins(phase, M, window=window, kernel="tricube")

    opts = dict(delta_max=None, ridge=0.0, on_ill_conditioned="raise")
    fit = connection_regression(sm.r, sm.r_dot, sm.xi, bins(1 + 2 * d + d * d), gamma_m,
                                gamma_dot_m, **opts)
    coeffs = {name: fit_fourier(centres, value, K, value_ndim=nd).coeffs
              for name, value, nd in (("c", fit.c, 1), ("b", fit.b, 2), ("A", fit.A, 2),
                                      ("dA", fit.dA, 3))}
    return phase, cycle.gamma.coeffs, coeffs, fit.se_A


def test_default_stages_reproduce_the_previous_defaults(recording):
    # 0.1's fixed complexity (the default "auto" keeps it unless it loses to the phase-averaged
    # velocity on held-out cycles, which it does here by 0.002 in v_x of one trial), 0.1's
    # phase order (the default is now "auto"; with two channels the SNR weights are the
    # coherence weights 0.1 used) and 0.1's regression on the smoothed velocities (the default
    # is now NoiseAwareRegression): all named options. The metric is the tied model.
    old_phaser = Phaser(order=3)
    est = ConnectionEstimator(phaser=old_phaser, regression=TubeRegression(),
                              complexity="fixed").fit(recording)
    phase, gamma, coeffs, se_A = _previous_defaults(recording)
    model = est.model_
    torch.testing.assert_close(est.trajectory_.phase, phase, rtol=0, atol=1e-12)
    torch.testing.assert_close(model.gamma.coeffs, gamma, rtol=0, atol=1e-12)
    for name, expected in coeffs.items():
        got = getattr(model, name).coeffs
        if name == "c":  # the intercept's order is chosen from the data (12 here), and its
            # series is kept at the bins' highest order with the harmonics above 12 zero
            assert set(model.meta["intercept_order"]) == {12}
            assert not bool(got[..., expected.shape[-2]:, :].any())
            got = got[..., :expected.shape[-2], :]
        torch.testing.assert_close(got, expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(model.bins.A_se, se_A, rtol=0, atol=1e-12)
    # and the estimates are real ones: A within a few per cent of the swimmer's exact A
    A_true = NLinkSwimmer(3).connection(model.bins.gamma)
    assert float((model.bins.A - A_true).norm() / A_true.norm()) < 0.3


def test_stage_options_validate_themselves():
    cases = [
        (lambda: TubeRegression(kernel="gauss"),
         "TubeRegression.kernel must be one of 'box', 'tricube', 'epanechnikov', got 'gauss'"),
        (lambda: TubeRegression(n_bins=2), "TubeRegression.n_bins must be >= 3, got 2"),
        (lambda: TubeRegression(n_bins=48.0), "TubeRegression.n_bins must be an integer"),
        (lambda: TubeRegression(window=0.0), "TubeRegression.window must be > 0"),
        (lambda: TubeRegression(window="auto"),
         "TubeRegression.window must be a finite number or None"),
        (lambda: TubeRegression(on_ill_conditioned="ignore"),
         "on_ill_conditioned must be one of 'raise', 'warn', 'ridge'"),
        (lambda: TubeRegression(n_bins=10, fourier_order=5), "2\\*fourier_order < n_bins=10"),
        (lambda: RTSSmoother(order=4), "RTSSmoother.order must be one of 2, 3, got 4"),
        (lambda: RTSSmoother(order=True), "RTSSmoother.order must be one of 2, 3, got True"),
        (lambda: Phaser(order=-1), "Phaser.order must be >= 0, got -1"),
        (lambda: Phaser(min_cycles=float("nan")), "Phaser.min_cycles must be a finite number"),
        (lambda: SelfConsistentCycle(order=0), "SelfConsistentCycle.order must be >= 1"),
    ]
    for make, message in cases:
        with pytest.raises(ValueError, match=message):
            make()
    with pytest.raises(TypeError):
        TubeRegression(48)  # keyword-only
    with pytest.raises(dataclasses.FrozenInstanceError):
        TubeRegression().n_bins = 24
    with pytest.raises(TypeError, match="regression must be a Regression"):
        ConnectionEstimator(regression=Phaser())


def test_get_and_set_params_follow_scikit_learn_without_it():
    est = ConnectionEstimator(regression=TubeRegression(n_bins=24, fourier_order=6), pool=True)
    shallow = est.get_params(deep=False)
    assert set(shallow) == {"smoother", "phaser", "cycle", "regression", "metric", "pool",
                            "complexity", "held_out_folds", "prior"}
    deep = est.get_params(deep=True)
    assert deep["regression__n_bins"] == 24 and deep["phaser__order"] == "auto"
    assert deep["smoother__order"] == 2 and deep["cycle__order"] == 8 and deep["pool"] is True
    shared = est.regression
    assert est.set_params(regression__n_bins=32, phaser__order=4, pool=False) is est
    assert est.regression.n_bins == 32 and est.regression.fourier_order == 6
    assert est.phaser.order == 4 and est.pool is False
    assert shared.n_bins == 24  # the stage object was replaced, never modified
    rebuilt = ConnectionEstimator(**est.get_params(deep=False))
    assert rebuilt.get_params() == est.get_params()
    with pytest.raises(ValueError, match=r"'regression__nbins' \(did you mean 'regression__n_bins'"):
        est.set_params(regression__nbins=3)
    with pytest.raises(ValueError, match="TubeRegression.n_bins must be >= 3"):
        est.set_params(phaser__order=2, regression__n_bins=2)
    with pytest.raises(TypeError, match="smoother must be a Smoother"):
        est.set_params(smoother=Phaser(), pool=True)
    assert est.get_params() == rebuilt.get_params()  # a refused call changes nothing
    with pytest.raises(ValueError, match="held_out_folds must be 0 .* or an integer >= 2, got 1"):
        est.set_params(held_out_folds=1)
    with pytest.raises(ValueError, match=r"prior must be None .* \(swimmer\), got 'rft'"):
        est.set_params(prior="rft")
    assert est.set_params(prior=None).prior is None
    with pytest.raises(ValueError, match="complexity must be one of"):
        estimator_from_settings({"complexity": "auto-ish"})
    assert "n_bins=32" in repr(est) and "Phaser(order=4" in repr(est)


def test_sklearn_clone_gives_an_unfitted_estimator_with_equal_parameters(recording):
    base = pytest.importorskip("sklearn.base")
    est = ConnectionEstimator(phaser=Phaser(order=4), metric=TiedMetric(enabled=False),
                              regression=TubeRegression(n_bins=24, fourier_order=6))
    est.fit(recording)
    twin = base.clone(est)
    assert not hasattr(twin, "model_") and not hasattr(twin, "phaser_")
    assert twin.get_params(deep=True) == est.get_params(deep=True)
    assert not hasattr(twin.phaser, "model_")  # the phase stage stays an unfitted option
    twin.set_params(regression__n_bins=32)
    assert est.regression.n_bins == 24
    # the clone fits to the same model
    torch.testing.assert_close(base.clone(est).fit(recording).model_.A.coeffs,
                               est.model_.A.coeffs, rtol=0, atol=0)


def test_settings_tables_build_the_estimator_and_name_bad_keys():
    nested = estimator_from_settings({
        "pool": True, "phaser": {"order": 4},
        "regression": {"n_bins": 24, "fourier_order": 6, "kernel": "box"},
    })
    assert nested.pool and nested.phaser == Phaser(order=4)
    assert nested.regression == NoiseAwareRegression(n_bins=24, fourier_order=6, kernel="box")
    assert estimator_from_settings(estimator_settings(nested)).get_params() == nested.get_params()
    assert estimator_settings(ConnectionEstimator())["regression"]["method"] == "noise_aware"
    # today's method is the default; torchconn 0.1's stays selectable by name
    tube = estimator_from_settings({"regression": {"method": "tube", "n_bins": 24,
                                                   "fourier_order": 6}})
    assert type(tube.regression) is TubeRegression and tube.regression.n_bins == 24
    assert estimator_settings(tube)["regression"]["method"] == "tube"
    bad = [
        ({"regresion": {}}, r"estimator: unknown key 'regresion' \(did you mean 'regression'\?\)"),
        ({"regression": {"n_bin": 3}},
         r"estimator.regression \(NoiseAwareRegression\): unknown key 'n_bin' \(did you mean "
         "'n_bins'"),
        ({"regression": {"n_bins": 4.5}},
         "estimator.regression: NoiseAwareRegression.n_bins must be an integer, got 4.5"),
        ({"smoother": {"method": "kalman"}}, r"estimator.smoother.method: unknown key 'kalman'"),
        ({"phaser": 3}, "estimator.phaser must be a table"),
        ({"pool": "yes"}, "estimator.pool must be true or false"),
        ({"phaser": {"order": -2}}, "Phaser.order must be >= 0, got -2"),
        ({"n_bins": 24}, r"estimator: unknown key 'n_bins'"),
    ]
    for settings, message in bad:
        with pytest.raises(ValueError, match=message):
            estimator_from_settings(settings)


def test_sweep_config_builds_the_estimator_and_its_fingerprint_follows_it(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text("""
name = "s"
seed = 1
[estimator.regression]
n_bins = 24
fourier_order = 6
[[experiment]]
system = "3link"
noise_kind = "system"
levels = [1.0]
trials = 1
""")
    config = load_config(path)
    est = config.make_estimator()
    assert est.regression.n_bins == 24 and est.regression.fourier_order == 6
    exp = config.experiments[0]
    same = load_config(path, ["estimator.regression.fourier_order=6"])
    assert same.fingerprint(same.experiments[0]) == config.fingerprint(exp)
    for change in ("estimator.regression.n_bins=32", "estimator.phaser.order=4",
                   "estimator.smoother.order=3", "estimator.cycle.order=5", "estimator.pool=true"):
        other = load_config(path, [change])
        assert other.fingerprint(other.experiments[0]) != config.fingerprint(exp), change
    with pytest.raises(ValueError, match=r"\[estimator\].regression: NoiseAwareRegression.n_bins"):
        load_config(path, ["estimator.regression.n_bins=2"])


def test_phaser_transform_reuses_the_fitted_origin_on_new_recordings():
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=16,
                    seeds=np.arange(2) + 3)
    r, truth = traj.r, traj.truth.phase
    half = r.shape[-2] // 2
    options = Phaser()
    fitted = options.fit(r[..., :half, :])
    assert not hasattr(options, "model_")  # fit returns a fitted copy; the options stay as given
    with pytest.raises(RuntimeError, match="not fitted"):
        options.transform(r)
    torch.testing.assert_close(fitted.phase_, estimate_phase(r[..., :half, :]), rtol=0, atol=0)
    torch.testing.assert_close(fitted.transform(r[..., :half, :]), fitted.phase_,
                               rtol=0, atol=1e-12)
    # on the unseen second half: the same phase origin, and an error of the fit's order (the
    # learned corrections carry the training half's noise: 0.055 / 0.047 rad here, against
    # 0.040 / 0.037 on the training half and 0.023 / 0.027 for a fresh estimate on the new half)
    new = fitted.transform(r[..., half:, :])

    def origin(est, true):  # circular mean of the estimate's offset from the true phase
        d = est - true
        return torch.atan2(torch.sin(d).mean(-1), torch.cos(d).mean(-1))

    shift = origin(new, truth[..., half:]) - origin(fitted.phase_, truth[..., :half])
    shift = torch.remainder(shift + math.pi, 2 * math.pi) - math.pi
    print(f"origin shift between fit and new half: {shift.tolist()} rad; rms error "
          f"{circular_rms(new, truth[..., half:]).tolist()}")
    assert shift.abs().max() < 0.03
    assert circular_rms(new, truth[..., half:]).max() < 0.08
    # a different number of channels is refused with the counts named
    with pytest.raises(ValueError, match="fitted to 2 channels, x has 1"):
        fitted.transform(r[..., :1])


def test_the_phase_stage_phases_padded_trials_over_their_own_spans():
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=8,
                    seeds=np.arange(2))
    r = traj.r.clone()
    r[1, -100:] = float("nan")  # the second trial ended earlier (padding on a shared grid)
    fitted = Phaser().fit(r)
    assert torch.isnan(fitted.phase_[1, -100:]).all()
    torch.testing.assert_close(fitted.phase_[1, :-100], estimate_phase(r[1, :-100]),
                               rtol=0, atol=0)
    torch.testing.assert_close(fitted.phase_[0], estimate_phase(r[0]), rtol=0, atol=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = fitted.transform(r)
    torch.testing.assert_close(again, fitted.phase_, rtol=0, atol=1e-12, equal_nan=True)


@dataclasses.dataclass(frozen=True, kw_only=True)
class _TruthSmoother(Smoother):
    """A user's own smoothing stage: the simulation's noise-free state (tests only)."""

    def smooth(self, traj):
        g = traj.truth
        return traj.with_fields(smoothed=SmoothedState(pose=g.pose, pose_dot=g.pose, r=g.r,
                                                       r_dot=g.r_dot, xi=g.xi))


def test_a_new_stage_slots_in_by_keyword(recording):
    est = ConnectionEstimator(smoother=_TruthSmoother(), metric=TiedMetric(enabled=False),
                              regression=TubeRegression(n_bins=24, fourier_order=6))
    est.fit(recording)
    assert est.trajectory_.smoothed.xi is recording.truth.xi
    settings = estimator_settings(est)
    assert settings["smoother"]["method"].endswith("_TruthSmoother")
    # exact velocities beat the RTS smoother's on this noisy recording (same regression)
    default = ConnectionEstimator(regression=est.regression).fit(recording)

    def error(e):
        b = e.model_.bins
        A_true = NLinkSwimmer(3).connection(b.gamma)
        return float((b.A - A_true).norm() / A_true.norm())

    print(f"relative RMS error of A: truth smoother {error(est):.4f}, RTS {error(default):.4f}")
    assert error(est) < 0.05 and error(est) < 0.5 * error(default)
