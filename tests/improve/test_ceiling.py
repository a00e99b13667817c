"""The ceiling: the best gait of the improvement loop's own family with the true connection."""

import math

import pytest
import torch

from torchconn import NLinkSwimmer
from torchconn.improve import LoopSettings, TrustRegion, ceiling, circle_gait, true_objective
from torchconn.improve.loop import gait_order
from torchconn.improve.propose import objective_value, penalised_objective
from torchconn.improve.truth import _CACHE, _winding_rate
from torchconn.physics.gaits import FourierGait, evaluate

SMALL = dict(peaks=(1.0,), random_starts=0, max_iter=40)


@pytest.fixture(scope="module")
def three_link():
    system = NLinkSwimmer(3)
    settings = LoopSettings()
    return system, settings, ceiling(system, "displacement", settings, **SMALL)


def test_ceiling_is_in_the_loops_family(three_link):
    _, settings, cap = three_link
    assert cap.order == gait_order(settings) == 3  # the change's order (3) > the circle's (1)
    assert cap.gait.coeffs.shape == (2 * cap.order + 1, 2)
    tr = settings.trust_region
    assert cap.peak <= tr.shape_bound * 1.01
    assert abs(float(cap.displacement[2])) <= tr.max_turn * 1.05
    phi = torch.linspace(0, 2 * math.pi, 512, dtype=torch.float64)
    assert bool((_winding_rate(cap.gait.coeffs, phi) > -1e-3).all())  # one winding per period


def _penalised(system, gait, tr):
    """The loop's penalised objective of ``gait`` (256 steps; shapes at 256 phases)."""
    disp = evaluate(system, gait).displacement
    phi = torch.linspace(0, 2 * math.pi, 257, dtype=torch.float64)[:-1]
    return float(penalised_objective(objective_value("displacement", disp, None), disp,
                                     gait(phi), "displacement", tr))


def test_ceiling_beats_the_start_and_random_gaits_of_the_family(three_link):
    """Higher (penalised by the limits, as the loop's proposals are) than the loop's start
    circle, random once-winding gaits of the family and random small changes of itself."""
    system, settings, cap = three_link
    tr = settings.trust_region
    best = _penalised(system, cap.gait, tr)
    assert cap.value > 2 * true_objective(system, circle_gait(2, 0.5), "displacement")
    assert best > _penalised(system, circle_gait(2, 0.5), tr)
    gen = torch.Generator().manual_seed(0)
    phi = torch.linspace(0, 2 * math.pi, 256, dtype=torch.float64)
    checked = 0
    for i in range(30):
        if i % 2:
            coeffs = cap.gait.coeffs + 0.02 * torch.randn(cap.gait.coeffs.shape, generator=gen,
                                                          dtype=torch.float64)
        else:
            coeffs = torch.zeros(2 * cap.order + 1, 2, dtype=torch.float64)
            direction = 1 - 2 * int(torch.randint(2, (1,), generator=gen))
            coeffs[:3] = circle_gait(2, 0.5 + 2.5 * float(torch.rand((), generator=gen)),
                                     direction).coeffs
            coeffs += 0.1 * torch.randn(coeffs.shape, generator=gen, dtype=torch.float64)
        if not bool((_winding_rate(coeffs, phi) >= 0).all()):
            continue
        checked += 1
        assert _penalised(system, FourierGait(coeffs), tr) < best
    assert checked >= 10


def test_ceiling_is_reproducible_and_cached(three_link):
    system, settings, cap = three_link
    assert ceiling(system, "displacement", settings, **SMALL) is cap
    key = next(k for k, v in _CACHE.items() if v is cap)
    del _CACHE[key]
    again = ceiling(NLinkSwimmer(3), "displacement", settings, **SMALL)
    assert again is not cap
    assert torch.equal(again.gait.coeffs, cap.gait.coeffs) and again.value == cap.value


def test_ceiling_follows_the_loops_limits(three_link):
    """A tighter joint limit is another family: a lower ceiling within that limit."""
    system, settings, cap = three_link
    tight = LoopSettings(trust_region=TrustRegion(shape_bound=1.0))
    low = ceiling(system, "displacement", tight, **SMALL)
    assert low.peak <= 1.0 * 1.01
    assert low.value < cap.value


def test_ceiling_rejects_bad_arguments():
    system = NLinkSwimmer(3)
    with pytest.raises(ValueError, match="objective must be one of"):
        ceiling(system, "speed")
    with pytest.raises(ValueError, match="peaks must be positive"):
        ceiling(system, peaks=(-1.0,))
    with pytest.raises(ValueError, match="random_starts are scaled to the largest of peaks"):
        ceiling(system, peaks=())
    with pytest.raises(ValueError, match="no start"):
        ceiling(system, peaks=(), random_starts=0)
    with pytest.raises(ValueError, match="starts must be Fourier gaits of 2 joints"):
        ceiling(system, starts=[circle_gait(4, 0.5)])
    with pytest.raises(TypeError, match="settings must be a LoopSettings"):
        ceiling(system, "displacement", {"rounds": 2})


def test_penalised_objective_charges_the_limits():
    tr = TrustRegion(shape_bound=1.0, max_turn=0.05)
    value = torch.tensor(0.3, dtype=torch.float64)
    inside = torch.full((4, 2), 0.5, dtype=torch.float64)
    straight = torch.tensor([0.3, 0.0, 0.01], dtype=torch.float64)
    assert penalised_objective(value, straight, inside, "displacement", tr) == value
    turning = torch.tensor([0.3, 0.0, 0.15], dtype=torch.float64)
    assert float(penalised_objective(value, turning, inside, "displacement", tr)) == \
        pytest.approx(0.3 - 1e3 * 0.1 ** 2)
    assert penalised_objective(value, turning, inside, "turning", tr) == value
    outside = torch.tensor([[2.0, 0.0], [0.0, 0.0]], dtype=torch.float64)
    assert float(penalised_objective(value, straight, outside, "displacement", tr)) == \
        pytest.approx(0.3 - 1e3 * 1.0 / 2)


def test_ceiling_from_a_given_start_is_a_local_optimum_above_it():
    """``starts=[gait]`` alone: the ascent from the loop's own start gait (the benchmark's
    ceiling) ends above that gait, in the family's order, and is cached by its start."""
    system = NLinkSwimmer(3)
    settings = LoopSettings()
    start = circle_gait(2, 0.5)
    local = ceiling(system, "displacement", settings, starts=[start], peaks=(), random_starts=0,
                    max_iter=40)
    assert local.values == (local.value,)  # one start, one run
    assert local.gait.coeffs.shape == (7, 2)
    assert _penalised(system, local.gait, settings.trust_region) > 2 * _penalised(
        system, start, settings.trust_region)
    other = ceiling(system, "displacement", settings, starts=[circle_gait(2, 0.6)], peaks=(),
                    random_starts=0, max_iter=40)
    assert other is not local
