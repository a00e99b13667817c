"""The interface every locomotion system in torchconn shares.

A system maps shapes ``r: (..., d)`` to its local connection ``A(r): (..., 3, d)`` (paper sign,
``xi = A(r) r_dot``) and dissipation metric ``M(r): (..., d, d)``. Derivatives, curvature and
body velocities are derived here once, by automatic differentiation, so every system (the
N-link swimmer, the toy, an augmented simulator of the discrepancy stage) gets them alike.
"""

from __future__ import annotations

import itertools
from abc import ABC, abstractmethod

import torch
from torch import Tensor

from ..._checks import check_shapes
from .. import se2

__all__ = ["LocomotionSystem", "check_shapes"]


class LocomotionSystem(ABC):
    """A principally kinematic system ``xi = A(r) r_dot`` with a dissipation metric ``M(r)``.

    Subclasses implement :meth:`_connection` and :meth:`_metric` for validated shapes; this base
    class provides the validated public methods, the connection's shape Jacobian (autograd,
    ``torch.func``), the curvature ``DA`` and body-velocity / power helpers.
    """

    #: number of shape variables ``d``
    shape_dim: int

    @abstractmethod
    def _connection(self, r: Tensor) -> Tensor:
        """``A(r)``: ``(..., d) -> (..., 3, d)`` for validated ``r``."""

    @abstractmethod
    def _metric(self, r: Tensor) -> Tensor:
        """``M(r)``: ``(..., d) -> (..., d, d)`` for validated ``r``."""

    def connection_and_metric(self, r: Tensor) -> tuple[Tensor, Tensor]:
        """``(A(r), M(r))`` together; subclasses override when sharing work is cheaper."""
        return self.connection(r), self.metric(r)

    # ------------------------------------------------------------------ public surface
    def connection(self, r: Tensor) -> Tensor:
        """Local connection ``A(r)``.

        Args:
            r: shapes ``(..., d)`` (rad).
        Returns:
            ``(..., 3, d)``; row ``k`` is the body-velocity component ``(v_x, v_y, omega)[k]``
            per unit shape velocity, so ``xi = A(r) @ r_dot``.
        """
        return self._connection(check_shapes(r, self.shape_dim))

    def metric(self, r: Tensor) -> Tensor:
        """Dissipation metric ``M(r)``: ``(..., d) -> (..., d, d)``; power ``P = r_dotᵀ M r_dot``."""
        return self._metric(check_shapes(r, self.shape_dim))

    def connection_jacobian(self, r: Tensor) -> Tensor:
        """``∂A/∂r``: ``(..., d) -> (..., 3, d, d)`` holding ``∂A^k_i/∂r_j`` at ``[..., k, i, j]``.

        Computed by forward-mode autograd (``torch.func.jacfwd``), vectorised over the batch.
        """
        return self._jacobian(self._connection, check_shapes(r, self.shape_dim))

    def metric_jacobian(self, r: Tensor) -> Tensor:
        """``∂M/∂r``: ``(..., d) -> (..., d, d, d)`` holding ``∂M_ij/∂r_k`` at ``[..., i, j, k]``."""
        return self._jacobian(self._metric, check_shapes(r, self.shape_dim))

    def _jacobian(self, fn, r: Tensor, constants: tuple[Tensor, ...] = ()) -> Tensor:
        """``∂fn/∂r`` with the shape derivative as the last axis, ``fn(r, *constants)``.

        ``fn`` maps each shape to its own value (no coupling across the batch), so one
        forward-mode JVP of the whole batch per shape direction gives every shape's Jacobian:
        ``d`` batched JVPs (vectorised with ``vmap`` over the directions) instead of a
        per-shape ``jacfwd``.

        ``constants``: tensors ``fn`` takes besides ``r``, held fixed (their tangent is 0).
        Passed so rather than read from the system, they give the same derivative bit for
        bit, and the forward pass never meets a constant operand: torch gives one an implicit
        zero tangent whose arithmetic runs through Python kernels that load ``torch._dynamo``
        and sympy on first use (about 1 s of CPU).
        """
        d = self.shape_dim
        eye = torch.eye(d, dtype=r.dtype, device=r.device)
        tangents = eye.reshape((d,) + (1,) * (r.ndim - 1) + (d,)).expand((d,) + r.shape)
        zeros = tuple(torch.zeros_like(c) for c in constants)
        jac = torch.func.vmap(
            lambda v: torch.func.jvp(fn, (r, *constants), (v, *zeros))[1])(tangents)
        return jac.movedim(0, -1)

    def curvature(self, r: Tensor) -> Tensor:
        """Curvature ``DA = dA + Σ_{i<j} [A_i, A_j]`` at ``r``.

        Returns ``(..., 3, d(d-1)/2)``; column ``p`` is the pair ``(i, j)``, ``i < j``, in
        lexicographic order, with ``dA_ij = ∂A_j/∂r_i − ∂A_i/∂r_j`` and the se(2) commutator
        of the columns ``A_i``, ``A_j``. A small counter-clockwise loop of area ``a`` in the
        ``(r_i, r_j)`` plane displaces the body by ``≈ DA_ij · a``.
        """
        r = check_shapes(r, self.shape_dim)
        A = self._connection(r)
        J = self._jacobian(self._connection, r)  # [..., k, i, j] = dA^k_i / dr_j
        cols = []
        for i, j in itertools.combinations(range(self.shape_dim), 2):
            dA = J[..., :, j, i] - J[..., :, i, j]
            cols.append(dA + se2.bracket(A[..., :, i], A[..., :, j]))
        if not cols:
            return A.new_zeros(A.shape[:-1] + (0,))
        return torch.stack(cols, -1)

    def body_velocity(self, r: Tensor, r_dot: Tensor) -> Tensor:
        """``xi = A(r) r_dot``: ``(..., d), (..., d) -> (..., 3)``."""
        r_dot = check_shapes(r_dot, self.shape_dim, "r_dot")
        return (self.connection(r) @ r_dot.unsqueeze(-1)).squeeze(-1)

    def power(self, r: Tensor, r_dot: Tensor) -> Tensor:
        """Dissipated power ``P = r_dotᵀ M(r) r_dot``: ``(..., d), (..., d) -> (...)``."""
        r_dot = check_shapes(r_dot, self.shape_dim, "r_dot")
        return torch.einsum("...i,...ij,...j->...", r_dot, self.metric(r), r_dot)
