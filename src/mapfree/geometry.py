"""Rigid poses, rotations, intrinsics and pinhole projection, vectorised over numpy arrays.

Conventions: OpenCV camera axes, metres, world-to-camera poses ``X_cam = R X_world + t``,
quaternions in ``w x y z`` order. Nothing here imports anything else from mapfree.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

__all__ = [
    "quat_to_rotmat",
    "rotmat_to_quat",
    "normalize_quat",
    "rotation_angle_deg",
    "Pose",
    "Poses",
    "Intrinsics",
    "project",
    "backproject",
    "backproject_depth",
    "sample_depth",
    "to_original",
    "focal_from_pointmap",
]


# --------------------------------------------------------------------------- rotations


def normalize_quat(q: np.ndarray) -> np.ndarray:
    """Scale quaternions to unit length, so that they are valid rotations.

    Args:
        q: (..., 4) quaternions, any order of components.

    Returns:
        (..., 4) float64 unit quaternions.

    Raises:
        ValueError: A quaternion has zero or non-finite norm.
    """
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n == 0) or not np.all(np.isfinite(n)):
        raise ValueError("quaternion has zero or non-finite norm")
    return q / n


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of quaternions (the pose files' rotation format).

    Args:
        q: (..., 4) quaternions, ``w x y z``; normalised here.

    Returns:
        (..., 3, 3) rotation matrices.

    Raises:
        ValueError: A quaternion has zero or non-finite norm.
    """
    q = normalize_quat(q)
    w, x, y, z = np.moveaxis(q, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternions of rotation matrices, by Shepperd's method (stable near every angle).

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4) unit quaternions ``w x y z`` with ``w >= 0``.
    """
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    # Candidate 4*q_i^2 for each component; pick the largest to avoid dividing by a small number.
    d = np.stack([1 + tr, 1 + 2 * m[:, 0, 0] - tr, 1 + 2 * m[:, 1, 1] - tr, 1 + 2 * m[:, 2, 2] - tr], axis=1)
    k = np.argmax(d, axis=1)
    a = m
    # Scaled by 4|q_k|: the chosen component is d_k = 4 q_k^2, the others are sums/differences of entries.
    dk = d[np.arange(len(m)), k]
    cases = [
        (dk, a[:, 2, 1] - a[:, 1, 2], a[:, 0, 2] - a[:, 2, 0], a[:, 1, 0] - a[:, 0, 1]),
        (a[:, 2, 1] - a[:, 1, 2], dk, a[:, 0, 1] + a[:, 1, 0], a[:, 0, 2] + a[:, 2, 0]),
        (a[:, 0, 2] - a[:, 2, 0], a[:, 0, 1] + a[:, 1, 0], dk, a[:, 1, 2] + a[:, 2, 1]),
        (a[:, 1, 0] - a[:, 0, 1], a[:, 0, 2] + a[:, 2, 0], a[:, 1, 2] + a[:, 2, 1], dk),
    ]
    q = np.empty((len(m), 4))
    for i, c in enumerate(cases):
        sel = k == i
        q[sel] = np.stack([comp[sel] for comp in c], axis=1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    return q.reshape(R.shape[:-2] + (4,))


def rotation_angle_deg(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations: the rotation error of the benchmark.

    Args:
        R1: (..., 3, 3) rotation matrices.
        R2: (..., 3, 3) rotation matrices, broadcast against ``R1``.

    Returns:
        (...) angles in degrees, in [0, 180].
    """
    R = np.einsum("...ji,...jk->...ik", R1, R2)  # R1^T R2
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


# --------------------------------------------------------------------------- poses


@dataclass(frozen=True)
class Pose:
    """A world-to-camera rigid transform: ``X_cam = R @ X_world + t``.

    Compose with ``a @ b`` (``b`` first, then ``a``).

    Attributes:
        R: (3, 3) rotation, world to camera.
        t: (3,) translation in metres.
    """

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3))

    @classmethod
    def identity(cls) -> Pose:
        """The identity transform (a camera at the world origin, axes aligned)."""
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_qt(cls, q_wxyz: Iterable[float], t: Iterable[float]) -> Pose:
        """A pose from a quaternion and a translation, as pose files store it.

        Args:
            q_wxyz: (4,) rotation quaternion ``w x y z``; normalised here.
            t: (3,) translation in metres.

        Returns:
            The pose.
        """
        return cls(quat_to_rotmat(np.asarray(q_wxyz, dtype=np.float64)), np.asarray(t, dtype=np.float64))

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> Pose:
        """A pose from a homogeneous transform.

        Args:
            T: (4, 4) or (3, 4) matrix ``[R | t]``.

        Returns:
            The pose.
        """
        T = np.asarray(T, dtype=np.float64)
        return cls(T[:3, :3], T[:3, 3])

    def qt(self) -> tuple[np.ndarray, np.ndarray]:
        """The pose as pose files store it.

        Returns:
            (4,) unit quaternion ``w x y z`` (``w >= 0``) and (3,) translation in metres.
        """
        return rotmat_to_quat(self.R), self.t.copy()

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix ``[[R, t], [0, 1]]``."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.t

    def inverse(self) -> Pose:
        """The inverse transform (camera-to-world for a world-to-camera pose)."""
        return Pose(self.R.T, -self.R.T @ self.t)

    def __matmul__(self, other: Pose) -> Pose:
        """Composition: ``(a @ b)(X) = a(b(X))``."""
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def transform(self, X: np.ndarray) -> np.ndarray:
        """Apply the transform to points.

        Args:
            X: (N, 3) points in the source frame (world), metres.

        Returns:
            (N, 3) points in the target frame (camera), metres.
        """
        return np.asarray(X) @ self.R.T + self.t

    def relative_to(self, first: Pose) -> Pose:
        """Pose of this camera relative to ``first``: what a relocalization method estimates.

        Args:
            first: World-to-camera pose of the other camera (the reference).

        Returns:
            The transform from ``first``'s camera frame to this camera's (``q12 = q2 q1^-1``,
                ``t12 = t2 - R12 t1``).
        """
        return self @ first.inverse()

    def is_finite(self) -> bool:
        """Whether every entry of ``R`` and ``t`` is finite (no NaN, no inf)."""
        return bool(np.all(np.isfinite(self.R)) and np.all(np.isfinite(self.t)))


@dataclass(frozen=True)
class Poses:
    """N world-to-camera poses as stacked arrays, for vectorised work over a whole scene.

    Attributes:
        R: (N, 3, 3) rotations, world to camera.
        t: (N, 3) translations in metres.
    """

    R: np.ndarray
    t: np.ndarray

    @classmethod
    def from_qt(cls, q_wxyz: np.ndarray, t: np.ndarray) -> Poses:
        """Poses from quaternions and translations, as pose files store them.

        Args:
            q_wxyz: (N, 4) rotation quaternions ``w x y z``; normalised here.
            t: (N, 3) translations in metres.

        Returns:
            The N poses.
        """
        return cls(quat_to_rotmat(np.asarray(q_wxyz, dtype=np.float64)), np.asarray(t, dtype=np.float64))

    @classmethod
    def stack(cls, poses: Iterable[Pose]) -> Poses:
        """Stack single poses (at least one).

        Args:
            poses: The poses, in order.

        Returns:
            The poses as (N, 3, 3) and (N, 3) arrays.
        """
        poses = list(poses)
        return cls(np.stack([p.R for p in poses]), np.stack([p.t for p in poses]))

    def __len__(self) -> int:
        return len(self.t)

    def __getitem__(self, i: int) -> Pose:
        return Pose(self.R[i], self.t[i])

    def qt(self) -> tuple[np.ndarray, np.ndarray]:
        """The poses as pose files store them.

        Returns:
            (N, 4) unit quaternions ``w x y z`` (``w >= 0``) and (N, 3) translations in metres.
        """
        return rotmat_to_quat(self.R), self.t.copy()

    @property
    def centers(self) -> np.ndarray:
        """(N, 3) camera centres in world coordinates, metres (``-R^T t``)."""
        return -np.einsum("nji,nj->ni", self.R, self.t)

    def inverse(self) -> Poses:
        """The inverse transforms (camera-to-world for world-to-camera poses)."""
        Rt = np.swapaxes(self.R, 1, 2)
        return Poses(Rt, -np.einsum("nij,nj->ni", Rt, self.t))

    def __matmul__(self, other: Poses) -> Poses:
        return Poses(self.R @ other.R, np.einsum("nij,nj->ni", self.R, other.t) + self.t)

    def relative_to(self, first: Poses) -> Poses:
        """Each pose relative to the matching pose of ``first`` (see ``Pose.relative_to``).

        Args:
            first: N world-to-camera poses of the other cameras.

        Returns:
            N transforms from ``first[i]``'s camera frame to camera i's.
        """
        return self @ first.inverse()


# --------------------------------------------------------------------------- intrinsics and projection


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of one frame, with the image size.

    Pixel centres sit at integer coordinates (OpenCV's convention).

    Attributes:
        fx: Focal length along x, pixels.
        fy: Focal length along y, pixels.
        cx: Principal point x, pixels.
        cy: Principal point y, pixels.
        width: Image width, pixels.
        height: Image height, pixels.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """(3, 3) calibration matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> Intrinsics:
        """Intrinsics from a calibration matrix (skew is dropped).

        Args:
            K: (3, 3) calibration matrix.
            width: Image width, pixels.
            height: Image height, pixels.

        Returns:
            The intrinsics.
        """
        K = np.asarray(K, dtype=np.float64)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))

    @property
    def mean_focal(self) -> float:
        """Mean of ``fx`` and ``fy``, pixels."""
        return 0.5 * (self.fx + self.fy)

    @property
    def diagonal(self) -> float:
        """Image diagonal, pixels (the VCRE thresholds are fractions of it)."""
        return float(np.hypot(self.width, self.height))

    def scaled(self, sx: float, sy: float | None = None) -> Intrinsics:
        """Intrinsics of the image resized by a factor (half-pixel-centre rule, as OpenCV resizes).

        Args:
            sx: Horizontal scale factor.
            sy: Vertical scale factor; ``sx`` when None.

        Returns:
            The intrinsics of the resized image (size rounded to whole pixels).
        """
        sy = sx if sy is None else sy
        return Intrinsics(
            self.fx * sx,
            self.fy * sy,
            sx * (self.cx + 0.5) - 0.5,
            sy * (self.cy + 0.5) - 0.5,
            int(round(self.width * sx)),
            int(round(self.height * sy)),
        )

    def resized(self, width: int, height: int) -> Intrinsics:
        """Intrinsics of the image resized to an exact size.

        Args:
            width: New width, pixels.
            height: New height, pixels.

        Returns:
            The intrinsics of the resized image.
        """
        out = self.scaled(width / self.width, height / self.height)
        return Intrinsics(out.fx, out.fy, out.cx, out.cy, int(width), int(height))


def project(X: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection of camera-frame points.

    Args:
        X: (..., 3) points in the camera frame, metres.
        K: (3, 3) calibration matrix.

    Returns:
        (..., 2) pixel coordinates; points at ``z <= 0`` give inf or NaN, for the caller to mask.
    """
    X = np.asarray(X, dtype=np.float64)
    uvw = X @ np.asarray(K, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return uvw[..., :2] / uvw[..., 2:3]


def backproject(uv: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Lift pixels with known depth to 3D points in the camera frame.

    Args:
        uv: (N, 2) pixel coordinates.
        depth: (N,) depth along the optical axis (z), metres.
        K: (3, 3) calibration matrix.

    Returns:
        (N, 3) camera-frame points, metres.
    """
    uv = np.asarray(uv, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    z = np.asarray(depth, dtype=np.float64)
    x = (uv[..., 0] - K[0, 2]) / K[0, 0]
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    return np.stack([x * z, y * z, z], axis=-1)


def backproject_depth(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Lift a whole depth map to a point map in the camera frame.

    Args:
        depth: (H, W) depth along the optical axis (z), metres.
        K: (3, 3) calibration matrix.

    Returns:
        (H, W, 3) camera-frame points, metres (pixel centres at integer coordinates).
    """
    H, W = depth.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    return backproject(np.stack([u, v], axis=-1), depth, K)


def sample_depth(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Depth at pixel positions, nearest pixel (the depth of a keypoint).

    Args:
        depth: (H, W) depth map, metres; 0 marks invalid pixels.
        uv: (N, 2) pixel coordinates.

    Returns:
        (N,) depths in metres; 0 outside the map or where the map is not finite.
    """
    uv = np.asarray(uv, dtype=np.float64)
    H, W = depth.shape[:2]
    u = np.rint(uv[:, 0]).astype(np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    out = np.zeros(len(uv), dtype=np.float64)
    out[inside] = depth[v[inside], u[inside]]
    out[~np.isfinite(out)] = 0.0
    return out


def to_original(kpts: np.ndarray, scale: tuple[float, float]) -> np.ndarray:
    """Map pixel coordinates of a resized image back to the original image (half-pixel rule).

    Args:
        kpts: (N, 2) pixel coordinates in the resized image.
        scale: (sx, sy) factors the original was resized by.

    Returns:
        (N, 2) pixel coordinates in the original image.
    """
    kpts = np.asarray(kpts, dtype=np.float64).reshape(-1, 2)
    if scale == (1.0, 1.0):
        return kpts
    s = np.asarray(scale, dtype=np.float64)
    return (kpts + 0.5) / s - 0.5


def focal_from_pointmap(pts: np.ndarray, iterations: int = 10) -> float:
    """The focal length that best explains a pointmap, its principal point at the image centre.

    DUSt3R's ``estimate_focal_knowing_depth`` (its ``weiszfeld`` mode): ``f = argmin sum |p - f (x, y) / z|`` over
    the pixels ``p`` (relative to the centre), a least-squares start then re-weighted least squares. Pixel centres
    sit at integer coordinates, so the centre is ``((W - 1) / 2, (H - 1) / 2)``.

    Args:
        pts: (H, W, 3) points in the camera's own frame (any unit); points with z <= 0 or not finite are left out.
        iterations: Re-weighting steps.

    Returns:
        The focal length in pixels of the (H, W) grid; NaN when fewer than 2 points are usable.
    """
    pts = np.asarray(pts, dtype=np.float64)
    H, W = pts.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    px = np.stack([u - (W - 1) / 2, v - (H - 1) / 2], axis=-1).reshape(-1, 2)
    p = pts.reshape(-1, 3)
    ok = np.isfinite(p).all(axis=1) & (p[:, 2] > 0)
    if ok.sum() < 2:
        return float("nan")
    px, xy = px[ok], p[ok, :2] / p[ok, 2:3]
    dot_xy_px = (xy * px).sum(axis=1)
    dot_xy_xy = (xy * xy).sum(axis=1)
    focal = dot_xy_px.mean() / max(dot_xy_xy.mean(), 1e-300)
    for _ in range(iterations):
        w = 1.0 / np.maximum(np.linalg.norm(px - focal * xy, axis=1), 1e-8)
        focal = (w * dot_xy_px).sum() / max((w * dot_xy_xy).sum(), 1e-300)
    return float(focal)
