"""The physics reference (regression/reference.py): its drag ratio fitted to clean simulated
swimmers, its predictions against the simulator's, and its first-order local model."""

import math

import numpy as np
import pytest
import torch

from torchconn import ConnectionEstimator, NLinkSwimmer, TubeRegression, observe, simulate
from torchconn.physics.gaits import FourierGait
from torchconn.regression.reference import PhysicsReference, default_frame, fit_reference

F64 = torch.float64


def _gait(radius: float = 0.8) -> FourierGait:
    """A 3-link circle-like gait, first harmonic only."""
    coeffs = torch.zeros(3, 2, dtype=F64)
    coeffs[1] = torch.tensor([radius, 0.0], dtype=F64)
    coeffs[2] = torch.tensor([0.0, radius], dtype=F64)
    return FourierGait(coeffs)


def _clean(k: float, n_trials: int = 1):
    """The noise-free shapes, rates and body velocity of a 3-link swimmer of drag ratio ``k``
    whose gait wanders (η = 0.1), 3 cycles at 64 samples per cycle."""
    traj = simulate(NLinkSwimmer(3, drag_ratio=k), _gait(), eta=0.1, n_cycles=3,
                    samples_per_cycle=64, seeds=np.arange(n_trials))
    t = traj.truth
    return t.r, t.r_dot, t.xi


@pytest.mark.parametrize("k", [2.0, 5.0])
def test_the_drag_ratio_of_a_clean_swimmer_is_recovered(k):
    r, r_dot, xi = _clean(k)
    ref = fit_reference(r, r_dot, xi)
    assert ref.family == "swimmer" and ref.frame == "center" and ref.n_links == 3
    assert ref.parameters["drag_ratio"].shape == (1,)
    assert abs(float(ref.parameters["drag_ratio"][0]) / k - 1) < 0.02
    pooled = fit_reference(r, r_dot, xi, pool=True)
    assert pooled.parameters["drag_ratio"].shape == ()
    assert abs(float(pooled.parameters["drag_ratio"]) / k - 1) < 0.02


def test_one_drag_ratio_per_trial_unless_pooled():
    """Two trials of different swimmers stacked: each gets its own drag ratio."""
    parts = [_clean(k) for k in (2.0, 5.0)]
    r, r_dot, xi = (torch.cat(x) for x in zip(*parts, strict=True))
    fitted = fit_reference(r, r_dot, xi).parameters["drag_ratio"]
    torch.testing.assert_close(fitted, torch.tensor([2.0, 5.0], dtype=F64), rtol=0.02, atol=0)


def test_predict_is_the_swimmer_s_body_velocity_and_nan_stays_nan():
    r, r_dot, _ = _clean(3.0)
    ref = PhysicsReference("swimmer", "center", 3, {"drag_ratio": torch.tensor([3.0],
                                                                                 dtype=F64)})
    exact = NLinkSwimmer(3, drag_ratio=3.0).body_velocity(r, r_dot)
    torch.testing.assert_close(ref.predict(r, r_dot), exact, rtol=1e-12, atol=1e-14)
    r = r.clone()
    r[0, 5, 1] = math.nan
    pred = ref.predict(r, r_dot)
    assert bool(pred[0, 5].isnan().all())
    keep = torch.ones(r.shape[1], dtype=torch.bool)
    keep[5] = False
    torch.testing.assert_close(pred[0, keep], exact[0, keep], rtol=1e-12, atol=1e-14)


def test_nan_samples_are_skipped_by_the_fit():
    r, r_dot, xi = _clean(5.0)
    r = r.clone()
    r[:, ::3] = math.nan  # a third of the samples missing
    k = float(fit_reference(r, r_dot, xi).parameters["drag_ratio"][0])
    assert abs(k / 5.0 - 1) < 0.02


def test_unknown_family_and_too_few_samples_are_refused():
    r, r_dot, xi = _clean(2.0)
    with pytest.raises(ValueError, match="unknown reference family 'fish'.*swimmer"):
        fit_reference(r, r_dot, xi, family="fish")
    with pytest.raises(ValueError, match="usable samples"):
        fit_reference(torch.full_like(r, math.nan), r_dot, xi)


def test_default_frame():
    assert default_frame(3) == "center" and default_frame(4) == "com-mean"


def test_local_model_is_exact_to_second_order_in_the_offsets():
    """On samples ``γ(φ) + εu``, ``γ̇(φ) + εv`` around a fitted cycle the reference's local
    model misses the exact body velocity by ``O(ε²)`` (halving ε about quarters the error:
    its first-order part is exact), and on the cycle it is exact up to the Fourier series'
    interpolation between bins."""
    system = NLinkSwimmer(3, drag_ratio=3.0)
    traj = simulate(system, _gait(), eta=0.05, n_cycles=10, samples_per_cycle=64,
                    seeds=np.arange(1))
    est = ConnectionEstimator(regression=TubeRegression(n_bins=32, fourier_order=6),
                              complexity="fixed", held_out_folds=0)
    est.set_params(metric__enabled=False)
    model = est.fit(observe(traj, 0.001, seeds=np.arange(1)), phase=traj.truth.phase).model_
    ref = PhysicsReference("swimmer", "center", 3, {"drag_ratio": torch.tensor([3.0],
                                                                                 dtype=F64)})
    local = ref.local_model(model)
    assert local.meta["reference"] == ref.describe()
    phi = torch.linspace(0, 2 * math.pi, 200, dtype=F64)[None]
    u = torch.stack([torch.cos(3 * phi), torch.sin(2 * phi)], -1)
    v = torch.stack([torch.sin(phi), -torch.cos(2 * phi)], -1)

    def error(eps: float, order: int = 1) -> float:
        r, r_dot = model.gamma_at(phi) + eps * u, model.gamma_dot_at(phi) + eps * v
        exact = system.body_velocity(r, r_dot)
        pred = local.predict(phi, r, r_dot) if order else local.c(phi)
        return float((pred - exact).abs().max())

    scale = float(system.body_velocity(model.gamma_at(phi), model.gamma_dot_at(phi)).abs().max())
    assert error(0.0) < 1e-4 * scale
    ratio = error(0.2) / error(0.1)
    assert 3.3 < ratio < 4.6, ratio
    # the cycle's velocity alone (ĉ) misses by O(ε): the offset terms are what is exact
    assert error(0.1, order=0) > 20 * error(0.1)
