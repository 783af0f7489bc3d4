"""Metric scale of an SfM model: from the phone's tracking poses, or from metric depth maps.

Device poses: per scan, a robust similarity (pycolmap's LO-RANSAC Sim3) from the SfM camera centres to the
device's; the scans' scales are combined by their median. Tracking drifts, so the inlier threshold is a
fraction of the scan's extent and the residual is reported relative to it.
Depth: the median ratio of measured depth to SfM depth at every triangulated keypoint.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry import Pose, rotation_angle_deg

__all__ = ["ScaleFit", "scale_from_device", "scale_from_depth"]


@dataclass
class ScaleFit:
    """SfM units -> metres. ``residual`` is relative: trajectory misfit / extent (device) or MAD / median (depth)."""

    scale: float
    source: str  # "device" | "depth" | "none"
    residual: float
    per_scan: dict[str, float] = field(default_factory=dict)
    inliers: int = 0
    used: int = 0
    outliers: list[str] = field(default_factory=list)  # frames inconsistent with the device track


def _robust_sim3(src: np.ndarray, dst: np.ndarray, rel_threshold: float):
    """pycolmap's LO-RANSAC similarity ``dst ~ s R src + t`` and the target extent; None if degenerate."""
    import pycolmap

    extent = float(np.linalg.norm(np.ptp(dst, axis=0)))
    if len(src) < 3 or extent < 1e-6 or np.linalg.norm(np.ptp(src, axis=0)) < 1e-12:
        return None
    opts = pycolmap.RANSACOptions()
    opts.max_error = rel_threshold * extent
    opts.random_seed = 0
    sim = pycolmap.estimate_sim3d_robust(src, dst, opts)
    # the stub says Sim3d | None; pycolmap 4.x returns a dict (tgt_from_src, num_inliers, inlier_mask) or None
    return None if sim is None else (sim["tgt_from_src"], extent)  # type: ignore[index]


def scale_from_device(
    sfm: dict[str, dict[str, Pose]],
    device: dict[str, dict[str, Pose]],
    rel_threshold: float = 0.05,
    max_rotation_deg: float = 5.0,
    min_frames: int = 4,
) -> ScaleFit | None:
    """Scale from ``{scan: {frame: world-to-camera pose}}`` of SfM and of the device; None without enough frames.

    Frames whose SfM pose disagrees with the fitted device track (centre off by more than ``rel_threshold``
    of the scan's extent, or orientation by more than ``max_rotation_deg``) are listed in ``outliers``:
    misregistered images, typically on repeated textures.
    """
    scales, residuals, outliers, inliers, used = {}, [], [], 0, 0
    for scan, poses in sfm.items():
        dev = device.get(scan, {})
        common = [n for n in poses if n in dev]
        if len(common) < min_frames:
            continue
        src = np.stack([poses[n].center for n in common])
        dst = np.stack([dev[n].center for n in common])
        fit = _robust_sim3(src, dst, rel_threshold)
        if fit is None:
            continue
        sim, extent = fit
        A = sim.rotation.matrix()
        err = np.linalg.norm(src @ (sim.scale * A).T + sim.translation - dst, axis=1) / extent
        rot = np.array([rotation_angle_deg(A @ poses[n].R.T, dev[n].R.T) for n in common])
        ok = (err <= rel_threshold) & (rot <= max_rotation_deg)
        outliers += [n for n, good in zip(common, ok) if not good]
        scales[scan] = float(sim.scale)
        residuals.append(float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else 1.0)
        inliers += int(ok.sum())
        used += len(common)
    if not scales:
        return None
    s = float(np.median(list(scales.values())))
    spread = float(np.max(np.abs(np.array(list(scales.values())) / s - 1)))  # scans disagreeing on the scale
    return ScaleFit(s, "device", max(float(np.max(residuals)), spread), scales, inliers, used, sorted(outliers))


def scale_from_depth(sfm_depth: np.ndarray, measured: np.ndarray, min_points: int = 20) -> ScaleFit | None:
    """Scale from SfM depths of keypoints and the metric depth measured there (0 = invalid)."""
    ok = (measured > 0) & (sfm_depth > 1e-9) & np.isfinite(measured) & np.isfinite(sfm_depth)
    if ok.sum() < min_points:
        return None
    r = measured[ok] / sfm_depth[ok]
    s = float(np.median(r))
    mad = float(np.median(np.abs(r - s)))
    inl = int((np.abs(r - s) <= 3 * 1.4826 * mad + 1e-12).sum())
    return ScaleFit(s, "depth", mad / s, {}, inl, int(ok.sum()))
