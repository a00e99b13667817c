import math

import numpy as np
import pytest
import torch

from torchconn.physics import se2

torch.manual_seed(0)


def _rand(*shape):
    return torch.randn(*shape, 3, dtype=torch.float64)


def test_exp_matches_matrix_exponential():
    xi = _rand(5, 4)
    expected = torch.linalg.matrix_exp(se2.hat(xi))
    assert torch.allclose(se2.to_matrix(se2.exp(xi)), expected, atol=1e-12)


def test_exp_log_round_trip_including_small_rotations():
    xi = _rand(100)
    xi[:10, 2] = torch.logspace(-12, -5, 10, dtype=torch.float64)
    xi[:, 2] = se2.wrap_angle(xi[:, 2])
    assert torch.allclose(se2.log(se2.exp(xi)), xi, atol=1e-12)


def test_compose_inverse_and_matrix_forms_agree():
    g, h = _rand(7), _rand(7)
    gh = se2.to_matrix(se2.compose(g, h))
    assert torch.allclose(gh, se2.to_matrix(g) @ se2.to_matrix(h), atol=1e-12)
    eye = se2.to_matrix(se2.compose(g, se2.inverse(g)))
    assert torch.allclose(eye, torch.eye(3, dtype=torch.float64).expand(7, 3, 3), atol=1e-12)


def test_adjoint_and_bracket_definitions():
    g, xi, eta = _rand(6), _rand(6), _rand(6)
    G = se2.to_matrix(g)
    lhs = G @ se2.hat(xi) @ torch.linalg.inv(G)
    assert torch.allclose(lhs, se2.hat((se2.adjoint(g) @ xi[..., None])[..., 0]), atol=1e-12)
    comm = se2.hat(xi) @ se2.hat(eta) - se2.hat(eta) @ se2.hat(xi)
    assert torch.allclose(se2.vee(comm), se2.bracket(xi, eta), atol=1e-12)


def test_integrate_constant_velocity_is_exact():
    xi = torch.tensor([0.3, -0.1, 0.7], dtype=torch.float64)
    steps = xi.expand(50, 3)
    for method in ("exp", "midpoint"):
        poses = se2.integrate(steps, 0.02, method=method)
        n = poses.shape[-2] - 1
        assert torch.allclose(poses[-1], se2.exp(xi * 0.02 * n), atol=1e-12)


def test_midpoint_integration_is_second_order():
    def xi_of(t):
        return torch.stack([1 + 0.5 * torch.sin(t), 0.3 * torch.cos(2 * t), torch.cos(t)], -1)

    def final(n, method):
        t = torch.linspace(0, 2, n + 1, dtype=torch.float64)
        return se2.integrate(xi_of(t), 2 / n, method=method)[-1]

    truth = final(2**15, "midpoint")
    ns = np.array([50, 100, 200, 400])
    errs = [float((final(int(n), "midpoint") - truth).norm()) for n in ns]
    slope = np.polyfit(np.log(ns), np.log(errs), 1)[0]
    assert -2.3 < slope < -1.7


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"xi must have shape \(\.\.\., 3\)"):
        se2.exp(torch.zeros(4, 2))
    with pytest.raises(ValueError, match="method"):
        se2.integrate(torch.zeros(3, 3), 0.1, method="rk4")


def test_wrap_angle_range():
    a = torch.linspace(-20, 20, 101, dtype=torch.float64)
    w = se2.wrap_angle(a)
    assert (w >= -math.pi).all() and (w < math.pi).all()
    assert torch.allclose(torch.sin(w), torch.sin(a), atol=1e-12)
