"""Reading a place of raw scans: image folders or videos, intrinsics, timestamps and device tracking poses.

A place is a folder of scan folders (sorted by name: the first is scan 0, the reference scan). A scan holds

- images (``*.jpg|*.jpeg|*.png``, depth PNGs ``name.SUFFIX.png`` excluded) or one video (``*.mp4|*.mov|...``)
  sampled at ``fps`` frames per second;
- optional ``intrinsics.txt`` (our format, names relative to the scan), else the EXIF focal length
  (``mapfree.data.intrinsics``: the project's one convention), else none;
- optional ``rgb.txt`` (TUM: ``timestamp filename``); without it image i is at time i (video: its time in s);
- optional ``device_poses.txt`` (TUM: ``t tx ty tz qx qy qz qw``, camera-to-world, metres), interpolated at
  each image's time.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..data.intrinsics import exif_intrinsics
from ..data.io import FormatError, iter_records, read_intrinsics, write_image
from ..geometry import Intrinsics, Pose

__all__ = [
    "ScanFrame",
    "Scan",
    "Place",
    "read_place",
    "read_tum",
    "interpolate_track",
    "exif_intrinsics",
    "DEVICE_AXES",
]

IMAGE_EXT = {".jpg", ".jpeg", ".png"}
VIDEO_EXT = {".mp4", ".mov", ".avi", ".mkv", ".m4v"}
DEVICE_FILE = "device_poses.txt"
_DEPTH_RE = re.compile(r"\.[A-Za-z0-9_-]+\.png$")  # frame_00000.sensor.png
# Camera axes of the device poses -> OpenCV (x right, y down, z forward). ARKit/ARCore use OpenGL axes.
DEVICE_AXES = {"opencv": np.eye(3), "opengl": np.diag([1.0, -1.0, -1.0])}


@dataclass
class ScanFrame:
    """One image of a scan: its file, capture time, intrinsics (when known) and device pose (world-to-camera)."""

    path: Path
    time: float
    intrinsics: Intrinsics | None = None
    device: Pose | None = None


@dataclass
class Scan:
    """One scan of a place: its frames in time order.

    Attributes:
        name: Scan folder name.
        folder: The scan folder.
        frames: Images (or sampled video frames) with their times, intrinsics and device poses.
    """

    name: str
    folder: Path
    frames: list[ScanFrame] = field(default_factory=list)

    @property
    def has_device(self) -> bool:
        """Whether any frame has a device pose."""
        return any(f.device is not None for f in self.frames)


@dataclass
class Place:
    """A place: two or more scans of it, the first being the reference scan.

    Attributes:
        name: Place folder name.
        folder: The place folder.
        scans: The scans, sorted by folder name.
    """

    name: str
    folder: Path
    scans: list[Scan]


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(times (N,), centres (N,3), rotations (N,3,3) camera-to-world)`` of a device track, in file order.

    Times must increase strictly from line to line (a track is a log in time order: repeated or backward times
    mean a corrupt export, and interpolating between them is undefined); errors name ``file:line``."""
    times, rows = [], []
    prev: tuple[float, int] | None = None
    for lineno, first, v in iter_records(path, 7):
        try:
            t = float(first)
        except ValueError:
            raise FormatError(path, lineno, f"timestamp {first!r} is not a number") from None
        if not np.isfinite(t):
            raise FormatError(path, lineno, f"timestamp {first!r} is not finite")
        if prev is not None and not t > prev[0]:
            raise FormatError(
                path,
                lineno,
                f"timestamp {first} is {'equal to' if t == prev[0] else 'before'} the "
                f"previous one ({prev[0]!r}, line {prev[1]}): a device track's times "
                "must increase from line to line",
            )
        if not np.linalg.norm(v[3:]) > 0:
            raise FormatError(path, lineno, "zero quaternion")
        times.append(t)
        rows.append(v)
        prev = (t, lineno)
    if not rows:
        raise FormatError(path, None, "no poses")
    arr = np.array(rows)
    return np.asarray(times), arr[:, :3], Rotation.from_quat(arr[:, 3:]).as_matrix()


def interpolate_track(
    times: np.ndarray, centres: np.ndarray, rots: np.ndarray, at: np.ndarray, max_gap: float = 1.0
) -> list[Pose | None]:
    """Camera-to-world poses at times ``at`` (linear centres, slerp rotations); None outside the track."""
    out: list[Pose | None] = [None] * len(at)
    if len(times) == 1:
        for i, t in enumerate(at):
            if abs(t - times[0]) <= 1e-6:
                out[i] = Pose(rots[0], centres[0])
        return out
    times_u, keep = np.unique(times, return_index=True)
    at = np.asarray(at, dtype=np.float64)
    j = np.clip(np.searchsorted(times_u, at), 1, len(times_u) - 1)
    ok = (at >= times_u[0]) & (at <= times_u[-1]) & (times_u[j] - times_u[j - 1] <= max_gap)
    if not ok.any():
        return out
    t_ok = at[ok]  # all frames at once: one slerp call and one interpolation per axis
    R = Slerp(times_u, Rotation.from_matrix(rots[keep]))(t_ok).as_matrix()
    C = np.stack([np.interp(t_ok, times_u, centres[keep][:, k]) for k in range(3)], axis=1)
    for i, Ri, ci in zip(np.flatnonzero(ok).tolist(), R, C):
        out[i] = Pose(Ri, ci)
    return out


def _sample_video(video: Path, fps: float, cache: Path) -> list[ScanFrame]:
    """Frames of ``video`` every 1/fps seconds, written once as JPEGs under ``cache``."""
    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise FormatError(video, None, "cannot open video")
    rate = cap.get(cv2.CAP_PROP_FPS) or 30.0
    cache.mkdir(parents=True, exist_ok=True)
    frames: list[ScanFrame] = []
    k, next_t = 0, 0.0
    while True:
        ok, img = cap.read()
        if not ok:
            break
        t = k / rate
        k += 1
        if t + 1e-9 < next_t:
            continue
        next_t += 1.0 / fps
        path = cache / f"frame_{len(frames):05d}.jpg"
        if not path.exists():
            write_image(path, img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        frames.append(ScanFrame(path, t))
    cap.release()
    if not frames:
        raise FormatError(video, None, "no frames could be decoded")
    return frames


def _read_times(path: Path) -> dict[str, float]:
    out = {}
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        f = line.split()
        if not f or f[0].startswith("#"):
            continue
        if len(f) != 2:
            raise FormatError(path, lineno, f"expected 'timestamp filename', found {len(f)} fields")
        try:
            out[Path(f[1]).name] = float(f[0])
        except ValueError:
            raise FormatError(path, lineno, f"timestamp {f[0]!r} is not a number") from None
    return out


def read_scan(folder: Path, fps: float = 2.0, cache: Path | None = None, device_axes: str = "opencv") -> Scan:
    """One scan folder -> Scan (frames in time order, intrinsics and device poses attached when available)."""
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXT and not _DEPTH_RE.search(p.name))
    videos = sorted(p for p in folder.iterdir() if p.suffix.lower() in VIDEO_EXT)
    if images:
        times = _read_times(folder / "rgb.txt") if (folder / "rgb.txt").is_file() else {}
        missing = [p.name for p in images if times and p.name not in times]
        if missing:
            raise FormatError(folder / "rgb.txt", None, f"no timestamp for {missing[0]}")
        frames = [ScanFrame(p, times.get(p.name, float(i))) for i, p in enumerate(images)]
        frames.sort(key=lambda f: f.time)
    elif videos:
        frames = _sample_video(videos[0], fps, (cache or folder / ".frames") / folder.name)
    else:
        raise FormatError(folder, None, "no images (*.jpg, *.png) or video (*.mp4, *.mov, ...) in the scan")
    intr = read_intrinsics(folder / "intrinsics.txt") if (folder / "intrinsics.txt").is_file() else {}
    for f in frames:
        if f.path.name in intr:
            f.intrinsics = intr[f.path.name]
        else:
            f.intrinsics = exif_intrinsics(f.path)
    if (folder / DEVICE_FILE).is_file():
        t, c, r = read_tum(folder / DEVICE_FILE)
        axes = DEVICE_AXES[device_axes]
        for f, p in zip(frames, interpolate_track(t, c, r, np.array([f.time for f in frames]))):
            if p is not None:
                f.device = Pose(p.R @ axes, p.t).inverse()  # camera-to-world (OpenCV axes) -> world-to-camera
    return Scan(folder.name, folder, frames)


def read_place(folder: Path, fps: float = 2.0, cache: Path | None = None, device_axes: str = "opencv") -> Place:
    """Read a place: its scan folders with images or a video, intrinsics, timestamps and device poses.

    Args:
        folder: The place folder (scan sub-folders; hidden folders are skipped).
        fps: Frames per second sampled from a video, Hz.
        cache: Folder of the frames sampled from videos; a ``.frames`` folder inside each scan when None.
        device_axes: Camera axes of the device poses: ``opencv``, or ``opengl`` (ARKit/ARCore).

    Returns:
        The place, scans sorted by name.

    Raises:
        ValueError: ``device_axes`` is unknown.
        FormatError: Fewer than two scans, a scan without images or video, or a malformed file.
    """
    folder = Path(folder)
    if device_axes not in DEVICE_AXES:
        raise ValueError(f"device_axes must be one of {sorted(DEVICE_AXES)}, got {device_axes!r}")
    subs = sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
    if len(subs) < 2:
        raise FormatError(folder, None, f"a place needs two or more scan folders, found {len(subs)}")
    return Place(folder.name, folder, [read_scan(s, fps, cache, device_axes) for s in subs])
