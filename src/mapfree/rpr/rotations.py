"""Rotation and direction parameterisations: 6D Gram–Schmidt, quaternions, whole-degree Euler and spherical bins.

Batched over the leading axis; everything is differentiable except the argmax bin decoders.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = [
    "rot6d_to_matrix",
    "matrix_to_rot6d",
    "quat_to_matrix",
    "geodesic_angle",
    "euler_from_matrix",
    "matrix_from_euler",
    "euler_bin_index",
    "euler_bin_angles",
    "direction_to_spherical",
    "spherical_bin_index",
    "spherical_to_direction",
    "EULER_BINS",
    "EULER_OFFSETS",
    "SPHERICAL_BINS",
    "angle_between",
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
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
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

    scipy's ``Rotation.from_euler("xyz", ..., degrees=True).as_matrix()`` (how the public release decodes its
    bins) redone in torch on the input's device, operation by operation in float64 (elementary half-angle
    quaternions composed z·(y·x), then the quaternion's matrix), so that bin decoding needs no copy to the CPU
    (a device sync every step) and gives scipy's numbers bit for bit on the CPU (checked on all 23.3M bins).
    Returned in the input's float dtype (float32 for integer input).
    """
    rad = euler_deg.detach().double() * (torch.pi / 180.0)
    q = _axis_quat(0, rad[..., 0])
    for axis in (1, 2):  # extrinsic: each new rotation composed on the left
        q = _quat_compose(_axis_quat(axis, rad[..., axis]), q)
    x, y, z, w = q.unbind(-1)
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    R = torch.stack(
        [
            x2 - y2 - z2 + w2,
            2 * (xy - zw),
            2 * (xz + yw),
            2 * (xy + zw),
            -x2 + y2 - z2 + w2,
            2 * (yz - xw),
            2 * (xz - yw),
            2 * (yz + xw),
            -x2 - y2 + z2 + w2,
        ],
        -1,
    ).reshape(q.shape[:-1] + (3, 3))
    dtype = euler_deg.dtype if euler_deg.is_floating_point() else torch.float32
    return R.to(dtype)


def _axis_quat(axis: int, angle_rad: torch.Tensor) -> torch.Tensor:
    """Quaternions (x, y, z, w) of rotations by ``angle_rad`` about coordinate axis 0, 1 or 2."""
    q = angle_rad.new_zeros(angle_rad.shape + (4,))
    q[..., 3] = torch.cos(angle_rad / 2.0)
    q[..., axis] = torch.sin(angle_rad / 2.0)
    return q


def _quat_compose(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Hamilton product p·q of (x, y, z, w) quaternions, in scipy's order of operations (the cross product is
    written out: one fused kernel could round differently)."""
    px, py, pz, pw = p.unbind(-1)
    qx, qy, qz, qw = q.unbind(-1)
    cx, cy, cz = py * qz - pz * qy, pz * qx - px * qz, px * qy - py * qx
    return torch.stack(
        [pw * qx + qw * px + cx, pw * qy + qw * py + cy, pw * qz + qw * pz + cz, pw * qw - px * qx - py * qy - pz * qz],
        -1,
    )


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
    return torch.stack(
        [torch.remainder(idx[..., 0], SPHERICAL_BINS[0]), idx[..., 1].clamp(0, SPHERICAL_BINS[1] - 1)], -1
    )


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
