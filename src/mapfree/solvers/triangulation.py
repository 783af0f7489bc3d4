"""Pose triangulation (the paper's K >= 2 baseline, §5.1): metric query pose from relative *directions* only.

Each reference ``i`` has a known world-to-camera pose and an up-to-scale relative pose ``(R_i, t̂_i)`` of the
query (e.g. Ess.Mat without depth). The query rotation follows from any of them (``R_i R_ref_i``); its centre
lies on the ray from reference ``i``'s centre along ``-R_ref_i^T R_i^T t̂_i``. Intersecting two or more rays
(least squares) fixes the centre, and with it the metric translation: the scale comes from the distance
between the references, not from depth.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..estimate import Estimate
from ..geometry import Pose
from ..options import Options, option

__all__ = ["TriangulationOptions", "triangulate_pose", "query_rays"]


@dataclass
class TriangulationOptions(Options):
    """Rays closer than ``min_ray_angle_deg`` to parallel, or meeting behind a reference, give no estimate."""

    min_ray_angle_deg: float = option(1.0, min=0, max=90)
    min_baseline_m: float = option(1e-3, min=0)  # references closer than this cannot fix a scale


def query_rays(ref_poses: Sequence[Pose], relative: Sequence[Pose]) -> tuple[np.ndarray, np.ndarray]:
    """Rays from each reference's centre towards the query's.

    Args:
        ref_poses: The references' world-to-camera poses.
        relative: Each reference-to-query relative pose (its translation's direction is used).

    Returns:
        Origins (n, 3) (the reference centres, world frame) and unit world directions (n, 3).
    """
    origins = np.stack([p.center for p in ref_poses])
    dirs = []
    for ref, rel in zip(ref_poses, relative):
        t = rel.t / max(np.linalg.norm(rel.t), 1e-12)
        dirs.append(-ref.R.T @ rel.R.T @ t)
    d = np.stack(dirs)
    return origins, d / np.linalg.norm(d, axis=1, keepdims=True)


def _mean_rotation(Rs: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted chordal mean of rotations: the rotation nearest (Frobenius) to their weighted sum."""
    U, _, Vt = np.linalg.svd(np.einsum("n,nij->ij", w, Rs))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def triangulate_pose(
    ref_poses: Sequence[Pose],
    relative: Sequence[Pose],
    weights: Sequence[float] | None = None,
    options: TriangulationOptions | None = None,
) -> Estimate:
    """World-to-camera query pose from n >= 2 references and the query's up-to-scale relative poses.

    The centre is the weighted least-squares intersection of the rays (``query_rays``); the rotation the weighted
    chordal mean of ``R_i R_ref_i``.

    Args:
        ref_poses: The references' world-to-camera poses.
        relative: ``relative[i]`` maps reference ``i``'s camera to the query camera (``X_q = R_i X_i + s t̂_i``);
            only the direction of its translation is used.
        weights: Per reference (e.g. inlier counts); default all 1.
        options: Ray-angle and baseline limits.

    Returns:
        The estimate (metric: the scale comes from the distance between the references); its confidence is the
        smallest weight (every ray must be trustworthy). A failure for fewer than 2 references, nearly parallel
        rays, too short a baseline or rays that meet behind a reference.
    """
    o = options or TriangulationOptions()
    n = len(ref_poses)
    if n < 2 or len(relative) != n:
        return Estimate.failure(f"pose triangulation needs >= 2 references with relative poses, got {n}")
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    w = np.where(np.isfinite(w) & (w > 0), w, 0.0)
    if np.count_nonzero(w) < 2:
        w = np.ones(n)
    if not all(r.is_finite() and np.linalg.norm(r.t) > 0 for r in relative):
        return Estimate.failure("pose triangulation: a relative pose has no translation direction")
    origins, dirs = query_rays(ref_poses, relative)
    baseline = float(np.max(np.linalg.norm(origins[:, None] - origins[None], axis=-1)))
    if baseline < o.min_baseline_m:
        return Estimate.failure(f"pose triangulation: references {baseline:.4f} m apart cannot fix the scale")
    cos = np.clip(np.abs(dirs @ dirs.T), 0.0, 1.0)
    widest = float(np.degrees(np.arccos(cos.min())))
    if widest < o.min_ray_angle_deg:
        return Estimate.failure(f"pose triangulation: rays {widest:.2f}° apart are nearly parallel")
    P = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # projectors orthogonal to each ray
    A = np.einsum("n,nij->ij", w, P)
    b = np.einsum("n,nij,nj->i", w, P, origins)
    center = np.linalg.solve(A, b)
    along = np.einsum("ni,ni->n", center - origins, dirs)
    if np.any(along <= 0):
        return Estimate.failure("pose triangulation: the rays meet behind a reference")
    miss = np.linalg.norm(np.einsum("nij,nj->ni", P, center - origins), axis=1)
    R = _mean_rotation(np.stack([rel.R @ ref.R for ref, rel in zip(ref_poses, relative)]), w / w.sum())
    pose = Pose(R, -R @ center)
    extras = {
        "ray_angle_deg": widest,
        "ray_miss_m": float(miss.max()),
        "baseline_m": baseline,
        "distances_m": along.tolist(),
    }
    return Estimate(pose, float(w.min()), int(w.min()), extras=extras)
