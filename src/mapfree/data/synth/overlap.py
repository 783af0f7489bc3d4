"""Co-visibility between frames: the overlap stored in ``overlaps.npz`` and a dense depth-based check.

``overlap = shared visible points / max(points visible in either frame)``, over a fixed set of
surface points of the scene standing in for the SfM points of the real dataset: like features, they are
spread evenly over the images (a few hundred per frame, back-projected with the exact depth), so near and far
surfaces weigh as they do in real reconstructions.
"""

from __future__ import annotations

import numpy as np

from ...geometry import Intrinsics, Pose, backproject
from .render import rasterize
from .world import World

__all__ = ["sample_frame_points", "visible_points", "overlap_matrix", "overlap_pairs", "depth_overlap"]


def sample_frame_points(
    world: World, pose: Pose, K: Intrinsics, n: int, rng: np.random.Generator, scale: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """``(points (m,3) world, quad (m,))``: up to ``n`` surface points seen at random pixels of a frame.

    Rendered at ``scale`` resolution (the points are exact surface points whatever the resolution).
    """
    Ks = K.scaled(scale)
    qid, depth = rasterize(world, pose, Ks)
    v, u = np.nonzero(qid >= 0)
    if len(v) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    pick = rng.choice(len(v), size=min(n, len(v)), replace=False)
    v, u = v[pick], u[pick]
    X = backproject(np.stack([u, v], 1).astype(np.float64), depth[v, u].astype(np.float64), Ks.K)
    return pose.inverse().transform(X), qid[v, u].astype(np.int64)


def _pixels(X_cam: np.ndarray, K: Intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest pixel (u, v) of camera-frame points and whether it is in the image and in front."""
    z = X_cam[:, 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    u = np.rint(K.fx * X_cam[:, 0] / zs + K.cx).astype(np.int64)
    v = np.rint(K.fy * X_cam[:, 1] / zs + K.cy).astype(np.int64)
    ok = front & (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    return np.where(ok, u, 0), np.where(ok, v, 0), ok


def visible_points(
    points: np.ndarray, point_quad: np.ndarray, pose: Pose, K: Intrinsics, qid: np.ndarray
) -> np.ndarray:
    """(N,) bool: the point is in front, inside the image, and the surface seen at its pixel is its own.

    Comparing surface ids is the depth test made exact: an occluder at any depth, even a poster 2 cm in
    front of a wall, hides the point.
    """
    u, v, ok = _pixels(pose.transform(points), K)
    return ok & (qid[v, u] == point_quad)


def overlap_matrix(vis: np.ndarray) -> np.ndarray:
    """(F,F) overlaps from (F,N) visibility: shared / max(visible in either); 0 where neither sees any."""
    V = vis.astype(np.float32)
    shared = V @ V.T
    n = V.sum(1)
    denom = np.maximum(n[:, None], n[None, :])
    return np.divide(shared, denom, out=np.zeros_like(shared), where=denom > 0)


def overlap_pairs(ov: np.ndarray, seq: np.ndarray, number: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every ordered pair of distinct frames with non-zero overlap: ``idxs (M,4) = seqA frameA seqB frameB``."""
    a, b = np.nonzero(ov > 0)
    keep = a != b
    a, b = a[keep], b[keep]
    idxs = np.stack([seq[a], number[a], seq[b], number[b]], 1).astype(np.int64)
    return idxs, ov[a, b].astype(np.float64)


def depth_overlap(
    depth_a: np.ndarray,
    K_a: Intrinsics,
    pose_a: Pose,
    depth_b: np.ndarray,
    K_b: Intrinsics,
    pose_b: Pose,
    step: int = 1,
    rel_tol: float = 0.03,
    abs_tol: float = 0.03,
) -> float:
    """Fraction of A's valid pixels (every ``step``-th) seen by B on a surface at the depth B measures there.

    Works for any frames with metric depth and poses (synthetic or real), e.g. to check that a query
    really shares nothing with its reference. Vectorised over the pixel grid (float32, no per-point copies).
    """
    f32 = np.float32
    d = np.asarray(depth_a, f32)[::step, ::step]
    valid = d > 0
    n_valid = int(valid.sum())
    if n_valid == 0:
        return 0.0
    rel = pose_b @ pose_a.inverse()
    R, t = rel.R.astype(f32), rel.t.astype(f32)
    H, W = depth_a.shape
    rx = ((np.arange(0, W, step) - K_a.cx) / K_a.fx).astype(f32)[None, :]
    ry = ((np.arange(0, H, step) - K_a.cy) / K_a.fy).astype(f32)[:, None]
    x, y, z = (d * (R[i, 0] * rx + R[i, 1] * ry + R[i, 2]) + t[i] for i in range(3))
    front = valid & (z > 1e-6)
    zs = np.where(front, z, f32(1))
    u = np.rint(f32(K_b.fx) * x / zs + f32(K_b.cx))
    v = np.rint(f32(K_b.fy) * y / zs + f32(K_b.cy))
    Hb, Wb = depth_b.shape
    ok = front & (u >= 0) & (u <= Wb - 1) & (v >= 0) & (v <= Hb - 1)
    if not ok.any():
        return 0.0
    db = np.asarray(depth_b, f32)[v[ok].astype(np.int64), u[ok].astype(np.int64)]
    hit = (db > 0) & (np.abs(z[ok] - db) <= abs_tol + rel_tol * db)
    return float(hit.sum() / n_valid)
