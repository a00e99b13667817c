"""The N-link swimmer against closed forms, an independent NumPy derivation, and autograd."""

import itertools
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchconn import NLinkSwimmer
from torchconn.discrepancy.simulate import LateralSlipSwimmer
from torchconn.physics import se2
from torchconn.physics.systems import LocomotionSystem
from torchconn.testing.numpy_swimmer import connection_and_metric_numpy

F64 = torch.float64


def test_straight_three_link_closed_forms():
    s = NLinkSwimmer(3)
    r = torch.zeros(2, dtype=F64)
    expected = torch.tensor([[0, 0], [-1 / 18, -1 / 18], [7 / 27, -7 / 27]], dtype=F64)
    assert torch.allclose(s.connection(r), expected, atol=1e-14)
    assert s.curvature(r)[0, 0].item() == pytest.approx(-5 / 243, abs=1e-14)


@pytest.mark.parametrize("n", [3, 5, 9])
@pytest.mark.parametrize("frame", ["center", "com-mean"])
def test_matches_independent_numpy_derivation(n, frame):
    rng = np.random.default_rng(n)
    lengths = rng.uniform(0.5, 1.5, n)
    lengths /= lengths.sum()
    s = NLinkSwimmer(n, drag_ratio=2.7, frame=frame, link_lengths=lengths)
    shapes = rng.normal(scale=0.8, size=(6, n - 1))
    A, M = s.connection_and_metric(torch.tensor(shapes))
    for k, r in enumerate(shapes):
        a_ref, m_ref = connection_and_metric_numpy(r, lengths, 2.7, frame)
        assert np.abs(A[k].numpy() - a_ref).max() < 1e-12
        assert np.abs(M[k].numpy() - m_ref).max() < 1e-12


def test_metric_is_frame_independent_and_connection_obeys_frame_change():
    r = torch.tensor([[0.4, -0.7, 0.2, 0.9], [-1.0, 0.3, 0.5, -0.2]], dtype=F64)
    center, commean = NLinkSwimmer(5), NLinkSwimmer(5, frame="com-mean")
    assert torch.allclose(center.metric(r), commean.metric(r), atol=1e-14)
    # g' = g h(r)  =>  A' = Ad_{h^-1} A + (h^-1 dh/dr)^vee
    h = center.frame_transform(r, "com-mean")
    dh = torch.func.vmap(torch.func.jacfwd(lambda q: center._frame_transform(q, "com-mean")))(r)
    # the body velocity of frame h moving with the shape: rotate dh into h's own frame
    c, s_ = torch.cos(h[..., 2]), torch.sin(h[..., 2])
    rot_t = torch.stack([torch.stack([c, s_], -1), torch.stack([-s_, c], -1)], -2)
    h_inv_dh = torch.cat([rot_t @ dh[..., :2, :], dh[..., 2:, :]], -2)
    expected = se2.adjoint(se2.inverse(h)) @ center.connection(r) + h_inv_dh
    assert torch.allclose(commean.connection(r), expected, atol=1e-12)


def test_jacobian_matches_central_differences_and_gradcheck():
    s = NLinkSwimmer(5)
    r = torch.tensor([0.3, -0.4, 0.8, 0.1], dtype=F64)
    J = s.connection_jacobian(r)
    eps = 1e-6
    for j in range(4):
        e = torch.zeros(4, dtype=F64)
        e[j] = eps
        fd = (s.connection(r + e) - s.connection(r - e)) / (2 * eps)
        assert torch.allclose(J[..., j], fd, atol=1e-8)
    assert torch.autograd.gradcheck(s.connection, (r.clone().requires_grad_(),))
    assert torch.autograd.gradcheck(s.metric, (r.clone().requires_grad_(),))


@pytest.mark.parametrize("n", [3, 5, 9])
@pytest.mark.parametrize("frame", ["center", "com-mean"])
def test_jacobian_is_the_plain_forward_mode_one_bit_for_bit(n, frame):
    """The swimmer's geometry enters its Jacobian's forward pass as constants of zero tangent:
    the derivative of the connection as a function of the shape alone, bit for bit (signed
    zeros too, at a straight body and with joints at 0), and for a subclass that adds terms
    to the connection, its own connection's."""
    s = NLinkSwimmer(n, drag_ratio=3.1, frame=frame)
    r = torch.randn(40, n - 1, dtype=F64, generator=torch.Generator().manual_seed(n))
    r[:2] = 0.0
    r[2:4, 0] = 0.0
    plain = LocomotionSystem._jacobian(s, s._connection, r)  # fn closes over the geometry
    got = s.connection_jacobian(r)
    assert torch.equal(got.view(torch.int64), plain.view(torch.int64))
    if n == 3 and frame == "center":
        eps = 0.2  # LateralSlipSwimmer: NLinkSwimmer(3) and a slip ε (r2, r1) in v_y
        slip = LateralSlipSwimmer(eps).connection_jacobian(r) - NLinkSwimmer(3).connection_jacobian(r)
        expected = torch.zeros(3, 2, 2, dtype=F64)
        expected[1] = torch.tensor([[0.0, eps], [eps, 0.0]], dtype=F64)  # ∂(ε r2, ε r1)/∂r
        assert torch.allclose(slip, expected.expand_as(slip), atol=1e-15)


def test_jacobian_and_curvature_load_no_compiler():
    """Forward mode on a constant operand loads torch._dynamo and sympy (about 1 s of CPU);
    the swimmer's Jacobian and curvature have none."""
    code = ("import sys, torch\nfrom torchconn import NLinkSwimmer\n"
            "r = torch.randn(8, 4, dtype=torch.float64)\n"
            "NLinkSwimmer(5).connection_jacobian(r); NLinkSwimmer(5).curvature(r)\n"
            "print(sorted({'torch._dynamo', 'sympy'} & set(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]"


def test_differentiable_in_parameters():
    k = torch.tensor(2.0, dtype=F64, requires_grad=True)
    lengths = torch.full((3,), 1 / 3, dtype=F64, requires_grad=True)
    r = torch.tensor([0.5, -0.3], dtype=F64)

    def a_of(k_, l_):
        return NLinkSwimmer(3, drag_ratio=k_, link_lengths=l_).connection(r)

    assert torch.autograd.gradcheck(a_of, (k, lengths))


def test_curvature_layout_and_batching():
    s = NLinkSwimmer(5)
    r = torch.randn(2, 3, 4, dtype=F64)
    DA = s.curvature(r)
    assert DA.shape == (2, 3, 3, 6)
    A, J = s.connection(r), s.connection_jacobian(r)
    for p, (i, j) in enumerate(itertools.combinations(range(4), 2)):
        manual = J[..., :, j, i] - J[..., :, i, j] + se2.bracket(A[..., :, i], A[..., :, j])
        assert torch.allclose(DA[..., p], manual)
    one_by_one = torch.stack([s.connection(x) for x in r.reshape(-1, 4)]).reshape(2, 3, 3, 4)
    assert torch.allclose(s.connection(r), one_by_one, atol=1e-15)


def test_follows_input_dtype():
    s = NLinkSwimmer(3)
    assert s.connection(torch.zeros(2, dtype=torch.float32)).dtype == torch.float32


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(n_links=1), "n_links must be an integer >= 2"),
        (dict(n_links=4), "odd number of links"),
        (dict(n_links=3, link_lengths=[0.5, -0.1, 0.6]), "link_lengths must be finite and positive"),
        (dict(n_links=3, link_lengths=[0.5, 0.5]), r"link_lengths must have shape \(3,\)"),
        (dict(n_links=3, drag_ratio=0.0), "drag_ratio must be finite and positive"),
        (dict(n_links=3, frame="head"), "frame must be one of"),
    ],
)
def test_bad_construction_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        NLinkSwimmer(**kwargs)


def test_bad_shapes_raise():
    s = NLinkSwimmer(3)
    with pytest.raises(ValueError, match=r"r must have shape \(\.\.\., 2\)"):
        s.connection(torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="NaN"):
        s.metric(torch.tensor([0.1, float("nan")], dtype=F64))
    with pytest.raises(TypeError, match="floating-point"):
        s.connection(torch.zeros(2, dtype=torch.long))


def test_even_link_swimmer_in_com_mean_frame():
    s = NLinkSwimmer(4, frame="com-mean")
    A = s.connection(torch.zeros(3, dtype=F64))
    # straight and symmetric: no forward or lateral/rotational asymmetry in x
    assert torch.allclose(A[0], torch.zeros(3, dtype=F64), atol=1e-15)
