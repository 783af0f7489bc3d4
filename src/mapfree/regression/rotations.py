"""Rotation and direction parameterisations: 6D Gram–Schmidt, quaternions, whole-degree Euler and spherical bins.

Batched over the leading axis; everything is differentiable except the argmax bin decoders.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = [
    "rot6d_to_matrix", "matrix_to_rot6d", "quat_to_matrix", "geodesic_angle", "euler_from_matrix",
    "matrix_from_euler", "euler_bin_index", "euler_bin_angles", "direction_to_spherical", "spherical_bin_index",
    "spherical_to_direction", "EULER_BINS", "EULER_OFFSETS", "SPHERICAL_BINS", "angle_between",
]

#: Whole-degree bins of the public release: angles about x, y, z (extrinsic "xyz"), index = angle + offset.
EULER_BINS = (360, 180, 360)
EULER_OFFSETS = (180.0, 90.0, 180.0)
#: Whole-degree bins of a unit translation's azimuth phi in [0, 360) and polar angle theta in [0, 180).
SPHERICAL_BINS = (360, 180)


def rot6d_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """(B,6) two 3-vectors -> (B,3,3) rotation by partial Gram–Schmidt (Zhou et al.); columns b1, b2, b1×b2."""
    a1, a2 = x[..., :3], x[..., 3:6]
    b1 = F.normalize(a1, dim=-1, eps=1e-8)
    b2 = F.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1, eps=1e-8)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def matrix_to_rot6d(R: torch.Tensor) -> torch.Tensor:
    """(B,3,3) -> (B,6): the first two columns."""
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(B,4) wxyz (normalised here) -> (B,3,3)."""
    q = F.normalize(q, dim=-1, eps=1e-8)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def geodesic_angle(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """(B,) angle in radians between rotations, via atan2(sin, cos): exact 0 at equality, finite gradients."""
    M = R1.transpose(-1, -2) @ R2
    cos = (M.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    v = torch.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)
    sin = _safe_norm(v) / 2  # |v| = 2 sin(angle)
    return torch.atan2(sin, cos)


def matrix_from_euler(euler_deg: torch.Tensor) -> torch.Tensor:
    """(B,3) angles in degrees about the fixed x, y, z axes (extrinsic "xyz", R = Rz Ry Rx) -> (B,3,3).

    Computed by scipy in float64 and returned in the input's float dtype, as the public release decodes its bins.
    """
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("xyz", euler_deg.detach().cpu().double().numpy(), degrees=True).as_matrix()
    dtype = euler_deg.dtype if euler_deg.is_floating_point() else torch.float32
    return torch.from_numpy(R).to(device=euler_deg.device, dtype=dtype)


def euler_from_matrix(R: torch.Tensor) -> torch.Tensor:
    """Inverse of ``matrix_from_euler``: (B,3,3) -> (B,3) degrees, x and z in [-180, 180], y in [-90, 90]."""
    from scipy.spatial.transform import Rotation

    e = Rotation.from_matrix(R.detach().cpu().double().numpy()).as_euler("xyz", degrees=True)
    return torch.from_numpy(e).to(device=R.device, dtype=R.dtype)


def euler_bin_index(euler_deg: torch.Tensor) -> torch.Tensor:
    """(B,3) degrees -> (B,3) bin indices: the angle plus (180, 90, 180) rounded to whole degrees, clamped."""
    idx = torch.round(euler_deg + euler_deg.new_tensor(EULER_OFFSETS)).long()
    return torch.stack([idx[..., i].clamp(0, n - 1) for i, n in enumerate(EULER_BINS)], -1)


def euler_bin_angles(index: torch.Tensor) -> torch.Tensor:
    """(B,3) bin indices -> (B,3) whole-degree angles (the bin's value, not a centre)."""
    return index - index.new_tensor(EULER_OFFSETS).to(index.dtype)


def direction_to_spherical(d: torch.Tensor) -> torch.Tensor:
    """(B,3) vectors -> (B,2) azimuth phi = atan2(y, x) in [0, 360) and polar theta from +z in [0, 180], degrees."""
    d = F.normalize(d, dim=-1, eps=1e-12)
    phi = torch.remainder(torch.atan2(d[..., 1], d[..., 0]), 2 * torch.pi)
    theta = torch.acos(d[..., 2].clamp(-1.0, 1.0))
    return torch.rad2deg(torch.stack([phi, theta], -1))


def spherical_bin_index(angles_deg: torch.Tensor) -> torch.Tensor:
    """(B,2) phi, theta in degrees -> (B,2) whole-degree bins (phi 360 wraps to 0, theta clamped to 179)."""
    idx = torch.round(angles_deg).long()
    return torch.stack([torch.remainder(idx[..., 0], SPHERICAL_BINS[0]), idx[..., 1].clamp(0, SPHERICAL_BINS[1] - 1)], -1)


def spherical_to_direction(angles_deg: torch.Tensor) -> torch.Tensor:
    """(B,2) phi, theta in degrees -> (B,3) unit vectors (sin θ cos φ, sin θ sin φ, cos θ)."""
    phi, theta = torch.deg2rad(angles_deg).unbind(-1)
    return torch.stack([torch.cos(phi) * torch.sin(theta), torch.sin(phi) * torch.sin(theta), torch.cos(theta)], -1)


def angle_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(B,) angle in radians between vectors, atan2 form (exact 0 for parallel vectors)."""
    cross = torch.linalg.cross(a, b, dim=-1)
    return torch.atan2(_safe_norm(cross), (a * b).sum(-1))


def _safe_norm(v: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over the last axis with a zero (not NaN) gradient at v = 0."""
    sq = (v * v).sum(-1)
    pos = sq > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, sq, torch.ones_like(sq))), torch.zeros_like(sq))

