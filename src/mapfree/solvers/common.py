"""Helpers every solver shares: input cleaning, depth look-up at keypoints, normalisation, Kabsch."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, Generic, Literal, TypeVar, get_args

import cv2
import numpy as np

from ..estimate import Estimate
from ..geometry import Intrinsics, backproject
from ..matching.base import Matches
from .base import Solver, SolverOptions

__all__ = [
    "DEPTH_SAMPLING",
    "DepthSampling",
    "BACKENDS",
    "Backend",
    "MAX_DEPTH",
    "SolverError",
    "Timer",
    "finite_matches",
    "normalize_points",
    "sample_depth_at",
    "valid_depth_map",
    "backproject_keypoints",
    "kabsch",
    "rotation_is_valid",
    "scale_ratio",
    "GuardedSolver",
]

OptionsT = TypeVar("OptionsT", bound=SolverOptions)

#: How a depth map is read at a keypoint: the nearest pixel, the truncated pixel (the public code's) or bilinear.
DepthSampling = Literal["nearest", "floor", "bilinear"]
DEPTH_SAMPLING: tuple[DepthSampling, ...] = get_args(DepthSampling)
#: Whose RANSAC a solver runs: OpenCV's (the paper's) or PoseLib's.
Backend = Literal["opencv", "poselib"]
BACKENDS: tuple[Backend, ...] = get_args(Backend)
MAX_DEPTH = 1e4  # metres; larger values are "at infinity" and treated as invalid (no sensor or network gives them)


class SolverError(Exception):
    """Raised inside a solver to turn into ``Estimate.failure(str(error))`` at its boundary."""


class Timer:
    """Accumulates named wall-clock durations (seconds) for ``Estimate.timings``."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0


def finite_matches(kpts0: np.ndarray, kpts1: np.ndarray) -> np.ndarray:
    """Which matches have finite coordinates (NaN/inf keypoints are dropped, not fatal).

    Args:
        kpts0: (N, 2) pixels in image 0.
        kpts1: (N, 2) pixels in image 1.

    Returns:
        (N,) bool mask of the matches whose four coordinates are finite.
    """
    return np.all(np.isfinite(kpts0), axis=1) & np.all(np.isfinite(kpts1), axis=1)


def normalize_points(uv: np.ndarray, K: Intrinsics) -> np.ndarray:
    """Pixels to normalised image coordinates with this frame's own intrinsics.

    Args:
        uv: (N, 2) pixels.
        K: The frame's intrinsics.

    Returns:
        (N, 2) ``((u - cx) / fx, (v - cy) / fy)``.
    """
    return np.stack([(uv[:, 0] - K.cx) / K.fx, (uv[:, 1] - K.cy) / K.fy], axis=1)


def valid_depth_map(depth: np.ndarray | None) -> bool:
    """Whether a depth map is usable: 2-D with at least one finite value in (0, ``MAX_DEPTH``).

    Args:
        depth: (H, W) metres, or None.

    Returns:
        True for a usable map.
    """
    if depth is None:
        return False
    d = np.asarray(depth)
    if d.ndim != 2 or d.size == 0:
        return False
    with np.errstate(invalid="ignore"):
        if 0 < d.max() < MAX_DEPTH:  # the usual case in one pass: the maximum itself is valid (NaN fails the test)
            return True
        return bool(np.any(np.isfinite(d) & (d > 0) & (d < MAX_DEPTH)))


def _to_depth_pixels(uv: np.ndarray, K: Intrinsics, shape: tuple[int, int]) -> np.ndarray:
    """Map image pixels to depth-map pixels when the map is not at the image size (half-pixel rule)."""
    H, W = shape
    if (K.width, K.height) == (W, H) or K.width <= 0 or K.height <= 0:
        return uv
    sx, sy = W / K.width, H / K.height
    return np.stack([sx * (uv[:, 0] + 0.5) - 0.5, sy * (uv[:, 1] + 0.5) - 0.5], axis=1)


def sample_depth_at(depth: np.ndarray, uv: np.ndarray, K: Intrinsics, mode: DepthSampling = "nearest") -> np.ndarray:
    """Depth at image pixels; 0 where invalid (outside, non-finite, <= 0, >= ``MAX_DEPTH``).

    A map at another size than the image is read through the half-pixel rule.

    Args:
        depth: (H, W) metres.
        uv: (N, 2) pixels of the image ``K`` describes.
        K: The image's intrinsics.
        mode: ``nearest`` rounds to the closest pixel centre, ``floor`` truncates like the public Map-free code,
            ``bilinear`` interpolates only where all four neighbours are valid (no blending across holes).

    Returns:
        (N,) float64 metres, 0 where invalid.

    Raises:
        ValueError: An unknown ``mode``.
    """
    if mode not in DEPTH_SAMPLING:
        raise ValueError(f"depth sampling must be one of {DEPTH_SAMPLING}, got {mode!r}")
    d = np.asarray(depth)  # values are gathered first, then made float64 (exact): no copy of the whole map per call
    H, W = d.shape
    out = np.zeros(len(uv))
    if len(uv) == 0:
        return out
    p = _to_depth_pixels(np.asarray(uv, dtype=np.float64), K, (H, W))
    # Keep coordinates in a safe range before integer conversion (huge/inf pixels are simply outside).
    p = np.where(np.isfinite(p), np.clip(p, -2.0, float(max(H, W)) + 2.0), -2.0)
    if mode == "bilinear":
        u0, v0 = np.floor(p[:, 0]).astype(np.int64), np.floor(p[:, 1]).astype(np.int64)
        fu, fv = p[:, 0] - u0, p[:, 1] - v0
        inside = (u0 >= 0) & (v0 >= 0) & (u0 + 1 < W) & (v0 + 1 < H)
        u0, v0, fu, fv = u0[inside], v0[inside], fu[inside], fv[inside]
        q = np.stack([d[v0, u0], d[v0, u0 + 1], d[v0 + 1, u0], d[v0 + 1, u0 + 1]], axis=1).astype(np.float64)
        with np.errstate(invalid="ignore"):
            ok = np.all(np.isfinite(q) & (q > 0) & (q < MAX_DEPTH), axis=1)
        w = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=1)
        vals = np.where(ok, np.sum(np.where(ok[:, None], q, 0.0) * w, axis=1), 0.0)
        out[inside] = vals
        return out
    r = np.floor(p) if mode == "floor" else np.rint(p)
    u, v = r[:, 0].astype(np.int64), r[:, 1].astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    out[inside] = d[v[inside], u[inside]]  # float64 ``out``: the assignment converts
    with np.errstate(invalid="ignore"):
        out[~(np.isfinite(out) & (out > 0) & (out < MAX_DEPTH))] = 0.0
    return out


def backproject_keypoints(uv: np.ndarray, depth: np.ndarray, K: Intrinsics, mode: DepthSampling) -> np.ndarray:
    """Camera-frame 3D points of keypoints with their depths.

    Args:
        uv: (N, 2) pixels.
        depth: (N,) metres along the optical axis.
        K: The image's intrinsics.
        mode: The depth sampling mode; ``floor`` back-projects the truncated pixel, as the public code does.

    Returns:
        (N, 3) points in metres, camera frame.
    """
    if mode == "floor":
        uv = np.floor(uv)
    return backproject(uv, depth, K.K)


def kabsch(P: np.ndarray, Q: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (R, t) minimising ``sum w |R P + t - Q|^2``, batched over leading axes.

    Args:
        P: (..., N, 3) points.
        Q: (..., N, 3) corresponding points.
        w: (..., N) non-negative weights (default: all 1).

    Returns:
        R (..., 3, 3), a proper rotation, and t (..., 3).
    """
    if w is None:
        w = np.ones(P.shape[:-1])
    w = w / np.sum(w, axis=-1, keepdims=True)
    mp = np.einsum("...n,...nk->...k", w, P)
    mq = np.einsum("...n,...nk->...k", w, Q)
    H = np.einsum("...n,...ni,...nj->...ij", w, P - mp[..., None, :], Q - mq[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = V @ D @ np.swapaxes(U, -1, -2)
    t = mq - np.einsum("...ij,...j->...i", R, mp)
    return R, t


def scale_ratio(P: np.ndarray, Q: np.ndarray) -> float | None:
    """How much larger the query's 3-D points are than the reference's: two independent metric scales of the same
    rigid set of points (each image's own depth), 1 when they agree.

    Args:
        P: (N, 3) points from the reference's depth, metres.
        Q: (N, 3) the same points from the query's depth, metres.

    Returns:
        RMS spread of ``Q`` about its centroid over that of ``P``; None with fewer than 3 points or no spread.
    """
    if len(P) < 3:
        return None
    sp = float(np.sqrt(np.mean(np.sum((P - P.mean(axis=0)) ** 2, axis=1))))
    sq = float(np.sqrt(np.mean(np.sum((Q - Q.mean(axis=0)) ** 2, axis=1))))
    return sq / sp if sp > 0 and sq > 0 else None


def rotation_is_valid(R: np.ndarray, tol: float = 1e-6) -> bool:
    """Whether ``R`` is a finite, orthonormal 3x3 matrix with determinant +1.

    Args:
        R: The matrix.
        tol: Tolerance (scaled by 100 for the checks).

    Returns:
        True for a rotation.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        return False
    return bool(np.allclose(R.T @ R, np.eye(3), atol=tol * 100) and abs(np.linalg.det(R) - 1) < tol * 100)


class GuardedSolver(Solver, Generic[OptionsT]):
    """Shared shell of the solvers: options dataclass + overrides, and a ``solve`` that never raises.

    Subclasses set ``Options`` and implement ``_solve(matches, K_ref, K_query, depth_ref, depth_query, timer)``,
    raising ``SolverError`` for expected failures; library errors become "no estimate" with their message too.

    Args:
        options: The solver's options dataclass (default: the paper's values).
        **overrides: Option values over ``options`` (``ransac_threshold_px=2.0``), checked (``OptionError``).
    """

    Options: type[OptionsT]
    _errors: tuple[type[BaseException], ...] = (cv2.error, np.linalg.LinAlgError, ValueError, RuntimeError, MemoryError)

    def __init__(self, options: OptionsT | None = None, **overrides: Any) -> None:
        self.options: OptionsT = self.Options.build(overrides, owner=f"solver {self.name!r}", base=options)

    @property
    def confidence_mode(self) -> str:
        """Which confidence its estimates report: the ``confidence`` option."""
        return self.options.confidence

    def solve(
        self,
        matches: Matches,
        K_ref: Intrinsics,
        K_query: Intrinsics,
        depth_ref: np.ndarray | None,
        depth_query: np.ndarray | None = None,
    ) -> Estimate:
        """See ``Solver.solve``: never raises on bad input.

        Args:
            matches: ``kpts0`` reference pixels, ``kpts1`` query pixels, (N, 2) each.
            K_ref: Intrinsics of the reference image.
            K_query: Intrinsics of the query image.
            depth_ref: (H, W) metres at the reference's size (0 = invalid), or None.
            depth_query: (H, W) metres at the query's size, or None.

        Returns:
            The estimate; ``timings`` hold ``solve`` and the solver's own stages, in seconds.
        """
        timer = Timer()
        try:
            with timer("solve"):
                est = self._solve(matches, K_ref, K_query, depth_ref, depth_query, timer)
        except SolverError as e:
            est = Estimate.failure(str(e))
        except self._errors as e:
            est = Estimate.failure(f"solver error: {type(e).__name__}: {str(e).strip()[:200]}")
        est.timings = {**est.timings, **timer.timings}
        return est

    def _solve(
        self,
        matches: Matches,
        K_ref: Intrinsics,
        K_query: Intrinsics,
        depth_ref: np.ndarray | None,
        depth_query: np.ndarray | None,
        timer: Timer,
    ) -> Estimate:
        raise NotImplementedError

    @staticmethod
    def _finite_matches(matches: Matches, minimum: int) -> tuple[np.ndarray, np.ndarray]:
        """The matches with finite coordinates; ``SolverError`` when fewer than ``minimum`` remain."""
        ok = finite_matches(matches.kpts0, matches.kpts1)
        if ok.sum() < minimum:
            raise SolverError(f"too few matches ({int(ok.sum())} < {minimum})")
        return matches.kpts0[ok], matches.kpts1[ok]
