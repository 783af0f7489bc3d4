"""Procrustes: both sides lifted to 3D, rigid Kabsch alignment in RANSAC, optional ICP.

The RANSAC draws batches of 3-point samples and scores them all at once (numpy), stops adaptively at
the paper's confidence, then refits on the inliers until the inlier set stops growing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..estimate import Estimate, Signals
from ..geometry import Intrinsics, Pose, backproject_depth
from ..options import option
from .base import SolverOptions
from .common import (
    DEPTH_SAMPLING,
    MAX_DEPTH,
    DepthSampling,
    GuardedSolver,
    SolverError,
    Timer,
    backproject_keypoints,
    kabsch,
    rotation_is_valid,
    sample_depth_at,
    scale_ratio,
    valid_depth_map,
)
from .confidence import CONFIDENCE_MODES, ConfidenceMode, choose, confidences
from .icp import ICP_METHODS, IcpMethod, icp

__all__ = ["ProcrustesOptions", "ProcrustesSolver", "ransac_rigid"]


@dataclass
class ProcrustesOptions(SolverOptions):
    """Defaults follow the public code (Open3D's RANSAC on correspondences: 3-point samples, 0.05 m,
    at most 100000 iterations, confidence 0.999); ICP off."""

    inlier_threshold: float = option(0.05, min=0, min_open=True)  # metres
    max_iterations: int = option(100_000, min=1)
    ransac_confidence: float = option(0.999, min=0, max=1, min_open=True, max_open=True)
    refine_steps: int = option(3, min=0)  # refits on the inliers (local optimisation)
    icp: bool = False
    icp_max_iterations: int = option(30, min=1)
    icp_max_points: int = option(20_000, min=3)  # per cloud, regular subsampling of the back-projected depth maps
    icp_method: IcpMethod = option("point_to_point", choices=ICP_METHODS)  # the public code's | "point_to_plane"
    depth_sampling: DepthSampling = option("nearest", choices=DEPTH_SAMPLING)
    min_matches: int = option(5, min=3)
    confidence: ConfidenceMode = option("inliers", choices=CONFIDENCE_MODES)
    seed: int = 0


def _count(P: np.ndarray, Q: np.ndarray, R: np.ndarray, t: np.ndarray, thr: float) -> np.ndarray:
    return np.linalg.norm(P @ R.T + t - Q, axis=1) < thr


def ransac_rigid(
    P: np.ndarray,
    Q: np.ndarray,
    threshold: float,
    max_iterations: int = 100_000,
    confidence: float = 0.999,
    refine_steps: int = 3,
    seed: int = 0,
):
    """Robust rigid alignment ``Q ≈ R P + t`` (3-point RANSAC, then refits on the inliers).

    Args:
        P: (N, 3) points, metres.
        Q: (N, 3) corresponding points, metres.
        threshold: Inlier distance, metres.
        max_iterations: At most this many hypotheses.
        confidence: Stop when a better hypothesis is this unlikely.
        refine_steps: Refits on the inliers while they grow.
        seed: The random stream's seed.

    Returns:
        R (3, 3), t (3,) and the (N,) inlier mask.

    Raises:
        SolverError: No consistent triplet.
    """
    n = len(P)
    rng = np.random.default_rng(seed)
    batch = int(np.clip(2_000_000 // max(n, 1), 16, 512))
    best, best_R, best_t = 0, None, None
    needed, done = max_iterations, 0
    while done < min(needed, max_iterations):
        b = min(batch, max_iterations - done)
        idx = np.argsort(rng.random((b, n)), axis=1)[:, :3] if n <= 64 else rng.integers(0, n, (b, 3))
        S, T = P[idx], Q[idx]
        area = np.linalg.norm(np.cross(S[:, 1] - S[:, 0], S[:, 2] - S[:, 0]), axis=1)
        good = (area > 1e-8) & (idx[:, 0] != idx[:, 1]) & (idx[:, 0] != idx[:, 2]) & (idx[:, 1] != idx[:, 2])
        done += b
        if not good.any():
            continue
        R, t = kabsch(S[good], T[good])
        res = np.linalg.norm(np.einsum("bij,nj->bni", R, P) + t[:, None] - Q[None], axis=2)
        counts = np.sum(res < threshold, axis=1)
        j = int(np.argmax(counts))
        if counts[j] > best:
            best, best_R, best_t = int(counts[j]), R[j], t[j]
            w = best / n
            p_fail = 1.0 - w**3
            needed = 0 if p_fail <= 0 else int(np.ceil(np.log(1 - confidence) / np.log(p_fail)))
    if best_R is None or best_t is None or best < 3:
        raise SolverError("rigid RANSAC found no consistent triplet")
    mask = _count(P, Q, best_R, best_t, threshold)
    for _ in range(refine_steps):
        R, t = kabsch(P[mask], Q[mask])
        m2 = _count(P, Q, R, t, threshold)
        if m2.sum() < mask.sum() or m2.sum() < 3:
            break
        best_R, best_t, grew, mask = R, t, m2.sum() > mask.sum(), m2
        if not grew:
            break
    return best_R, best_t, mask


def _collinear(X: np.ndarray) -> bool:
    """True when the points span (numerically) at most a line: rotation about it is undetermined."""
    sv = np.linalg.svd(X - X.mean(0), compute_uv=False)
    return not sv[1] > 1e-6 * max(sv[0], 1e-12)


def _cloud(depth: np.ndarray, K: Intrinsics, max_points: int) -> np.ndarray:
    """Back-projected valid pixels of a depth map on a regular 2-D pixel grid of at most ``max_points``."""
    d = np.asarray(depth, dtype=np.float64)
    if d.shape != (K.height, K.width):
        K = K.resized(d.shape[1], d.shape[0])
    X = backproject_depth(d, K.K)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(d) & (d > 0) & (d < MAX_DEPTH)
    step = max(1, int(np.ceil(np.sqrt(ok.sum() / max(max_points, 1)))))
    return X[::step, ::step][ok[::step, ::step]]


class ProcrustesSolver(GuardedSolver[ProcrustesOptions]):
    """3D–3D rigid alignment of the matched, back-projected keypoints. Never raises on bad input."""

    name = "procrustes"
    Options = ProcrustesOptions

    def _solve(self, matches, K_ref, K_query, depth_ref, depth_query, timer: Timer) -> Estimate:
        opt = self.options
        k0, k1 = self._finite_matches(matches, max(opt.min_matches, 3))
        n = len(k0)
        missing = [s for s, d in (("reference", depth_ref), ("query", depth_query)) if not valid_depth_map(d)]
        if missing:
            raise SolverError(f"no valid depth for the {' and '.join(missing)} image")
        d0 = sample_depth_at(depth_ref, k0, K_ref, opt.depth_sampling)
        d1 = sample_depth_at(depth_query, k1, K_query, opt.depth_sampling)
        valid = (d0 > 0) & (d1 > 0)
        n_valid = int(valid.sum())
        if n_valid < 3:
            raise SolverError(f"too few matches with valid depth in both images ({n_valid} < 3)")
        P = backproject_keypoints(k0[valid], d0[valid], K_ref, opt.depth_sampling)
        Q = backproject_keypoints(k1[valid], d1[valid], K_query, opt.depth_sampling)
        if _collinear(P) or _collinear(Q):
            raise SolverError("degenerate geometry: the points are collinear")
        with timer("ransac"):
            R, t, mask = ransac_rigid(
                P, Q, opt.inlier_threshold, opt.max_iterations, opt.ransac_confidence, opt.refine_steps, opt.seed
            )
        if _collinear(P[mask]):
            raise SolverError("degenerate geometry: the inlier points are collinear")
        extras: dict = {"n_matches": n, "n_depth_valid": n_valid, "icp": bool(opt.icp), "metric": True}
        if opt.icp:
            with timer("icp"):
                src, dst = (
                    _cloud(depth_ref, K_ref, opt.icp_max_points),
                    _cloud(depth_query, K_query, opt.icp_max_points),
                )
                R, t, fitness, rmse = icp(
                    src, dst, R, t, opt.inlier_threshold, opt.icp_max_iterations, method=opt.icp_method
                )
            extras.update(icp_fitness=fitness, icp_rmse=rmse)
            mask = _count(P, Q, R, t, opt.inlier_threshold)
        if not rotation_is_valid(R) or not np.all(np.isfinite(t)):
            raise SolverError("degenerate rigid alignment")
        n_in = int(mask.sum())
        res = np.linalg.norm(P[mask] @ R.T + t - Q[mask], axis=1)
        ratio = n_in / n_valid
        values = confidences(n_in, ratio)
        extras.update(
            values, n_inliers=n_in, inlier_ratio=ratio, rmse=float(np.sqrt(np.mean(res**2))) if n_in else -1.0
        )
        signals = Signals(
            n_matches=n,
            n_inliers=n_in,
            inlier_ratio=ratio,
            score=values["confidence_score"],
            residual=float(np.sqrt(np.mean(res**2))) if n_in else None,
            depth_valid_fraction=n_valid / n,
            scale_ratio=scale_ratio(P[mask], Q[mask]),
        )
        return Estimate(Pose(R, t), choose(opt.confidence, values), n_in, extras=extras, signals=signals)
