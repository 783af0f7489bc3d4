"""Build one Map-free scene from one place of raw scans: SfM, metric scale, layout, overlaps, report.

Everything is written into a staging folder and moved into ``ROOT/SPLIT/sNNNNN`` only when the place
succeeded, so a scene folder is always complete and its ``build_report.json`` marks it as done (resumable).
A place that fails leaves its report under ``ROOT/SPLIT/.build/sNNNNN/`` with the reason.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..data.device import DEVICE_FILE, multiframe_bursts, rebase_bursts, write_device_poses
from ..data.io import (
    FormatError,
    depth_path_for,
    read_depth,
    read_image,
    write_depth,
    write_image,
    write_intrinsics,
    write_poses,
)
from ..data.overlaps import Overlaps, write_overlaps
from ..data.scene import REFERENCE_NAME, frame_number
from ..geometry import Intrinsics, Pose
from .correspondences import CorrespondenceOptions, depth_correspondences, write_correspondences
from .inputs import Place, read_place
from .overlaps import depth_overlaps, sfm_overlaps
from .scale import ScaleFit, scale_from_depth, scale_from_device
from .sfm import SfmModel, SfmOptions, reconstruct

__all__ = ["BuildOptions", "BuildError", "PlaceResult", "build_place", "REPORT_FILE", "SFM_DEPTH_SUFFIX"]

log = logging.getLogger(__name__)

REPORT_FILE = "build_report.json"
SFM_DEPTH_SUFFIX = "sfm"


class BuildError(RuntimeError):
    """A place that cannot become a scene (the message says why); other places go on."""


@dataclass(frozen=True)
class BuildOptions:
    """How ``build_place`` turns scans into a scene (``mapfree build`` options).

    Attributes:
        split: Split the scene is written for: ``train`` (every scan a sequence), or ``val``/``test`` (the
            reference and the queries of scan 1; ``test`` hides the poses).
        fps: Frames per second sampled from a video, Hz.
        device_axes: Camera axes of the device poses: ``opencv``, or ``opengl`` for ARKit/ARCore exports.
        min_registered: Fraction of each scan's images SfM must register.
        allow_unscaled: Without device poses or depth, keep SfM units instead of failing.
        sfm_depth: Write sparse SfM depth maps ``frame_NNNNN.sfm.png``.
        correspondences: Write ``correspondences.npz`` (training correspondences from depth).
        corr: Settings of the correspondences.
        sfm: Settings of the reconstruction.
        keep_work: Keep the COLMAP database and model.
        overlap_points: Points the overlaps are computed from: ``depth`` (every frame has metric depth),
            ``sfm`` (SfM tracks), or ``auto`` (depth when it can).
        report_plot: Draw ``build_report.png``.
    """

    split: str = "train"
    fps: float = 2.0  # video sampling rate
    device_axes: str = "opencv"  # camera axes of the device poses ("opengl" for ARKit/ARCore exports)
    min_registered: float = 0.5  # fraction of each scan's images SfM must register
    allow_unscaled: bool = False  # no device poses and no depth: keep SfM units instead of failing
    sfm_depth: bool = False  # write sparse depth frame_NNNNN.sfm.png
    correspondences: bool = False
    corr: CorrespondenceOptions = CorrespondenceOptions()
    sfm: SfmOptions = SfmOptions()
    keep_work: bool = False  # keep the COLMAP database and model
    overlap_points: str = "auto"  # "depth" (every frame has metric depth), "sfm" (SfM tracks); auto: depth if it can
    report_plot: bool = True


@dataclass
class PlaceResult:
    """What became of one place.

    Attributes:
        place: Place folder name.
        scene: Scene folder name.
        status: ``ok``, ``failed`` or ``skipped`` (already built).
        reason: Why it failed or was skipped.
        seconds: Wall time of the build.
        report: The build report (``build_report.json``): registration, scale, overlaps, timings.
    """

    place: str
    scene: str
    status: str  # "ok" | "failed" | "skipped" (already built)
    reason: str = ""
    seconds: float = 0.0
    report: dict = field(default_factory=dict)


def _stage(
    place: Place, images: Path
) -> tuple[dict[str, Path], dict[str, Intrinsics | None], dict[str, Pose | None], dict[str, int]]:
    """Link every frame as ``seqK/frame_NNNNN.jpg`` (PNG inputs re-encoded); returns sources, intrinsics, device."""
    src, intr, dev, seq_of = {}, {}, {}, {}
    for k, scan in enumerate(place.scans):
        (images / f"seq{k}").mkdir(parents=True, exist_ok=True)
        for i, f in enumerate(scan.frames):
            name = f"seq{k}/frame_{i:05d}.jpg"
            dst = images / name
            if f.path.suffix.lower() in (".jpg", ".jpeg"):
                os.symlink(f.path.resolve(), dst)
            else:
                img = cv2.cvtColor(read_image(f.path), cv2.COLOR_RGB2BGR)  # upright, like every reader of ours
                write_image(dst, img, [cv2.IMWRITE_JPEG_QUALITY, 95])
            src[name], intr[name], dev[name], seq_of[name] = f.path, f.intrinsics, f.device, k
    return src, intr, dev, seq_of


def _depth_suffixes(path: Path) -> list[str]:
    stem = path.stem
    return sorted(p.name[len(stem) + 1 : -4] for p in path.parent.glob(f"{stem}.*.png"))


def _check_registration(
    place: Place, model: SfmModel | None, seq_of: dict[str, int], min_fraction: float, dropped_by_device: int = 0
) -> dict:
    total = {s.name: len(s.frames) for s in place.scans}
    reg = {s.name: 0 for s in place.scans}
    for n in model.poses if model else {}:
        reg[place.scans[seq_of[n]].name] += 1
    stats = {s: {"images": total[s], "registered": reg[s]} for s in total}
    if model is None or not model.poses:
        raise BuildError("SfM reconstructed nothing (too few matches: blurred, textureless or tiny images?)")
    for s in place.scans:
        if reg[s.name] == 0 and model.models > 1:
            raise BuildError(
                f"scans do not overlap: {s.name} was not registered with the others "
                f"(SfM made {model.models} separate models)"
            )
        if reg[s.name] < max(2, min_fraction * total[s.name]):
            dropped = f", {dropped_by_device} inconsistent with the device track" if dropped_by_device else ""
            raise BuildError(
                f"too few images registered in {s.name}: {reg[s.name]}/{total[s.name]} "
                f"(need {min_fraction:.0%}{dropped})"
            )
    return stats


def _metric_scale(
    place: Place,
    model: SfmModel,
    seq_of: dict[str, int],
    device: dict[str, Pose | None],
    images: Path,
    allow_unscaled: bool,
) -> ScaleFit:
    sfm_p: dict[str, dict] = {}
    dev_p: dict[str, dict] = {}
    for n, p in model.poses.items():
        scan = place.scans[seq_of[n]].name
        sfm_p.setdefault(scan, {})[n] = p
        if device.get(n) is not None:
            dev_p.setdefault(scan, {})[n] = device[n]
    fit = scale_from_device(sfm_p, dev_p)
    if fit is not None:
        return fit
    z_sfm, z_meas = [], []
    for n, p in model.poses.items():
        uv, ids = model.observations[n]
        suffixes = [s for s in _depth_suffixes(images / n) if s != SFM_DEPTH_SUFFIX]
        if not suffixes or len(ids) == 0:
            continue
        depth = read_depth(depth_path_for(images / n, suffixes[0]))
        H, W = depth.shape
        u = np.clip(np.rint(uv[:, 0]).astype(int), 0, W - 1)
        v = np.clip(np.rint(uv[:, 1]).astype(int), 0, H - 1)
        z_sfm.append(p.transform(model.point_array(ids))[:, 2])
        z_meas.append(depth[v, u])
    fit = scale_from_depth(np.concatenate(z_sfm), np.concatenate(z_meas)) if z_sfm else None
    if fit is not None:
        return fit
    if allow_unscaled:
        return ScaleFit(1.0, "none", float("nan"))
    raise BuildError(
        "no metric scale: no scan has device poses (device_poses.txt) for 4+ registered images and "
        "no depth maps were found; pass --allow-unscaled to keep SfM units"
    )


def _copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)


def _sparse_depth(model: SfmModel, name: str, pose: Pose, K: Intrinsics) -> np.ndarray:
    """Metric depth of the SfM points a frame observes, at their keypoints (0 elsewhere; nearest point wins)."""
    uv, ids = model.observations[name]
    depth = np.zeros((K.height, K.width), np.float32)
    if len(ids) == 0:
        return depth
    z = pose.transform(model.point_array(ids))[:, 2]
    u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    ok = (z > 0) & (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    order = np.argsort(-z[ok])  # far first, so nearer points overwrite them
    depth[v[ok][order], u[ok][order]] = z[ok][order]
    return depth


def _histogram(ov: Overlaps) -> dict:
    bins = np.linspace(0, 1, 11)
    cross = ov.idxs[:, 0] != ov.idxs[:, 2]
    return {
        "bins": bins.round(2).tolist(),
        "within": np.histogram(ov.overlaps[~cross], bins)[0].tolist(),
        "across": np.histogram(ov.overlaps[cross], bins)[0].tolist(),
    }


def _write_scene(
    out: Path,
    place: Place,
    model: SfmModel,
    fit: ScaleFit,
    src: dict[str, Path],
    images: Path,
    device: dict[str, Pose | None],
    seq_of: dict[str, int],
    opts: BuildOptions,
    private_gt: Path | None,
) -> dict:
    """The Map-free layout in ``out``; returns the report's layout section."""
    metric = {n: Pose(p.R, p.t * fit.scale) for n, p in model.poses.items()}
    scan0 = sorted(n for n in metric if seq_of[n] == 0)
    ref_raw = scan0[0]  # the first registered frame of scan 0 is the reference / world origin
    to_ref = metric[ref_raw].inverse()
    if opts.split == "train":
        keep = sorted(metric)
        rename = {n: n for n in keep}
    else:  # val/test: the reference and the queries of scan 1
        keep = [ref_raw] + sorted(n for n in metric if seq_of[n] == 1)
        rename = {n: n for n in keep}
        rename[ref_raw] = REFERENCE_NAME
        if not keep[1:]:
            raise BuildError("no image of the query scan (scan 1) was registered")
    names = [rename[n] for n in keep]
    poses = [metric[n] @ to_ref for n in keep]
    intr = {rename[n]: model.intrinsics[n] for n in keep}
    for n in keep:
        _copy(images / n, out / rename[n])  # the staged JPEG (a link to the input, or the re-encoded PNG)
        for suffix in _depth_suffixes(images / n):
            _copy(depth_path_for(images / n, suffix), depth_path_for(out / rename[n], suffix))
        if opts.sfm_depth or opts.correspondences:
            depth = _sparse_depth(model, n, metric[n], model.intrinsics[n])
            write_depth(depth_path_for(out / rename[n], SFM_DEPTH_SUFFIX), depth)
    write_intrinsics(out / "intrinsics.txt", intr)
    hide = opts.split == "test"
    write_poses(out / "poses.txt", names, [None] * len(names) if hide else poses)
    if hide and private_gt is not None:
        private_gt.mkdir(parents=True, exist_ok=True)
        write_intrinsics(private_gt / "intrinsics.txt", intr)
        write_poses(private_gt / "poses.txt", names, poses)
    _write_device(out, keep, rename, device, seq_of, opts.split)
    seq = np.array([int(rename[n][3]) for n in keep])
    number = np.array([frame_number(rename[n]) for n in keep])
    ov, points = _overlaps(
        model, keep, poses, [model.intrinsics[n] for n in keep], images, seq, number, opts.overlap_points
    )
    write_overlaps(out / "overlaps.npz", ov)
    section = {
        "frames": {rename[n]: str(src[n]) for n in keep},
        "overlap_pairs": len(ov),
        "overlap_points": points,
        "overlap_histogram": _histogram(ov),
    }
    if opts.correspondences:
        section["correspondences"] = _write_correspondences(out, names, poses, intr, ov, opts.corr)
    return section


def _overlaps(
    model: SfmModel,
    keep: list[str],
    poses: list[Pose],
    intr: list[Intrinsics],
    images: Path,
    seq: np.ndarray,
    number: np.ndarray,
    mode: str,
) -> tuple[Overlaps, str]:
    """Depth-based overlaps where every frame has metric depth (and ``mode`` allows), else SfM tracks."""
    if mode not in ("auto", "depth", "sfm"):
        raise ValueError(f"overlap_points must be auto, depth or sfm, not {mode!r}")
    dense = [[s for s in _depth_suffixes(images / n) if s != SFM_DEPTH_SUFFIX] for n in keep]
    if mode != "sfm" and all(dense):
        depths = [read_depth(depth_path_for(images / n, d[0])) for n, d in zip(keep, dense)]
        return depth_overlaps(poses, intr, depths, seq, number), "depth"
    if mode == "depth":
        raise BuildError("--overlap-points depth needs a depth map (frame_NNNNN.SUFFIX.png) beside every image")
    return sfm_overlaps([model.observations[n][1] for n in keep], seq, number), "sfm"


def _write_device(
    out: Path,
    keep: list[str],
    rename: dict[str, str],
    device: dict[str, Pose | None],
    seq_of: dict[str, int],
    split: str,
) -> None:
    """``poses_device.txt``: val/test re-based per multi-frame burst; train per scan (first frame = I)."""
    dev = {rename[n]: p for n in keep if (p := device.get(n)) is not None}
    if not dev:
        return
    rebased: dict[str, Pose]
    if split == "train":
        rebased = {}
        for k in sorted({seq_of[n] for n in keep}):
            scan = [rename[n] for n in keep if seq_of[n] == k and rename[n] in dev]
            if scan:
                first = dev[scan[0]].inverse()
                rebased.update({n: dev[n] @ first for n in scan})
    else:
        bursts = [(q, b) for q, b in multiframe_bursts(list(dev)) if all(n in dev for n in b)]
        rebased = rebase_bursts(dev, bursts)
    if rebased:
        write_device_poses(out / DEVICE_FILE, rebased)


def _write_correspondences(
    out: Path, names: list[str], poses: list[Pose], intr: dict[str, Intrinsics], ov: Overlaps, co: CorrespondenceOptions
) -> dict:
    pose_of = dict(zip(names, poses))
    by_key = {(int(n[3]), frame_number(n)): n for n in names}
    rows = [
        i
        for i in ov.within(co.min_overlap, co.max_overlap)
        if (ov.idxs[i, 0], ov.idxs[i, 1]) < (ov.idxs[i, 2], ov.idxs[i, 3])
    ]
    rows = sorted(rows, key=lambda i: -ov.overlaps[i])[: co.max_pairs]
    dense = [s for s in _depth_suffixes(out / names[0]) if s != SFM_DEPTH_SUFFIX]
    suffix = dense[0] if dense else SFM_DEPTH_SUFFIX
    cache: dict[str, np.ndarray] = {}

    def depth(n: str) -> np.ndarray:
        if n not in cache:
            cache[n] = read_depth(depth_path_for(out / n, suffix))
        return cache[n]

    pairs: list[tuple[int, int, int, int]] = []
    matches: list[tuple[np.ndarray, np.ndarray]] = []
    for i in sorted(rows):
        a, b = by_key[tuple(ov.idxs[i, :2])], by_key[tuple(ov.idxs[i, 2:])]
        k0, k1 = depth_correspondences(
            depth(a), intr[a], pose_of[a], depth(b), intr[b], pose_of[b], co, sparse=suffix == SFM_DEPTH_SUFFIX
        )
        pairs.append((int(ov.idxs[i, 0]), int(ov.idxs[i, 1]), int(ov.idxs[i, 2]), int(ov.idxs[i, 3])))
        matches.append((k0, k1))
    write_correspondences(out / "correspondences.npz", pairs, matches)
    counts = [len(m[0]) for m in matches]
    return {"pairs": len(pairs), "depth": suffix, "median_per_pair": float(np.median(counts)) if counts else 0.0}


def build_place(
    place_dir: Path,
    scene_dir: Path,
    options: BuildOptions = BuildOptions(),
    private_gt: Path | None = None,
    force: bool = False,
) -> PlaceResult:
    """Build one place of scans into a Map-free scene; never raises for a bad place (the result says why).

    Args:
        place_dir: Folder of two or more scan folders.
        scene_dir: The scene folder written (replaced only when the build succeeds).
        options: How to build.
        private_gt: Folder that receives the poses a test scene hides (``private_gt/SCENE/poses.txt``).
        force: Rebuild a scene that already has a report.

    Returns:
        The status, the reason of a failure, the time taken and the build report.
    """
    place_dir, scene_dir = Path(place_dir), Path(scene_dir)
    if not force and (scene_dir / REPORT_FILE).is_file():
        done = json.loads((scene_dir / REPORT_FILE).read_text())
        return PlaceResult(place_dir.name, scene_dir.name, "skipped", "already built", 0.0, done)
    work = scene_dir.parent / ".build" / scene_dir.name
    shutil.rmtree(work, ignore_errors=True)
    staged = work / "scene"
    t0 = time.perf_counter()
    report: dict = {
        "place": str(place_dir),
        "scene": scene_dir.name,
        "split": options.split,
        "options": _jsonable(asdict(options)),
    }
    try:
        _build(place_dir, work, options, private_gt / scene_dir.name if private_gt else None, report)
        report["status"] = "ok"
    except (BuildError, FormatError, OSError, ValueError) as e:
        report.update(status="failed", reason=str(e))
    except Exception as e:  # pycolmap / numerical surprises: still only this place fails
        log.exception("place %s", place_dir)
        report.update(status="failed", reason=f"{type(e).__name__}: {e}")
    report["seconds"] = round(time.perf_counter() - t0, 2)
    _publish(report, staged, scene_dir, work, options)
    return PlaceResult(
        place_dir.name, scene_dir.name, report["status"], report.get("reason", ""), report["seconds"], report
    )


def _build(place_dir: Path, work: Path, options: BuildOptions, private_gt: Path | None, report: dict) -> None:
    """Reconstruct a place, fit its metric scale and write the scene into ``work/scene``, each step recorded in
    ``report``; ``private_gt`` receives the poses a test scene hides.

    Raises:
        BuildError: Too few images registered, no metric scale, or another reason the place cannot be a scene.
    """
    staged, images = work / "scene", work / "images"
    place = read_place(place_dir, options.fps, work / "video", options.device_axes)
    src, intr, device, seq_of = _stage(place, images)
    for n, p in src.items():  # depth maps beside the inputs travel with the images
        for suffix in _depth_suffixes(p):
            os.symlink(depth_path_for(p, suffix).resolve(), depth_path_for(images / n, suffix))
    t_sfm = time.perf_counter()
    model = reconstruct(images, sorted(src), intr, work / "colmap", options.sfm)
    report["sfm_seconds"] = round(time.perf_counter() - t_sfm, 2)
    report["scans"] = _check_registration(place, model, seq_of, options.min_registered)
    assert model is not None  # _check_registration raised BuildError otherwise
    report["registered"] = len(model.poses)
    report["images"] = len(src)
    report["points3D"] = len(model.points)
    report["reprojection_error_px"] = model.reprojection_error
    report["models"] = model.models
    fit = _metric_scale(place, model, seq_of, device, images, options.allow_unscaled)
    report["scale"] = _jsonable(asdict(fit))
    if fit.outliers:  # misregistered images (the device track disagrees): dropped, then re-checked
        for n in fit.outliers:
            model.poses.pop(n)
        report["scans"] = _check_registration(place, model, seq_of, options.min_registered, len(fit.outliers))
        report["registered"] = len(model.poses)
    staged.mkdir(parents=True)
    report.update(_write_scene(staged, place, model, fit, src, images, device, seq_of, options, private_gt))


def _publish(report: dict, staged: Path, scene_dir: Path, work: Path, options: BuildOptions) -> None:
    """Put a built scene in place of ``scene_dir`` (with its report and plot), or keep a failed build's report in
    the work folder."""
    if report["status"] == "ok":
        (staged / REPORT_FILE).write_text(json.dumps(report, indent=1))
        if options.report_plot:
            from .report import plot_report

            plot_report(staged, report, staged / "build_report.png")
        shutil.rmtree(scene_dir, ignore_errors=True)
        os.replace(staged, scene_dir)
        if not options.keep_work:
            shutil.rmtree(work, ignore_errors=True)
    else:
        shutil.rmtree(staged, ignore_errors=True)
        work.mkdir(parents=True, exist_ok=True)
        (work / REPORT_FILE).write_text(json.dumps(report, indent=1))


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if not np.isfinite(x) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    return x
