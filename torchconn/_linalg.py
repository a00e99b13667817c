"""Factorisations of matrices built from user data, each with a defined outcome.

``torch.linalg`` raises ``LinAlgError`` when LAPACK does not converge or a matrix is singular,
and whether it converges on a hard matrix can depend on the CPU's code path (MKL's AVX-512 and
AVX2 kernels differ). Every factorisation of a data-derived matrix goes through this module:

- on the normal path each function is exactly its ``torch.linalg`` namesake (same kernel, same
  result);
- a matrix with NaN or inf entries raises :class:`FactorisationError` naming the matrix;
- a convergence failure on a finite matrix is retried element by element through SciPy's LAPACK
  (another implementation and driver), and raises :class:`FactorisationError` only if that
  fails too;
- a singular system (``solve``, ``cholesky``, ``inv``) raises :class:`FactorisationError`.

``what`` names the matrix in the words a user knows, e.g. ``"the metric's normal matrix"``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["FactorisationError", "eigh", "eigvalsh", "svd", "svdvals", "solve", "lstsq", "pinv",
           "cholesky", "inv"]


class FactorisationError(ValueError):
    """A factorisation of data-derived values failed; the message names the matrix and the
    data's likely problem."""


def _nonfinite(a: Tensor, what: str) -> None:
    bad = ~torch.isfinite(a)
    if bool(bad.any()):
        idx = tuple(int(i) for i in torch.nonzero(bad)[0])
        raise FactorisationError(
            f"{what} has {int(bad.sum())} NaN or inf entries (first at index {idx}): the data "
            "it is built from hold non-finite values or overflow (check the recording for "
            "NaN/inf cells, huge values or constant columns)")


def _failed(what: str, kind: str, err: Exception | None = None) -> FactorisationError:
    detail = f" ({str(err).splitlines()[0]})" if err is not None else ""
    return FactorisationError(
        f"{what} could not be factorised: {kind}{detail}. The data do not determine it: "
        "too few samples, a channel that does not move, or channels that move together")


def _per_element(fn, *arrays: Tensor, like: Tensor):
    """Apply the NumPy function ``fn`` to each batch element of ``arrays`` (on the CPU, in
    float64 or complex128) and stack the results back onto ``like``'s device and dtype."""
    batch = arrays[0].shape[:-2]
    flat = [a.detach().cpu().reshape(-1, *a.shape[-2:]).numpy() for a in arrays]
    outs = [fn(*(f[k] for f in flat)) for k in range(flat[0].shape[0])]
    single = not isinstance(outs[0], tuple)
    outs = [(o,) if single else o for o in outs] if outs else []
    results = []
    for j in range(len(outs[0]) if outs else 0):
        stacked = torch.as_tensor(np.stack([o[j] for o in outs]))
        stacked = stacked.reshape(batch + stacked.shape[1:])
        # real outputs (eigenvalues, singular values) in the real dtype of ``like``
        dtype = like.dtype if stacked.is_complex() else like.real.dtype
        results.append(stacked.to(device=like.device, dtype=dtype))
    return results[0] if single else tuple(results)


def eigh(a: Tensor, what: str) -> tuple[Tensor, Tensor]:
    """Eigenvalues (ascending) and eigenvectors of the Hermitian ``a (..., n, n)``."""
    try:
        return torch.linalg.eigh(a)
    except torch.linalg.LinAlgError as err:
        _nonfinite(a, what)
        import scipy.linalg  # only on this fallback path: importing torchconn does not load scipy

        try:
            return _per_element(lambda m: scipy.linalg.eigh(m, driver="evr"), a, like=a)
        except (np.linalg.LinAlgError, ValueError):
            raise _failed(what, "the eigenvalue solver did not converge", err) from None


def eigvalsh(a: Tensor, what: str) -> Tensor:
    """Eigenvalues (ascending) of the Hermitian ``a (..., n, n)``."""
    try:
        return torch.linalg.eigvalsh(a)
    except torch.linalg.LinAlgError:
        return eigh(a, what)[0]


def svd(a: Tensor, what: str) -> tuple[Tensor, Tensor, Tensor]:
    """Thin singular value decomposition ``U, S, Vᴴ`` of ``a (..., m, n)``."""
    try:
        return torch.linalg.svd(a, full_matrices=False)
    except torch.linalg.LinAlgError as err:
        _nonfinite(a, what)
        import scipy.linalg  # only on this fallback path: importing torchconn does not load scipy

        try:
            return _per_element(
                lambda m: scipy.linalg.svd(m, full_matrices=False, lapack_driver="gesvd"), a,
                like=a)
        except (np.linalg.LinAlgError, ValueError):
            raise _failed(what, "the singular value solver did not converge", err) from None


def svdvals(a: Tensor, what: str) -> Tensor:
    """Singular values (descending) of ``a (..., m, n)``."""
    try:
        return torch.linalg.svdvals(a)
    except torch.linalg.LinAlgError:
        return svd(a, what)[1]


def pinv(a: Tensor, what: str) -> Tensor:
    """Moore–Penrose pseudo-inverse of ``a (..., m, n)``."""
    try:
        return torch.linalg.pinv(a)
    except torch.linalg.LinAlgError:
        u, s, vh = svd(a, what)
        tol = s[..., :1] * max(a.shape[-2:]) * torch.finfo(s.dtype).eps
        s_inv = torch.where(s > tol, 1 / torch.where(s > tol, s, 1), 0)
        return (vh.mH * s_inv.unsqueeze(-2)) @ u.mH


def lstsq(a: Tensor, b: Tensor, what: str) -> Tensor:
    """Least-squares solution of ``a x = b`` for ``a (..., m, n)``, ``b (..., m, k)``."""
    try:
        return torch.linalg.lstsq(a, b).solution
    except torch.linalg.LinAlgError:
        _nonfinite(b, what)
        return pinv(a, what) @ b


def _or_fail(call, a: Tensor, what: str, kind: str) -> Tensor:
    """``call()``, or a :class:`FactorisationError` naming ``what`` where LAPACK fails."""
    try:
        return call()
    except torch.linalg.LinAlgError:
        _nonfinite(a, what)
        raise _failed(what, kind) from None


def solve(a: Tensor, b: Tensor, what: str) -> Tensor:
    """``a⁻¹ b`` for the square ``a (..., n, n)``; a singular ``a`` raises."""
    return _or_fail(lambda: torch.linalg.solve(a, b), a, what, "the matrix is singular")


def inv(a: Tensor, what: str) -> Tensor:
    """``a⁻¹`` for the square ``a (..., n, n)``; a singular ``a`` raises."""
    return _or_fail(lambda: torch.linalg.inv(a), a, what, "the matrix is singular")


def cholesky(a: Tensor, what: str) -> Tensor:
    """Lower Cholesky factor of the positive-definite ``a (..., n, n)``."""
    return _or_fail(lambda: torch.linalg.cholesky(a), a, what,
                    "the matrix is not positive definite")
