"""Write synthetic scenes in the exact Map-free layout: train scans with overlaps, val/test pairs.

Every scene is drawn from its own seed (``seed``, split, scene number), with separate streams for the world,
the cameras, the lighting and the noise, so the same seed always writes byte-identical files.
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ...geometry import Intrinsics, Pose
from ..device import (
    DEVICE_FILE,
    DriftModel,
    multiframe_bursts,
    rebase_bursts,
    simulate_device_trajectory,
    write_device_poses,
)
from ..io import depth_path_for, write_depth, write_image, write_intrinsics, write_poses
from ..overlaps import Overlaps, write_overlaps
from ..scene import SPLITS
from .cameras import jitter_intrinsics, look_along, look_at, orbit_point, walk
from .depth import MonoDepthModel, simulate_mono_depth
from .overlap import depth_overlap, overlap_matrix, overlap_pairs, sample_frame_points, visible_points
from .render import Lighting, ShadowMap, random_lighting, rasterize, shade
from .textures import load_atlas
from .world import World, make_world

__all__ = ["GT_DEPTH_SUFFIX", "EST_DEPTH_SUFFIX", "SynthOptions", "generate", "generate_scene"]

GT_DEPTH_SUFFIX = "sensor"  # metric ground truth, like the sample data's sensor depth
EST_DEPTH_SUFFIX = "mono"  # simulated monocular estimate (scale bias, distortion, noise)


@dataclass(frozen=True)
class SynthOptions:
    """Everything that shapes a synthetic split; defaults mimic the Map-free dataset."""

    queries: int = 40  # val/test queries per scene
    train_frames: int = 50  # frames per train scan (two scans per scene)
    width: int = 540
    height: int = 720
    focal: float | None = None  # pixels; default 600 at 540 px wide, scaled with the width
    no_overlap_fraction: float = 0.2  # val/test queries looking away from everything the reference sees
    first_scene: int = 0  # scene ids start at s{first_scene:05d}
    jpeg_quality: int = 92
    pixel_noise: float = 1.5  # sensor noise std (8-bit levels)
    lighting_change: float = 1.0  # how far each scan's light strays from neutral
    max_depth: float = 40.0  # ground-truth depth beyond this is written as 0 (invalid)
    points_per_frame: int = 300  # "SfM" points each train frame contributes to the set behind overlaps.npz
    ref_distance: tuple[float, float] = (1.5, 5.0)  # reference camera distance from the object's side (m)
    mono: MonoDepthModel = field(default_factory=MonoDepthModel)
    drift: DriftModel = field(default_factory=DriftModel)  # device tracking of val/test queries (poses_device.txt)
    write_mono: bool = True
    texture_size: int = 512
    workers: int = 1  # scenes rendered in parallel processes (output is identical for any value)

    @property
    def focal_px(self) -> float:
        return self.focal if self.focal is not None else 600.0 * self.width / 540.0


@dataclass
class _Scan:
    """One sequence of frames to render under one lighting."""

    seq: int
    poses: list[Pose]
    intrinsics: list[Intrinsics]
    light: Lighting


def _streams(seed: int, split: str, number: int) -> list[np.random.Generator]:
    """Independent generators for world, cameras, lighting, noise, depth and device tracking of one scene.

    ``spawn`` children depend only on their index, so adding a stream leaves the others' draws unchanged."""
    ss = np.random.SeedSequence([int(seed), SPLITS.index(split), int(number)])
    return [np.random.default_rng(s) for s in ss.spawn(6)]


class _FrameWriter:
    """Shades and writes the frames of one scene: JPEG, ground-truth depth and the simulated estimate."""

    def __init__(
        self, world: World, opts: SynthOptions, noise_rng: np.random.Generator, depth_rng: np.random.Generator
    ):
        self.world, self.opts = world, opts
        self.atlas = load_atlas(opts.texture_size)
        H, W = opts.height, opts.width
        # One bank of sensor noise per scene; each frame takes a random window of it (cheaper than fresh noise).
        self.noise_bank = noise_rng.standard_normal((H + 64, W + 64), dtype=np.float32) * np.float32(opts.pixel_noise)
        self.noise_rng, self.depth_rng = noise_rng, depth_rng
        self.shadows: list[tuple[Lighting, ShadowMap]] = []

    def _shadow(self, light: Lighting) -> ShadowMap:
        for known, shadow in self.shadows:
            if known is light:
                return shadow
        self.shadows.append((light, ShadowMap.build(self.world, self.atlas, light)))
        return self.shadows[-1][1]

    def write(self, path: Path, pose: Pose, K: Intrinsics, light: Lighting, qid: np.ndarray, depth: np.ndarray) -> None:
        opts = self.opts
        oy, ox = self.noise_rng.integers(0, 64, 2)
        noise = self.noise_bank[oy : oy + opts.height, ox : ox + opts.width]
        exposure = float(np.exp(self.noise_rng.normal(0, 0.04)))
        img = shade(self.world, self.atlas, pose, K, qid, depth, light, noise, exposure, self._shadow(light))
        path.parent.mkdir(parents=True, exist_ok=True)
        write_image(path, np.ascontiguousarray(img[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, opts.jpeg_quality])
        gt = np.where(depth <= opts.max_depth, depth, 0.0)
        write_depth(depth_path_for(path, GT_DEPTH_SUFFIX), gt)
        if opts.write_mono:
            est, _ = simulate_mono_depth(gt, self.depth_rng, opts.mono)
            write_depth(depth_path_for(path, EST_DEPTH_SUFFIX), est)


def _name(seq: int, i: int) -> str:
    return f"seq{seq}/frame_{i:05d}.jpg"


def _train_scene(out: Path, world: World, opts: SynthOptions, rngs: list[np.random.Generator]) -> None:
    _, cam, lit, noise, drng, _ = rngs
    n = opts.train_frames
    theta0 = cam.uniform(0, 2 * np.pi)
    scans = []
    for seq in (0, 1):
        start = theta0 + (0 if seq == 0 else cam.uniform(-1.5, 1.5))
        sweep = cam.choice([-1, 1]) * cam.uniform(np.pi / 2, np.pi)
        poses = walk(cam, world, n, start, sweep, (1.0, 10.0))
        Ks = jitter_intrinsics(cam, opts.width, opts.height, opts.focal_px, n)
        scans.append(_Scan(seq, poses, Ks, random_lighting(lit, opts.lighting_change)))
    sampled = [
        sample_frame_points(world, p, K, opts.points_per_frame, rngs[0])
        for scan in scans
        for p, K in zip(scan.poses, scan.intrinsics)
    ]
    points = np.concatenate([p for p, _ in sampled])
    point_quad = np.concatenate([q for _, q in sampled])
    writer = _FrameWriter(world, opts, noise, drng)
    names, poses, intr, vis, seqs, nums = [], [], {}, [], [], []
    for scan in scans:
        for i, (pose, K) in enumerate(zip(scan.poses, scan.intrinsics)):
            name = _name(scan.seq, i)
            qid, depth = rasterize(world, pose, K)
            writer.write(out / name, pose, K, scan.light, qid, depth)
            vis.append(visible_points(points, point_quad, pose, K, qid))
            names.append(name)
            poses.append(pose)
            seqs.append(scan.seq)
            nums.append(i)
            intr[name] = K
    write_intrinsics(out / "intrinsics.txt", intr)
    write_poses(out / "poses.txt", names, poses)
    idxs, ov = overlap_pairs(overlap_matrix(np.stack(vis)), np.array(seqs), np.array(nums))
    write_overlaps(out / "overlaps.npz", Overlaps(idxs, ov))


def _look_away(cam: np.random.Generator, world: World, center: np.ndarray, ref: Pose, attempt: int) -> Pose:
    """A view from ``center`` turned away from the object and from what the reference sees."""
    away = center - world.target
    away[2] = 0
    back = -ref.R[2].copy()  # opposite to the reference's viewing direction
    back[2] = 0
    d = away / np.linalg.norm(away) + back / np.linalg.norm(back)
    yaw = np.arctan2(d[1], d[0]) + cam.uniform(-0.6, 0.6) / (1 + attempt)
    pitch = np.radians(cam.uniform(-12, 8) + 6 * attempt)
    fwd = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
    return look_along(center, fwd, cam.normal(0, 2))


def _pair_scene(
    out: Path,
    world: World,
    opts: SynthOptions,
    rngs: list[np.random.Generator],
    n_queries: int,
    hide_poses: bool,
    private_dir: Path | None,
) -> None:
    _, cam, lit, noise, drng, device_rng = rngs
    o = world.object_radius
    # The reference photographs the place of interest: a mural from its painted side, a sculpture from anywhere.
    theta = cam.uniform(0, 2 * np.pi)
    if world.facing:
        theta = world.facing[int(cam.integers(len(world.facing)))] + cam.uniform(-0.7, 0.7)
    radius = o + cam.uniform(*opts.ref_distance)
    aim = world.target + cam.normal(0, 0.25, 3) * [1, 1, 0.5]
    ref = look_at(orbit_point(world, theta, radius, cam.uniform(1.35, 1.75)), aim, cam.normal(0, 2))
    K_ref = jitter_intrinsics(cam, opts.width, opts.height, opts.focal_px, 1)[0]
    queries = walk(cam, world, n_queries, theta + cam.uniform(-0.4, 0.4), cam.uniform(-1.2, 1.2), (1.0, o + 7.0))
    K_q = jitter_intrinsics(cam, opts.width, opts.height, opts.focal_px, n_queries)
    n_away = int(round(opts.no_overlap_fraction * n_queries))
    start = int(cam.integers(0, n_queries - n_away + 1)) if n_away else 0
    ref_light, query_light = random_lighting(lit, opts.lighting_change), random_lighting(lit, opts.lighting_change)

    writer = _FrameWriter(world, opts, noise, drng)
    ref_qid, ref_depth = rasterize(world, ref, K_ref)
    writer.write(out / _name(0, 0), ref, K_ref, ref_light, ref_qid, ref_depth)
    names, poses, intr = [_name(0, 0)], [ref], {_name(0, 0): K_ref}
    for i, (pose, K) in enumerate(zip(queries, K_q)):
        qid, depth = rasterize(world, pose, K)
        if start <= i < start + n_away:  # turn away until it shares nothing with the reference, both ways
            for attempt in range(8):
                cand = _look_away(cam, world, pose.center, ref, attempt)
                cq, cd = rasterize(world, cand, K)
                if all(
                    depth_overlap(ref_depth, K_ref, ref, cd, K, cand, step=s) == 0
                    and depth_overlap(cd, K, cand, ref_depth, K_ref, ref, step=s) == 0
                    for s in (4, 1)
                ):
                    pose, qid, depth = cand, cq, cd
                    break
        name = _name(1, i)
        writer.write(out / name, pose, K, query_light, qid, depth)
        names.append(name)
        poses.append(pose)
        intr[name] = K

    # The world frame becomes the reference camera: it gets the identity, queries their pose relative to it.
    rel = [p.relative_to(ref) for p in poses]
    rel[0] = Pose.identity()
    write_intrinsics(out / "intrinsics.txt", intr)
    write_poses(out / "poses.txt", names, [None] * len(names) if hide_poses else rel)
    # The phone's own tracking of the query scan (public in test too): drifting, re-based per burst;
    # no file when the scene has too few queries for a multi-frame burst.
    device = simulate_device_trajectory(poses[1:], np.array([0.0, 0.0, 1.0]), device_rng, opts.drift)
    bursts = multiframe_bursts(names)
    if bursts:
        write_device_poses(out / DEVICE_FILE, rebase_bursts(dict(zip(names[1:], device)), bursts))
    if private_dir is not None:
        private_dir.mkdir(parents=True, exist_ok=True)
        write_intrinsics(private_dir / "intrinsics.txt", intr)
        write_poses(private_dir / "poses.txt", names, rel)


def generate_scene(
    root: os.PathLike | str,
    split: str,
    number: int,
    seed: int = 0,
    n_queries: int | None = None,
    private_gt_dir: os.PathLike | str | None = None,
    options: SynthOptions | None = None,
) -> Path:
    """Write one scene ``root/split/s{number:05d}`` and return its folder."""
    opts = options or SynthOptions()
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r} (expected one of {', '.join(SPLITS)})")
    out = Path(root) / split / f"s{number:05d}"
    for old in ("seq0", "seq1"):  # regenerating replaces the scene: no stale frames from an earlier run
        shutil.rmtree(out / old, ignore_errors=True)
    for old in ("intrinsics.txt", "poses.txt", "overlaps.npz", "poses_device.txt"):
        (out / old).unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    rngs = _streams(seed, split, number)
    world = make_world(rngs[0], load_atlas(opts.texture_size))
    if split == "train":
        _train_scene(out, world, opts, rngs)
    else:
        private = None
        if split == "test" and private_gt_dir is not None:
            private = Path(private_gt_dir) / "test" / out.name
        _pair_scene(out, world, opts, rngs, n_queries or opts.queries, split == "test", private)
    return out


def _one(args: tuple) -> Path:
    return generate_scene(*args)


def _single_threaded() -> None:
    """Worker processes already use every core: keep OpenCV from adding threads of its own."""
    cv2.setNumThreads(1)


def generate(
    root: os.PathLike | str,
    split: str = "val",
    n_scenes: int = 10,
    n_queries: int | None = None,
    seed: int = 0,
    private_gt_dir: os.PathLike | str | None = None,
    options: SynthOptions | None = None,
    progress: bool = True,
) -> list[Path]:
    """Write ``n_scenes`` synthetic scenes of ``split`` under ``root`` (Map-free layout); returns their folders.

    ``n_queries`` (default ``options.queries``) is the number of val/test queries per scene. For the test
    split, ``poses.txt`` holds all-zero lines and, when ``private_gt_dir`` is given, the true poses and
    intrinsics go to ``private_gt_dir/test/sNNNNN/`` (a ground-truth root for the evaluator).
    """
    opts = options or SynthOptions()
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r} (expected one of {', '.join(SPLITS)})")
    if n_scenes < 0 or (n_queries is not None and n_queries < 1) or opts.queries < 1 or opts.train_frames < 1:
        raise ValueError("n_scenes must be >= 0 and queries / train frames >= 1")
    if opts.width < 16 or opts.height < 16 or not 0 <= opts.no_overlap_fraction < 1:
        raise ValueError("images must be at least 16x16 pixels and 0 <= no_overlap_fraction < 1")
    jobs = [(root, split, opts.first_scene + k, seed, n_queries, private_gt_dir, opts) for k in range(n_scenes)]
    from tqdm.auto import tqdm

    bar = tqdm(total=len(jobs), desc=f"synth {split}", unit="scene", disable=not progress)
    out: list[Path] = []
    try:
        if opts.workers > 1 and len(jobs) > 1:
            # "spawn": forking a process whose OpenCV thread pool has run can deadlock the children.
            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=opts.workers, mp_context=ctx, initializer=_single_threaded) as pool:
                for path in pool.map(_one, jobs):
                    out.append(path)
                    bar.update()
        else:
            for job in jobs:
                out.append(_one(job))
                bar.update()
    finally:
        bar.close()
    return out
