"""Keypoints rendered from a simulated swimmer: what a video tracker would hand over.

The rendering is the forward kinematics of the swimmer's link chain
(:meth:`~torchconn.physics.systems.NLinkSwimmer.link_poses`, the physics code's own geometry),
so the tracking converter, which inverts it, is checked against an independent computation.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import torch

from ..io.tracking.readers import Keypoints
from ..physics.systems.swimmer import NLinkSwimmer
from ..trajectory import Trajectory

__all__ = ["render_keypoints", "write_sleap_csv"]


def render_keypoints(
    traj: Trajectory,
    system: NLinkSwimmer,
    *,
    per_link: int = 1,
    pixels_per_length: float = 200.0,
    noise_px: float = 0.0,
    y_down: bool = True,
    origin_px: tuple[float, float] = (640.0, 360.0),
    dropout: float = 0.0,
    seed: int = 0,
    fps: float | None = None,
) -> list[Keypoints]:
    """Keypoints along the body of each trial, in pixels, head first.

    Args:
        traj: recorded poses and shapes, batch ``(n_trials,)`` (or none).
        system: the swimmer (its frame and link lengths place the links).
        per_link: keypoints per link: the link's start and ``per_link − 1`` more along it; the
            head's tip closes the list (``N·per_link + 1`` keypoints).
        pixels_per_length: pixels per body length.
        noise_px: standard deviation of Gaussian pixel noise on every coordinate.
        y_down: image y axis pointing down (world y is flipped).
        origin_px: pixel position of the world origin.
        dropout: probability that a keypoint is lost (NaN, score 0).
        seed: random seed of the noise, drop-outs and scores.
        fps: frames per second the returned ``times`` assume (default: ``1 / traj.dt``).

    Returns:
        one :class:`Keypoints` per trial (format ``"points"``, ``scores`` in [0, 1]: high for
        tracked points, 0 for lost ones), ``times`` from the trajectory's ``t``.
    """
    pose = traj.pose.reshape(-1, traj.n_samples, 3)
    r = traj.r.reshape(-1, traj.n_samples, traj.shape_dim)
    links = system.link_poses(torch.nan_to_num(r))  # (B, T, N, 3) midpoints in the body frame
    lengths = system.link_lengths.to(r)
    u = torch.arange(per_link, dtype=r.dtype) / per_link  # fractions along a link
    c, s = torch.cos(links[..., 2]), torch.sin(links[..., 2])
    start = links[..., :2] - (lengths / 2)[:, None] * torch.stack([c, s], -1)
    along = start[..., None, :] + (u[:, None] * lengths[:, None, None]) [None, None] * \
        torch.stack([c, s], -1)[..., None, :]
    pts = along.reshape(*links.shape[:-2], -1, 2)  # (B, T, N·per_link, 2) tail to head
    tip = links[..., -1, :2] + (lengths[-1] / 2) * torch.stack([c[..., -1], s[..., -1]], -1)
    pts = torch.cat([pts, tip[..., None, :]], -2)
    # body frame to world: rotate by θ, shift by (x, y)
    th = pose[..., 2][..., None]
    wx = pose[..., 0][..., None] + torch.cos(th) * pts[..., 0] - torch.sin(th) * pts[..., 1]
    wy = pose[..., 1][..., None] + torch.sin(th) * pts[..., 0] + torch.cos(th) * pts[..., 1]
    px = origin_px[0] + pixels_per_length * wx
    py = origin_px[1] + (-1 if y_down else 1) * pixels_per_length * wy
    img = torch.stack([px, py], -1).flip(-2).numpy()  # head first
    rng = np.random.default_rng(seed)
    img = img + noise_px * rng.standard_normal(img.shape)
    lost = rng.random(img.shape[:-1]) < dropout
    lost |= ~np.isfinite(img).all(-1)
    img[lost] = np.nan
    scores = np.where(lost, 0.0, rng.uniform(0.8, 1.0, lost.shape))
    K = img.shape[-2]
    names = tuple(["head"] + [f"k{i}" for i in range(1, K - 1)] + ["tail"])
    t = traj.t.numpy()
    if fps is not None:
        t = t[0] + np.arange(len(t)) / fps
    return [Keypoints(points=img[b], names=names, frames=np.arange(len(t), dtype=np.int64),
                      scores=scores[b], times=t.copy(), source=f"rendered trial {b}",
                      format="points", units="px") for b in range(img.shape[0])]


def write_sleap_csv(kp: Keypoints, path: str | Path, track: str = "track_0") -> Path:
    """Write keypoints in SLEAP's analysis CSV layout (``track, frame_idx, instance.score,
    <node>.x, <node>.y, <node>.score, ...``; a lost point has empty cells)."""
    path = Path(path)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["track", "frame_idx", "instance.score"]
                   + [f"{n}.{a}" for n in kp.names for a in ("x", "y", "score")])
        scores = kp.scores if kp.scores is not None else np.ones(kp.points.shape[:2])
        for f, pts, sc in zip(kp.frames, kp.points, scores, strict=True):
            ok = np.isfinite(pts).all(-1)
            if not ok.any():
                continue  # SLEAP writes no row for a frame without an instance
            row = [track, int(f), f"{float(np.mean(sc[ok])):.4f}"]
            for (x, y), s_, o in zip(pts, sc, ok, strict=True):
                row += [f"{x:.3f}", f"{y:.3f}", f"{s_:.4f}"] if o else ["", "", ""]
            w.writerow(row)
    return path
