"""Multi-frame track: burst selection, device drift, poses_device.txt, fusion, `mapfree run/evaluate --track multi`."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapfree.benchmark import evaluate, format_table, load_truth, read_submission, write_submission
from mapfree.cli import main as cli_main
from mapfree.data import Dataset, DriftModel, FormatError, load_device_poses, multiframe_bursts, scene_bursts
from mapfree.data.device import rebase_bursts, simulate_device_trajectory
from mapfree.data.synth import SynthOptions, generate
from mapfree.geometry import Pose, rotation_angle_deg
from mapfree.relocalize.multiframe import Hypothesis, frames_path, fuse, hypotheses, run_multi

NO_DRIFT = DriftModel(0, 0, 0, 0, 0, 0)


def _name(i: int) -> str:
    return f"seq1/frame_{i:05d}.jpg"


def _pose_error(a: Pose, b: Pose) -> tuple[float, float]:
    return float(np.linalg.norm(a.center - b.center)), float(rotation_angle_deg(a.R, b.R))


def test_bursts_are_the_public_loaders_scored_queries_and_their_eight_predecessors():
    # The public loader's own example (scene s00470): frames 2 and 4 missing, query 11 uses 1,3,5,…,11.
    numbers = [0, 1, 3, 5, 6, 7, 8, 9, 10, 11, *range(12, 33)]
    names = ["seq0/frame_00000.jpg"] + [_name(i) for i in reversed(numbers)]  # file order does not matter
    bursts = multiframe_bursts(names)
    assert [q for q, _ in bursts] == [_name(11), _name(21), _name(31)]
    assert bursts[0][1] == [_name(i) for i in (1, 3, 5, 6, 7, 8, 9, 10, 11)]
    assert bursts[1][1] == [_name(i) for i in range(13, 22)]
    assert multiframe_bursts(names[:10]) == []  # 9 queries: nothing is scored


def test_derived_device_poses_drift_a_few_cm_per_metre_and_are_reproducible(realmini):
    scene = Dataset(realmini).scene("val", "s00001")
    dev = load_device_poses(scene)
    assert dev.derived and not (scene.path / "poses_device.txt").exists()
    assert load_device_poses(scene).poses.keys() == dev.poses.keys()
    assert all(
        np.allclose(a.matrix, b.matrix) for a, b in zip(dev.poses.values(), load_device_poses(scene).poses.values())
    )
    other = load_device_poses(scene, seed=1)
    bursts = scene_bursts(scene)
    assert len(bursts) == 3 and set(dev.poses) == {n for _, b in bursts for n in b}
    drifted = []
    for query, burst in bursts:
        assert np.allclose(dev.poses[query].matrix, np.eye(4))  # re-based: the query is the identity
        truth_q = scene.frame(query).pose
        for name in burst[:-1]:
            truth = truth_q @ scene.frame(name).pose.inverse()  # frame camera -> query camera
            t_err, r_err = _pose_error(dev.relative(name, query), truth)
            travel = np.linalg.norm(truth.center)
            assert t_err < 0.02 + 0.06 * travel and r_err < 3.0
            drifted.append(t_err)
            assert not np.allclose(other.relative(name, query).matrix, dev.relative(name, query).matrix)
    assert max(drifted) > 1e-3  # it is a simulation of tracking, not a copy of the truth
    # Over a long walk the heading error grows: the far end of the scan drifts more than the first metre.
    truth = [scene.frame(n).pose for n in sorted(n for n in scene.frames if n.startswith("seq1/"))]
    errs = []
    for seed in range(8):
        track = simulate_device_trajectory(truth, np.array([0, -1.0, 0]), np.random.default_rng(seed))
        errs.append([_pose_error(t.relative_to(track[0]), g.relative_to(truth[0]))[0] for t, g in zip(track, truth)])
    errs = np.mean(errs, axis=0)
    assert errs[-1] > 3 * errs[2] and errs[-1] < 0.5


def test_synth_writes_device_poses_for_val_and_test(tmp_path):
    opts = SynthOptions(width=90, height=120, texture_size=64, queries=21, write_mono=False)
    generate(tmp_path, "val", 1, seed=2, options=opts, progress=False)
    generate(tmp_path, "test", 1, seed=2, options=opts, private_gt_dir=tmp_path / "gt", progress=False)
    scene = Dataset(tmp_path).scene("val", "s00000")
    dev = load_device_poses(scene, derive=False)
    assert not dev.derived and sorted(dev.poses) == [_name(i) for i in (*range(1, 10), *range(11, 20))]
    for query, burst in scene_bursts(scene):
        for name in burst:
            truth = scene.frame(query).pose @ scene.frame(name).pose.inverse()
            t_err, r_err = _pose_error(dev.relative(name, query), truth)
            assert t_err < 0.02 + 0.06 * np.linalg.norm(truth.center) and r_err < 3.0
    test_scene = Dataset(tmp_path).scene("test", "s00000")
    assert len(load_device_poses(test_scene, derive=False).poses) == 18  # public, while poses.txt is zeros
    (test_scene.path / "poses_device.txt").unlink()
    with pytest.raises(FormatError, match=r"poses_device.txt: missing, and the scene has no ground-truth"):
        load_device_poses(Dataset(tmp_path).scene("test", "s00000"))


def _noisy(pose: Pose, rng: np.random.Generator, deg: float, metres: float) -> Pose:
    R = Rotation.from_rotvec(np.radians(deg) * rng.normal(size=3) / np.sqrt(3)).as_matrix() @ pose.R
    c = pose.center + rng.normal(0, metres / np.sqrt(3), 3)
    return Pose(R, -R @ c)


def test_fusion_drops_outliers_averages_the_rest_and_scores_agreement(realmini):
    truth = Dataset(realmini).scene("val", "s00000").frame(_name(9)).pose
    rng = np.random.default_rng(0)
    good = [Hypothesis(f"f{i}", _noisy(truth, rng, 3.0, 0.15), 50.0 + i) for i in range(6)]
    bad = [
        Hypothesis("far", _noisy(truth, rng, 40.0, 2.0), 400.0),
        Hypothesis("turned", _noisy(truth, rng, 60.0, 0.1), 30.0),
        Hypothesis("off", _noisy(truth, rng, 1.0, 1.5), 30.0),
    ]
    est = fuse(good + bad, 9)
    assert est.ok and sorted(est.extras["frames_used"]) == sorted(h.frame for h in good)
    t_err, r_err = _pose_error(est.pose, truth)
    singles = [_pose_error(h.pose, truth) for h in good]
    assert t_err < np.median([s[0] for s in singles]) and r_err < np.median([s[1] for s in singles])
    # Confidence grows with agreement: the same six frames, with three more agreeing instead of disagreeing.
    more = fuse(good + [Hypothesis(f"g{i}", _noisy(truth, rng, 3.0, 0.15), 30.0) for i in range(3)], 9)
    assert more.confidence > est.confidence > fuse(good[:1], 9).confidence > 0
    # Constant-zero confidences (regression methods) vote equally; nothing at all is "no estimate".
    flat = fuse([replace(h, confidence=c) for h, c in zip(good + bad, [0.0, np.nan, -1.0] * 3)], 9)
    assert flat.ok and flat.extras["support"] == 6 and np.isfinite(flat.confidence)
    none = fuse([], 9)
    assert not none.ok and "no frame" in none.reason


def test_hypotheses_carry_each_frame_to_the_query_through_the_device_poses(realmini):
    scene = Dataset(realmini).scene("val", "s00002")
    dev = load_device_poses(scene, model=NO_DRIFT)
    query, burst = scene_bursts(scene)[0]
    estimates = {n: (scene.frame(n).pose, 10.0) for n in burst if n != burst[3]}  # one frame without estimate
    dev.poses.pop(burst[0])  # and one without a device pose: both skipped
    hyps = hypotheses(query, burst, estimates, dev)
    assert [h.frame for h in hyps] == burst[1:3] + burst[4:]
    for h in hyps:
        assert np.allclose(h.pose.matrix, scene.frame(query).pose.matrix, atol=1e-9)
    fused = fuse(hyps, len(burst))
    assert fused.extras["support"] == 7 and np.allclose(fused.pose.matrix, scene.frame(query).pose.matrix, atol=1e-9)


def test_rebasing_is_independent_of_the_device_frame(realmini):
    scene = Dataset(realmini).scene("val", "s00000")
    names = sorted(n for n in scene.frames if n.startswith("seq1/"))
    poses = {n: scene.frame(n).pose for n in names}
    moved = Pose(Rotation.from_euler("xyz", [10, 50, -5], degrees=True).as_matrix(), np.array([3.0, -1, 2]))
    a = rebase_bursts(poses, multiframe_bursts(names))
    b = rebase_bursts({n: p @ moved for n, p in poses.items()}, multiframe_bursts(names))
    assert all(np.allclose(a[n].matrix, b[n].matrix) for n in a)


def test_evaluate_multi_track_scores_exactly_the_burst_queries(realmini):
    truth = load_truth(realmini, "val", track="multi")
    assert {s: t.names for s, t in truth.items()} == {
        "s00000": [_name(9), _name(19)],
        "s00001": [_name(9), _name(19), _name(29)],
        "s00002": [_name(9), _name(19)],
        "s00003": [_name(9)],
    }
    ds = Dataset(realmini)
    perfect = {s.name: [(f.name, f.pose, 1.0) for f in s.queries] for s in ds.scenes("val")}
    for compat in ("default", "official"):
        report = evaluate(perfect, realmini, "val", compat=compat, track="multi")
        assert len(report.frame) == 8 and report.metrics["Precision @ VCRE < 90px"] == 1.0
    single = evaluate(perfect, realmini, "val")
    assert len(single.frame) == 20


@pytest.fixture(scope="module")
def multi_run(realmini, tmp_path_factory):
    out = tmp_path_factory.mktemp("multi") / "multi.zip"
    code = cli_main(
        [
            "run",
            str(realmini),
            "--track",
            "multi",
            "--method",
            "sift_pnp_sensor",
            "-o",
            str(out),
            "--scenes",
            "s00000,s00003",
            "--no-progress",
        ]
    )
    assert code == 0
    return out


def test_run_multi_writes_one_fused_pose_per_scored_query(multi_run, realmini):
    estimates, problems = read_submission(multi_run)
    assert not problems and set(estimates) == {"s00000", "s00003"}
    assert estimates["s00000"].names == [_name(9), _name(19)] and len(estimates["s00003"].names) == 0
    failures = [json.loads(line) for line in multi_run.with_name("multi.failures.jsonl").read_text().splitlines()]
    assert failures == [{"scene": "s00003", "frame": _name(9), "reason": "no frame of the burst has an estimate"}]
    frames, _ = read_submission(frames_path(multi_run))
    assert len(frames["s00000"].names) == 18  # every burst frame ran once, on its own
    fusion = [json.loads(line) for line in multi_run.with_name("multi.fusion.jsonl").read_text().splitlines()]
    assert all(f["support"] >= 3 for f in fusion if f["ok"])


def test_multi_beats_single_frame_on_the_same_scored_queries(multi_run, realmini, capsys):
    code = cli_main(["evaluate", str(multi_run), "--dataset", str(realmini), "--track", "multi", "--json"])
    multi = json.loads(capsys.readouterr().out)["metrics"]
    single = evaluate(frames_path(multi_run), realmini, "val", track="multi").metrics
    assert code == 0
    for key in ("Precision @ VCRE < 90px", "AUC @ VCRE < 90px"):
        assert multi[key] > single[key], key
    assert multi["Average Median Reprojection Error"] < single["Average Median Reprojection Error"]


def test_bad_device_poses_are_a_clear_error(realmini, tmp_path, capsys):
    root = tmp_path / "root"
    shutil.copytree(realmini / "val" / "s00000", root / "val" / "s00000")
    bad = root / "val" / "s00000" / "poses_device.txt"
    bad.write_text(f"{_name(1)} 1 0 0 0 0 0 0\n{_name(2)} 1 0 0 nan 0 0 0\n")
    with pytest.raises(FormatError, match=r"poses_device.txt:2: non-finite"):
        load_device_poses(Dataset(root).scene("val", "s00000"))
    code = cli_main(
        [
            "run",
            str(root),
            "--track",
            "multi",
            "--method",
            "sift_pnp_sensor",
            "-o",
            str(tmp_path / "m.zip"),
            "--no-progress",
        ]
    )
    assert code == 1 and "poses_device.txt:2: non-finite" in capsys.readouterr().err
    bad.write_text(f"{_name(1)} 0 0 0 0 0 0 0\n")
    with pytest.raises(FormatError, match=r"poses_device.txt:1: zero quaternion"):
        load_device_poses(Dataset(root).scene("val", "s00000"))
    bad.unlink()
    with pytest.raises(FormatError, match=r"poses_device.txt: missing \(the multi-frame"):
        run_multi(root, "val", "sift_pnp_sensor", tmp_path / "m.zip", derive_device_poses=False, progress=False)
    assert not (tmp_path / "m.zip").exists()


def test_all_frames_with_the_multi_track_is_a_clear_error(realmini, tmp_path, capsys):
    """The multi track runs the bursts of the scored queries; --all-frames would be silently ignored."""
    out = tmp_path / "m.zip"
    code = cli_main(
        [
            "run",
            str(realmini),
            "--track",
            "multi",
            "--all-frames",
            "--method",
            "sift_pnp_sensor",
            "-o",
            str(out),
            "--no-progress",
        ]
    )
    err = capsys.readouterr().err
    assert code == 1 and "mapfree run: error: --all-frames" in err and "--track multi" in err
    assert not out.exists() and not frames_path(out).exists()
    with pytest.raises(ValueError, match="all_frames"):
        run_multi(realmini, "val", "sift_pnp_sensor", out, all_frames=True, progress=False)
    assert not frames_path(out).exists()


def test_the_report_names_its_track_in_json_and_table_title(realmini, tmp_path, capsys):
    """A multi-track report says so (JSON ``track``, table title); single-frame output only gains the field."""
    perfect = {s.name: [(f.name, f.pose, 1.0) for f in s.queries] for s in Dataset(realmini).scenes("val")}
    sub = tmp_path / "perfect.zip"
    write_submission(sub, perfect)
    for track in ("single", "multi"):
        assert cli_main(["evaluate", str(sub), "--dataset", str(realmini), "--track", track, "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["track"] == track and out["split"] == "val"
        assert cli_main(["evaluate", str(sub), "--dataset", str(realmini), "--track", track]) == 0
        title = capsys.readouterr().out.splitlines()[0]
        assert title.startswith("Map-free benchmark — val, 4 scenes, ")
        assert ("multi-frame track" in title) == (track == "multi"), title
    single = evaluate(sub, realmini, "val")
    assert single.track == "single" and "track" not in format_table(single).splitlines()[0]
    assert (
        format_table(evaluate(sub, realmini, "val", track="multi"))
        .splitlines()[0]
        .endswith("8 evaluated frames, 8 estimated, multi-frame track")
    )
