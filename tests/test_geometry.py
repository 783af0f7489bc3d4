import numpy as np
import pytest

from mapfree.geometry import (
    Intrinsics,
    Pose,
    Poses,
    backproject,
    backproject_depth,
    normalize_quat,
    project,
    quat_to_rotmat,
    rotation_angle_deg,
    rotmat_to_quat,
    sample_depth,
)


def random_pose(rng) -> Pose:
    return Pose.from_qt(normalize_quat(rng.normal(size=4)), rng.normal(size=3))


def test_quaternion_round_trip_and_sign():
    rng = np.random.default_rng(0)
    q = normalize_quat(rng.normal(size=(500, 4)))
    q[:5] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0.6, 0.8, 0]]  # w=0 / axis cases
    R = quat_to_rotmat(q)
    assert np.allclose(np.einsum("nij,nkj->nik", R, R), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1)
    q2 = rotmat_to_quat(R)
    assert np.allclose(quat_to_rotmat(q2), R, atol=1e-12)
    assert np.allclose(np.abs(np.sum(q * q2, axis=1)), 1, atol=1e-12)
    assert np.all(q2[:, 0] >= 0)


def test_known_rotation_angle():
    a = np.radians(37.0)
    R = quat_to_rotmat(np.array([np.cos(a / 2), 0, np.sin(a / 2), 0]))
    assert rotation_angle_deg(np.eye(3), R) == pytest.approx(37.0, abs=1e-9)
    # rotation about y by a: x' = cos a x + sin a z
    assert np.allclose(R, [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    assert rotation_angle_deg(R, R) == pytest.approx(0.0, abs=1e-6)
    assert quat_to_rotmat(np.array([2.0, 0, 0, 0])) == pytest.approx(np.eye(3))  # scaled quaternion normalised


def test_zero_quaternion_rejected():
    with pytest.raises(ValueError):
        quat_to_rotmat(np.zeros(4))


def test_pose_algebra():
    rng = np.random.default_rng(1)
    a, b = random_pose(rng), random_pose(rng)
    X = rng.normal(size=(10, 3))
    assert np.allclose((a @ b).transform(X), a.transform(b.transform(X)))
    assert np.allclose((a @ a.inverse()).matrix, np.eye(4), atol=1e-12)
    assert np.allclose(a.transform(a.center[None]), 0, atol=1e-12)
    # SPEC: q12 = q2 q1^-1, t12 = t2 - R12 t1
    rel = b.relative_to(a)
    assert np.allclose(rel.R, b.R @ a.R.T)
    assert np.allclose(rel.t, b.t - rel.R @ a.t)
    q, t = a.qt()
    assert np.allclose(Pose.from_qt(q, t).matrix, a.matrix)


def test_batched_poses_match_single():
    rng = np.random.default_rng(2)
    ps = [random_pose(rng) for _ in range(7)]
    qs = [random_pose(rng) for _ in range(7)]
    P, Q = Poses.stack(ps), Poses.stack(qs)
    assert np.allclose(P.centers, [p.center for p in ps])
    rel = Q.relative_to(P)
    for i in range(7):
        assert np.allclose(rel[i].matrix, qs[i].relative_to(ps[i]).matrix)
    assert np.allclose(P.inverse()[3].matrix, ps[3].inverse().matrix)


def test_pure_shift_center_distance():
    a = Pose.identity()
    b = Pose(np.eye(3), [-1.0, 0, 0])  # camera moved +1 m along x
    assert np.linalg.norm(b.center - a.center) == pytest.approx(1.0)


def test_resize_half_pixel_rule():
    k = Intrinsics(500.0, 510.0, 269.5, 359.5, 540, 720)
    s = k.scaled(0.5)
    assert (s.fx, s.fy, s.width, s.height) == (250.0, 255.0, 270, 360)
    assert s.cx == pytest.approx(0.5 * (269.5 + 0.5) - 0.5)
    assert s.cy == pytest.approx(0.5 * (359.5 + 0.5) - 0.5)
    # The image centre stays the image centre; the round trip is the identity.
    assert s.cx == pytest.approx((s.width - 1) / 2) and s.cy == pytest.approx((s.height - 1) / 2)
    back = s.resized(540, 720)
    assert np.allclose(back.K, k.K)
    r = k.resized(270, 360)
    assert r == s


def test_project_backproject_round_trip():
    rng = np.random.default_rng(3)
    K = Intrinsics(480.0, 470.0, 270.0, 360.0, 540, 720).K
    uv = rng.uniform([0, 0], [540, 720], size=(100, 2))
    z = rng.uniform(0.5, 20, size=100)
    X = backproject(uv, z, K)
    assert np.allclose(X[:, 2], z)
    assert np.allclose(project(X, K), uv)
    depth = rng.uniform(1, 5, size=(6, 8))
    P = backproject_depth(depth, K)
    assert P.shape == (6, 8, 3) and np.allclose(P[..., 2], depth)
    assert np.allclose(project(P[2, 5], K), [5, 2])


def test_sample_depth_outside_and_nan():
    d = np.arange(12, dtype=float).reshape(3, 4)
    d[0, 0] = np.nan
    out = sample_depth(d, np.array([[1.2, 2.4], [-3, 0], [3.4, 0.0], [0, 0], [10, 10]]))
    assert out.tolist() == [9.0, 0.0, 3.0, 0.0, 0.0]
