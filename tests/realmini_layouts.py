"""Tiny folders in other datasets' native layouts, built from real realmini-dev images, depth and poses.

Used by test_retrieval.py, test_sevenscenes.py and test_scannet.py. Every function copies real files
(images re-encoded where the layout needs PNG) and writes poses in that layout's own convention.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np

from mapfree.data import Dataset, write_intrinsics, write_poses
from mapfree.geometry import Pose


def realmini_frames(root: Path, scene: str = "s00000"):
    """(reference, queries) Frames of a realmini-dev val scene (poses in the reference camera's frame)."""
    sc = Dataset(root).scene("val", scene)
    return sc.reference, sc.queries


def mapfree_multi_reference_scene(root: Path, out: Path, every: int = 4) -> Path:
    """A val scene whose mapping scan ``seq0`` holds the reference plus every ``every``-th query of s00000
    (posed, world = reference camera); the other queries (offset by every/2) stay in ``seq1``."""
    ref, queries = realmini_frames(root)
    scene = out / "val" / "s00000"
    (scene / "seq0").mkdir(parents=True)
    (scene / "seq1").mkdir()
    mapping = [ref] + queries[0::every]
    tests = queries[every // 2 :: every]
    names, poses, K = [], [], {}
    for seq, frames in (("seq0", mapping), ("seq1", tests)):
        for i, f in enumerate(frames):
            name = f"{seq}/frame_{i:05d}.jpg"
            shutil.copy(f.image_path, scene / name)
            shutil.copy(f.depth_path("sensor"), scene / name.replace(".jpg", ".sensor.png"))
            names.append(name)
            poses.append(f.pose)
            K[name] = f.intrinsics
    write_intrinsics(scene / "intrinsics.txt", K)
    write_poses(scene / "poses.txt", names, poses)
    return out


def seven_scenes(root: Path, out: Path, scenes: dict[str, str] | None = None, train_every: int = 3) -> Path:
    """7-Scenes layout: ``SCENE/seq-01`` (mapping: every ``train_every``-th frame of a realmini scene) and
    ``SCENE/seq-02`` (the others); ``frame-NNNNNN.color.png``, ``.depth.png`` (uint16 mm, 65535 = invalid),
    ``.pose.txt`` (4x4 camera-to-world); ``TrainSplit.txt`` / ``TestSplit.txt``."""
    scenes = scenes or {"office": "s00000"}
    for name, src in scenes.items():
        ref, queries = realmini_frames(root, src)
        frames = [ref] + queries
        d = out / name
        for seq in ("seq-01", "seq-02"):
            (d / seq).mkdir(parents=True)
        counters = {"seq-01": 0, "seq-02": 0}
        for i, f in enumerate(frames):
            seq = "seq-01" if i % train_every == 0 else "seq-02"
            stem = d / seq / f"frame-{counters[seq]:06d}"
            counters[seq] += 1
            cv2.imwrite(f"{stem}.color.png", cv2.imread(str(f.image_path)))
            depth = cv2.imread(str(f.depth_path("sensor")), cv2.IMREAD_ANYDEPTH)
            depth[depth == 0] = 65535  # the Kinect's "no measurement"
            cv2.imwrite(f"{stem}.depth.png", depth)
            np.savetxt(f"{stem}.pose.txt", f.pose.inverse().matrix, fmt="%.9f")
        (d / "TrainSplit.txt").write_text("sequence1\n")
        (d / "TestSplit.txt").write_text("sequence2\n")
    return out


def scannet_pairs(root: Path, out: Path, pairs: list[tuple[int, int]], scene: str = "scene0000_00") -> Path:
    """ScanNet layout (``SCENE/color/frame-NNNNNN.jpg``, ``SCENE/depth/frame-NNNNNN.png``) and a pair list in the
    SuperGlue format (``img0 img1 exif0 exif1 K0(9) K1(9) T_0to1(16)``) for ``pairs`` of realmini s00000 queries."""
    _, queries = realmini_frames(root)
    (out / scene / "color").mkdir(parents=True)
    (out / scene / "depth").mkdir(parents=True)
    lines = []
    for i, j in pairs:
        rel = []
        for k in (i, j):
            f = queries[k]
            shutil.copy(f.image_path, out / scene / "color" / f"frame-{k:06d}.jpg")
            shutil.copy(f.depth_path("sensor"), out / scene / "depth" / f"frame-{k:06d}.png")
            rel.append(f"{scene}/color/frame-{k:06d}.jpg")
        T = (queries[j].pose @ queries[i].pose.inverse()).matrix
        Ks = [" ".join(f"{v:.6f}" for v in queries[k].intrinsics.K.ravel()) for k in (i, j)]
        lines.append(" ".join([*rel, "0", "0", *Ks, " ".join(f"{v:.9f}" for v in T.ravel())]))
    (out / "pairs.txt").write_text("\n".join(lines) + "\n")
    return out / "pairs.txt"


__all__ = ["realmini_frames", "mapfree_multi_reference_scene", "seven_scenes", "scannet_pairs", "Pose"]
