"""Rotation and direction parameterisations in torch: 6D Gram–Schmidt, quaternions, Euler and spherical bins.

Batched over the leading axis; everything is differentiable except the argmax bin decoders.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = [
    "rot6d_to_matrix", "matrix_to_rot6d", "quat_to_matrix", "geodesic_angle", "euler_from_matrix",
    "matrix_from_euler", "bin_index", "bin_center", "direction_to_spherical", "spherical_to_direction",
    "EULER_BINS", "SPHERICAL_BINS", "angle_between",
]

#: (low, high, count) in degrees for yaw (about y), pitch (about x), roll (about z): 1° bins (SPEC §4).
EULER_BINS = ((-180.0, 180.0, 360), (-90.0, 90.0, 180), (-180.0, 180.0, 360))
#: (low, high, count) in degrees for azimuth phi and polar angle theta of a unit translation: 1° bins.
SPHERICAL_BINS = ((-180.0, 180.0, 360), (0.0, 180.0, 180))


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


def _axis_rot(angle: torch.Tensor, axis: int) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    o, z = torch.ones_like(angle), torch.zeros_like(angle)
    if axis == 0:
        rows = [o, z, z, z, c, -s, z, s, c]
    elif axis == 1:
        rows = [c, z, s, z, o, z, -s, z, c]
    else:
        rows = [c, -s, z, s, c, z, z, z, o]
    return torch.stack(rows, -1).reshape(angle.shape + (3, 3))


def matrix_from_euler(euler_deg: torch.Tensor) -> torch.Tensor:
    """(B,3) yaw, pitch, roll in degrees -> R = Ry(yaw) Rx(pitch) Rz(roll) (OpenCV axes: y down, z forward)."""
    a = torch.deg2rad(euler_deg)
    return _axis_rot(a[..., 0], 1) @ _axis_rot(a[..., 1], 0) @ _axis_rot(a[..., 2], 2)


def euler_from_matrix(R: torch.Tensor) -> torch.Tensor:
    """Inverse of ``matrix_from_euler``: (B,3,3) -> (B,3) degrees, pitch in [-90, 90]."""
    pitch = torch.asin(torch.clamp(-R[..., 1, 2], -1.0, 1.0))
    yaw = torch.atan2(R[..., 0, 2], R[..., 2, 2])
    roll = torch.atan2(R[..., 1, 0], R[..., 1, 1])
    return torch.rad2deg(torch.stack([yaw, pitch, roll], -1))


def bin_index(value: torch.Tensor, low: float, high: float, count: int) -> torch.Tensor:
    """Index of the bin of width (high-low)/count holding ``value`` (clamped into range)."""
    idx = torch.floor((value - low) / ((high - low) / count)).long()
    return idx.clamp(0, count - 1)


def bin_center(index: torch.Tensor, low: float, high: float, count: int) -> torch.Tensor:
    return low + (index.to(torch.get_default_dtype()) + 0.5) * ((high - low) / count)


def direction_to_spherical(d: torch.Tensor) -> torch.Tensor:
    """(B,3) vectors -> (B,2) azimuth phi = atan2(y, x) and polar theta from +z, in degrees."""
    d = F.normalize(d, dim=-1, eps=1e-12)
    phi = torch.atan2(d[..., 1], d[..., 0])
    theta = torch.acos(d[..., 2].clamp(-1.0, 1.0))
    return torch.rad2deg(torch.stack([phi, theta], -1))


def spherical_to_direction(angles_deg: torch.Tensor) -> torch.Tensor:
    phi, theta = torch.deg2rad(angles_deg).unbind(-1)
    return torch.stack([torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi), torch.cos(theta)], -1)


def angle_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(B,) angle in radians between vectors, atan2 form (exact 0 for parallel vectors)."""
    cross = torch.linalg.cross(a, b, dim=-1)
    return torch.atan2(_safe_norm(cross), (a * b).sum(-1))


def _safe_norm(v: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over the last axis with a zero (not NaN) gradient at v = 0."""
    sq = (v * v).sum(-1)
    pos = sq > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, sq, torch.ones_like(sq))), torch.zeros_like(sq))

