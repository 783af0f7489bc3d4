"""PnP: reference keypoints lifted to 3D with the reference depth, P3P in RANSAC, refined on inliers."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..estimate import Estimate, Signals
from ..geometry import Intrinsics, Pose, project
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
    rotation_is_valid,
    sample_depth_at,
    valid_depth_map,
)
from .confidence import CONFIDENCE_MODES, ConfidenceMode, choose, confidences

__all__ = ["PnPOptions", "PnPSolver"]


@dataclass
class PnPOptions(SolverOptions):
    """Defaults are the paper's."""

    ransac_iterations: int = option(1000, min=1)
    reprojection_threshold_px: float = option(3.0, min=0, min_open=True)
    ransac_confidence: float = option(0.9999, min=0, max=1, min_open=True, max_open=True)
    min_refine_inliers: int = option(6, min=4)  # iterative refinement on the inliers when at least this many
    max_translation: float = option(1000.0, min=0, min_open=True)  # metres; larger solutions are degenerate
    depth_sampling: DepthSampling = option("nearest", choices=DEPTH_SAMPLING)
    min_matches: int = option(5, min=4)
    backend: Backend = option("opencv", choices=BACKENDS)  # "opencv" (solvePnPRansac + P3P, the paper's) | "poselib"
    confidence: ConfidenceMode = option("inliers", choices=CONFIDENCE_MODES)


def _pnp_opencv(
    X: np.ndarray, uv: np.ndarray, K: np.ndarray, opt: PnPOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        X,
        uv,
        K,
        None,
        iterationsCount=int(opt.ransac_iterations),
        reprojectionError=float(opt.reprojection_threshold_px),
        confidence=float(opt.ransac_confidence),
        flags=cv2.SOLVEPNP_P3P,
    )
    if not ok or inl is None or len(inl) == 0:
        raise SolverError("PnP RANSAC found no solution")
    inl = inl.reshape(-1)
    if len(inl) >= opt.min_refine_inliers:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            X[inl],
            uv[inl],
            K,
            None,
            useExtrinsicGuess=True,
            rvec=rvec.copy(),
            tvec=tvec.copy(),
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        if n > 0 and np.all(np.isfinite(rvecs[0])) and np.all(np.isfinite(tvecs[0])):
            rvec, tvec = rvecs[0], tvecs[0]
    mask = np.zeros(len(X), dtype=bool)
    mask[inl] = True
    return cv2.Rodrigues(rvec)[0], tvec.reshape(3), mask


def _pnp_poselib(X: np.ndarray, uv: np.ndarray, K: Intrinsics, opt: PnPOptions):
    import poselib

    cam = {"model": "PINHOLE", "width": int(K.width), "height": int(K.height), "params": [K.fx, K.fy, K.cx, K.cy]}
    pose, info = poselib.estimate_absolute_pose(
        uv,
        X,
        cam,
        {
            "max_reproj_error": float(opt.reprojection_threshold_px),
            "max_iterations": int(opt.ransac_iterations),
            "success_prob": float(opt.ransac_confidence),
        },
        {},
    )
    mask = np.asarray(info.get("inliers", []), dtype=bool).reshape(-1)
    if len(mask) != len(X) or not mask.any():
        raise SolverError("PnP RANSAC found no solution")
    return np.asarray(pose.R, dtype=np.float64), np.asarray(pose.t, dtype=np.float64).reshape(3), mask


class PnPSolver(GuardedSolver[PnPOptions]):
    """2D–3D PnP; uses only the reference depth. Never raises on bad input."""

    name = "pnp"
    Options = PnPOptions
    depth_needs = ("ref",)

    def _solve(self, matches, K_ref, K_query, depth_ref, depth_query, timer: Timer) -> Estimate:
        opt = self.options
        k0, k1 = self._finite_matches(matches, max(opt.min_matches, 5))
        n = len(k0)
        if not valid_depth_map(depth_ref):
            raise SolverError("no valid depth for the reference image")
        d0 = sample_depth_at(depth_ref, k0, K_ref, opt.depth_sampling)
        valid = d0 > 0
        n_valid = int(valid.sum())
        if n_valid < 4:
            raise SolverError(f"too few matches with valid reference depth ({n_valid} < 4)")
        X = backproject_keypoints(k0[valid], d0[valid], K_ref, opt.depth_sampling)
        uv = np.ascontiguousarray(k1[valid])
        with timer("ransac"):
            if opt.backend == "poselib":
                R, t, mask = _pnp_poselib(X, uv, K_query, opt)
            else:
                R, t, mask = _pnp_opencv(np.ascontiguousarray(X), uv, K_query.K, opt)
        if not rotation_is_valid(R) or not np.all(np.isfinite(t)):
            raise SolverError("degenerate PnP solution")
        if np.linalg.norm(t) > opt.max_translation:
            raise SolverError(f"degenerate PnP solution (|t| > {opt.max_translation:g} m)")
        n_in = int(mask.sum())
        # Reprojection error of the final pose on the RANSAC inliers (a diagnostic for the score).
        Xc = X[mask] @ R.T + t
        front = Xc[:, 2] > 0
        err = (
            np.linalg.norm(project(Xc[front], K_query.K) - uv[mask][front], axis=1)
            if front.any()
            else np.array([np.inf])
        )
        ratio = n_in / n_valid
        values = confidences(n_in, ratio)
        extras = {
            "n_matches": n,
            "n_depth_valid": n_valid,
            "n_inliers": n_in,
            "inlier_ratio": ratio,
            "median_reprojection_px": float(np.median(err)) if np.all(np.isfinite(err)) else -1.0,
            "backend": opt.backend,
            "metric": True,
            **values,
        }
        signals = Signals(
            n_matches=n,
            n_inliers=n_in,
            inlier_ratio=ratio,
            score=values["confidence_score"],
            residual=float(np.median(err)),
            depth_valid_fraction=n_valid / n,
        )
        return Estimate(Pose(R, t), choose(opt.confidence, values), n_in, extras=extras, signals=signals)
