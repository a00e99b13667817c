"""Plain per-shape NumPy reference for the N-link swimmer (tests and benchmarks only).

Deliberately derived another way than :mod:`torchconn.physics.systems.swimmer`: the chain is walked
link by link, shape velocities are joint rotations about the joint positions, forces are
balanced in link 1's frame, and the body frame is reached by the frame-change formula. It
handles one shape at a time, the way a straightforward script would; the benchmarks time it
against the batched code and the tests compare the two to 1e-12.
"""

from __future__ import annotations

import numpy as np

__all__ = ["connection_and_metric_numpy"]


def _rot(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


def _unit(a: float) -> np.ndarray:
    return np.array([np.cos(a), np.sin(a)])


def _perp(v: np.ndarray) -> np.ndarray:
    return np.array([-v[1], v[0]])


def connection_and_metric_numpy(
    r: np.ndarray, lengths: np.ndarray, drag_ratio: float = 2.0, frame: str = "center"
) -> tuple[np.ndarray, np.ndarray]:
    """``A (3, d)`` and ``M (d, d)`` for one shape ``r (d,)``."""
    n = len(lengths)
    d = n - 1
    # Link poses in link 1's midpoint frame.
    ang = np.concatenate([[0.0], np.cumsum(r)])
    mid = np.zeros((n, 2))
    joints = np.zeros((d, 2))
    for i in range(1, n):
        joints[i - 1] = mid[i - 1] + lengths[i - 1] / 2 * _unit(ang[i - 1])
        mid[i] = joints[i - 1] + lengths[i] / 2 * _unit(ang[i])
    # Columns: effect of (v_x, v_y, omega) of link 1's frame and of each joint rate on each link's
    # twist in its own frame. Joint j turns every link beyond it about the joint's position.
    jac = np.zeros((n, 3, 3 + d))
    for i in range(n):
        rt = _rot(ang[i]).T
        jac[i, :2, 0] = rt @ np.array([1.0, 0.0])
        jac[i, :2, 1] = rt @ np.array([0.0, 1.0])
        jac[i, :2, 2] = rt @ _perp(mid[i])
        jac[i, 2, 2] = 1.0
        for j in range(i):  # joints 0..i-1 lie between link 1 and link i
            jac[i, :2, 3 + j] = rt @ _perp(mid[i] - joints[j])
            jac[i, 2, 3 + j] = 1.0
    drag = np.stack([lengths, drag_ratio * lengths, drag_ratio * lengths**3 / 12], -1)
    force = np.zeros((3, 3 + d))
    for i in range(n):
        force += jac[i].T[:3] @ (drag[i][:, None] * jac[i])
    a_ref = -np.linalg.solve(force[:, :3], force[:, 3:])  # link-1 frame
    total = np.zeros((d, d))
    for i in range(n):
        tw = jac[i][:, :3] @ a_ref + jac[i][:, 3:]
        total += tw.T @ (drag[i][:, None] * tw)

    # Body frame pose h (in link 1's frame) and its shape derivative.
    if frame == "center":
        w = np.zeros(n)
        w[n // 2] = 1.0
    elif frame == "com-mean":
        w = lengths / lengths.sum()
    else:
        raise ValueError(frame)
    h_pos = w @ mid
    h_ang = w @ ang
    dpos = np.zeros((2, d))
    dang = np.zeros(d)
    for i in range(n):
        for j in range(i):
            dpos[:, j] += w[i] * _perp(mid[i] - joints[j])
            dang[j] += w[i]
    # xi_body = Ad_{h^-1} xi_ref + h^{-1} dh/dr r_dot
    rt = _rot(h_ang).T
    ad_inv = np.zeros((3, 3))
    ad_inv[:2, :2] = rt
    # velocity of the point h_pos moving with link-1 frame twist (v, w): v + w × h_pos.
    ad_inv[:2, 2] = rt @ _perp(h_pos)
    ad_inv[2, 2] = 1.0
    body_from_h = np.zeros((3, d))
    body_from_h[:2] = rt @ dpos
    body_from_h[2] = dang
    a_body = ad_inv @ a_ref + body_from_h
    return a_body, 0.5 * (total + total.T)
