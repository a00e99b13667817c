"""The physics prior: its weight against closed forms, the blend, and the estimator's use."""

import math
import warnings

import numpy as np
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, observe, simulate
from torchconn.physics.gaits import reference_gait
from torchconn.regression.reference import PhysicsReference
from torchconn.regression.selection import blend, forward_checked, prior_weights

F64 = torch.float64


def _predictions(sd_fit: float, sd_ref: float, n: int = 1200, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    truth = torch.randn(n, 3, generator=g, dtype=F64)
    fitted = truth + sd_fit * torch.randn(n, 3, generator=g, dtype=F64)
    reference = truth + sd_ref * torch.randn(n, 3, generator=g, dtype=F64)
    return truth, fitted, reference, torch.arange(n) // 40


def test_the_weight_is_the_blends_least_squares_weight():
    # independent errors of variances s_f², s_r²: the best blend weight is s_f²/(s_f² + s_r²)
    y, fitted, reference, cycle = _predictions(0.5, 0.25)
    w = prior_weights(y, fitted, reference, cycle)
    assert torch.allclose(w, torch.full((3,), 0.25 / (0.25 + 0.0625), dtype=F64), atol=0.05)
    e, d = y - fitted, reference - fitted
    torch.testing.assert_close(w, ((e * d).sum(0) / (d * d).sum(0)).clamp(0, 1))


def test_no_weight_where_the_reference_does_not_clearly_help():
    y, fitted, reference, cycle = _predictions(0.05, 1.0)
    assert bool((prior_weights(y, fitted, reference, cycle) == 0).all())
    # a reference that is the truth takes all the weight
    y, fitted, _, cycle = _predictions(0.5, 0.0)
    torch.testing.assert_close(prior_weights(y, fitted, y, cycle),
                               torch.ones(3, dtype=F64))
    # unscored samples (NaN, no cycle) do not count
    y[:600] = math.nan
    assert bool((prior_weights(y, fitted, y, cycle) == 1).all())


def test_the_reference_is_delivered_where_it_wins_on_both_checks():
    # the reference predicts better than the blend at weight 0.3 everywhere (sd 0.1 vs 0.5)
    y, fitted, reference, cycle = _predictions(0.5, 0.1)
    forward = cycle >= 20  # the last third of the 30 cycles
    weight = torch.full((3,), 0.3, dtype=F64)
    torch.testing.assert_close(forward_checked(weight, y, fitted, reference, forward),
                               torch.ones(3, dtype=F64))
    # where it loses on the forward block (there it is off by 3 on v_x), the weight stays
    reference[forward, 0] += 3.0
    got = forward_checked(weight, y, fitted, reference, forward)
    assert float(got[0]) == 0.3 and bool((got[1:] == 1).all())
    # and where the blend already wins on both, nothing changes
    torch.testing.assert_close(forward_checked(weight, y, y, reference, forward), weight)


def test_blend_mixes_each_components_rows():
    seeds = np.arange(2)
    traj = simulate(NLinkSwimmer(3), reference_gait("3link"), eta=0.025, n_cycles=10,
                    seeds=seeds)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ConnectionEstimator(pool=True, held_out_folds=0).set_params(
            metric__enabled=False).fit(traj).model_
    other = NLinkSwimmer(3, drag_ratio=3.0)
    ref = PhysicsReference("swimmer", "center", 3, {"drag_ratio": torch.tensor(3.0)})
    local = ref.local_model(model)
    weight = torch.tensor([0.0, 0.5, 1.0], dtype=F64)
    mixed = blend(model, local, weight)
    phi = torch.linspace(0, 2 * math.pi, 17, dtype=F64)[:-1]
    a, b, m = model.connection(phi), local.connection(phi), mixed.connection(phi)
    torch.testing.assert_close(m[..., 0, :], a[..., 0, :])
    torch.testing.assert_close(m[..., 1, :], 0.5 * (a[..., 1, :] + b[..., 1, :]))
    torch.testing.assert_close(m[..., 2, :], b[..., 2, :])
    # the reference along the cycle, to the truncation of its order-12 series
    torch.testing.assert_close(local.connection(phi), other.connection(model.gamma_at(phi)),
                               atol=1e-5, rtol=0)
    assert blend(model, local, torch.zeros(3, dtype=F64)) is model


def test_the_estimator_shrinks_the_forecasts_of_a_short_noisy_recording():
    # 8 cycles at 16 samples per cycle of the prior's own family: the reference (the
    # simulator, drag ratio fitted) predicts held-out cycles better than the fitted model
    seeds = np.arange(1)
    swimmer = NLinkSwimmer(3)
    traj = observe(simulate(swimmer, reference_gait("3link"), eta=0.025, n_cycles=8,
                            samples_per_cycle=16, seeds=seeds), 0.005, seeds=seeds)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = ConnectionEstimator().set_params(metric__enabled=False).fit(traj)
        plain = ConnectionEstimator(prior=None).set_params(metric__enabled=False).fit(traj)
    w = est.prior_weight_
    assert w.shape == (1, 3) and bool(((w >= 0) & (w <= 1)).all()) and bool((w > 0).any())
    assert plain.prior_weight_ is None
    assert est.model_.meta["forecast_model"]["prior_weight"] == w.tolist()
    assert est.forecast_model_ is not est.model_
    # the delivered forecasts predict held-out cycles at least as well as the model alone
    assert bool((est.held_out_skill_.r2 >= plain.held_out_skill_.r2 - 1e-12).all())
    # the connection model is kept as estimated
    assert "prior_weight" not in (est.model_.meta or {})
    for name in ("c", "b", "A", "dA"):
        assert torch.equal(getattr(est.model_, name).coeffs,
                           getattr(plain.model_, name).coeffs), name
