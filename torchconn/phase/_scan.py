"""Parallel-in-time evaluation of recurrences, and the small-matrix algebra it runs on.

:func:`scan_states` evaluates a recurrence ``s_t = e_t(s_{t-1})`` whose maps compose
associatively (the Kalman filter's and the RTS smoother's, :mod:`torchconn.phase.smoothing`)
with the work-efficient odd/even recursion of a Blelloch scan (the form of
``jax.lax.associative_scan``): about ``T`` compositions and ``T`` applications in ``2 log2 T``
rounds of batched tensor operations, instead of ``T`` sequential steps.

Layout ("structure of arrays"). Every tensor has time at dim 0 and its batch dimensions *last*;
a small ``n × m`` matrix per time and batch element is ``(T, n, m, *batch)`` and a vector
``(T, n, *batch)``. Products of these tiny matrices are ``n`` fused multiply-adds over whole
slices (:func:`mm`, :func:`mv`), and 2 × 2 / 3 × 3 inverses, factors and solves are unrolled
in closed form, faster on the CPU than ``torch.matmul`` or ``torch.linalg.solve`` on
``(N, n, n)`` stacks; on a GPU it is a handful of large elementwise kernels per round.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

__all__ = ["scan_states", "mm", "mv", "mT", "inv", "cholesky", "solve_spd"]

Elements = tuple[Tensor, ...]


def scan_states(combine: Callable[[Elements, Elements], Elements],
                apply: Callable[[Elements, Elements], Elements],
                first: Sequence[Tensor], maps: Sequence[Tensor], *,
                reverse: bool = False) -> Elements:
    """All states of the recurrence ``s_0 = first``, ``s_t = e_t(s_{t-1})``, in log depth.

    The maps ``e_1 … e_{T-1}`` are composed pairwise (``combine``), the recurrence is solved on
    the ``⌈T/2⌉`` even-indexed states recursively, and each odd state is one ``apply`` away from
    the even state before it: about ``T`` compositions and ``T`` applications in ``2 log2 T``
    rounds of batched tensor operations (the odd/even form of the Blelloch scan).

    Args:
        combine: ``combine(e_i, e_j)`` is the map ``e_j ∘ e_i`` (``e_i`` applied first), for
            tuples of tensors elementwise in time; must be associative.
        apply: ``apply(s, e)`` is the state ``e(s)``.
        first: the state ``s_0``, tensors ``(...)``.
        maps: the maps ``e_1 … e_{T-1}``, tensors ``(T - 1, ...)``; a tensor of time size 1
            is a part shared by every map (e.g. the covariance part of identical Kalman
            steps): it is composed once per round instead of once per pair.
        reverse: run from the end instead: ``s_{T-1} = first`` and ``s_t = e_t(s_{t+1})`` with
            ``maps[t]`` the map ``e_t`` for ``t = 0 … T-2``.

    Returns:
        the states, a tuple of tensors ``(T, ...)``.
    """
    first, maps = tuple(first), tuple(maps)
    if reverse:
        flipped = scan_states(combine, apply, first, [e.flip(0) for e in maps])
        return tuple(s.flip(0) for s in flipped)
    n_maps = max(e.shape[0] for e in maps)
    if n_maps == 0:
        return tuple(f[None] for f in first)

    def take(e: Tensor, sl: slice) -> Tensor:  # a part shared by all maps (time size 1) stays
        return e if e.shape[0] == 1 and n_maps > 1 else e[sl]

    pairs = n_maps // 2
    even = scan_states(combine, apply, first,
                       combine(tuple(take(e, slice(0, 2 * pairs, 2)) for e in maps),
                               tuple(take(e, slice(1, 2 * pairs, 2)) for e in maps)))  # s_0, s_2..
    n_odd = (n_maps + 1) // 2
    odd = apply(tuple(s[:n_odd] for s in even),
                tuple(take(e, slice(0, None, 2)) for e in maps))  # s_1, s_3, ...
    out = []
    for ev, od in zip(even, odd, strict=True):
        full = ev.new_empty((n_maps + 1,) + ev.shape[1:])
        full[0::2] = ev
        full[1::2] = od
        out.append(full)
    return tuple(out)


def mm(a: Tensor, b: Tensor) -> Tensor:
    """``a (T, n, k, *batch) @ b (T, k, m, *batch) -> (T, n, m, *batch)`` (broadcasting)."""
    out = a[:, :, 0:1] * b[:, None, 0]
    for j in range(1, a.shape[2]):
        out.addcmul_(a[:, :, j:j + 1], b[:, None, j])
    return out


def mv(a: Tensor, x: Tensor) -> Tensor:
    """``a (T, n, k, *batch) @ x (T, k, *batch) -> (T, n, *batch)`` (broadcasting)."""
    out = a[:, :, 0] * x[:, 0:1]
    for j in range(1, a.shape[2]):
        out.addcmul_(a[:, :, j], x[:, j:j + 1])
    return out


def mT(a: Tensor) -> Tensor:
    """Transpose of each small matrix: ``(T, n, m, *batch) -> (T, m, n, *batch)``."""
    return a.transpose(1, 2)


def inv(a: Tensor) -> Tensor:
    """Inverse of each 2 × 2 or 3 × 3 matrix ``(T, n, n, *batch)`` (adjugate over determinant)."""
    n = a.shape[1]
    if n == 2:
        a00, a01, a10, a11 = a[:, 0, 0], a[:, 0, 1], a[:, 1, 0], a[:, 1, 1]
        det = a00 * a11 - a01 * a10
        adj = torch.stack([torch.stack([a11, -a01], 1), torch.stack([-a10, a00], 1)], 1)
        return adj / det[:, None, None]
    if n == 3:
        # (adj a)[i][j] = cofactor of a[j][i]
        adj = torch.stack([
            torch.stack([a[:, (j + 1) % 3, (i + 1) % 3] * a[:, (j + 2) % 3, (i + 2) % 3]
                         - a[:, (j + 1) % 3, (i + 2) % 3] * a[:, (j + 2) % 3, (i + 1) % 3]
                         for j in range(3)], 1)
            for i in range(3)], 1)
        det = a[:, 0, 0] * adj[:, 0, 0] + a[:, 0, 1] * adj[:, 1, 0] + a[:, 0, 2] * adj[:, 2, 0]
        return adj / det[:, None, None]
    raise ValueError(f"inv: 2 x 2 and 3 x 3 matrices are supported, got {n} x {n}")


def solve_spd(a: Tensor, b: Tensor) -> Tensor:
    """``a⁻¹ b`` for symmetric positive definite ``a (T, n, n, *batch)``, ``b (T, n, k, *batch)``.

    By the ``L D Lᵀ`` factorisation, unrolled over the small ``n``: backward stable for any
    condition number (unlike the adjugate, which for an ill-conditioned 3 × 3 -- the vague
    prior's first steps -- loses digits the sequential solve keeps).
    """
    n = a.shape[1]
    L = [[None] * n for _ in range(n)]
    d = [None] * n
    for j in range(n):
        s = a[:, j, j]
        for k in range(j):
            s = s - L[j][k] * L[j][k] * d[k]
        d[j] = s
        for i in range(j + 1, n):
            s = a[:, i, j]
            for k in range(j):
                s = s - L[i][k] * L[j][k] * d[k]
            L[i][j] = s / d[j]
    z = [None] * n
    for i in range(n):  # L z = b
        s = b[:, i]
        for k in range(i):
            s = s - L[i][k][:, None] * z[k]
        z[i] = s
    x = [None] * n
    for i in reversed(range(n)):  # D Lᵀ x = z
        s = z[i] / d[i][:, None]
        for k in range(i + 1, n):
            s = s - L[k][i][:, None] * x[k]
        x[i] = s
    return torch.stack(x, 1)


def cholesky(a: Tensor) -> Tensor:
    """Lower factor ``l``, ``l lᵀ = a``, of each positive *semi*-definite ``a (T, n, n, *batch)``.

    A pivot that rounding makes zero or negative (a singular ``a``) gives a zero column, so the
    factor exists for every positive semi-definite matrix.
    """
    n = a.shape[1]
    L = [[torch.zeros_like(a[:, 0, 0]) for _ in range(n)] for _ in range(n)]
    for j in range(n):
        d = a[:, j, j]
        for k in range(j):
            d = d - L[j][k] * L[j][k]
        ljj = d.clamp_min(0).sqrt()
        inv_ljj = torch.where(ljj > 0, 1.0 / ljj, torch.zeros_like(ljj))
        L[j][j] = ljj
        for i in range(j + 1, n):
            s = a[:, i, j]
            for k in range(j):
                s = s - L[i][k] * L[j][k]
            L[i][j] = s * inv_ljj
    return torch.stack([torch.stack(row, 1) for row in L], 1)
