"""Exact scoring (SPEC §3): hand-computed cases, AUC, missing frames/scenes in both modes, naive cross-check."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mapfree.benchmark import (
    METRIC_KEYS,
    EvaluationError,
    auc,
    evaluate,
    format_table,
    load_truth,
    precision_ratio_curve,
    write_submission,
)
from mapfree.benchmark.naive import evaluate_naive
from mapfree.cli import main as cli_main
from mapfree.data import REFERENCE_NAME, read_poses, write_intrinsics, write_poses
from mapfree.geometry import Intrinsics, Pose, quat_to_rotmat

BIG_K = Intrinsics(500.0, 500.0, 1000.0, 1000.0, 2000, 2000)  # nothing leaves the image in these tests


def make_scene(root: Path, scene: str, poses: list[Pose], K: Intrinsics = BIG_K, split: str = "val") -> list[str]:
    """Write a val scene whose queries seq1/frame_00000.. have the given world-to-camera poses."""
    names = [REFERENCE_NAME] + [f"seq1/frame_{i:05d}.jpg" for i in range(len(poses))]
    d = root / split / scene
    d.mkdir(parents=True)
    write_poses(d / "poses.txt", names, [Pose.identity()] + list(poses))
    write_intrinsics(d / "intrinsics.txt", {n: K for n in names})
    return names


def gt_estimates(root: Path, split: str = "val", conf: float = 1.0) -> dict:
    """A perfect submission: every query's ground-truth pose, as read back from poses.txt."""
    out = {}
    for d in sorted((root / split).iterdir()):
        table = read_poses(d / "poses.txt")
        out[d.name] = [(n, table.pose(i), conf) for i, n in enumerate(table.names) if n.startswith("seq1/")]
    return out


def rot_x(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def test_perfect_submission_scores_zero_errors_and_full_precision(tmp_path):
    rng = np.random.default_rng(0)
    poses = [Pose(quat_to_rotmat(np.r_[1, rng.normal(size=3) * 0.2]), rng.normal(size=3)) for _ in range(12)]
    make_scene(tmp_path, "s00000", poses)
    report = evaluate(gt_estimates(tmp_path), tmp_path, "val")
    assert list(report.metrics)[:8] == list(METRIC_KEYS)
    assert len(report.estimated) == 3  # keys 0, 5, 10 of 12 queries
    np.testing.assert_allclose(report.trans_err, 0, atol=1e-9)
    np.testing.assert_allclose(report.rot_err, 0, atol=1e-5)
    np.testing.assert_allclose(report.vcre, 0, atol=1e-6)
    for k in METRIC_KEYS[3:]:
        assert report.metrics[k] == pytest.approx(1.0)


def test_known_rotation_gives_its_angle_and_no_translation_error(tmp_path):
    make_scene(tmp_path, "s00000", [Pose.identity()] * 6)
    est = {
        "s00000": [
            ("seq1/frame_00000.jpg", Pose(rot_x(10.0), np.zeros(3)), 1.0),
            ("seq1/frame_00005.jpg", Pose(rot_x(-3.5) @ rot_x(-3.5), np.zeros(3)), 1.0),
        ]
    }
    r = evaluate(est, tmp_path, "val")
    np.testing.assert_allclose(r.rot_err, [10.0, 7.0], atol=1e-6)
    np.testing.assert_allclose(r.trans_err, 0, atol=1e-12)
    assert r.metrics["Precision @ Pose Error < (25.0cm, 5deg)"] == 0.0
    assert r.metrics["Precision @ Pose Error < (50.0cm, 10deg)"] == 0.5  # 7° < 10°, 10° is not < 10°


def test_pure_one_metre_shift_of_the_camera_centre(tmp_path):
    R = rot_x(20.0)
    gt = Pose(R, np.array([0.3, -0.2, 1.0]))
    make_scene(tmp_path, "s00000", [gt])
    c = gt.center + np.array([0.0, 0.6, 0.8])  # |shift| = 1 m
    est = {"s00000": [("seq1/frame_00000.jpg", Pose(R, -R @ c), 3.0)]}
    r = evaluate(est, tmp_path, "val")
    assert r.trans_err[0] == pytest.approx(1.0, abs=1e-8)
    assert r.rot_err[0] == pytest.approx(0.0, abs=1e-5)
    assert r.metrics["Average Median Translation Error"] == pytest.approx(1.0, abs=1e-8)


def test_vcre_of_a_sideways_shift_matches_the_hand_formula(tmp_path):
    # Query at the reference: R = I, c = 0. Estimated centre 2 cm to the right: every virtual point
    # (x, y, z) moves to x - 0.02 in the estimated camera, i.e. fx * 0.02 / z pixels; VCRE is the mean.
    make_scene(tmp_path, "s00000", [Pose.identity()])
    d = 0.02
    est = {"s00000": [("seq1/frame_00000.jpg", Pose(np.eye(3), np.array([-d, 0.0, 0.0])), 1.0)]}
    r = evaluate(est, tmp_path, "val")
    z = 1.8 + 0.3 * np.arange(7)
    assert r.vcre[0] == pytest.approx(500.0 * d * np.mean(1.0 / z), rel=1e-9)
    # A huge shift pushes every projection to the border: clipping bounds the error by the diagonal.
    est = {"s00000": [("seq1/frame_00000.jpg", Pose(np.eye(3), np.array([-500.0, 0.0, 0.0])), 1.0)]}
    assert 0 < evaluate(est, tmp_path, "val").vcre[0] <= np.hypot(2000, 2000)


def test_auc_equals_precision_with_constant_confidence():
    rng = np.random.default_rng(1)
    ok = rng.random(200) < 0.4
    for failures in (0, 37):
        assert auc(np.zeros(200), ok, failures) == pytest.approx(ok.sum() / (200 + failures), abs=1e-7)


def test_auc_hand_computed_ranking_with_ties():
    # Sorted by confidence: 3, 3 (tie: one threshold after both), 2, 1; one failure -> 5 frames in all.
    conf = np.array([2.0, 3.0, 1.0, 3.0])
    ok = np.array([True, True, True, False])
    ratio, prec = precision_ratio_curve(conf, ok, failures=1)
    np.testing.assert_allclose(ratio, [2 / 5, 3 / 5, 4 / 5], rtol=1e-7)
    np.testing.assert_allclose(prec, [1 / 2, 2 / 3, 3 / 4])
    assert auc(conf, ok, 1) == pytest.approx(0.4 * 0.5 + 0.2 * 2 / 3 + 0.2 * 0.75, abs=1e-7)
    # Confidence ranks the estimates: putting the wrong one first lowers the AUC, not the precision.
    assert auc(np.array([3.0, 2.0, 1.0, 4.0]), ok, 1) < auc(np.array([3.0, 2.0, 1.0, 0.0]), ok, 1)


def test_missing_frames_and_missing_scene_in_both_modes(tmp_path):
    rng = np.random.default_rng(2)
    for s, n in (("s00000", 20), ("s00001", 13)):
        make_scene(
            tmp_path,
            s,
            [Pose(quat_to_rotmat(np.r_[1, rng.normal(size=3) * 0.1]), rng.normal(size=3)) for _ in range(n)],
        )
    est = gt_estimates(tmp_path)
    est["s00000"] = [e for e in est["s00000"] if e[0] != "seq1/frame_00005.jpg"]  # 1 of 4 scored frames
    full = evaluate(est, tmp_path, "val")
    assert full.metrics["Estimates for % of frames"] == pytest.approx(6 / 7)  # 4 + 3 scored, one missing
    assert full.metrics["Precision @ VCRE < 90px"] == pytest.approx(6 / 7)
    assert not full.estimated[list(full.frame).index("seq1/frame_00005.jpg")]

    del est["s00001"]
    default = evaluate(est, tmp_path, "val")
    official = evaluate(est, tmp_path, "val", compat="official")
    # Default: the missing scene costs its 3 scored frames. Official: all its 13 keyed lines (the
    # reference shares key 0 with seq1/frame_00000), before the 1-in-5 subsampling.
    assert default.metrics["Estimates for % of frames"] == pytest.approx(3 / 7)
    assert official.metrics["Estimates for % of frames"] == pytest.approx(3 / (3 + 1 + 13))
    assert official.extra_failures == 13 - 3
    assert default.per_scene["s00001"]["Average Median Translation Error"] is None
    assert any(p.scene == "s00001" and "missing" in p.reason for p in default.problems)
    json.loads(default.to_json(frames=True))  # no NaN in the output


def test_negative_confidence_default_skips_line_official_aborts(tmp_path):
    make_scene(tmp_path, "s00000", [Pose.identity()] * 6)
    zpath = tmp_path / "sub.zip"
    with zipfile.ZipFile(zpath, "w") as zf:
        zf.writestr("pose_s00000.txt", "seq1/frame_00000.jpg 1 0 0 0 0 0 0 -1\nseq1/frame_00005.jpg 1 0 0 0 0 0 0 2\n")
    r = evaluate(zpath, tmp_path, "val")
    assert [(p.scene, p.line) for p in r.problems if "negative" in p.reason] == [("s00000", 1)]
    assert r.estimated.tolist() == [False, True]
    with pytest.raises(EvaluationError, match="s00000:1"):
        evaluate(zpath, tmp_path, "val", compat="official")


def _random_split(root: Path, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    est = {}
    for s in range(3):
        n = int(rng.integers(8, 40))
        q = np.c_[np.ones(n), rng.normal(size=(n, 3)) * 0.3]
        gt = [Pose(quat_to_rotmat(qi), ti) for qi, ti in zip(q, rng.normal(size=(n, 3)))]
        K = Intrinsics(590.0 + s, 588.5, 269.5, 359.5, 540, 720)
        names = make_scene(root, f"s{s:05d}", gt, K)
        items = []
        for i, name in enumerate(names[1:]):
            if rng.random() < 0.1:
                continue  # missing frame
            big = rng.random() < 0.15  # some wild estimates: behind the camera, 180° flips
            dR = quat_to_rotmat(np.r_[rng.normal() * (0 if big else 5), rng.normal(size=3)])
            p = gt[i]
            items.append(
                (name, Pose(dR @ p.R, p.t + rng.normal(size=3) * (3.0 if big else 0.2)), float(rng.integers(0, 6)))
            )
        est[f"s{s:05d}"] = items
    return est


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_vectorised_equals_naive_loop(tmp_path, seed):
    est = _random_split(tmp_path, seed)
    if seed == 2:
        del est["s00001"]  # a missing scene exercises both penalties
    zpath = tmp_path / "sub.zip"
    write_submission(zpath, est)
    for compat in ("default", "official"):
        report = evaluate(zpath, tmp_path, "val", compat=compat)
        metrics, frames = evaluate_naive(zpath, tmp_path, "val", compat=compat)
        assert set(metrics) == set(report.metrics)
        for k, v in metrics.items():
            assert report.metrics[k] == pytest.approx(v, abs=1e-6), k
        assert len(frames) == int(report.estimated.sum())
        index = {(s, f): i for i, (s, f) in enumerate(zip(report.scene, report.frame))}
        for key, (te, re, ve) in frames.items():
            i = index[key]
            assert (report.trans_err[i], report.rot_err[i], report.vcre[i]) == pytest.approx((te, re, ve), abs=1e-6)


def test_in_memory_and_zip_give_identical_reports(tmp_path):
    est = _random_split(tmp_path, 5)
    write_submission(tmp_path / "sub.zip", est)
    a = evaluate(est, tmp_path, "val")
    b = evaluate(tmp_path / "sub.zip", tmp_path, "val", truth=load_truth(tmp_path, "val"))
    for k in a.metrics:
        assert a.metrics[k] == pytest.approx(b.metrics[k], abs=1e-9)
    assert a.per_scene.keys() == b.per_scene.keys()
    assert set(a.per_scene["s00000"]) == set(a.metrics)  # same keys per scene


def test_private_ground_truth_root(tmp_path):
    rng = np.random.default_rng(3)
    poses = [Pose(quat_to_rotmat(np.r_[1, rng.normal(size=3) * 0.1]), rng.normal(size=3)) for _ in range(10)]
    names = make_scene(tmp_path / "private", "s00000", poses, split="test")
    public = tmp_path / "public" / "test" / "s00000"
    public.mkdir(parents=True)
    write_poses(public / "poses.txt", names, [None] * len(names))  # all-zero lines, as released
    write_intrinsics(public / "intrinsics.txt", {n: BIG_K for n in names})
    est = gt_estimates(tmp_path / "private", "test")
    with pytest.raises(Exception, match="gt_root"):
        evaluate(est, tmp_path / "public", "test")
    r = evaluate(est, tmp_path / "public", "test", gt_root=tmp_path / "private")
    assert r.metrics["Precision @ VCRE < 90px"] == pytest.approx(1.0)


def test_realmini_val_ground_truth_scores_perfectly_and_cli(realmini, tmp_path, capsys):
    est = gt_estimates(realmini)
    # Corrupt one scene's estimates by a 30 cm shift so that the numbers are not trivial.
    est["s00001"] = [(n, Pose(p.R, p.t + np.array([0.3, 0, 0])), c) for n, p, c in est["s00001"]]
    zpath = tmp_path / "sub.zip"
    write_submission(zpath, est)
    r = evaluate(zpath, realmini, "val")
    assert len(r.per_scene) == 4 and r.estimated.all()
    assert r.metrics["Precision @ Pose Error < (25.0cm, 5deg)"] == pytest.approx(1 - 6 / len(r.estimated))
    assert r.per_scene["s00001"]["Average Median Translation Error"] == pytest.approx(0.3, abs=1e-6)
    assert "Average Median Translation Error" in format_table(r, per_scene=True)

    assert cli_main(["evaluate", str(zpath), "--dataset", str(realmini), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["metrics"]["Estimates for % of frames"] == 1.0
    assert cli_main(["evaluate", str(zpath), "--dataset", str(realmini), "--per-scene"]) == 0
    out = capsys.readouterr().out
    assert "Precision @ VCRE < 90px" in out and "s00003" in out
    (tmp_path / "junk.zip").write_bytes(b"not a zip at all")
    assert cli_main(["evaluate", str(tmp_path / "junk.zip"), "--dataset", str(realmini)]) == 1
    err = capsys.readouterr().err
    assert f"{tmp_path / 'junk.zip'}: not a ZIP" in err and "pose_s00000.txt missing" not in err  # the cause only
    assert cli_main(["evaluate", str(tmp_path / "missing.zip"), "--dataset", str(realmini)]) == 1
    assert f"{tmp_path / 'missing.zip'}: cannot open submission" in capsys.readouterr().err


def test_reference_slot_when_seq1_has_no_frame_zero(tmp_path):
    # seq1 starts at frame 1: the reference keeps key 0's slot, and the public evaluator scores it as if it
    # were a query (official); by default only seq1 frames are scored.
    d = tmp_path / "val" / "s00000"
    d.mkdir(parents=True)
    names = [REFERENCE_NAME] + [f"seq1/frame_{i:05d}.jpg" for i in range(1, 11)]
    write_poses(d / "poses.txt", names, [Pose.identity()] * len(names))
    write_intrinsics(d / "intrinsics.txt", {n: BIG_K for n in names})
    est = {"s00000": [(n, Pose.identity(), 1.0) for n in names[1:]]}
    zpath = tmp_path / "sub.zip"
    write_submission(zpath, est)
    default = evaluate(zpath, tmp_path, "val")
    official = evaluate(zpath, tmp_path, "val", compat="official")
    assert default.frame.tolist() == ["seq1/frame_00005.jpg", "seq1/frame_00010.jpg"]
    assert official.frame.tolist() == [REFERENCE_NAME, "seq1/frame_00005.jpg", "seq1/frame_00010.jpg"]
    assert official.estimated.tolist() == [False, True, True]  # nothing numbered 0 in the submission
    for compat, r in (("default", default), ("official", official)):
        metrics, _ = evaluate_naive(zpath, tmp_path, "val", compat=compat)
        assert metrics["Estimates for % of frames"] == pytest.approx(r.metrics["Estimates for % of frames"])


def test_per_scene_figures_equal_scoring_each_scene_alone(tmp_path):
    est = _random_split(tmp_path, 7)
    del est["s00002"]
    for compat in ("default", "official"):
        r = evaluate(est, tmp_path, "val", compat=compat)
        for scene in ("s00000", "s00001", "s00002"):
            alone = evaluate(
                {scene: est[scene]} if scene in est else {},
                tmp_path,
                "val",
                compat="default",
                truth={scene: load_truth(tmp_path, "val")[scene]},
            )
            for k, v in r.per_scene[scene].items():
                if compat == "official" and scene == "s00002" and k != METRIC_KEYS[0]:
                    continue  # the public evaluator's penalty differs for a missing scene
                if v is None:
                    assert alone.metrics[k] is None, k
                else:
                    assert alone.metrics[k] == pytest.approx(v, abs=1e-12), (scene, k)


def test_scene_with_no_estimates_counts_as_failures_not_an_error(tmp_path):
    """`mapfree run` writes an empty pose file for a scene whose frames all failed."""
    make_scene(tmp_path, "s00000", [Pose.identity()] * 10)
    make_scene(tmp_path, "s00001", [Pose.identity()] * 10)
    est = gt_estimates(tmp_path)
    est["s00001"] = []
    rep = evaluate(est, tmp_path, "val")
    assert rep.metrics["Estimates for % of frames"] == pytest.approx(2 / 4)
    zpath = tmp_path / "sub.zip"
    write_submission(zpath, est)
    with zipfile.ZipFile(zpath) as z:
        assert z.read("pose_s00001.txt") == b""
    assert evaluate(zpath, tmp_path, "val").metrics == rep.metrics
