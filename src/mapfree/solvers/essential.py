"""Ess.Mat + D.Scale: 5-point essential matrix in MAGSAC++, cheirality, metric scale by depth vote.

Points are normalised with each frame's own intrinsics (phones refocus), so the robust estimation runs
with an identity camera and a threshold of ``px / mean focal``. The unit translation ``t̂`` is scaled by the
max-consensus vote over the per-inlier hypotheses ``s_i = (X1_i - R X0_i) · t̂`` (see ``scale.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..estimate import Estimate, Signals
from ..geometry import Intrinsics, Pose
from ..options import option
from .base import SolverOptions
from .common import (
    BACKENDS,
    DEPTH_SAMPLING,
    Backend,
    DepthSampling,
    GuardedSolver,
    SolverError,
    Timer,
    backproject_keypoints,
    normalize_points,
    rotation_is_valid,
    sample_depth_at,
    scale_ratio,
    valid_depth_map,
)
from .confidence import CONFIDENCE_MODES, ConfidenceMode, choose, confidences
from .scale import scale_vote

__all__ = [
    "EssentialOptions",
    "EssentialSolver",
    "relative_pose",
    "relative_pose_opencv",
    "relative_pose_poselib",
    "triangulated_depths",
]


@dataclass
class EssentialOptions(SolverOptions):
    """Defaults are the paper's; use ``ransac_threshold_px=2`` for learned matchers."""

    ransac_threshold_px: float = option(3.0, min=0, min_open=True)
    ransac_confidence: float = option(0.9999, min=0, max=1, min_open=True, max_open=True)
    max_iters: int = option(1000, min=1)  # OpenCV's default for findEssentialMat, as in the public code
    distance_threshold: float = option(50.0, min=0, min_open=True)  # recoverPose drops farther points (baselines)
    scale_threshold: float = option(0.1, min=0, min_open=True)  # metres, scale-vote inlier radius
    depth_sampling: DepthSampling = option("nearest", choices=DEPTH_SAMPLING)  # "floor": the public code's
    min_matches: int = option(5, min=5)
    backend: Backend = option("opencv", choices=BACKENDS)  # "opencv" (cv2 USAC_MAGSAC, the paper's) | "poselib"
    confidence: ConfidenceMode = option("inliers", choices=CONFIDENCE_MODES)  # "score": confidence.py
    allow_unscaled: bool = False  # without depth, return the unit-length translation instead of failing
    refine: bool = False  # polish (R, t̂) on the pose inliers (poselib, Sampson error, Cauchy loss); not in the paper


def triangulated_depths(x0: np.ndarray, x1: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depths of the DLT-triangulated correspondences in both cameras (``X1 = R X0 + t``).

    Args:
        x0: (N, 2) normalised coordinates in camera 0.
        x1: (N, 2) normalised coordinates in camera 1.
        R: (3, 3) rotation.
        t: (3,) translation (its scale sets the depths').

    Returns:
        (N,) depths in camera 0 and (N,) in camera 1 (NaN/inf for points at infinity).
    """
    P0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = np.hstack([R, t.reshape(3, 1)])
    A = np.stack(
        [
            x0[:, :1] * P0[2] - P0[0],
            x0[:, 1:2] * P0[2] - P0[1],
            x1[:, :1] * P1[2] - P1[0],
            x1[:, 1:2] * P1[2] - P1[1],
        ],
        axis=1,
    )
    X = np.linalg.svd(A)[2][:, -1]  # (N,4) homogeneous
    with np.errstate(divide="ignore", invalid="ignore"):
        z0 = X[:, 2] / X[:, 3]
        z1 = (X[:, :3] @ R[2] + t.reshape(3)[2] * X[:, 3]) / X[:, 3]
    return z0, z1


def relative_pose_opencv(x0: np.ndarray, x1: np.ndarray, opt: EssentialOptions, threshold: float):
    """Relative pose with OpenCV's MAGSAC++ and ``recoverPose``'s cheirality and distance check.

    Args:
        x0: (N, 2) normalised coordinates in the reference camera.
        x1: (N, 2) normalised coordinates in the query camera.
        opt: The solver's options (confidence, iterations, distance threshold).
        threshold: RANSAC threshold in normalised units (pixels / mean focal length).

    Returns:
        R (3, 3), unit t̂ (3,), the (N,) RANSAC inlier mask and the (N,) mask of inliers in front of both cameras.

    Raises:
        SolverError: No essential matrix, or no correspondence in front of both cameras.
    """
    E, mask = cv2.findEssentialMat(
        x0,
        x1,
        np.eye(3),
        method=cv2.USAC_MAGSAC,
        prob=opt.ransac_confidence,
        threshold=threshold,
        maxIters=int(opt.max_iters),
    )
    if E is None or mask is None or E.ndim != 2 or E.shape[1] != 3 or E.shape[0] % 3 or not np.all(np.isfinite(E)):
        raise SolverError("essential matrix estimation failed")
    ransac_mask = mask.reshape(-1) != 0
    best = None
    for Ei in np.split(E, E.shape[0] // 3):
        n, R, t, m, _ = cv2.recoverPose(
            Ei, x0, x1, np.eye(3), distanceThresh=float(opt.distance_threshold), mask=mask.copy()
        )
        if n > 0 and (best is None or n > best[0]):
            best = (n, R, t.reshape(3), m.reshape(-1) != 0)
    if best is None:
        raise SolverError("no correspondence passes the cheirality check (no parallax?)")
    return best[1], best[2], ransac_mask, best[3]


def refine_relative_pose(
    kpts0: np.ndarray,
    kpts1: np.ndarray,
    K0: Intrinsics,
    K1: Intrinsics,
    R: np.ndarray,
    t: np.ndarray,
    threshold_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Non-linear least squares on the inliers (poselib); returns the input when refinement fails."""
    import poselib

    init = poselib.CameraPose()
    init.R, init.t = R, t
    scale = 0.5 * threshold_px / np.mean([K0.fx, K0.fy, K1.fx, K1.fy])
    pose, _ = poselib.refine_relative_pose(
        kpts0, kpts1, init, _camera(K0), _camera(K1), {"loss_type": "CAUCHY", "loss_scale": float(scale)}
    )
    R2, t2 = np.asarray(pose.R, dtype=np.float64), np.asarray(pose.t, dtype=np.float64).reshape(3)
    norm = np.linalg.norm(t2)
    if not (np.all(np.isfinite(R2)) and np.isfinite(norm) and norm > 0 and float(t2 @ t) > 0):
        return R, t
    return R2, t2 / norm


def _camera(K: Intrinsics) -> dict:
    return {"model": "PINHOLE", "width": int(K.width), "height": int(K.height), "params": [K.fx, K.fy, K.cx, K.cy]}


def relative_pose_poselib(kpts0: np.ndarray, kpts1: np.ndarray, K0: Intrinsics, K1: Intrinsics, opt: EssentialOptions):
    """The outputs of ``relative_pose_opencv`` from poselib's LO-RANSAC with bundle refinement.

    Args:
        kpts0: (N, 2) reference pixels.
        kpts1: (N, 2) query pixels.
        K0: Reference intrinsics.
        K1: Query intrinsics.
        opt: The solver's options (threshold in pixels, confidence, iterations, distance threshold).

    Returns:
        R (3, 3), unit t̂ (3,), the RANSAC inlier mask and the cheirality-checked pose mask, (N,) each.

    Raises:
        SolverError: No essential matrix, or no correspondence in front of both cameras.
    """
    import poselib

    pose, info = poselib.estimate_relative_pose(
        kpts0,
        kpts1,
        _camera(K0),
        _camera(K1),
        {
            "max_epipolar_error": float(opt.ransac_threshold_px),
            "success_prob": float(opt.ransac_confidence),
            "max_iterations": int(opt.max_iters),
        },
        {},
    )
    ransac_mask = np.asarray(info.get("inliers", []), dtype=bool).reshape(-1)
    R, t = np.asarray(pose.R, dtype=np.float64), np.asarray(pose.t, dtype=np.float64).reshape(3)
    if (
        len(ransac_mask) != len(kpts0)
        or not ransac_mask.any()
        or not np.all(np.isfinite(R))
        or not np.linalg.norm(t) > 0
    ):
        raise SolverError("essential matrix estimation failed")
    t = t / np.linalg.norm(t)
    x0, x1 = normalize_points(kpts0, K0), normalize_points(kpts1, K1)
    z0, z1 = triangulated_depths(x0, x1, R, t)
    with np.errstate(invalid="ignore"):
        front = (z0 > 0) & (z1 > 0) & (z0 < opt.distance_threshold) & (z1 < opt.distance_threshold)
    pose_mask = ransac_mask & front
    if not pose_mask.any():
        raise SolverError("no correspondence passes the cheirality check (no parallax?)")
    return R, t, ransac_mask, pose_mask


def relative_pose(
    kpts0: np.ndarray, kpts1: np.ndarray, K0: Intrinsics, K1: Intrinsics, opt: EssentialOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The relative pose of two views from their matches, by the backend ``opt`` names, refined when it asks.

    Args:
        kpts0: (N, 2) pixel keypoints in the reference image.
        kpts1: (N, 2) matching keypoints in the query image.
        K0: Reference intrinsics.
        K1: Query intrinsics.
        opt: Backend, RANSAC threshold (pixels) and confidence, refinement.

    Returns:
        R (3, 3) and unit t (3,) taking reference-camera points to the query camera, the (N,) RANSAC inlier
        mask and the (N,) mask of the inliers in front of both cameras.

    Raises:
        SolverError: No pose.
    """
    if opt.backend == "poselib":
        R, t_hat, ransac_mask, pose_mask = relative_pose_poselib(kpts0, kpts1, K0, K1, opt)
    else:
        x0, x1 = normalize_points(kpts0, K0), normalize_points(kpts1, K1)
        thr = opt.ransac_threshold_px / np.mean([K0.fx, K0.fy, K1.fx, K1.fy])
        R, t_hat, ransac_mask, pose_mask = relative_pose_opencv(x0, x1, opt, float(thr))
    if opt.refine:
        R, t_hat = refine_relative_pose(kpts0[pose_mask], kpts1[pose_mask], K0, K1, R, t_hat, opt.ransac_threshold_px)
    return R, t_hat, ransac_mask, pose_mask


class EssentialSolver(GuardedSolver[EssentialOptions]):
    """Ess.Mat + D.Scale. ``solve`` never raises on bad input: it returns ``Estimate.failure(reason)``."""

    name = "essential"
    Options = EssentialOptions

    def _solve(self, matches, K_ref, K_query, depth_ref, depth_query, timer: Timer) -> Estimate:
        opt = self.options
        k0, k1 = self._finite_matches(matches, max(opt.min_matches, 5))
        n = len(k0)
        metric = valid_depth_map(depth_ref) and valid_depth_map(depth_query)
        if not metric and not opt.allow_unscaled:
            which = [s for s, d in (("reference", depth_ref), ("query", depth_query)) if not valid_depth_map(d)]
            raise SolverError(f"no valid depth for the {' and '.join(which)} image")

        with timer("ransac"):
            R, t_hat, ransac_mask, pose_mask = relative_pose(k0, k1, K_ref, K_query, opt)
        if not rotation_is_valid(R) or not np.all(np.isfinite(t_hat)):
            raise SolverError("degenerate relative pose")
        n_ransac, n_pose = int(ransac_mask.sum()), int(pose_mask.sum())
        extras: dict = {
            "n_matches": n,
            "n_ransac_inliers": n_ransac,
            "n_pose_inliers": n_pose,
            "inlier_ratio": n_ransac / n,
            "backend": opt.backend,
            "metric": metric,
        }

        if not metric:
            values = confidences(n_pose, n_ransac / n)
            extras.update(values, scale=1.0)
            signals = Signals(n, n_pose, n_ransac / n, values["confidence_score"])
            conf = choose(opt.confidence, values)
            return Estimate(Pose(R, t_hat), conf, n_pose, "unscaled: no depth", extras=extras, signals=signals)

        with timer("scale"):
            p0, p1 = k0[pose_mask], k1[pose_mask]
            d0 = sample_depth_at(depth_ref, p0, K_ref, opt.depth_sampling)
            d1 = sample_depth_at(depth_query, p1, K_query, opt.depth_sampling)
            valid = (d0 > 0) & (d1 > 0)
            n_valid = int(valid.sum())
            if n_valid < 1:
                raise SolverError("no inlier has valid depth in both images")
            X0 = backproject_keypoints(p0[valid], d0[valid], K_ref, opt.depth_sampling)
            X1 = backproject_keypoints(p1[valid], d1[valid], K_query, opt.depth_sampling)
            residual = X1 - X0 @ R.T
            hyps = residual @ t_hat
            vote = scale_vote(hyps, opt.scale_threshold)
            if vote.index < 0:
                raise SolverError("no finite scale hypothesis")
            s = float(hyps[vote.index])
            t = s * t_hat
            in_scale = np.abs(hyps - s) < opt.scale_threshold
            err3d = np.linalg.norm(residual - t, axis=1)
            # Depth agreement: inliers whose whole 3D residual (not only along t̂) is small.
            agree = float(np.mean(err3d < np.maximum(opt.scale_threshold, 0.05 * d1[valid])))
        consensus = vote.votes / n_valid
        values = confidences(vote.votes, n_ransac / n, consensus)
        extras.update(
            values,
            n_depth_valid=n_valid,
            n_scale_inliers=vote.votes,
            consensus_ratio=consensus,
            scale=s,
            scale_mad=float(np.median(np.abs(hyps[in_scale] - s))),
            depth_agreement=agree,
        )
        signals = Signals(
            n_matches=n,
            n_inliers=vote.votes,
            inlier_ratio=n_ransac / n,
            score=values["confidence_score"],
            residual=float(np.median(err3d[in_scale])) if in_scale.any() else None,
            depth_valid_fraction=n_valid / n_pose,
            scale_ratio=scale_ratio(X0, X1),
        )
        return Estimate(Pose(R, t), choose(opt.confidence, values), vote.votes, extras=extras, signals=signals)
