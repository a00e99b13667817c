"""The held-out check's baselines (the physics reference, zero) and its forward-in-time
split: the fit without the last block of cycles scored on it."""

import json
import warnings

import numpy as np
import pytest
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, TubeRegression, simulate
from torchconn.fit import main
from torchconn.io.trajectory_files import write_csv
from torchconn.phase.fourier import fit_fourier
from torchconn.physics.gaits import reference_gait
from torchconn.regression.reference import fit_reference
from torchconn.regression.selection import skill
from torchconn.simulation.observe import observe

F64 = torch.float64
K = 4.0  # the simulated swimmer's drag ratio (the default is 2)


def _recording(n_cycles: int, seeds, omega: float = 0.0):
    clean = simulate(NLinkSwimmer(3, drag_ratio=K), reference_gait("3link"), eta=0.025,
                     n_cycles=n_cycles, samples_per_cycle=64, seeds=np.asarray(seeds))
    return observe(clean, omega, seeds=np.asarray(seeds))


@pytest.fixture(scope="module")
def fitted():
    """Two trials of 9 cycles without jitter, one model per trial, the given complexity and
    no physics prior (the forecasting model is the fit itself); and 4 later cycles of the
    same trials."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = ConnectionEstimator(regression=TubeRegression(n_bins=24, fourier_order=6),
                                  complexity="fixed", prior=None).fit(_recording(9, [1, 2]))
    return est, _recording(4, [11, 12])


def _r2(y, pred):
    """R² per component of predictions of samples ``y (N, 3)``, computed directly."""
    return 1 - (y - pred).square().sum(0) / (y - y.mean(0)).square().sum(0)


def test_zero_baseline_is_one_minus_the_sum_of_squares_over_sst(fitted):
    est, later = fitted
    scored = est.score(later)
    view = skill.regression_view(est._prepare_new(later, None), est.regression_,
                                 est.forecast_model_, pool=False)
    for b in range(2):
        ok = torch.isfinite(view.phase[b]) & torch.isfinite(view.xi[b]).all(-1)
        y = view.xi[b, ok]
        expected = 1 - y.square().sum(0) / (y - y.mean(0)).square().sum(0)
        torch.testing.assert_close(scored.r2_zero[b], expected, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(scored.r2_zero[b], _r2(y, torch.zeros_like(y)),
                                   rtol=1e-10, atol=1e-12)
    # the held-out check's zero baseline likewise, and it never beats the model here
    for s in (est.held_out_skill_, est.forward_skill_):
        assert bool((s.r2_zero < s.r2).all())


def test_physics_reference_fits_the_drag_ratio_and_predicts_clean_data(fitted):
    est, later = fitted
    ref = est.reference_
    assert ref.frame == "center" and ref.n_links == 3
    k = ref.parameters["drag_ratio"]
    assert k.shape == (2,)  # one per trial: the fit is not pooled
    torch.testing.assert_close(k, torch.full((2,), K, dtype=F64), rtol=0.03, atol=0)
    for s in (est.held_out_skill_, est.forward_skill_, est.score(later)):
        assert s.r2_physics.shape == (2, 3)
        assert bool((s.r2_physics > 0.99).all()), s.r2_physics


def test_forward_skill_is_the_last_block_scored_by_the_fit_without_it(fitted):
    est, _ = fitted
    traj, reg, model = est.trajectory_, est.regression_, est.forecast_model_
    _, models, view, fold, _ = skill.fold_models(traj, est.limit_cycle_, reg, model,
                                                 pool=False, n_folds=3, refit=False)
    time = torch.arange(fold.shape[-1])
    for b in range(2):
        last, train = fold[b] == 2, (fold[b] >= 0) & (fold[b] < 2)
        # every training sample comes before every scored one
        assert int(time[train].max()) < int(time[last].min())
        ok = last & torch.isfinite(view.phase[b]) & torch.isfinite(view.xi[b]).all(-1)
        phase, r, r_dot, y = view.phase[b, ok], view.r[b, ok], view.r_dot[b, ok], view.xi[b, ok]
        pred = models[2].predict(phase[None], r[None], r_dot[None])[b]
        torch.testing.assert_close(est.forward_skill_.r2[b], _r2(y, pred), rtol=1e-9,
                                   atol=1e-12)
        # the phase average of the earlier blocks
        fit_ok = train & torch.isfinite(view.phase[b])
        base = fit_fourier(view.phase[b, fit_ok], view.xi[b, fit_ok], reg.fourier_order,
                           value_ndim=1)
        torch.testing.assert_close(est.forward_skill_.r2_phase_average[b],
                                   _r2(y, base(phase)), rtol=1e-9, atol=1e-12)
        # the physics reference fitted on the earlier blocks
        ref = fit_reference(view.r[b, fit_ok], view.r_dot[b, fit_ok], view.xi[b, fit_ok])
        torch.testing.assert_close(est.forward_skill_.r2_physics[b],
                                   _r2(y, ref.predict(r, r_dot)), rtol=1e-9, atol=1e-12)
        assert float(est.forward_skill_.n_samples[b]) == int(ok.sum())
    # the estimator's own cross_validate gives the same, and the interleaved check is the
    # one it always gave
    again = est.cross_validate(3, forward=True)
    assert torch.equal(again.r2, est.forward_skill_.r2)
    torch.testing.assert_close(again.r2_physics, est.forward_skill_.r2_physics)
    assert torch.equal(est.cross_validate(3).r2, est.held_out_skill_.r2)


def test_no_check_fits_no_reference_until_score(fitted):
    est, later = fitted
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        off = ConnectionEstimator(regression=TubeRegression(n_bins=24, fourier_order=6),
                                  complexity="fixed", held_out_folds=0).fit(est.trajectory_)
    assert off.held_out_skill_ is None and off.forward_skill_ is None
    assert off.reference_ is None
    scored = off.score(later)
    assert off.reference_ is not None and bool((scored.r2_physics > 0.99).all())


def test_fit_json_and_summary_carry_the_baselines(tmp_path, capsys):
    path = tmp_path / "trials.csv"
    write_csv(_recording(9, [5]), path)
    out = tmp_path / "fit"
    assert main([str(path), "--links", "3", "--out", str(out), "--no-figures",
                 "--complexity", "fixed", "--n-bins", "24", "--fourier-order", "6"]) == 0
    text = capsys.readouterr().out
    assert "How well it predicts cycles it did not see" in text
    assert "this model, later cycles only" in text
    assert "Physics: the 3-link viscous swimmer" in text and "drag ratio" in text
    sidecar = json.loads((out / "fit.json").read_text())
    held = sidecar["held_out"]
    assert held["folds"] == 3
    for split in ("interleaved", "forward"):
        assert set(held[split]) == {"v_x", "v_y", "omega"}
        for component in held[split].values():
            assert set(component) == {"model", "phase_average", "physics", "zero"}
            assert all(isinstance(v, float) for v in component.values())
    ref = sidecar["reference"]
    assert ref["family"] == "swimmer" and ref["frame"] == "center" and ref["n_links"] == 3
    assert abs(ref["parameters"]["drag_ratio"] / K - 1) < 0.03
    # the existing summary stays, with the same model R²
    assert [held["interleaved"][c]["model"] for c in ("v_x", "v_y", "omega")] == \
        sidecar["held_out_skill"]["model"]
