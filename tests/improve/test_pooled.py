"""One model from every gait recorded: distance weights, online additions, phase alignment,
several gaits in one model, excitation and the loop's steps."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from torchconn import NLinkSwimmer, simulate
from torchconn.improve import (
    LoopSettings,
    PooledConnection,
    circle_gait,
    excitation_gait,
    gait_recording,
    improve,
)
from torchconn.improve.pooled import aligned_recording, clock_phase, gait_distance
from torchconn.phase.fourier import FourierSeries
from torchconn.phase.smoothing import RTSSmoother
from torchconn.physics.gaits import FourierGait
from torchconn.simulation import observe

from ..regression.test_online import numpy_fit

M, WINDOW = 16, 1.5  # the bins numpy_fit uses: PooledConnection's defaults


def record(radius, seed, cycles=4, eta=0.025):
    gait = circle_gait(2, radius)
    traj = simulate(NLinkSwimmer(3), gait, eta=eta, n_cycles=cycles, seeds=np.array([seed]))
    return gait, traj


@pytest.fixture(scope="module")
def three_gaits():
    """Recordings of circles of radius 0.45, 0.55 and 0.65 (4 cycles each, 3-link)."""
    return [gait_recording(traj, gait, 4)
            for gait, traj in (record(a, s) for a, s in ((0.45, 0), (0.55, 1), (0.65, 2)))]


def test_gait_distance_of_concentric_circles_is_their_radii_difference():
    assert gait_distance(circle_gait(2, 0.4), circle_gait(2, 0.7)) == pytest.approx(0.3, rel=1e-12)
    assert gait_distance(circle_gait(2, 0.4), circle_gait(2, 0.4)) == 0.0


def test_pooled_regression_is_the_distance_weighted_batch_fit(three_gaits):
    """Every bin equals numpy's weighted lstsq on the stacked samples of all recordings, each
    weighted exp(−½ (D/ℓ)²) with D the difference of the circles' radii (closed form)."""
    length = 0.15
    pool = PooledConnection(length=length, ridge=0.0)
    for rec in three_gaits:
        pool.add(rec)
    centre = three_gaits[1].gait
    got = pool.online(centre).fit().coef  # (M, P, 3)
    radii = (0.45, 0.55, 0.65)
    weights = [math.exp(-0.5 * ((a - 0.55) / length) ** 2) for a in radii]
    stack = [torch.cat([getattr(rec, f) for rec in three_gaits])
             for f in ("phase", "r", "r_dot", "xi")]
    w = torch.cat([torch.full_like(rec.phase, wt) for rec, wt in zip(three_gaits, weights,
                                                                     strict=True)])
    centres = torch.arange(M, dtype=torch.float64) * (2 * math.pi / M)
    series = FourierSeries(centre.coeffs, 1)
    want = numpy_fit(series(centres), series.derivative()(centres), *stack, w)
    err = np.linalg.norm((got.numpy() - want).reshape(M, -1), axis=-1)
    assert np.all(err <= 1e-8 * np.linalg.norm(want.reshape(M, -1), axis=-1))


def test_adding_a_recording_online_equals_pooling_it_from_the_start(three_gaits):
    centre = three_gaits[1].gait
    online = PooledConnection()
    for rec in three_gaits[:2]:
        online.add(rec)
    online.online(centre)  # centred: the next recording is an update of the sums
    confidence = online.add(three_gaits[2])
    assert confidence is not None and confidence.cycle == 3
    batch = PooledConnection()
    for rec in three_gaits:
        assert batch.add(rec) is None  # no centre yet: nothing solved until asked
    a, b = online.online(centre).fit().coef, batch.online(centre).fit().coef
    torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    assert online.cycles == 12


def test_one_model_predicts_each_of_three_gaits(three_gaits):
    """A model pooled over three gaits predicts the body velocity of a fresh recording of
    each (R² ≥ 0.8 on every component), where the model of the middle gait alone, stretched
    to the outer gaits, does worse."""
    pooled, alone = PooledConnection(length=None), PooledConnection()
    for rec in three_gaits:
        pooled.add(rec)
    alone.add(three_gaits[1])
    centre = three_gaits[1].gait
    models = {"pooled": pooled.model(centre), "alone": alone.model(centre)}
    for radius, seed in ((0.45, 10), (0.55, 11), (0.65, 12)):
        gait, traj = record(radius, seed)
        fresh = gait_recording(traj, gait, 4)
        r2 = {}
        for name, model in models.items():
            pred = model.predict(fresh.phase, fresh.r, fresh.r_dot)
            resid = (fresh.xi - pred).square().sum(0)
            r2[name] = 1 - resid / (fresh.xi - fresh.xi.mean(0)).square().sum(0)
        assert bool((r2["pooled"] >= 0.8).all()), (radius, r2)
        if radius != 0.55:
            assert float(r2["pooled"].mean()) > float(r2["alone"].mean()), (radius, r2)


def test_aligned_recording_finds_the_phase_offset_of_another_estimate():
    """A noise-free recording phased 1 rad ahead of the centre's phase is shifted back by
    1 rad (to the grid's 2π/256) and its cycle is the centre's."""
    gait, traj = record(0.55, 3, cycles=6, eta=0.0)
    shifted = traj.with_fields(phase=clock_phase(traj, 1.0))
    prepared = gait_recording(traj, gait, 6)  # smoothed samples, clock phase
    rec = aligned_recording(RTSSmoother().smooth(shifted), FourierSeries(gait.coeffs, 1))
    offset = float((rec.phase - prepared.phase).nanmean())  # 0 when aligned to the clock
    assert abs((offset + math.pi) % (2 * math.pi) - math.pi) <= math.pi / 256
    assert gait_distance(rec.gait, gait) < 0.01
    with pytest.raises(ValueError, match="must be prepared"):
        aligned_recording(traj, FourierSeries(gait.coeffs, 1))


def test_standard_errors_are_inflated_for_correlated_residuals():
    """Under motion-capture noise the smoothed residuals are correlated over several samples:
    the bins' standard errors grow by the factor, the estimates stay."""
    gait, traj = record(0.55, 1)
    pool = PooledConnection()
    pool.add(gait_recording(observe(traj, 0.005, seeds=np.array([5])), gait, 4))
    model = pool.model(gait)
    raw = pool.online(gait).model()
    factor = torch.tensor(model.meta["se_inflation"], dtype=torch.float64)
    assert bool((factor >= 1).all()) and float(factor.max()) > 1.5
    torch.testing.assert_close(model.bins.A_se, raw.bins.A_se * factor[:, None])
    torch.testing.assert_close(model.bins.A, raw.bins.A)


def test_excitation_moves_the_least_known_joints_by_the_peak_asked(three_gaits):
    pool = PooledConnection()
    pool.add(three_gaits[1])
    gait = three_gaits[1].gait
    model = pool.model(gait)
    phi = torch.linspace(0, 2 * math.pi, 512, dtype=torch.float64)
    out = excitation_gait(model, gait, 0.2, seed=0)
    eps = out(phi) - gait(phi)
    assert float(torch.linalg.vector_norm(eps, dim=-1).max()) == pytest.approx(0.2, rel=1e-3)
    assert torch.equal(out.coeffs[0], gait.coeffs[0])  # the first harmonic only
    # a joint whose derivative is known exactly is not perturbed
    dA_se = model.bins.dA_se.clone()
    dA_se[..., 1] = 0
    known = dataclasses.replace(model, bins=dataclasses.replace(model.bins, dA_se=dA_se))
    eps = excitation_gait(known, gait, 0.2, seed=0)(phi) - gait(phi)
    assert float(eps[:, 1].abs().max()) < 1e-12 and float(eps[:, 0].abs().max()) > 0.1


def _loop(**kw):
    return improve(NLinkSwimmer(3), circle_gait(2, 0.5), LoopSettings(seed=0, **kw))


def test_loop_counts_every_cycle_and_never_keeps_a_worse_gait():
    res = _loop(rounds=3)
    assert [r.cycles_used for r in res.rounds] == [3, 6, 9]
    assert res.rounds[0].kind == "start" and res.rounds[0].moved
    kept = [r.kept_true for r in res.rounds]
    assert kept[-1] > 2 * res.start_true
    for r in res.rounds[1:]:
        assert r.kind in ("proposal", "repeat", "excited")
    assert all(b >= a - 1e-3 for a, b in zip(kept, kept[1:], strict=False))


@pytest.mark.parametrize("excitation, kind", [(0.5, "excited"), (0.0, "repeat")])
def test_loop_records_again_until_the_gain_interval_excludes_zero(excitation, kind):
    """At a level whose intervals never exclude zero the loop never moves: it records the
    kept gait again, perturbed (excitation > 0) by the peak asked, or as it is."""
    res = _loop(rounds=2, level=1 - 1e-12, excitation=excitation)
    first, second = res.rounds
    assert not first.moved and second.kind == kind
    phi = torch.linspace(0, 2 * math.pi, 256, dtype=torch.float64)
    peak = float(torch.linalg.vector_norm(second.gait(phi) - first.gait(phi), dim=-1).max())
    if excitation:
        assert second.excitation > 0 and peak == pytest.approx(second.excitation, rel=1e-2)
    else:
        assert second.excitation == 0 and peak == 0
    assert isinstance(second.kept, FourierGait)


def test_excitation_keeps_the_joint_limits(three_gaits):
    """A perturbation that would take a shape past ``shape_bound`` is shrunk until none does."""
    pool = PooledConnection()
    pool.add(three_gaits[1])
    gait = three_gaits[1].gait  # a circle of radius 0.55
    model = pool.model(gait)
    phi = torch.linspace(0, 2 * math.pi, 512, dtype=torch.float64)
    out = excitation_gait(model, gait, 1.0, seed=0, shape_bound=0.8)
    assert float(torch.linalg.vector_norm(out(phi), dim=-1).max()) <= 0.8 + 1e-9
    assert not torch.equal(out.coeffs, gait.coeffs)


def test_loop_records_the_kept_gait_again_until_every_phase_bin_can_be_fitted():
    """The 9-link's 81 regressors per bin need more than one 3-cycle recording: the loop
    proposes nothing (NaN predictions) and records the start again, without failing."""
    res = improve(NLinkSwimmer(9), circle_gait(8, 0.5), LoopSettings(seed=0, rounds=2))
    first, second = res.rounds
    assert not first.moved and math.isnan(first.predicted)
    assert second.kind == "repeat" and second.cycles_used == 6
    assert torch.equal(second.gait.coeffs, first.gait.coeffs)
