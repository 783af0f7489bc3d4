"""Raw phone scans of synthetic places: the input of ``mapfree build`` (``mapfree synth ROOT --split scans``).

A place is two (or more) walks round one synthetic object. Each scan folder holds what a phone app exports:

    ROOT/scans/sNNNNN/scanK/frame_00000.jpg ...     images sampled from the walk
    ROOT/scans/sNNNNN/scanK/intrinsics.txt          "frame_00000.jpg fx fy cx cy width height"
    ROOT/scans/sNNNNN/scanK/rgb.txt                 "timestamp frame_00000.jpg" (TUM RGB-D style)
    ROOT/scans/sNNNNN/scanK/device_poses.txt        TUM "t tx ty tz qx qy qz qw", camera-to-world, 3x the frame rate
    ROOT/scans/sNNNNN/scanK/frame_00000.sensor.png  metric depth (optional input of the build)

The device track drifts like visual-inertial odometry (``data.device.DriftModel``: a scale error of about 2 %,
heading drift and a position random walk growing with the distance walked), in its own gravity-aligned frame
(random heading and origin). With
``private_gt_dir`` the true world-to-camera poses (``scanK/poses.txt``, our format) and the overlaps computed
from the synthetic geometry (``overlaps.npz``, seq = scan index) go to ``private_gt_dir/scans/sNNNNN/``.
The overlaps follow the same definition as synth's train/val/test scenes (``overlap.py``): surface points
spread evenly over every frame, counted where they are visible (exact surface id, so occlusion is exact);
shared / max(points visible in either frame), within and across scans.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ...geometry import Pose
from ..device import DriftModel, simulate_device_trajectory
from ..io import write_intrinsics, write_poses
from ..overlaps import Overlaps, write_overlaps
from .cameras import jitter_intrinsics, walk
from .generate import SynthOptions, _FrameWriter
from .overlap import overlap_matrix, overlap_pairs, sample_frame_points, visible_points
from .render import random_lighting, rasterize
from .textures import load_atlas
from .world import UP, make_world

__all__ = ["ScanOptions", "device_track", "write_tum", "generate_scans", "generate_place"]

_SCANS_STREAM = 3  # seed-sequence key of the scans split (train/val/test use 0/1/2)


@dataclass(frozen=True)
class ScanOptions:
    """Shape of the scans split; ``synth`` holds image size, focal, noise, textures."""

    frames: int = 12  # images per scan
    scans: int = 2  # scans per place
    device_rate: int = 3  # device poses per image (the app tracks faster than it saves frames)
    frame_interval: float = 0.5  # seconds between saved images
    drift: DriftModel = DriftModel()
    synth: SynthOptions = SynthOptions(write_mono=False)


def device_track(rng: np.random.Generator, poses: list[Pose], drift: DriftModel = DriftModel()) -> list[Pose]:
    """Camera-to-world device poses for true world-to-camera ``poses``: drifting (data.device's VIO model) and
    expressed in the device's own frame, gravity-aligned with an arbitrary heading and origin."""
    tracked = simulate_device_trajectory(poses, UP, rng, drift)
    frame = Rotation.from_euler("z", rng.uniform(0, 2 * np.pi)).as_matrix()
    origin = rng.normal(0, 3, 3)
    return [Pose(frame @ p.R.T, frame @ p.center + origin) for p in tracked]  # R = rotation, t = centre


def write_tum(path: os.PathLike | str, times: np.ndarray, cam_to_world: list[Pose]) -> None:
    """TUM trajectory ``t tx ty tz qx qy qz qw`` (camera-to-world, quaternion x y z w)."""
    lines = []
    for t, p in zip(times, cam_to_world):
        q = Rotation.from_matrix(p.R).as_quat()  # x y z w
        lines.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*p.t, *q)) + "\n")
    Path(path).write_text("".join(lines))


def _rng(seed: int, number: int) -> list[np.random.Generator]:
    ss = np.random.SeedSequence([int(seed), _SCANS_STREAM, int(number)])
    return [np.random.default_rng(s) for s in ss.spawn(7)]


def generate_place(
    root: os.PathLike | str,
    number: int,
    seed: int = 0,
    options: ScanOptions | None = None,
    private_gt_dir: os.PathLike | str | None = None,
) -> Path:
    """Write the raw scans of one place ``root/scans/s{number:05d}`` and return its folder."""
    o = options or ScanOptions()
    s = o.synth
    out = Path(root) / "scans" / f"s{number:05d}"
    shutil.rmtree(out, ignore_errors=True)
    world_rng, cam, lit, noise, drng, dev, pts_rng = _rng(seed, number)
    world = make_world(world_rng, load_atlas(s.texture_size))
    writer = _FrameWriter(world, s, noise, drng)
    n_dense = (o.frames - 1) * o.device_rate + 1
    theta0 = cam.uniform(0, 2 * np.pi)
    gt_names: list[list[str]] = []
    gt_poses: list[list[Pose]] = []
    seqs, nums, frames, sampled = [], [], [], []
    scans = []
    for k in range(o.scans):
        start = theta0 + (0 if k == 0 else cam.uniform(-1.0, 1.0))
        sweep = cam.choice([-1, 1]) * cam.uniform(np.pi / 3, 2 * np.pi / 3)
        dense = walk(cam, world, n_dense, start, sweep, (1.5, 6.0))
        Ks = jitter_intrinsics(cam, s.width, s.height, s.focal_px, o.frames)
        scans.append((dense, dense[:: o.device_rate], Ks, random_lighting(lit, s.lighting_change)))
    for k, (dense, poses, Ks, light) in enumerate(scans):
        folder = out / f"scan{k}"
        names = [f"frame_{i:05d}.jpg" for i in range(o.frames)]
        t0 = float(dev.uniform(1e3, 1e5))
        times = t0 + np.arange(n_dense) * o.frame_interval / o.device_rate
        for i, (name, pose, K) in enumerate(zip(names, poses, Ks)):
            qid, depth = rasterize(world, pose, K)
            writer.write(folder / name, pose, K, light, qid, depth)
            sampled.append(sample_frame_points(world, pose, K, s.points_per_frame, pts_rng))
            frames.append((pose, K, qid.astype(np.int16)))
            seqs.append(k)
            nums.append(i)
        write_intrinsics(folder / "intrinsics.txt", dict(zip(names, Ks)))
        (folder / "rgb.txt").write_text(
            "# timestamp filename\n" + "".join(f"{times[i * o.device_rate]:.6f} {n}\n" for i, n in enumerate(names))
        )
        write_tum(folder / "device_poses.txt", times, device_track(dev, dense, o.drift))
        gt_names.append(names)
        gt_poses.append(poses)
    points = np.concatenate([p for p, _ in sampled])
    point_quad = np.concatenate([q for _, q in sampled])
    vis = [visible_points(points, point_quad, pose, K, qid) for pose, K, qid in frames]
    if private_gt_dir is not None:
        gt = Path(private_gt_dir) / "scans" / out.name
        shutil.rmtree(gt, ignore_errors=True)
        for k in range(o.scans):
            (gt / f"scan{k}").mkdir(parents=True, exist_ok=True)
            write_poses(gt / f"scan{k}" / "poses.txt", gt_names[k], gt_poses[k])
        idxs, ov = overlap_pairs(overlap_matrix(np.stack(vis)), np.array(seqs), np.array(nums))
        write_overlaps(gt / "overlaps.npz", Overlaps(idxs, ov))
    return out


def _one(args: tuple) -> Path:
    return generate_place(*args)


def generate_scans(
    root: os.PathLike | str,
    n_places: int = 2,
    seed: int = 0,
    options: ScanOptions | None = None,
    private_gt_dir: os.PathLike | str | None = None,
    first_place: int = 0,
    progress: bool = True,
) -> list[Path]:
    """Write ``n_places`` places of raw scans under ``root/scans``; returns their folders."""
    o = options or ScanOptions()
    if n_places < 0 or o.frames < 3 or o.scans < 1 or o.device_rate < 1:
        raise ValueError("n_places must be >= 0, frames per scan >= 3, scans >= 1, device_rate >= 1")
    if o.synth.write_mono:
        o = replace(o, synth=replace(o.synth, write_mono=False))  # raw scans carry sensor depth only
    from tqdm.auto import tqdm

    return [
        _one((root, first_place + k, seed, o, private_gt_dir))
        for k in tqdm(range(n_places), desc="synth scans", unit="place", disable=not progress)
    ]
