"""A short ICP (kd-tree nearest neighbours) with Open3D's stopping rule: point-to-point or point-to-plane.

Point-to-point (Kabsch on nearest pairs) is what the public Map-free code runs through Open3D; on
subsampled depth maps it is biased by the sampling grid. Point-to-plane (linearised, normals from a
local PCA of the target) slides along surfaces and converges to the surface alignment instead.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal, get_args

import numpy as np

from .common import kabsch

if TYPE_CHECKING:  # SciPy's spatial module loads only when ICP runs (a third of a second of every CLI start)
    from scipy.spatial import cKDTree

__all__ = ["ICP_METHODS", "IcpMethod", "icp", "estimate_normals"]

#: How ICP measures a point's distance: to its neighbour (the public code's) or to the neighbour's tangent plane.
IcpMethod = Literal["point_to_point", "point_to_plane"]
ICP_METHODS: tuple[IcpMethod, ...] = get_args(IcpMethod)


def estimate_normals(X: np.ndarray, tree: cKDTree, k: int = 10) -> np.ndarray:
    """Unit normals of points: the smallest principal axis of each point's k nearest neighbours.

    Args:
        X: (N, 3) points.
        tree: A KD-tree of ``X``.
        k: Neighbours per point.

    Returns:
        (N, 3) unit normals (sign arbitrary).
    """
    _, nn = tree.query(X, k=min(k, len(X)))
    nb = X[nn] - X[nn].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    return np.linalg.eigh(cov)[1][:, :, 0]


def _rotvec(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    a = float(np.linalg.norm(w))
    if a < 1e-15:
        return np.eye(3)
    k = w / a
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * Kx + (1 - np.cos(a)) * Kx @ Kx


def _point_to_plane_step(p: np.ndarray, q: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Small rigid update (dR, dt) minimising sum(((dR p + dt - q) . n)^2), linearised in the rotation."""
    A = np.hstack([np.cross(p, n), n])
    b = np.einsum("ij,ij->i", q - p, n)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    return _rotvec(x[:3]), x[3:]


def icp(
    src: np.ndarray,
    dst: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    max_distance: float,
    max_iterations: int = 30,
    relative_fitness: float = 1e-4,
    relative_rmse: float = 1e-4,
    method: str = "point_to_point",
):
    """Refine ``dst ≈ R src + t`` from an initial guess (point-to-point or point-to-plane ICP).

    Stops when fitness and rmse change by less than the given amounts, or when fewer than 6 pairs remain (keeping
    the last pose).

    Args:
        src: (N, 3) points, metres.
        dst: (M, 3) points, metres.
        R: (3, 3) initial rotation.
        t: (3,) initial translation.
        max_distance: Pairs farther apart are not used, metres.
        max_iterations: At most this many updates.
        relative_fitness: Stop when the fitness changes by less.
        relative_rmse: Stop when the rmse changes by less (metres).
        method: ``point_to_point`` or ``point_to_plane``.

    Returns:
        (R, t, fitness, rmse): fitness is the fraction of ``src`` with a neighbour within ``max_distance``, rmse
        theirs (metres).

    Raises:
        ValueError: An unknown method.
    """
    if method not in ICP_METHODS:
        raise ValueError(f"ICP method must be one of {ICP_METHODS}, got {method!r}")
    if len(src) < 6 or len(dst) < 6:
        return R, t, 0.0, 0.0
    from scipy.spatial import cKDTree

    tree = cKDTree(dst)
    normals = estimate_normals(dst, tree) if method == "point_to_plane" else None
    prev = None
    fitness, rmse = 0.0, 0.0
    for _ in range(max_iterations + 1):
        moved = src @ R.T + t
        dist, j = tree.query(moved, distance_upper_bound=max_distance)
        m = np.isfinite(dist)
        fitness = float(m.mean())
        rmse = float(np.sqrt(np.mean(dist[m] ** 2))) if m.any() else 0.0
        if m.sum() < 6:
            break
        if prev is not None and abs(prev[0] - fitness) < relative_fitness and abs(prev[1] - rmse) < relative_rmse:
            break
        prev = (fitness, rmse)
        if normals is None:
            R, t = kabsch(src[m], dst[j[m]])
        else:
            dR, dt = _point_to_plane_step(moved[m], dst[j[m]], normals[j[m]])
            R, t = dR @ R, dR @ t + dt
    return R, t, fitness, rmse
