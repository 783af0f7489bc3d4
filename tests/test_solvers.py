"""Pose solvers on synthetic geometry with known poses, adversarial input, and one real image pair."""

from __future__ import annotations

import math
import time

import cv2
import numpy as np
import pytest

from mapfree.estimate import Estimate
from mapfree.geometry import Intrinsics, Pose, backproject, project, rotation_angle_deg
from mapfree.matching.base import Matches
from mapfree.solvers import (
    EssentialSolver,
    PnPSolver,
    ProcrustesSolver,
    Solver,
    available,
    create,
    scale_vote,
    scale_vote_bruteforce,
)
from mapfree.solvers.common import MAX_DEPTH, sample_depth_at, valid_depth_map
from mapfree.solvers.icp import icp
from mapfree.solvers.procrustes import _cloud
from mapfree.solvers.scale import vote_counts

K_REF = Intrinsics(500.0, 505.0, 320.0, 240.0, 640, 480)
K_QRY = Intrinsics(610.0, 598.0, 300.5, 251.0, 640, 480)  # a different camera: per-frame intrinsics
NAMES = ("essential", "pnp", "procrustes")


def rot(rx: float, ry: float, rz: float) -> np.ndarray:
    return cv2.Rodrigues(np.array([rx, ry, rz], dtype=np.float64))[0]


TRUE = Pose(rot(0.05, -0.12, 0.03), np.array([0.45, -0.1, 0.2]))


def synthetic_pair(
    rng: np.random.Generator,
    n: int = 300,
    pose: Pose = TRUE,
    outliers: float = 0.0,
    K0: Intrinsics = K_REF,
    K1: Intrinsics = K_QRY,
):
    """Exact matches between two cameras and sparse depth maps that hold the exact depth at the pixel each
    keypoint rounds to (reference keypoints sit on integer pixels; colliding query pixels are dropped)."""
    uv0 = np.stack([rng.integers(0, K0.width, n), rng.integers(0, K0.height, n)], axis=1).astype(np.float64)
    z0 = rng.uniform(2.0, 6.0, n)
    X0 = backproject(uv0, z0, K0.K)
    X1 = pose.transform(X0)
    uv1 = project(X1, K1.K)
    r1 = np.rint(uv1).astype(int)
    keep = (X1[:, 2] > 0) & (r1[:, 0] >= 0) & (r1[:, 0] < K1.width) & (r1[:, 1] >= 0) & (r1[:, 1] < K1.height)
    _, first0 = np.unique(uv0[:, 1] * K0.width + uv0[:, 0], return_index=True)
    _, first1 = np.unique(r1[:, 1] * K1.width + r1[:, 0], return_index=True)
    unique = np.zeros(n, bool)
    unique[np.intersect1d(first0, first1)] = True
    keep &= unique
    uv0, uv1, z0, z1, r1 = uv0[keep], uv1[keep], z0[keep], X1[keep, 2], r1[keep]
    D0 = np.zeros((K0.height, K0.width))
    D1 = np.zeros((K1.height, K1.width))
    D0[uv0[:, 1].astype(int), uv0[:, 0].astype(int)] = z0
    D1[r1[:, 1], r1[:, 0]] = z1
    if outliers > 0:
        m = len(uv0)
        bad = rng.permutation(m)[: int(round(outliers * m))]
        # Random query pixels with plausible depth there: wrong in 2D and in 3D.
        ub = np.stack([rng.integers(0, K1.width, len(bad)), rng.integers(0, K1.height, len(bad))], axis=1)
        free = D1[ub[:, 1], ub[:, 0]] == 0
        bad, ub = bad[free], ub[free]
        uv1 = uv1.copy()
        uv1[bad] = ub
        D1[ub[:, 1], ub[:, 0]] = rng.uniform(2.0, 6.0, len(bad))
    return Matches(uv0, uv1, np.ones(len(uv0))), D0, D1


def errors(est: Estimate, gt: Pose) -> tuple[float, float]:
    assert est.ok, est.reason
    return float(np.linalg.norm(est.pose.t - gt.t)), float(rotation_angle_deg(est.pose.R, gt.R))


def assert_clean(est: Estimate) -> None:
    """No NaN anywhere: a finite pose (or none, with a reason), finite confidence and numeric extras."""
    assert isinstance(est, Estimate)
    assert math.isfinite(est.confidence) and est.confidence >= 0
    if est.ok:
        assert est.pose.is_finite()
    else:
        assert est.reason and est.confidence == 0
    for k, v in est.extras.items():
        if isinstance(v, (int, float)):
            assert math.isfinite(v), k
    for v in est.timings.values():
        assert math.isfinite(v) and v >= 0


# --------------------------------------------------------------------------- registry


def test_registry_names_aliases_and_presets():
    assert {"essential", "emat", "pnp", "procrustes"} <= set(available())
    assert isinstance(create("emat"), EssentialSolver)
    assert isinstance(create("PnP"), PnPSolver)
    assert isinstance(create("procrustes"), ProcrustesSolver)
    for name in NAMES:
        s = create(name)
        assert isinstance(s, Solver)
        assert s.options.confidence == "inliers"  # the paper's
        assert create(name, preset="best").options.confidence == "score"
    e = create("essential")
    assert (e.options.ransac_threshold_px, e.options.ransac_confidence, e.options.scale_threshold) == (3.0, 0.9999, 0.1)
    p = create("pnp").options
    assert (p.ransac_iterations, p.reprojection_threshold_px, p.ransac_confidence) == (1000, 3.0, 0.9999)
    assert create("procrustes").options.inlier_threshold == 0.05
    assert create("essential", ransac_threshold_px=2.0).options.ransac_threshold_px == 2.0
    with pytest.raises(KeyError, match="unknown solver"):
        create("nope")
    with pytest.raises(TypeError, match="unknown option"):
        create("pnp", thresold=3)
    with pytest.raises(ValueError):
        create("essential", confidence="votes")


# --------------------------------------------------------------------------- exact recovery


@pytest.mark.parametrize(
    "name,kw",
    [
        ("essential", {"refine": True}),
        ("essential", {"backend": "poselib"}),
        ("pnp", {}),
        ("pnp", {"backend": "poselib"}),
        ("procrustes", {}),
    ],
)
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_exact_correspondences_recover_pose(name, kw, seed):
    rng = np.random.default_rng(seed)
    m, D0, D1 = synthetic_pair(rng)
    est = create(name, **kw).solve(m, K_REF, K_QRY, D0, D1)
    assert_clean(est)
    dt, dr = errors(est, TRUE)
    assert dt < 1e-6 and math.radians(dr) < 1e-6, (dt, dr)  # metres, radians
    assert est.inliers == len(m) and est.confidence == len(m)
    assert est.extras["confidence_inliers"] == len(m) and est.extras["confidence_score"] == pytest.approx(len(m))
    assert "solve" in est.timings and "ransac" in est.timings


def test_paper_essential_is_exact_up_to_opencv_polishing():
    """OpenCV's MAGSAC++ polishes E only to ~1e-5: the paper's path (no refinement) is exact to 1e-3."""
    for seed in range(5):
        m, D0, D1 = synthetic_pair(np.random.default_rng(seed))
        dt, dr = errors(create("essential").solve(m, K_REF, K_QRY, D0, D1), TRUE)
        assert dt < 1e-3 and math.radians(dr) < 1e-3, (seed, dt, dr)


@pytest.mark.parametrize(
    "name,kw", [("essential", {}), ("essential", {"backend": "poselib"}), ("pnp", {}), ("procrustes", {})]
)
def test_forty_percent_outliers(name, kw):
    rng = np.random.default_rng(2)
    m, D0, D1 = synthetic_pair(rng, n=400, outliers=0.4)
    est = create(name, **kw).solve(m, K_REF, K_QRY, D0, D1)
    assert_clean(est)
    dt, dr = errors(est, TRUE)
    assert dt < 0.01 and dr < 0.1, (dt, dr)
    # The outliers are found: inliers are about 60 % of the matches, never all of them.
    assert 0.5 * len(m) < est.inliers < 0.7 * len(m)
    # The ranking score discounts by agreement ratios, so it is below the inlier count here.
    assert 0 < est.extras["confidence_score"] < est.extras["confidence_inliers"] == est.inliers


def test_per_frame_intrinsics_matter():
    """Using the reference K for the query (one K per scene) breaks the estimate; per-frame K recovers it."""
    rng = np.random.default_rng(3)
    m, D0, D1 = synthetic_pair(rng)
    good = create("essential", refine=True).solve(m, K_REF, K_QRY, D0, D1)
    bad = create("essential", refine=True).solve(m, K_REF, K_REF, D0, D1)
    assert math.radians(errors(good, TRUE)[1]) < 1e-6
    assert not bad.ok or errors(bad, TRUE)[1] > 0.5


def test_depth_maps_at_another_resolution():
    """A depth map smaller than the image is looked up with the half-pixel rule."""
    d = np.arange(12, dtype=float).reshape(3, 4) + 1
    K = Intrinsics(100, 100, 3.5, 2.5, 8, 6)  # image 8x6, depth 4x3
    uv = np.array([[0.0, 0.0], [7.0, 5.0], [2.4, 2.6]])
    assert sample_depth_at(d, uv, K).tolist() == [1.0, 12.0, 6.0]


def test_depth_lookups_equal_the_float64_map(realmini):
    """Depth is gathered at the keypoints and then made float64 (no float64 copy of the whole map per call): the
    same values as looking up in the converted map, in every sampling mode, on a real sensor map with holes made
    invalid in every way; ``valid_depth_map``'s one-pass shortcut agrees with the full test."""
    from mapfree.data import Dataset

    frame = Dataset(realmini).scene("val", "s00001").reference
    d = frame.depth("sensor")
    d[:5, :5], d[10, 10], d[11, 11], d[12, 12], d[13, 13] = np.nan, np.inf, -1.0, 2 * MAX_DEPTH, 0.0
    rng = np.random.default_rng(0)
    uv = rng.uniform(-3, [d.shape[1] + 2, d.shape[0] + 2], (3000, 2))
    uv = np.vstack([uv, [[2, 2], [10, 10], [11, 11], [12, 12]]])  # the NaN, inf, negative and too-far pixels
    for K in (frame.intrinsics, frame.intrinsics.scaled(2.0, 2.0)):  # same size, and a map at half the image size
        for mode in ("nearest", "floor", "bilinear"):
            got, want = sample_depth_at(d, uv, K, mode), sample_depth_at(d.astype(np.float64), uv, K, mode)
            assert got.dtype == np.float64 and np.array_equal(got, want) and (got > 0).sum() > 1000
    for m, ok in (
        (d, True),
        (np.where(np.isfinite(d), 0.0, d), False),
        (np.full((4, 4), np.inf), False),
        (np.array([[np.nan, 2 * MAX_DEPTH], [np.inf, 1.0]]), True),
        (np.full((3, 3), 2 * MAX_DEPTH), False),
    ):
        with np.errstate(invalid="ignore"):
            full = bool(np.any(np.isfinite(m) & (m > 0) & (m < MAX_DEPTH)))
        assert valid_depth_map(m) is ok is full


def test_confidence_option_switches_the_reported_confidence():
    rng = np.random.default_rng(4)
    m, D0, D1 = synthetic_pair(rng, outliers=0.3)
    for name in NAMES:
        a = create(name, confidence="inliers").solve(m, K_REF, K_QRY, D0, D1)
        b = create(name, confidence="score").solve(m, K_REF, K_QRY, D0, D1)
        assert a.confidence == a.extras["confidence_inliers"] == a.inliers
        assert b.confidence == pytest.approx(b.extras["confidence_score"])
        assert 0 < b.confidence < a.confidence


def test_essential_without_depth_can_return_unit_translation():
    rng = np.random.default_rng(5)
    m, D0, D1 = synthetic_pair(rng)
    assert not create("essential").solve(m, K_REF, K_QRY, None, None).ok
    est = create("essential", allow_unscaled=True, refine=True).solve(m, K_REF, K_QRY, None, None)
    assert est.ok and est.extras["metric"] is False
    assert np.allclose(est.pose.t, TRUE.t / np.linalg.norm(TRUE.t), atol=1e-6)


def test_procrustes_icp_refines_on_dense_depth():
    """Dense depth of a box-shaped room; matches with 3 cm depth noise; ICP on the full clouds
    brings the pose closer to the truth than RANSAC on the noisy keypoints alone."""
    K = Intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240)
    pose = Pose(rot(0.02, -0.08, 0.01), np.array([0.15, 0.02, -0.1]))

    def render(cam_from_world: Pose) -> np.ndarray:
        # Room: floor y=1.2, ceiling y=-1.5, walls x=±2.5, back wall z=5, in world coordinates.
        u, v = np.meshgrid(np.arange(K.width, dtype=float), np.arange(K.height, dtype=float))
        rays_c = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], -1)
        Rw = cam_from_world.R.T
        o = cam_from_world.center
        d = rays_c @ Rw.T  # world directions whose camera z-component is 1
        best = np.full(u.shape, np.inf)
        for axis, value in ((1, 1.2), (1, -1.5), (0, 2.5), (0, -2.5), (2, 5.0)):
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = (value - o[axis]) / d[..., axis]
            best = np.where((lam > 0) & (lam < best), lam, best)
        return np.where(np.isfinite(best), best, 0.0)  # lam is the camera z because rays have z = 1

    D0, D1 = render(Pose.identity()), render(pose)
    rng = np.random.default_rng(6)
    uv0 = np.stack([rng.integers(0, K.width, 150), rng.integers(0, K.height, 150)], 1).astype(float)
    X1 = pose.transform(backproject(uv0, sample_depth_at(D0, uv0, K), K.K))
    uv1 = project(X1, K.K)
    noisy = D0.copy()
    noisy[uv0[:, 1].astype(int), uv0[:, 0].astype(int)] += rng.normal(0, 0.03, len(uv0))
    m = Matches(uv0, uv1, np.ones(len(uv0)))
    plain = create("procrustes", inlier_threshold=0.1).solve(m, K, K, noisy, D1)
    # ICP on the exact full clouds, started from the noisy RANSAC result.
    e_plain = np.linalg.norm(plain.pose.t - pose.t)
    assert e_plain > 0.005
    src, dst = _cloud(D0, K, 20000), _cloud(D1, K, 20000)
    for method, tol in (("point_to_point", 0.01), ("point_to_plane", 0.004)):
        R, t, fitness, _ = icp(src, dst, plain.pose.R, plain.pose.t, 0.1, method=method)
        e_icp = np.linalg.norm(t - pose.t)
        assert fitness > 0.8  # the part of the reference room the query also sees
        assert e_icp < 0.5 * e_plain and e_icp < tol, (method, e_plain, e_icp)
        assert rotation_angle_deg(R, pose.R) < 0.2
    est = create("procrustes", icp=True).solve(m, K, K, D0, D1)
    assert_clean(est)
    assert est.extras["icp"] and est.extras["icp_fitness"] > 0.8
    assert errors(est, pose)[0] < 0.01


# --------------------------------------------------------------------------- no estimate, never an exception


@pytest.mark.parametrize("name", NAMES)
def test_degenerate_inputs_give_no_estimate(name):
    rng = np.random.default_rng(7)
    m, D0, D1 = synthetic_pair(rng)
    s = create(name)
    cases = {
        "no matches": (Matches.empty(), D0, D1),
        "four matches": (m.subset(np.arange(4)), D0, D1),
        "all-zero depth": (m, np.zeros_like(D0), np.zeros_like(D1)),
        "no depth": (m, None, None),
        "NaN depth": (m, np.full_like(D0, np.nan), np.full_like(D1, np.nan)),
    }
    for case, (mm, d0, d1) in cases.items():
        est = s.solve(mm, K_REF, K_QRY, d0, d1)
        assert_clean(est)
        assert not est.ok, case
    assert "too few matches" in s.solve(Matches.empty(), K_REF, K_QRY, D0, D1).reason
    assert "depth" in s.solve(m, K_REF, K_QRY, np.zeros_like(D0), np.zeros_like(D1)).reason


def test_identical_images_have_no_parallax():
    """Zero flow: the essential matrix is undetermined -> no estimate; PnP/Procrustes give the identity."""
    rng = np.random.default_rng(8)
    m, D0, _ = synthetic_pair(rng, K1=K_REF)
    same = Matches(m.kpts0, m.kpts0.copy(), m.scores)
    est = create("essential").solve(same, K_REF, K_REF, D0, D0)
    assert_clean(est)
    assert not est.ok and "parallax" in est.reason
    for name in ("pnp", "procrustes"):
        est = create(name).solve(same, K_REF, K_REF, D0, D0)
        assert errors(est, Pose.identity())[0] < 1e-6


def test_collinear_points_are_degenerate_for_procrustes():
    u = np.arange(100, 400, 10, dtype=float)
    uv = np.stack([u, np.full_like(u, 240.0)], 1)  # one image row, constant depth: a 3D line
    D = np.zeros((480, 640))
    D[240, 100:400] = 3.0
    est = create("procrustes").solve(Matches(uv, uv, np.ones(len(uv))), K_REF, K_REF, D, D)
    assert_clean(est)
    assert not est.ok and "collinear" in est.reason


@pytest.mark.parametrize("name", NAMES)
def test_adversarial_input_never_nan(name):
    rng = np.random.default_rng(9)
    s = create(name, max_iterations=2000) if name == "procrustes" else create(name)  # keep the test fast
    for trial in range(12):
        m, D0, D1 = synthetic_pair(rng, n=60, outliers=0.5 * (trial % 3))
        k0, k1 = m.kpts0.copy(), m.kpts1.copy()
        sel = rng.random(len(k0)) < 0.2
        k0[sel, 0] = np.nan  # NaN keypoints
        k1[rng.random(len(k1)) < 0.1] = np.inf
        k1[rng.random(len(k1)) < 0.1] *= 1e12  # far outside the image
        D0[rng.random(D0.shape) < 0.01] = np.inf  # points at infinity
        D1[rng.random(D1.shape) < 0.01] = np.nan
        D1[rng.random(D1.shape) < 0.01] = 1e30
        if trial % 4 == 3:
            D0 = np.zeros_like(D0)
        est = s.solve(Matches(k0, k1, np.ones(len(k0))), K_REF, K_QRY, D0, D1)
        assert_clean(est)
    # All points at (numerically) infinite depth, and a depth map of the wrong dimensionality.
    m, D0, D1 = synthetic_pair(rng, n=60)
    for d0, d1 in ((np.where(D0 > 0, 1e300, 0), np.where(D1 > 0, 1e300, 0)), (D0[None], D1[None])):
        assert_clean(s.solve(m, K_REF, K_QRY, d0, d1))


# --------------------------------------------------------------------------- scale vote


def test_fast_scale_vote_equals_bruteforce():
    rng = np.random.default_rng(10)
    for trial in range(400):
        n = int(rng.integers(0, 120))
        kind = trial % 5
        if kind == 0:
            s = rng.normal(0, 0.3, n)
        elif kind == 1:  # many exact ties and values exactly one threshold apart
            s = rng.integers(-10, 10, n) * 0.05
        elif kind == 2:  # duplicates of few values
            s = rng.choice(rng.normal(0, 0.2, 4), n) if n else np.zeros(0)
        elif kind == 3:  # with non-finite hypotheses
            s = rng.normal(0, 0.3, n)
            s[rng.random(n) < 0.2] = np.nan
            s[rng.random(n) < 0.1] = np.inf
        else:  # boundary-heavy: pairs at threshold +- one ulp
            base = rng.normal(0, 1, max(n // 2, 0))
            s = np.concatenate([base, np.nextafter(base + 0.1, rng.choice([-np.inf, np.inf], len(base)))])
        thr = 0.1 if trial % 2 else float(rng.choice([0.05, 0.1, 0.3]))
        fast, slow = scale_vote(s, thr), scale_vote_bruteforce(s, thr)
        assert np.array_equal(fast.counts, slow.counts), trial
        assert (fast.index, fast.votes) == (slow.index, slow.votes), trial
    for n in (1500, 3000):  # larger inputs, ties and threshold-apart values
        s = np.concatenate([rng.integers(-40, 40, n) * 0.05, rng.normal(0, 1, n // 2)])
        assert np.array_equal(vote_counts(s, 0.1), scale_vote_bruteforce(s, 0.1).counts)
    # Tie rule: the first hypothesis (in input order) with the most votes wins.
    assert scale_vote(np.array([5.0, 1.0, 1.05, 5.02]), 0.1)[:2] == (0, 2)
    assert scale_vote(np.array([]), 0.1)[:2] == (-1, 0)
    assert scale_vote(np.array([np.nan]), 0.1)[:2] == (-1, 0)


def test_scale_vote_is_subquadratic():
    s = np.random.default_rng(11).normal(0, 2, 100_000)
    t0 = time.perf_counter()
    counts = vote_counts(s, 0.1)
    assert time.perf_counter() - t0 < 5.0  # the O(n^2) loop would take minutes here (1e10 comparisons)
    i = np.argsort(s)[1000]
    assert counts[i] == np.sum(np.abs(s - s[i]) < 0.1)


# --------------------------------------------------------------------------- real images


def _rootsift(img: np.ndarray):
    sift = cv2.SIFT_create(nfeatures=2048)
    kp, d = sift.detectAndCompute(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), None)
    d = np.sqrt(d / (d.sum(1, keepdims=True) + 1e-8)).astype(np.float32)
    return np.array([k.pt for k in kp]), d


def test_real_pair_sift_sensor_depth(realmini):
    from mapfree.data import Dataset

    scene = Dataset(realmini).scene("val", "s00000")
    ref, qry = scene.reference, scene.frame("seq1/frame_00009.jpg")  # about 0.25 m from the reference
    k0, d0 = _rootsift(ref.image())
    k1, d1 = _rootsift(qry.image())
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)
    good = [a for a, b in knn if a.distance < 0.8 * b.distance]
    m = Matches(k0[[g.queryIdx for g in good]], k1[[g.trainIdx for g in good]], np.ones(len(good)))
    assert len(m) > 50
    D0, D1 = ref.depth("sensor"), qry.depth("sensor")
    gt = qry.pose
    for name in NAMES:
        est = create(name).solve(m, ref.intrinsics, qry.intrinsics, D0, D1)
        assert_clean(est)
        assert est.ok, (name, est.reason)
        dc = np.linalg.norm(est.pose.center - gt.center)
        assert dc < 0.25 and rotation_angle_deg(est.pose.R, gt.R) < 5.0, name
        assert est.inliers >= 10
