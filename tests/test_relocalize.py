"""Relocalizer end to end on real images, its no-estimate cases, and the pictures it draws."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mapfree.data import Dataset
from mapfree.geometry import Intrinsics, Pose, project, rotation_angle_deg
from mapfree.relocalize import Relocalizer, View
from mapfree.viz import epipolar_inliers, relocalization_figure, save_png, vcre_grid, vcre_px

EASY_QUERY = "seq1/frame_00010.jpg"  # 0.2 m from the reference in val/s00000


@pytest.fixture(scope="module")
def scene(realmini):
    return Dataset(realmini).scene("val", "s00000")


@pytest.fixture(scope="module")
def sift_sensor():
    return Relocalizer("sift", "files:sensor", "essential")


def test_real_pair_within_benchmark_threshold(scene, sift_sensor):
    est = sift_sensor.relocalize(scene.reference, scene.frame(EASY_QUERY))
    gt = scene.frame(EASY_QUERY).pose  # the reference is the world frame in val scenes
    assert est.ok, est.reason
    assert np.linalg.norm(est.pose.center - gt.center) < 0.25
    assert rotation_angle_deg(est.pose.R, gt.R) < 5.0
    assert est.confidence > 0 and est.inliers >= 5
    assert {"match", "depth", "solve", "total"} <= set(est.timings)
    assert all(np.isfinite(v) and v >= 0 for v in est.timings.values())
    assert est.timings["total"] >= est.timings["match"] + est.timings["solve"] - 1e-9


def test_cached_reference_gives_the_same_pose(scene, sift_sensor):
    query = scene.frame(EASY_QUERY)
    once = sift_sensor.relocalize(scene.reference, query)
    anchor = sift_sensor.set_reference(scene.reference)
    cached = sift_sensor.localize(query)
    assert sift_sensor.anchor is anchor and len(anchor.features) > 100
    assert np.allclose(once.pose.R, cached.pose.R) and np.allclose(once.pose.t, cached.pose.t)
    # The cached call does not pay for the reference: its timings hold no reference stage.
    assert cached.timings["match"] < once.timings["match"]


def test_tuple_inputs_with_explicit_depth(scene, sift_sensor):
    ref, q = scene.reference, scene.frame(EASY_QUERY)
    est = sift_sensor.relocalize(
        (ref.image_path, ref.intrinsics.K, ref.depth("sensor")), (q.image(), q.intrinsics, q.depth("sensor"))
    )
    assert est.ok and np.linalg.norm(est.pose.center - q.pose.center) < 0.25


def test_identical_images_give_the_identity_and_blank_ones_no_estimate(scene, sift_sensor):
    ref = scene.reference
    same = sift_sensor.relocalize(ref, ref)  # the query is the reference photo: it was taken from there
    assert same.ok and same.extras["same_viewpoint"], same.reason
    assert np.allclose(same.pose.R, np.eye(3)) and np.allclose(same.pose.t, 0)
    assert same.inliers > 100 and same.confidence == same.inliers  # every match stayed put
    scale_free = Relocalizer("sift", "none", "essential").relocalize(ref, ref)  # needs no depth either
    assert scale_free.ok and np.allclose(scale_free.pose.t, 0)
    K = ref.intrinsics
    blank = View(np.full((K.height, K.width, 3), 127, np.uint8), K, np.ones((K.height, K.width), np.float32))
    tiny = View(np.zeros((4, 4, 3), np.uint8), Intrinsics(4, 4, 2, 2, 4, 4))  # the matcher rejects it
    for pair in ((blank, blank), (ref, blank), (blank, ref), (tiny, ref), (ref, tiny)):
        est = sift_sensor.relocalize(*pair)
        assert not est.ok and est.reason and est.pose is None


def test_missing_depth_is_no_estimate(realmini, sift_sensor):
    s3 = Dataset(realmini).scene("val", "s00003")  # this scene has no depth files
    est = sift_sensor.relocalize(s3.reference, s3.queries[3])
    assert not est.ok and "depth" in est.reason


def test_scale_free_method_flags_its_output(scene):
    loc = Relocalizer("sift", "none", "essential", solver_opts={"allow_unscaled": True})
    est = loc.relocalize(scene.reference, scene.frame(EASY_QUERY))
    assert est.ok and est.extras.get("scale_free") is True
    assert abs(np.linalg.norm(est.pose.t) - 1.0) < 1e-6


def test_emat_none_by_name_gives_the_direction(scene, capsys):
    """``sift_emat_none`` (offered by the service for anchors without depth, "direction only") returns the
    flagged up-to-scale pose from ``mapfree relocalize`` and ``Relocalizer.from_method``; before, every query
    failed with "no valid depth" unless the caller set ``allow_unscaled`` itself."""
    from mapfree.cli import main

    est = Relocalizer.from_method("sift_emat_none").relocalize(scene.reference, scene.frame(EASY_QUERY))
    gt = scene.frame(EASY_QUERY).pose
    assert est.ok and est.extras.get("scale_free") is True, est.reason
    assert rotation_angle_deg(est.pose.R, gt.R) < 2.0
    assert np.degrees(np.arccos(np.clip(est.pose.t @ gt.t / np.linalg.norm(gt.t), -1, 1))) < 10.0
    ref, q = scene.reference.image_path, scene.frame(EASY_QUERY).image_path
    assert main(["relocalize", str(ref), str(q), "--method", "sift_emat_none"]) == 0
    import json

    out = json.loads(capsys.readouterr().out)
    assert out["ok"] and abs(np.linalg.norm(out["t"]) - 1.0) < 1e-6


def test_epipolar_inliers_and_vcre_on_exact_geometry():
    K = Intrinsics(500, 500, 320, 240, 640, 480)
    rng = np.random.default_rng(1)
    X0 = np.c_[rng.uniform(-1, 1, (50, 2)), rng.uniform(2, 5, 50)]
    pose = Pose.from_qt([0.99, 0.05, -0.1, 0.02], [0.3, -0.05, 0.1])
    k0, k1 = project(X0, K.K), project(pose.transform(X0), K.K)
    k1_bad = k1.copy()
    k1_bad[:10] += 25.0
    inl = epipolar_inliers(k0, k1_bad, K, K, pose, 2.0)
    assert inl[10:].all() and inl[:10].sum() <= 1
    assert vcre_px(pose, pose, K) == pytest.approx(0.0, abs=1e-9)
    moved = Pose(pose.R, pose.t + [0.1, 0, 0])
    assert 5 < vcre_px(moved, pose, K) < 60
    assert vcre_grid().shape == (196, 3)


def test_viz_writes_png(tmp_path, scene, sift_sensor):
    q = scene.frame(EASY_QUERY)
    est = sift_sensor.relocalize(scene.reference, q)
    m = est.matches
    fig = relocalization_figure(
        scene.reference.image(),
        q.image(),
        scene.reference.intrinsics,
        q.intrinsics,
        m.kpts0,
        m.kpts1,
        est.pose,
        q.pose,
        title="sift",
    )
    path = save_png(tmp_path / "out" / "viz.png", fig)
    back = cv2.imread(str(path))
    assert back is not None and back.shape == fig.shape and back.shape[0] > 2 * q.intrinsics.height
    # Orange estimate dots and cyan ground-truth dots were drawn in the AR panel (bottom right).
    ar = fig[-q.intrinsics.height :, scene.reference.intrinsics.width :]
    assert np.any(np.all(ar == (255, 150, 0), axis=2)) and np.any(np.all(ar == (0, 200, 255), axis=2))
    none = [
        scene.reference.image(),
        q.image(),
        scene.reference.intrinsics,
        q.intrinsics,
        np.zeros((0, 2)),
        np.zeros((0, 2)),
        None,
    ]
    failed = relocalization_figure(*none)
    assert save_png(tmp_path / "none.png", failed).is_file()
    # Without a pose the AR panel says why: only its second label row changes, and it reaches further right.
    why = relocalization_figure(*none, reason="too few matches (3 < 8) after the ratio test")
    rows, cols = np.nonzero(np.any(why != failed, axis=2))
    top = why.shape[0] - q.intrinsics.height  # the AR panel's first row
    assert rows.size and rows.min() >= top + 20 and rows.max() <= top + 60 and cols.max() > 300
    # OpenCV draws ASCII only: a reason with a degree sign reads "deg", not "?" (pose triangulation's reason has one).
    deg = relocalization_figure(*none, reason="rays 0.40° apart are nearly parallel")
    assert np.array_equal(deg, relocalization_figure(*none, reason="rays 0.40 deg apart are nearly parallel"))


def test_localize_many_equals_localize(scene, sift_sensor):
    queries = scene.queries[8:11] + [scene.reference]
    anchor = sift_sensor.prepare(scene.reference)
    one = [sift_sensor.localize(q, anchor) for q in queries]
    many = list(sift_sensor.localize_many(queries, anchor, prefetch=2))
    assert len(many) == len(queries)
    for a, b in zip(one, many):
        assert a.ok == b.ok and a.reason == b.reason
        if a.ok:
            assert np.allclose(a.pose.R, b.pose.R) and np.allclose(a.pose.t, b.pose.t)
    assert many[-1].ok and np.allclose(many[-1].pose.t, 0)  # the reference itself: the identity


def test_clean_depth_maps_are_not_copied_and_dirty_ones_are_cleaned(scene):
    """``_fit_depth`` skips its copy for a clean map the caller handed over (one read from a PNG) and still
    replaces NaN/inf/negative depths; the user's own arrays are never returned (so never aliased)."""
    from mapfree.relocalize.views import fit_depth as _fit_depth

    K, d = scene.reference.intrinsics, scene.reference.depth("sensor")
    assert _fit_depth(d, K, owned=True) is d
    got = _fit_depth(d, K)
    assert got is not d and np.array_equal(got, d)
    dirty = d.copy()
    dirty[0, :4] = [np.nan, np.inf, -np.inf, -2.0]
    for owned in (False, True):
        clean = _fit_depth(dirty, K, owned=owned)
        assert clean is not dirty and clean[0, :4].tolist() == [0.0] * 4 and np.array_equal(clean[1:], d[1:])
    half = _fit_depth(d[::2, ::2].astype(np.float64), K)  # another size and dtype: resized, float32
    assert half.shape == d.shape and half.dtype == np.float32


def test_sift_emat_sensor_equals_the_straightforward_spec4_code(realmini):
    """The cached, vectorised ``sift_emat_sensor`` path gives the poses of the plain SPEC §4 implementation the
    benchmark compares it with (bench/reference_spec4.py): same matches, same RANSAC, same scale vote."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "bench" / "reference_spec4.py"
    spec = importlib.util.spec_from_file_location("reference_spec4", path)
    ref_impl = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ref_impl)
    loc = Relocalizer.from_method("sift_emat_sensor")
    for name, count in (("s00001", 3), ("s00002", 2)):
        s = Dataset(realmini).scene("val", name)
        loc.set_reference(s.reference)
        for q in s.scored_queries()[:count]:
            est = loc.localize(q)
            R, t, conf = ref_impl.relocalize_pair(
                s.reference.image(),
                q.image(),
                s.reference.intrinsics.K,
                q.intrinsics.K,
                s.reference.depth("sensor"),
                q.depth("sensor"),
            )
            assert est.ok and rotation_angle_deg(est.pose.R, R) < 1e-5 and np.linalg.norm(est.pose.t - t) < 1e-9
            assert est.confidence == conf


def test_a_depth_map_of_another_aspect_ratio_is_refused(scene, sift_sensor):
    """A map at half resolution is resized onto the image; one of another aspect ratio (another frame's, rotated)
    would put depth on the wrong pixels: a clean "no estimate" naming both sizes (``set_reference`` raises it)."""
    ref, q = scene.reference, scene.frame(EASY_QUERY)
    d, query = ref.depth("sensor"), (q.image(), q.intrinsics, q.depth("sensor"))
    est = sift_sensor.relocalize((ref.image(), ref.intrinsics, d[::2, ::2].copy()), query)
    assert est.ok and np.linalg.norm(est.pose.center - q.pose.center) < 0.25
    rotated = (ref.image(), ref.intrinsics, d.T.copy())
    est = sift_sensor.relocalize(rotated, query)
    assert not est.ok and "depth map is 360x540 but the image is 540x360" in est.reason
    with pytest.raises(ValueError, match=r"depth map is 360x540 but the image is 540x360"):
        sift_sensor.set_reference(rotated)


def test_figure_of_a_method_without_matches_has_no_matches_panel(synth):
    """A regression method (RPR) has no correspondences: its --viz showed an empty "0 matches" panel."""
    from mapfree.data import Dataset
    from mapfree.estimate import Estimate
    from mapfree.viz import estimate_figure

    scene = Dataset(synth).scene("val", "s00000")
    ref, q = scene.reference, scene.queries[5]
    rel = q.pose @ ref.pose.inverse()
    args = (ref.image(), q.image(), ref.intrinsics, q.intrinsics)
    h, w = ref.image().shape[:2]
    regression = estimate_figure(*args, Estimate(rel, 1.0), rel, title="rpr")
    assert regression.shape[:2] == (h, 2 * w)  # the AR check alone
    import numpy as np

    from mapfree.matching.base import Matches

    k = np.array([[10.0, 10.0], [50.0, 60.0]])
    matched = estimate_figure(*args, Estimate(rel, 1.0, matches=Matches(k, k + 1, np.ones(2))), rel)
    assert matched.shape[:2] == (2 * h + 6, 2 * w)


def test_from_method_always_gives_a_relocalizer_and_build_localizer_any_method():
    """``Relocalizer.from_method`` returns what it says (a matching method's ``Relocalizer``) and refuses the methods
    whose localizer is something else, naming ``build_localizer``, which builds those."""
    import dataclasses

    from mapfree.calibration import CALIBRATION_OPTION
    from mapfree.methods import get
    from mapfree.relocalize import build_localizer

    assert type(Relocalizer.from_method("sift_pnp_sensor")) is Relocalizer
    assert type(build_localizer("sift_pnp_sensor")) is Relocalizer
    calibrated = dataclasses.replace(get("sift_pnp_sensor"), options={CALIBRATION_OPTION: "x.calib.json"})
    for method, what in (
        ("rpr-3d3d", "a regression method"),
        ("sift_pnp_sensor+sift_emat_sensor", "a cascade method"),
        (calibrated, "calibrated"),
    ):
        with pytest.raises(ValueError, match=f"is {what}: .*build_localizer"):
            Relocalizer.from_method(method)
