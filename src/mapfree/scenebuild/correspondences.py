"""Ground-truth correspondences for training pairs, from depth and the built poses (no matching needed).

Pixels of frame A with depth are back-projected, moved by the relative pose into frame B and projected;
a pixel survives when B sees a surface at the depth it arrives with (so occluded points drop out).
Stored per scene in ``correspondences.npz``: ``pairs (P,4) = seqA frameA seqB frameB``, ``offsets (P+1,)``,
``kpts0 / kpts1 (N,2)`` pixels; pair p owns rows ``offsets[p]:offsets[p+1]``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry import Intrinsics, Pose, backproject, project

__all__ = ["CorrespondenceOptions", "depth_correspondences", "write_correspondences", "read_correspondences"]


@dataclass(frozen=True)
class CorrespondenceOptions:
    """Settings of the training correspondences computed from depth (``correspondences.npz``).

    Attributes:
        min_overlap: Pairs with overlap above this (exclusive; covers the paper's 0.4-0.8 and low-overlap 0.2).
        max_overlap: Pairs with overlap below this (exclusive).
        step: Pixel grid of frame A: every ``step``-th pixel.
        rel_tol: Depth agreement in B, relative: ``|z - d_B| <= abs_tol + rel_tol * d_B``.
        abs_tol: Depth agreement in B, metres.
        sparse_radius: Sparse (SfM) depth in B is dilated by this many pixels before the check.
        max_pairs: Pairs per scene, the highest-overlap pairs first.
    """

    min_overlap: float = 0.2  # pairs with min < overlap < max (covers the paper's 0.4-0.8 and low-overlap 0.2)
    max_overlap: float = 0.8
    step: int = 8  # pixel grid of frame A (every step-th pixel)
    rel_tol: float = 0.03  # depth agreement in B: |z - d_B| <= abs_tol + rel_tol d_B
    abs_tol: float = 0.03
    sparse_radius: int = 3  # sparse (SfM) depth in B is dilated by this many pixels before the check
    max_pairs: int = 2000  # per scene, the highest-overlap pairs first


def depth_correspondences(
    depth_a: np.ndarray,
    K_a: Intrinsics,
    pose_a: Pose,
    depth_b: np.ndarray,
    K_b: Intrinsics,
    pose_b: Pose,
    opts: CorrespondenceOptions = CorrespondenceOptions(),
    sparse: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """``(kpts_a (n,2), kpts_b (n,2))`` float32 pixels of A's depth pixels that B sees at a consistent depth.

    ``sparse``: the depth maps hold SfM points only; every one of A's is tried and B's is dilated.
    """
    step = 1 if sparse else opts.step
    d = depth_a[::step, ::step]
    v, u = np.nonzero(d > 0)
    uv = np.stack([u * step, v * step], 1).astype(np.float64)
    if len(uv) == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
    X = (pose_b @ pose_a.inverse()).transform(backproject(uv, d[v, u].astype(np.float64), K_a.K))
    z = X[:, 2]
    front = z > 1e-6
    uv_b = project(np.where(front[:, None], X, 1.0), K_b.K)
    ub, vb = np.rint(uv_b[:, 0]).astype(np.int64), np.rint(uv_b[:, 1]).astype(np.int64)
    H, W = depth_b.shape
    inside = front & (ub >= 0) & (ub < W) & (vb >= 0) & (vb < H)
    db = depth_b
    if sparse and opts.sparse_radius > 0:  # nearest SfM point within the radius stands in for a dense map
        r = 2 * opts.sparse_radius + 1
        db = cv2.dilate(np.asarray(depth_b, np.float32), np.ones((r, r), np.uint8))
    dz = np.zeros(len(z))
    dz[inside] = db[vb[inside], ub[inside]]
    ok = inside & (dz > 0) & (np.abs(z - dz) <= opts.abs_tol + opts.rel_tol * dz)
    return uv[ok].astype(np.float32), uv_b[ok].astype(np.float32)


def write_correspondences(
    path: os.PathLike | str, pairs: list[tuple[int, int, int, int]], matches: list[tuple[np.ndarray, np.ndarray]]
) -> None:
    sizes = np.array([len(a) for a, _ in matches], np.int64)
    offsets = np.r_[0, np.cumsum(sizes)].astype(np.int64)
    k0 = np.concatenate([a for a, _ in matches]) if matches else np.zeros((0, 2), np.float32)
    k1 = np.concatenate([b for _, b in matches]) if matches else np.zeros((0, 2), np.float32)
    np.savez_compressed(path, pairs=np.asarray(pairs, np.int32).reshape(-1, 4), offsets=offsets, kpts0=k0, kpts1=k1)


def read_correspondences(path: os.PathLike | str) -> dict[tuple[int, int, int, int], tuple[np.ndarray, np.ndarray]]:
    """Read the training correspondences of a built scene.

    Args:
        path: The scene's ``correspondences.npz``.

    Returns:
        ``{(seqA, frameA, seqB, frameB): (kpts0, kpts1)}``, each (n, 2) pixel coordinates in frame A and B.
    """
    with np.load(path) as z:
        pairs, off, k0, k1 = z["pairs"], z["offsets"], z["kpts0"], z["kpts1"]
    return {
        (int(p[0]), int(p[1]), int(p[2]), int(p[3])): (k0[off[i] : off[i + 1]], k1[off[i] : off[i + 1]])
        for i, p in enumerate(pairs)
    }
