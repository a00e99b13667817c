"""Factorisations of data-derived matrices have a defined outcome (torchconn._linalg): the
torch result on the normal path, SciPy's LAPACK where torch's does not converge, and a clear
error naming the matrix where the data cannot be factorised."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch

from torchconn import _linalg
from torchconn._linalg import FactorisationError

F64 = torch.float64
PACKAGE = Path(__file__).resolve().parents[1] / "torchconn"

#: calls that raise on a hard matrix; the *_ex forms, triangular solves and cholesky_solve don't
RAISING = {"eigh", "eigvalsh", "svd", "svdvals", "solve", "lstsq", "pinv", "inv", "cholesky",
           "eig", "eigvals", "matrix_rank", "cond"}


def _spd(n=5, batch=(3,), seed=0):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(*batch, n, n, generator=g, dtype=F64)
    return a @ a.mT + 0.1 * torch.eye(n, dtype=F64)


def _fail(*args, **kwargs):
    raise torch.linalg.LinAlgError("simulated: the algorithm failed to converge")


def test_every_raising_factorisation_in_the_package_goes_through_linalg():
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        if path.name == "_linalg.py" or path.parent.name == "testing":
            continue  # testing/: independent reference implementations, not user data
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Attribute) and node.attr in RAISING
                    and ast.unparse(node.value) in {"torch.linalg", "np.linalg", "numpy.linalg",
                                                    "scipy.linalg"}):
                offenders.append(f"{path.relative_to(PACKAGE)}:{node.lineno} {ast.unparse(node)}")
            if (isinstance(node, ast.Attribute) and node.attr in {"inverse", "cholesky", "pinverse"}
                    and ast.unparse(node.value) == "torch"):
                offenders.append(f"{path.relative_to(PACKAGE)}:{node.lineno} {ast.unparse(node)}")
    assert not offenders, offenders


def test_normal_path_is_torch_exactly():
    a = _spd()
    b = torch.randn(3, 5, 2, dtype=F64, generator=torch.Generator().manual_seed(1))
    w, v = _linalg.eigh(a, "A")
    w0, v0 = torch.linalg.eigh(a)
    assert torch.equal(w, w0) and torch.equal(v, v0)
    assert torch.equal(_linalg.solve(a, b, "A"), torch.linalg.solve(a, b))
    assert torch.equal(_linalg.cholesky(a, "A"), torch.linalg.cholesky(a))
    assert torch.equal(_linalg.inv(a, "A"), torch.linalg.inv(a))
    # MKL's AVX2 least-squares kernel is not bit-reproducible from call to call (its result
    # depends on the operands' memory alignment), so this one is compared to rounding
    torch.testing.assert_close(_linalg.lstsq(a, b, "A"), torch.linalg.lstsq(a, b).solution,
                               rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("complex_", [False, True])
def test_eigh_falls_back_to_scipy_when_torch_does_not_converge(monkeypatch, complex_):
    a = _spd()
    if complex_:
        im = torch.randn(3, 5, 5, dtype=F64, generator=torch.Generator().manual_seed(2))
        a = a.to(torch.complex128) + 1j * (im - im.mT)
    w0, v0 = torch.linalg.eigh(a)
    monkeypatch.setattr(torch.linalg, "eigh", _fail)
    monkeypatch.setattr(torch.linalg, "eigvalsh", _fail)
    w, v = _linalg.eigh(a, "A")
    assert w.dtype == w0.dtype and v.dtype == v0.dtype
    torch.testing.assert_close(w, w0, rtol=1e-12, atol=1e-12)
    # eigenvectors up to a phase: compare the reconstruction
    torch.testing.assert_close((v * w.unsqueeze(-2).to(v)) @ v.mH, a, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(_linalg.eigvalsh(a, "A"), w0, rtol=1e-12, atol=1e-12)


def test_svd_and_pinv_fall_back_to_scipy(monkeypatch):
    a = torch.randn(2, 6, 4, dtype=F64, generator=torch.Generator().manual_seed(3))
    s0, p0 = torch.linalg.svdvals(a), torch.linalg.pinv(a)
    monkeypatch.setattr(torch.linalg, "svd", _fail)
    monkeypatch.setattr(torch.linalg, "svdvals", _fail)
    monkeypatch.setattr(torch.linalg, "pinv", _fail)
    u, s, vh = _linalg.svd(a, "A")
    torch.testing.assert_close(s, s0, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close((u * s.unsqueeze(-2)) @ vh, a, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(_linalg.pinv(a, "A"), p0, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("fn", ["eigh", "svd", "pinv"])
def test_a_nonfinite_matrix_that_does_not_converge_is_named(monkeypatch, fn):
    a = _spd()
    a[1, 2, 3] = float("inf")
    for name in ("eigh", "svd", "pinv"):
        monkeypatch.setattr(torch.linalg, name, _fail)
    with pytest.raises(FactorisationError, match=r"the test matrix has 1 NaN or inf entries "
                       r"\(first at index \(1, 2, 3\)\)"):
        getattr(_linalg, fn)(a, "the test matrix")


@pytest.mark.parametrize("fn", ["solve", "inv", "cholesky"])
def test_singular_matrix_is_a_clear_error(fn):
    a = torch.zeros(2, 3, 3, dtype=F64)
    args = (a, torch.ones(2, 3, 1, dtype=F64)) if fn == "solve" else (a,)
    with pytest.raises(FactorisationError, match="the normal matrix could not be factorised"):
        getattr(_linalg, fn)(*args, "the normal matrix")


def test_lstsq_of_a_singular_system_is_the_minimum_norm_solution(monkeypatch):
    a = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=F64)
    b = torch.tensor([[2.0], [2.0]], dtype=F64)
    monkeypatch.setattr(torch.linalg, "lstsq", _fail)
    monkeypatch.setattr(torch.linalg, "pinv", _fail)
    torch.testing.assert_close(_linalg.lstsq(a, b, "A"), torch.ones(2, 1, dtype=F64))
