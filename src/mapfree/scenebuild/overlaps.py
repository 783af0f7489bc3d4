"""Overlaps of a built scene as the paper defines them: shared 3D points / max(points seen in either frame).

Two point sets, one ratio:
- ``sfm_overlaps``: the SfM points, seen where a frame observes them (its tracks) — the paper's own recipe,
  used when frames have no depth. Tracks miss points the matcher could not link (light changes between
  scans, wide baselines), so it undercounts overlap across scans.
- ``depth_overlaps``: with metric depth for every frame (LiDAR, RGB-D), surface points spread evenly over each
  frame (back-projected with the built pose), seen in every frame where they project inside the image and
  agree with that frame's depth (unoccluded). Dense and unbiased by texture or lighting.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import sparse

from ..data.overlaps import Overlaps
from ..geometry import Intrinsics, Pose, backproject

__all__ = ["sfm_overlaps", "depth_overlaps", "covisibility_overlaps", "visible_in_depth"]


def covisibility_overlaps(V: sparse.csr_matrix, seq: np.ndarray, number: np.ndarray) -> Overlaps:
    """Every ordered pair of distinct frames sharing a point, from a (frames x points) 0/1 incidence matrix.

    One sparse product, so a scene of thousands of frames and a million points stays cheap.
    """
    V = sparse.csr_matrix(V, dtype=np.float32)
    shared = (V @ V.T).tocoo()
    n = np.asarray(V.sum(1)).ravel().astype(np.float64)
    keep = (shared.row != shared.col) & (shared.data > 0)
    a, b, common = shared.row[keep], shared.col[keep], shared.data[keep]
    order = np.lexsort((b, a))
    a, b, common = a[order], b[order], common[order]
    seq, number = np.asarray(seq), np.asarray(number)
    idxs = np.stack([seq[a], number[a], seq[b], number[b]], 1).astype(np.int64).reshape(-1, 4)
    return Overlaps(idxs, common / np.maximum(np.maximum(n[a], n[b]), 1))


def sfm_overlaps(point_ids: list[np.ndarray], seq: np.ndarray, number: np.ndarray) -> Overlaps:
    """Overlaps from SfM tracks: ``point_ids[i]`` are the SfM points frame i observes."""
    sets = [np.unique(p) for p in point_ids]
    rows = np.repeat(np.arange(len(sets)), [len(s) for s in sets])
    cols = np.concatenate(sets) if sets else np.zeros(0, np.int64)
    _, cols = np.unique(cols, return_inverse=True)
    V = sparse.csr_matrix(
        (np.ones(len(rows), np.float32), (rows, cols.ravel())),
        shape=(len(sets), int(cols.max()) + 1 if len(cols) else 0),
    )
    return covisibility_overlaps(V, seq, number)


def _grid_samples(depth: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``n`` pixels with depth, evenly spread over the frame (deterministic): ``(uv (m,2), z (m,))``."""
    v, u = np.nonzero(depth > 0)
    if len(v) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    pick = np.unique(np.linspace(0, len(v) - 1, min(n, len(v))).round().astype(np.int64))
    return np.stack([u[pick], v[pick]], 1).astype(np.float64), depth[v[pick], u[pick]].astype(np.float64)


def visible_in_depth(
    X_world: np.ndarray, pose: Pose, K: Intrinsics, depth: np.ndarray, abs_tol: float = 0.05, rel_tol: float = 0.05
) -> np.ndarray:
    """(N,) bool: the point projects inside the frame, in front, onto a pixel with depth, and is not behind
    that surface by more than the tolerance (occluded). One-sided: a point a little in front of the surface
    (pose error on a grazing floor) still counts, as the surface seen there is its own."""
    X = pose.transform(X_world)
    z = X[:, 2]
    zs = np.where(z > 1e-6, z, 1.0)
    u = np.rint(K.fx * X[:, 0] / zs + K.cx).astype(np.int64)
    v = np.rint(K.fy * X[:, 1] / zs + K.cy).astype(np.int64)
    H, W = depth.shape
    ok = (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    d = np.zeros(len(z))
    d[ok] = depth[v[ok], u[ok]]
    return ok & (d > 0) & (z - d <= abs_tol + rel_tol * d)


def depth_overlaps(
    poses: list[Pose],
    intrinsics: list[Intrinsics],
    depths: list[np.ndarray],
    seq: np.ndarray,
    number: np.ndarray,
    points_per_frame: int = 300,
    abs_tol: float = 0.05,
    rel_tol: float = 0.05,
    window: float = 0.025,
) -> Overlaps:
    """Overlaps from metric depth and metric world-to-camera poses (see the module docstring).

    The occlusion test takes the farthest depth within a window of ``window`` x the image's longer side:
    SfM poses bend by a few tenths of a degree over a scan, and that many pixels of error on a grazing floor
    or at an object's silhouette must not hide a point that is there.
    """
    test = []
    for d in depths:
        k = 2 * int(round(window * max(d.shape) / 2)) + 1
        test.append(cv2.dilate(np.asarray(d, np.float32), np.ones((k, k), np.uint8)) if k > 1 else d)
    pts = []
    for pose, K, d in zip(poses, intrinsics, depths):
        uv, z = _grid_samples(d, points_per_frame)
        pts.append(pose.inverse().transform(backproject(uv, z, K.K)))
    X = np.concatenate(pts) if pts else np.zeros((0, 3))
    vis = [visible_in_depth(X, p, K, d, abs_tol, rel_tol) for p, K, d in zip(poses, intrinsics, test)]
    return covisibility_overlaps(sparse.csr_matrix(np.stack(vis)) if vis else sparse.csr_matrix((0, 0)), seq, number)
