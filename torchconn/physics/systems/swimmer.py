"""The viscous N-link swimmer (resistive-force theory), exact and batched.

Conventions (docs/conventions.md, matching Hatton's GSP up to the sign of A):
N rigid links in a chain, link 1 the tail, body +x from tail to head; shape ``r_i`` is the
angle of link i+1 minus that of link i. A straight link of length ``l`` moving with twist
``xi_link`` in its midpoint frame feels the drag wrench
``F = -c · diag(l, k l, k l³/12) · xi_link`` (``c`` longitudinal drag per unit length, ``k`` the
lateral/longitudinal drag ratio). The body moves so that the links' wrenches balance, which
gives ``xi = A(r) r_dot``; the dissipated power is ``r_dotᵀ M(r) r_dot``.

How it is computed: every link's pose in the body frame is ``(p_i, theta_i)`` with
``theta = Θ r`` and ``p = C · (cos theta, sin theta)`` for constant matrices ``Θ (N×d)`` and
``C (N×N)`` that depend only on the link lengths and the body frame. Each link's twist is then
``J_g,i xi + J_r,i r_dot``, the force balance is a 3×3 solve per shape, and everything is plain
tensor algebra over the leading batch dimensions — differentiable in ``r`` and in the
parameters (link lengths, drag ratio), which may be tensors requiring grad.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ... import _checks
from .. import se2
from .base import LocomotionSystem, check_shapes

__all__ = ["NLinkSwimmer", "FRAMES"]

FRAMES = ("center", "com-mean")


def _as_param(value, name: str, shape: tuple[int, ...] | None = None) -> Tensor:
    """Parameters are kept as float64 tensors (grad-tracking ones are kept as given)."""
    t = value if isinstance(value, Tensor) else torch.as_tensor(value, dtype=torch.float64)
    if not t.is_floating_point():
        t = t.to(torch.float64)
    if shape is not None and tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    if not torch.isfinite(t).all() or (t <= 0).any():
        raise ValueError(f"{name} must be finite and positive, got {t.detach().tolist()}")
    return t


class NLinkSwimmer(LocomotionSystem):
    """Viscous N-link swimmer.

    Args:
        n_links: number of links ``N >= 2``; the shape has ``d = N - 1`` joint angles.
        drag_ratio: lateral/longitudinal drag ratio ``k`` (default 2). A float or a scalar tensor
            (which may require grad).
        frame: body frame, ``"center"`` (odd N: midpoint and orientation of the middle link) or
            ``"com-mean"`` (length-weighted mean of link midpoints, length-weighted mean link
            angle; for equal links the plain means). Even N must use ``"com-mean"``.
        link_lengths: ``(N,)`` positive lengths; default equal links of total length 1.
        drag_coefficient: longitudinal drag per unit length ``c`` (default 1).
    """

    def __init__(
        self,
        n_links: int,
        drag_ratio: float | Tensor = 2.0,
        frame: str = "center",
        link_lengths=None,
        drag_coefficient: float | Tensor = 1.0,
    ):
        _checks.integer(n_links, "n_links", minimum=2)
        if frame not in FRAMES:
            raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
        if frame == "center" and n_links % 2 == 0:
            raise ValueError(
                f"frame='center' needs an odd number of links (got {n_links}); "
                "use frame='com-mean' for an even number of links"
            )
        self.n_links = n_links
        self.shape_dim = n_links - 1
        self.frame = frame
        self.drag_ratio = _as_param(drag_ratio, "drag_ratio", ())
        self.drag_coefficient = _as_param(drag_coefficient, "drag_coefficient", ())
        if link_lengths is None:
            link_lengths = torch.full((n_links,), 1.0 / n_links, dtype=torch.float64)
        self.link_lengths = _as_param(link_lengths, "link_lengths", (n_links,))

    def __repr__(self) -> str:
        return (
            f"NLinkSwimmer(n_links={self.n_links}, drag_ratio={float(self.drag_ratio):g}, "
            f"frame={self.frame!r}, link_lengths={self.link_lengths.detach().tolist()})"
        )

    # ------------------------------------------------------------------ geometry
    def _geometry(self, like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``Θ (N, d)``, ``C (N, N)`` and the drag diagonal ``(N, 3)`` on ``like``'s dtype/device."""
        n = self.n_links
        kw = dict(dtype=like.dtype, device=like.device)
        l = self.link_lengths.to(**kw)
        k = self.drag_ratio.to(**kw)
        c = self.drag_coefficient.to(**kw)
        # Reference frame: link 1's midpoint and angle. theta_i = r_1 + ... + r_{i-1}.
        theta_ref = torch.tril(torch.ones(n, n - 1, **kw), diagonal=-1)
        # p_i = sum_{j<i} (l_j/2 e_j + l_{j+1}/2 e_{j+1}): row i weighs link j's unit vector by
        # l_j/2 for each of the (up to two) half-links of j that lie between link 1 and link i.
        strictly = torch.tril(torch.ones(n, n, **kw), diagonal=-1)
        upto = torch.tril(torch.ones(n, n, **kw))
        upto[:, 0] = 0
        c_ref = (strictly + upto) * (l / 2)
        if self.frame == "center":
            w = torch.zeros(n, **kw)
            w[n // 2] = 1
            w_pos = w_ang = w
        else:
            w_pos = w_ang = l / l.sum()
        eye = torch.eye(n, **kw)
        theta_mat = (eye - w_ang[None, :]) @ theta_ref
        c_mat = (eye - w_pos[None, :]) @ c_ref
        drag = c * torch.stack([l, k * l, k * l**3 / 12], -1)
        return theta_mat, c_mat, drag

    def link_poses(self, r: Tensor) -> Tensor:
        """Pose of every link's midpoint frame in the body frame: ``(..., d) -> (..., N, 3)``."""
        return self._link_poses(check_shapes(r, self.shape_dim))

    def _link_poses(self, r: Tensor) -> Tensor:
        theta_mat, c_mat, _ = self._geometry(r)
        th = r @ theta_mat.T
        return torch.stack([torch.cos(th) @ c_mat.T, torch.sin(th) @ c_mat.T, th], -1)

    # ------------------------------------------------------------------ physics
    def connection_and_metric(self, r: Tensor) -> tuple[Tensor, Tensor]:
        return self._connection_and_metric(check_shapes(r, self.shape_dim))

    def _link_terms(self, r: Tensor, geometry: tuple[Tensor, Tensor, Tensor] | None = None):
        """Per-link kinematics and the connection: ``(A, u_r, w_r, b, drag, Θ)``;
        ``geometry``: :meth:`_geometry`'s ``(Θ, C, drag)`` (None: computed here)."""
        theta_mat, c_mat, drag = self._geometry(r) if geometry is None else geometry
        th = _rows(r, theta_mat.T)  # (..., N) link angles in the body frame
        cs, sn = torch.cos(th), torch.sin(th)
        # Link i's twist in its own frame is (u, w, Ω) = J_g xi + J_r r_dot. With
        # p_i = Σ_j C_ij e(θ_j) every entry is a C-weighted sum of sin/cos(θ_i − θ_j); expanding
        # those differences keeps the work in matrix products with C instead of N×N tables.
        pc, ps = _rows(cs, c_mat.T), _rows(sn, c_mat.T)  # Σ_j C_ij cos θ_j, Σ_j C_ij sin θ_j
        u3, w3 = sn * pc - cs * ps, cs * pc + sn * ps  # J_g's rotation column (u and w rows)
        # Σ_j C_ij cos θ_j Θ_j, (..., N, d)
        qc = _rows((cs[..., :, None] * theta_mat).transpose(-1, -2), c_mat.T).transpose(-1, -2)
        qs = _rows((sn[..., :, None] * theta_mat).transpose(-1, -2), c_mat.T).transpose(-1, -2)
        u_r = sn[..., None] * qc - cs[..., None] * qs  # J_r's u and w rows, (..., N, d)
        w_r = cs[..., None] * qc + sn[..., None] * qs
        k1, k2, k3 = drag.unbind(-1)  # longitudinal, lateral, rotational drag per link

        def total(x: Tensor) -> Tensor:  # Σ over links
            return x.sum(-1)

        def link_sum(w: Tensor, x: Tensor) -> Tensor:  # Σ_n w_n x_n: (..., N), (..., N, d)
            return (w[..., None] * x).sum(-2)

        # Body resistance H = Σ J_gᵀ K J_g (symmetric 3×3), columns of J_g: (c, −s, 0),
        # (s, c, 0), (u3, w3, 1) for v_x, v_y, ω.
        h11 = total(k1 * cs * cs + k2 * sn * sn)
        h12 = total((k1 - k2) * cs * sn)
        h22 = total(k1 * sn * sn + k2 * cs * cs)
        h13 = total(k1 * cs * u3 - k2 * sn * w3)
        h23 = total(k1 * sn * u3 + k2 * cs * w3)
        h33 = total(k1 * u3 * u3 + k2 * w3 * w3) + k3.sum()
        # Shape coupling B = Σ J_gᵀ K J_r, (..., 3, d). Tiny products are written as
        # broadcast-and-sum: batched matmuls of 3×3 blocks are slow, worst under forward AD.
        b = torch.stack(
            [
                link_sum(k1 * cs, u_r) - link_sum(k2 * sn, w_r),
                link_sum(k1 * sn, u_r) + link_sum(k2 * cs, w_r),
                link_sum(k1 * u3, u_r) + link_sum(k2 * w3, w_r) + (k3 @ theta_mat),
            ],
            -2,
        )
        a = -_solve_sym3(h11, h12, h13, h22, h23, h33, b)
        return a, u_r, w_r, b, drag, theta_mat

    def _connection(self, r: Tensor) -> Tensor:
        return self._link_terms(r)[0]

    def _connection_of(self, r: Tensor, *geometry: Tensor) -> Tensor:
        """:meth:`_connection` with :meth:`_geometry`'s ``(Θ, C, drag)`` given."""
        return self._link_terms(r, geometry)[0]

    def _jacobian(self, fn, r: Tensor, constants: tuple[Tensor, ...] = ()) -> Tensor:
        """The base class's, with the geometry ``(Θ, C, drag)`` a constant of the swimmer's
        own connection (not of a subclass's, which may add terms): the same numbers, bit for
        bit, without the forward pass loading ``torch._dynamo``."""
        if fn == self._connection and type(self)._connection is NLinkSwimmer._connection:
            return super()._jacobian(self._connection_of, r, self._geometry(r))
        return super()._jacobian(fn, r, constants)

    def _connection_and_metric(self, r: Tensor) -> tuple[Tensor, Tensor]:
        a, u_r, w_r, b, drag, theta_mat = self._link_terms(r)
        k1, k2, k3 = drag.unbind(-1)

        def gram(k: Tensor, x: Tensor) -> Tensor:  # Σ_n k_n x_nᵀ x_n: (..., N, d) -> (..., d, d)
            return (k[:, None] * x).transpose(-1, -2) @ x

        # Power of the link twists (J_g A + J_r) r_dot; with H A = −B it reduces to this form.
        m = (
            gram(k1, u_r) + gram(k2, w_r)
            + theta_mat.T @ (k3[:, None] * theta_mat)
            + b.transpose(-1, -2) @ a
        )
        return a, 0.5 * (m + m.transpose(-1, -2))

    def _metric(self, r: Tensor) -> Tensor:
        return self._connection_and_metric(r)[1]

    def frame_transform(self, r: Tensor, frame: str) -> Tensor:
        """Pose ``h(r)`` of ``frame``'s body frame seen from this swimmer's body frame: ``(..., 3)``.

        With ``g' = g h(r)`` the connections are related by
        ``A' = Ad_{h^-1} A + (h^-1 ∂h/∂r)^∨``.
        """
        return self._frame_transform(check_shapes(r, self.shape_dim), frame)

    def _frame_transform(self, r: Tensor, frame: str) -> Tensor:
        other = NLinkSwimmer(
            self.n_links, self.drag_ratio, frame, self.link_lengths, self.drag_coefficient
        )
        here = self._link_poses(r)[..., 0, :]
        there = other._link_poses(r)[..., 0, :]
        # Link 1's pose is the same physical frame in both: h = here · there^{-1}.
        return se2.compose(here, se2.inverse(there))



def _rows(x: Tensor, m: Tensor) -> Tensor:
    """``x (..., k) @ m (k, l)`` as one 2-D GEMM over the flattened batch (fast under autograd,
    forward mode included, where broadcast matmuls become many tiny batched products)."""
    return (x.reshape(-1, x.shape[-1]) @ m).reshape(x.shape[:-1] + (m.shape[-1],))


def _solve_sym3(h11, h12, h13, h22, h23, h33, b: Tensor) -> Tensor:
    """Solve ``H x = b`` for symmetric 3×3 ``H`` given by its entries ``(...)`` and ``b (..., 3, d)``.

    The adjugate formula is elementwise, so millions of tiny systems cost a few vector ops
    instead of one LAPACK call each; H is the positive-definite resistance of the body.
    """
    c11 = h22 * h33 - h23 * h23
    c12 = h13 * h23 - h12 * h33
    c13 = h12 * h23 - h13 * h22
    c22 = h11 * h33 - h13 * h13
    c23 = h12 * h13 - h11 * h23
    c33 = h11 * h22 - h12 * h12
    det = h11 * c11 + h12 * c12 + h13 * c13
    adj = torch.stack(
        [torch.stack([c11, c12, c13], -1), torch.stack([c12, c22, c23], -1),
         torch.stack([c13, c23, c33], -1)], -2,
    )
    return (adj[..., :, :, None] * b[..., None, :, :]).sum(-2) / det[..., None, None]
