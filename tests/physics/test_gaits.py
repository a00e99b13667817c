"""Gait displacement, cost, efficiency and the optimiser, checked against independent integration."""

import math

import numpy as np
import pytest
import torch

from torchconn import NLinkSwimmer
from torchconn.physics.gaits import (
    CallableGait,
    ModalGait,
    displacement,
    evaluate,
    nine_link_modes,
    optimised_gait,
    reference_gait,
    three_link_gait,
)
from torchconn.physics.gaits.optimize import optimise_gait
from torchconn.physics.gaits.reference import load_gaits
from torchconn.testing.numpy_swimmer import connection_and_metric_numpy

F64 = torch.float64


def _rk4_numpy(gait, n_links, n=4000):
    """Independent integration: classic RK4 of (x, y, θ) with the NumPy reference connection,
    plus a trapezoid rule for the cost (spectrally accurate for smooth periodic integrands)."""
    lengths = np.full(n_links, 1 / n_links)

    def rhs(t, q):
        phi = torch.tensor(t, dtype=F64)
        r, rd = gait(phi).numpy(), gait.velocity(phi).numpy()
        a, _ = connection_and_metric_numpy(r, lengths)
        xi = a @ rd
        c, s = math.cos(q[2]), math.sin(q[2])
        return np.array([c * xi[0] - s * xi[1], s * xi[0] + c * xi[1], xi[2]])

    h = 2 * math.pi / n
    q = np.zeros(3)
    for k in range(n):
        t = k * h
        k1 = rhs(t, q)
        k2 = rhs(t + h / 2, q + h / 2 * k1)
        k3 = rhs(t + h / 2, q + h / 2 * k2)
        k4 = rhs(t + h, q + h * k3)
        q = q + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    cost = 0.0
    for k in range(n):
        phi = torch.tensor(k * h, dtype=F64)
        r, rd = gait(phi).numpy(), gait.velocity(phi).numpy()
        _, m = connection_and_metric_numpy(r, lengths)
        cost += h * math.sqrt(rd @ m @ rd)
    return q, cost


def test_reference_gait_displacement_and_cost_match_independent_integration():
    gait = three_link_gait("extremal")
    metrics = evaluate(NLinkSwimmer(3), gait)
    q, cost = _rk4_numpy(gait, 3, n=1000)
    assert np.abs(metrics.displacement.numpy() - q).max() < 1e-6
    assert metrics.cost.item() == pytest.approx(cost, rel=1e-6)
    assert metrics.efficiency.item() == pytest.approx(np.hypot(q[0], q[1]) / cost, rel=1e-6)


def test_displacement_converges_at_fourth_order():
    s, gait = NLinkSwimmer(3), three_link_gait()
    truth = displacement(s, gait, 4096)
    ns = np.array([16, 32, 64, 128])
    errs = [float((displacement(s, gait, int(n)) - truth).norm()) for n in ns]
    slope = np.polyfit(np.log(ns), np.log(errs), 1)[0]
    assert -4.5 < slope < -3.5
    assert float((displacement(s, gait) - truth).norm()) < 1e-8


def test_time_reversal_reverses_the_displacement():
    s = NLinkSwimmer(3)
    fwd = displacement(s, three_link_gait("efficient"))
    back = displacement(s, three_link_gait("efficient").reversed())
    # running the loop backwards undoes it: g_back = g_fwd^{-1}
    from torchconn.physics import se2

    assert torch.allclose(back, se2.inverse(fwd), atol=1e-9)
    assert fwd[0] > 0 > back[0]


def test_efficient_gait_is_more_efficient_than_extremal():
    s = NLinkSwimmer(3)
    ext, eff = evaluate(s, three_link_gait("extremal")), evaluate(s, three_link_gait("efficient"))
    assert ext.displacement[0] > eff.displacement[0]
    assert eff.efficiency > ext.efficiency


def test_holonomy_small_loops_approach_curvature_times_area():
    s = NLinkSwimmer(5)
    r0 = torch.tensor([0.3, -0.2, 0.5, 0.1], dtype=F64)
    da = s.curvature(r0)[:, 4]  # pair (r2, r4): the 5th of the lexicographic pairs
    eps = np.array([0.2, 0.1, 0.05, 0.025])
    errs = []
    for e in eps:
        def loop(phi, e=float(e)):
            z = torch.zeros_like(phi)
            return r0 + torch.stack([z, e * torch.cos(phi), z, e * torch.sin(phi)], -1)

        d = displacement(s, CallableGait(loop, 4), 256)
        errs.append(float((d - da * math.pi * e * e).norm()))
    slope = np.polyfit(np.log(eps), np.log(errs), 1)[0]
    # the displacement is DA·area + O(ε³): the error falls faster than the area (ε²)
    assert slope > 2.5


def test_stored_optimised_gaits_are_what_they_claim():
    table = load_gaits()
    s3, s9 = NLinkSwimmer(3), NLinkSwimmer(9)
    g3 = optimised_gait("three_link_x_extremal")
    x3 = evaluate(s3, g3, 512).displacement[0].item()
    assert x3 == pytest.approx(table["three_link_x_extremal"]["x_displacement"], rel=1e-8)
    assert x3 >= evaluate(s3, three_link_gait(), 512).displacement[0].item()
    g9 = reference_gait("9link")
    x9 = evaluate(s9, g9, 512).displacement[0].item()
    assert x9 == pytest.approx(table["nine_link_x_extremal"]["x_displacement"], rel=1e-8)
    assert g9(torch.zeros(3, dtype=F64)).shape == (3, 8)


def test_optimiser_reaches_a_stationary_extremal_gait():
    s = NLinkSwimmer(9)
    run = optimise_gait(s, modes=nine_link_modes(), order=2, radius=0.5, max_radius=math.pi / 2)
    start = displacement(s, optimise_gait(s, modes=nine_link_modes(), order=2, radius=0.5,
                                          max_radius=math.pi / 2, max_iter=1).gait)[0]
    assert run.x_displacement > start.item()
    # first-order optimality: the gradient of the x-displacement w.r.t. the loop vanishes
    plane = run.gait.plane_gait
    logit = plane.logit.coeffs[:, 0].clone().requires_grad_(True)
    from torchconn.physics.gaits import PolarGait

    g = ModalGait(nine_link_modes(), PolarGait([0.0, 0.0], logit, plane.direction, plane.max_radius))
    displacement(s, g, 128)[0].backward()
    assert logit.grad.abs().max() < 1e-5


def test_gait_with_wrong_dimension_raises():
    with pytest.raises(ValueError, match="gait has 2 joints but the system has 8"):
        evaluate(NLinkSwimmer(9), three_link_gait())
