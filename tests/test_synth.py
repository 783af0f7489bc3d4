"""Synthetic scenes: Map-free layout round trip, determinism, depth/pose consistency, overlaps, mono depth."""

from __future__ import annotations

import hashlib
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from mapfree.cli import main as cli_main
from mapfree.data import Dataset, read_intrinsics, read_poses
from mapfree.data.synth import EST_DEPTH_SUFFIX, GT_DEPTH_SUFFIX, SynthOptions, depth_overlap, generate
from mapfree.geometry import Intrinsics, Pose, backproject, project, rotation_angle_deg

SMALL = dict(width=180, height=240, texture_size=128)


@pytest.fixture(scope="module")
def val_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth")
    generate(root, "val", 2, 10, seed=3, options=SynthOptions(no_overlap_fraction=0.3, **SMALL), progress=False)
    return root


@pytest.fixture(scope="module")
def train_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth-train")
    generate(root, "train", 1, seed=4, options=SynthOptions(train_frames=8, **SMALL), progress=False)
    return root


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _planar(depth: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood lies on one plane (inverse depth has no second difference there)."""
    inv = np.where(depth > 0, 1 / np.maximum(depth, 1e-6), 0)
    p = np.pad(inv, 1, mode="edge")
    dxx = p[1:-1, 2:] + p[1:-1, :-2] - 2 * inv
    dyy = p[2:, 1:-1] + p[:-2, 1:-1] - 2 * inv
    return (depth > 0) & (np.abs(dxx) < 1e-3 * inv) & (np.abs(dyy) < 1e-3 * inv)


def _reproject(depth_a, K_a: Intrinsics, pose_a: Pose, depth_b, K_b: Intrinsics, pose_b: Pose):
    """Forward–backward pixel error A -> B -> A through both GT depth maps, on pixels B sees un-occluded.

    A pixel of A goes to B with A's depth; there B's depth (bilinear in inverse depth, exact on a plane, so
    only stencils away from depth edges and creases) must agree (not occluded) and carries it back to A.
    """
    v, u = np.nonzero(depth_a > 0)
    uv = np.stack([u, v], 1).astype(np.float64)
    X_b = (pose_b @ pose_a.inverse()).transform(backproject(uv, depth_a[v, u], K_a.K))
    uv_b = project(X_b, K_b.K)
    H, W = depth_b.shape
    ok = (X_b[:, 2] > 0) & (uv_b[:, 0] >= 0) & (uv_b[:, 0] < W - 1) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] < H - 1)
    uv, uv_b, z_b = uv[ok], uv_b[ok], X_b[ok, 2]
    x0, y0 = np.floor(uv_b[:, 0]).astype(int), np.floor(uv_b[:, 1]).astype(int)
    fx, fy = uv_b[:, 0] - x0, uv_b[:, 1] - y0
    plane = _planar(depth_b)
    smooth = plane[y0, x0] & plane[y0, x0 + 1] & plane[y0 + 1, x0] & plane[y0 + 1, x0 + 1]
    corners = np.stack([depth_b[y0, x0], depth_b[y0, x0 + 1], depth_b[y0 + 1, x0], depth_b[y0 + 1, x0 + 1]], 1)
    inv = 1 / np.where(corners > 0, corners, 1.0)
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    d_b = 1 / (inv * w).sum(1)
    seen = smooth & (np.abs(d_b - z_b) < 0.002 * z_b + 0.002)  # visible, not occluded (mm quantisation aside)
    back = (pose_a @ pose_b.inverse()).transform(backproject(uv_b[seen], d_b[seen], K_b.K))
    return np.linalg.norm(project(back, K_a.K) - uv[seen], axis=1)


def test_val_split_reads_back_in_mapfree_layout(val_root):
    scenes = Dataset(val_root).scenes("val")
    assert [s.name for s in scenes] == ["s00000", "s00001"]
    for scene in scenes:
        assert set(p.name for p in scene.path.iterdir()) == {
            "intrinsics.txt",
            "poses.txt",
            "poses_device.txt",
            "seq0",
            "seq1",
        }
        assert scene.poses.names == list(scene.intrinsics) and len(scene.queries) == 10
        ref = scene.reference
        assert np.allclose(ref.pose.R, np.eye(3)) and np.allclose(ref.pose.t, 0)
        fx = [k.fx for k in scene.intrinsics.values()]
        assert np.std(fx) > 0 and abs(np.mean(fx) - 600 * 180 / 540) < 5  # per-frame, around the default focal
        for f in [ref, *scene.queries]:
            img = f.image()
            assert img.shape == (f.intrinsics.height, f.intrinsics.width, 3) == (240, 180, 3)
            gt, est = f.depth(GT_DEPTH_SUFFIX), f.depth(EST_DEPTH_SUFFIX)
            assert gt.shape == est.shape == img.shape[:2]
            assert (gt > 0).mean() > 0.3 and gt.max() <= 40.0 and np.all(est > 0)
            assert img.std() > 20  # textured, not a flat render
        # the written poses are exactly the rotations/translations read back (unit quaternions, 9 decimals)
        assert all(np.isclose(np.linalg.norm(q), 1, atol=1e-8) for q in scene.poses.q)
        assert len(scene.scored_queries()) == 2


def test_same_seed_same_bytes_other_seed_other_scene(tmp_path):
    opts = SynthOptions(width=90, height=120, texture_size=64, queries=3)
    generate(tmp_path / "a", "val", 1, seed=7, options=opts, progress=False)
    generate(tmp_path / "b", "val", 2, seed=7, options=replace(opts, workers=2), progress=False)  # in parallel
    shutil.rmtree(tmp_path / "b/val/s00001")
    generate(tmp_path / "c", "val", 1, seed=8, options=opts, progress=False)
    a, b, c = (_tree_digest(tmp_path / x) for x in "abc")
    assert a == b and len(a) == 2 + 4 * 3  # 2 text files + 4 frames x (jpg, sensor, mono)
    assert a.keys() == c.keys() and a["val/s00000/seq1/frame_00000.jpg"] != c["val/s00000/seq1/frame_00000.jpg"]


def test_gt_depth_reprojects_between_frames_with_gt_poses(val_root, train_root):
    pairs = []
    for scene in Dataset(val_root).scenes("val"):
        for q in scene.queries:
            pairs.append((scene.reference, q))
    train = Dataset(train_root).scenes("train")[0]
    frames = list(train.frames.values())
    pairs += [(frames[i], frames[i + 1]) for i in range(0, len(frames) - 1, 3)]
    checked = 0
    for a, b in pairs:
        err = _reproject(a.depth(GT_DEPTH_SUFFIX), a.intrinsics, a.pose, b.depth(GT_DEPTH_SUFFIX), b.intrinsics, b.pose)
        if len(err) < 200:
            continue  # looking away: nothing in common
        checked += 1
        assert np.median(err) < 0.1 and err.max() < 0.5, (a.name, b.name, np.median(err), err.max())
    assert checked >= 8


def test_no_overlap_queries_share_nothing_with_the_reference(val_root):
    for scene in Dataset(val_root).scenes("val"):
        ref = scene.reference
        d_ref = ref.depth(GT_DEPTH_SUFFIX)
        ov = []
        for q in scene.queries:
            d_q = q.depth(GT_DEPTH_SUFFIX)
            ov.append(
                (
                    depth_overlap(d_ref, ref.intrinsics, ref.pose, d_q, q.intrinsics, q.pose),
                    depth_overlap(d_q, q.intrinsics, q.pose, d_ref, ref.intrinsics, ref.pose),
                )
            )
        ov = np.array(ov)
        assert np.sum(np.all(ov == 0, 1)) >= 3  # 30 % of 10 queries look away, and really see nothing
        assert np.sum(np.all(ov > 0.1, 1)) >= 4  # most others share a good part of the view


def test_train_overlaps_from_geometry(train_root):
    scene = Dataset(train_root).scenes("train")[0]
    assert {n.split("/")[0] for n in scene.frames} == {"seq0", "seq1"}
    ov = scene.overlaps
    assert ov.idxs.shape == (len(ov), 4) and len(ov) > 20
    assert np.all((ov.overlaps > 0) & (ov.overlaps <= 1))
    table = {tuple(r): o for r, o in zip(ov.idxs.tolist(), ov.overlaps)}
    assert all(np.isclose(table.get((c, d, a, b), -1), o, atol=1e-6) for (a, b, c, d), o in table.items())
    assert any(r[0] != r[2] for r in table) and any(r[0] == r[2] for r in table)  # across and within scans
    assert all(r[:2] != r[2:] for r in table)
    # The stored overlap agrees with a dense, symmetric reprojection of the ground-truth depth maps.
    frames = {(int(n[3]), int(n[-9:-4])): f for n, f in scene.frames.items()}

    def dense(fa, fb):
        return depth_overlap(
            fa.depth(GT_DEPTH_SUFFIX), fa.intrinsics, fa.pose, fb.depth(GT_DEPTH_SUFFIX), fb.intrinsics, fb.pose, step=2
        )

    agree = []
    for a, b, c, d in list(table)[:: max(1, len(table) // 40)]:
        fa, fb = frames[(a, b)], frames[(c, d)]
        agree.append((table[(a, b, c, d)], min(dense(fa, fb), dense(fb, fa))))
    assert np.corrcoef(np.array(agree).T)[0, 1] > 0.6
    # neighbours along a walk overlap more than frames far apart on it
    near = [o for (a, b, c, d), o in table.items() if a == c and abs(b - d) == 1]
    far = [table.get((s, i, s, j), 0.0) for s in (0, 1) for i in range(8) for j in range(8) if abs(i - j) >= 5]
    assert np.mean(near) > np.mean(far) + 0.1


def test_mono_depth_has_a_per_image_scale_bias(val_root):
    scales, spreads = [], []
    for scene in Dataset(val_root).scenes("val"):
        for f in [scene.reference, *scene.queries]:
            gt, est = f.depth(GT_DEPTH_SUFFIX), f.depth(EST_DEPTH_SUFFIX)
            lr = np.log(est[gt > 0] / gt[gt > 0])
            scales.append(np.median(lr))
            spreads.append(np.percentile(lr, 75) - np.percentile(lr, 25))
    scales = np.array(scales)
    assert 0.04 < np.std(scales) < 0.25  # each image has its own scale, ~10 % log-normal
    assert np.mean(np.abs(scales) > 0.02) > 0.6
    assert 0.005 < np.median(spreads) < 0.2  # plus smooth distortion and noise, smaller than the bias


def test_test_split_hides_poses_and_writes_private_ground_truth(tmp_path):
    opts = SynthOptions(width=90, height=120, texture_size=64, first_scene=525)
    dirs = generate(
        tmp_path / "data", "test", 1, 4, seed=1, private_gt_dir=tmp_path / "gt", options=opts, progress=False
    )
    assert dirs == [tmp_path / "data/test/s00525"]
    public = read_poses(dirs[0] / "poses.txt")
    assert len(public) == 5 and np.all(public.q == 0) and np.all(public.t == 0)
    private = Dataset(tmp_path / "gt").scene("test", "s00525")
    assert private.poses.names == public.names
    assert private.poses.pose(0).qt()[0].tolist() == [1, 0, 0, 0]
    assert read_intrinsics(dirs[0] / "intrinsics.txt") == private.intrinsics
    moved = [np.linalg.norm(private.poses.pose(i).center) for i in range(1, 5)]
    assert max(moved) > 0.1


def test_reference_and_close_query_match_with_sift_consistently_with_gt(tmp_path):
    """Full-size images: SIFT (ratio test 0.8) finds hundreds of matches, most of them true under the GT pose."""
    (scene_dir,) = generate(tmp_path, "val", 1, 6, seed=0, options=SynthOptions(no_overlap_fraction=0), progress=False)
    scene = Dataset(tmp_path).scene("val", scene_dir.name)
    ref = scene.reference
    d_ref = ref.depth(GT_DEPTH_SUFFIX)
    best = max(
        scene.queries,
        key=lambda q: depth_overlap(
            d_ref, ref.intrinsics, ref.pose, q.depth(GT_DEPTH_SUFFIX), q.intrinsics, q.pose, step=4
        ),
    )
    assert rotation_angle_deg(np.eye(3), best.pose.R) > 1 or np.linalg.norm(best.pose.center) > 0.1
    sift = cv2.SIFT_create(2048)
    k0, d0 = sift.detectAndCompute(cv2.cvtColor(ref.image(), cv2.COLOR_RGB2GRAY), None)
    k1, d1 = sift.detectAndCompute(cv2.cvtColor(best.image(), cv2.COLOR_RGB2GRAY), None)
    good = [m for m, n in cv2.BFMatcher().knnMatch(d0, d1, k=2) if m.distance < 0.8 * n.distance]
    p0 = np.array([k0[m.queryIdx].pt for m in good])
    p1 = np.array([k1[m.trainIdx].pt for m in good])
    z = d_ref[np.rint(p0[:, 1]).astype(int), np.rint(p0[:, 0]).astype(int)]
    uv = project(best.pose.transform(backproject(p0, z, ref.intrinsics.K)), best.intrinsics.K)
    true = (z > 0) & (np.linalg.norm(uv - p1, axis=1) < 4)
    assert len(good) >= 200 and true.mean() > 0.6, (len(good), true.mean())


def test_cli_writes_a_split_and_rejects_bad_options(tmp_path, capsys):
    assert (
        cli_main(
            [
                "synth",
                str(tmp_path),
                "--scenes",
                "1",
                "--queries",
                "2",
                "--size",
                "90x120",
                "--quiet",
                "--first-scene",
                "3",
                "--no-mono",
            ]
        )
        == 0
    )
    scene = Dataset(tmp_path).scene("val", "s00003")
    assert len(scene.queries) == 2 and not scene.reference.has_depth(EST_DEPTH_SUFFIX)
    assert scene.reference.has_depth(GT_DEPTH_SUFFIX)
    assert "wrote 1 val scene" in capsys.readouterr().out
    assert cli_main(["synth", str(tmp_path), "--size", "big"]) == 1
    assert cli_main(["synth", str(tmp_path), "--split", "val", "--private-gt", str(tmp_path / "gt")]) == 1
    assert "--private-gt" in capsys.readouterr().err
