"""Readers and writers for the Map-free text, depth and overlap files.

Every reader names the file and the line of the first malformed entry it meets (``FormatError``).
Lines whose first field contains ``#`` are comments.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import Intrinsics, Pose
from .orientation import OrientationError, exif_orientation, orient_pixels

__all__ = [
    "FormatError",
    "depth_suffixes",
    "publish",
    "iter_records",
    "read_intrinsics",
    "write_intrinsics",
    "PoseTable",
    "read_poses",
    "write_poses",
    "read_depth",
    "check_depth_size",
    "same_aspect",
    "write_depth",
    "read_image",
    "depth_path_for",
]


class FormatError(ValueError):
    """A malformed dataset file; the message names the file and (1-based) line.

    Args:
        path: The file.
        line: 1-based line number, or None for the file as a whole.
        reason: What is wrong, in a few words.
    """

    def __init__(self, path: os.PathLike | str, line: int | None, reason: str):
        self.path, self.line, self.reason = str(path), line, reason
        where = f"{path}:{line}" if line is not None else str(path)
        super().__init__(f"{where}: {reason}")


def iter_records(path: os.PathLike | str, nvalues: int) -> Iterator[tuple[int, str, np.ndarray]]:
    """Yield ``(line_number, name, values)`` for each data line of a ``name v1 … vN`` text file."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise FormatError(path, None, "file not found") from None
    except UnicodeDecodeError as e:
        raise FormatError(path, None, f"not UTF-8 text ({e.reason})") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        fields = line.split()
        if not fields or "#" in fields[0]:
            continue
        if len(fields) != nvalues + 1:
            raise FormatError(path, lineno, f"expected {nvalues + 1} fields, found {len(fields)}")
        try:
            floats = [float(v) for v in fields[1:]]
        except ValueError:
            raise FormatError(path, lineno, f"unparseable number in {line.strip()!r}") from None
        if not all(map(math.isfinite, floats)):  # per-line numpy checks would dominate on 30k-line scenes
            raise FormatError(path, lineno, "non-finite number")
        yield lineno, fields[0], np.array(floats)


def read_intrinsics(path: os.PathLike | str) -> dict[str, Intrinsics]:
    """Read a scene's ``intrinsics.txt`` (``name fx fy cx cy width height`` per frame).

    Args:
        path: The file.

    Returns:
        Intrinsics by frame name, in file order.

    Raises:
        FormatError: The file is missing or a line is malformed (non-positive focal length or size).
    """
    out: dict[str, Intrinsics] = {}
    for lineno, name, v in iter_records(path, 6):
        fx, fy, cx, cy, w, h = v
        if fx <= 0 or fy <= 0 or w <= 0 or h <= 0 or w != int(w) or h != int(h):
            raise FormatError(path, lineno, "focal lengths and image size must be positive (size integral)")
        out[name] = Intrinsics(float(fx), float(fy), float(cx), float(cy), int(w), int(h))
    return out


def write_intrinsics(path: os.PathLike | str, intrinsics: Mapping[str, Intrinsics]) -> None:
    """Write an ``intrinsics.txt`` that ``read_intrinsics`` reads back.

    Args:
        path: The file, overwritten.
        intrinsics: Intrinsics by frame name, written in this order.
    """
    lines = [f"{n} {k.fx:.6f} {k.fy:.6f} {k.cx:.6f} {k.cy:.6f} {k.width} {k.height}\n" for n, k in intrinsics.items()]
    Path(path).write_text("".join(lines))


@dataclass
class PoseTable:
    """Poses of a file as arrays; zero quaternions (test split: private ground truth) are kept as is.

    Attributes:
        names: Frame names, in file order.
        q: (N, 4) world-to-camera quaternions ``w x y z``, as written.
        t: (N, 3) world-to-camera translations, metres.
    """

    names: list[str]
    q: np.ndarray  # (N,4) wxyz, as written
    t: np.ndarray  # (N,3)

    def __len__(self) -> int:
        return len(self.names)

    def index(self) -> dict[str, int]:
        """Row of each frame name."""
        return {n: i for i, n in enumerate(self.names)}

    def pose(self, i: int) -> Pose | None:
        """Pose of one row.

        Args:
            i: Row index.

        Returns:
            The world-to-camera pose, or None when the row has no valid rotation (all-zero test lines).
        """
        if not np.linalg.norm(self.q[i]) > 0:
            return None
        return Pose.from_qt(self.q[i], self.t[i])

    def as_dict(self) -> dict[str, Pose | None]:
        """Pose (or None, see ``pose``) by frame name."""
        return {n: self.pose(i) for i, n in enumerate(self.names)}


def read_poses(path: os.PathLike | str) -> PoseTable:
    """Read a pose file (``poses.txt``, ``poses_device.txt``: ``name qw qx qy qz tx ty tz`` per frame).

    Args:
        path: The file.

    Returns:
        The poses in file order.

    Raises:
        FormatError: The file is missing or a line is malformed.
    """
    names, rows = [], []
    for _, name, v in iter_records(path, 7):
        names.append(name)
        rows.append(v)
    arr = np.array(rows, dtype=np.float64).reshape(-1, 7)
    return PoseTable(names, arr[:, :4].copy(), arr[:, 4:].copy())


def write_poses(path: os.PathLike | str, names: Sequence[str], poses: Sequence[Pose | None]) -> None:
    """Write a pose file that ``read_poses`` reads back.

    Args:
        path: The file, overwritten.
        names: Frame names.
        poses: World-to-camera poses, one per name; None writes an all-zero line (as in the test split).
    """
    lines = []
    for n, p in zip(names, poses):
        if p is None:
            lines.append(f"{n} 0 0 0 0 0 0 0\n")
        else:
            q, t = p.qt()
            lines.append(f"{n} " + " ".join(f"{x:.9f}" for x in (*q, *t)) + "\n")
    Path(path).write_text("".join(lines))


def depth_path_for(image_path: os.PathLike | str, suffix: str) -> Path:
    """Where the depth map of an image is stored.

    Args:
        image_path: The image, e.g. ``seq1/frame_00012.jpg``.
        suffix: Depth source name, e.g. ``dptkitti``.

    Returns:
        The PNG beside the image, e.g. ``seq1/frame_00012.dptkitti.png``.
    """
    p = Path(image_path)
    return p.with_name(f"{p.stem}.{suffix}.png")


def publish(tmp: os.PathLike | str, path: os.PathLike | str) -> Path:
    """Move a finished temporary file (``tempfile.mkstemp``: mode 0600) to ``path`` atomically, with the mode every
    other output gets (0666 less the umask: 0644 usually)."""
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(tmp, 0o666 & ~mask)
    os.replace(tmp, path)
    return Path(path)


def depth_suffixes(image_path: os.PathLike | str) -> list[str]:
    """The depth suffixes of the maps beside an image: ``frame.sensor.png``, ``frame.mono.png`` -> sensor, mono."""
    p = Path(image_path)
    return sorted({q.name[len(p.stem) + 1 : -len(".png")] for q in p.parent.glob(f"{p.stem}.*.png")})


def _decode(data: np.ndarray, flags: int) -> np.ndarray | None:
    """``cv2.imdecode`` without OpenCV's own "[ WARN ] … buffer is incomplete" lines on stderr (the caller words
    the error, naming the file); None for bytes it cannot decode."""
    import cv2
    from cv2.utils import logging as cv_log

    level = cv_log.getLogLevel()
    cv_log.setLogLevel(cv_log.LOG_LEVEL_ERROR)
    try:
        return cv2.imdecode(data, flags)
    except cv2.error:  # OpenCV asserts on some truncated headers instead of returning None
        return None
    finally:
        cv_log.setLogLevel(level)


def read_depth(path: os.PathLike | str) -> np.ndarray:
    """Read a depth map stored as a 16-bit PNG of millimetres.

    Args:
        path: The PNG.

    Returns:
        (H, W) float32 depth in metres; 0 marks invalid pixels.

    Raises:
        FormatError: The file is missing, corrupt, not single-channel or not 16-bit.
    """
    import cv2  # here, not at the top: reading poses and intrinsics needs no OpenCV

    # Decoded from bytes: cv2.imread prints its own "[ WARN ] can't open/read file" line before our error.
    if not Path(path).is_file():
        raise FormatError(path, None, "depth image not found")
    data = np.fromfile(str(path), dtype=np.uint8)
    d = _decode(data, cv2.IMREAD_ANYDEPTH) if data.size else None
    if d is None:
        raise FormatError(path, None, "cannot read depth image (empty or corrupt)")
    if d.ndim != 2:
        raise FormatError(path, None, f"depth must be single-channel, got shape {d.shape}")
    if d.dtype == np.uint8:
        raise FormatError(path, None, "depth must be a 16-bit PNG of millimetres, got an 8-bit image")
    return d.astype(np.float32) / 1000.0


def check_depth_size(path: os.PathLike | str, shape: tuple[int, ...], width: int, height: int) -> None:
    """Refuse a depth map whose aspect ratio differs from its image's (2 % tolerance).

    A map may have another resolution than its image (it is resized), never another aspect ratio: that is
    another frame's map, rotated or cropped, and would put depth on the wrong pixels.

    Args:
        path: The depth map, named in the error.
        shape: Shape of the depth array, (H, W, ...).
        width: Image width, pixels.
        height: Image height, pixels.

    Raises:
        FormatError: The aspect ratios differ.
    """
    if not same_aspect(shape, width, height):
        h, w = shape[:2]
        raise FormatError(
            path,
            None,
            f"depth map is {w}x{h} but the image is {width}x{height} (intrinsics): "
            f"another aspect ratio, so not this frame's map",
        )


def same_aspect(shape: tuple[int, ...], width: int, height: int) -> bool:
    """Whether an array of ``shape`` (rows, cols, ...) has the aspect ratio of a width x height image (2 %)."""
    h, w = shape[:2]
    return abs(w * height - h * width) <= 0.02 * width * h


def write_depth(path: os.PathLike | str, depth_m: np.ndarray) -> None:
    """Write a depth map as a 16-bit PNG of millimetres that ``read_depth`` reads back.

    Args:
        path: The PNG, overwritten.
        depth_m: (H, W) depth in metres; NaN, inf, negative or beyond 65.535 m are written as 0 (invalid).

    Raises:
        OSError: OpenCV could not write the file.
    """
    import cv2

    d = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    mm = np.rint(d * 1000.0)
    mm[(mm < 0) | (mm > 65535)] = 0
    if not cv2.imwrite(str(path), mm.astype(np.uint16)):
        raise OSError(f"{path}: could not write depth PNG")


def read_image(path: os.PathLike | str) -> np.ndarray:
    """Read an image as displayed: decoded, then turned upright by its EXIF orientation.

    Args:
        path: The image file (any format OpenCV decodes).

    Returns:
        (H, W, 3) uint8 RGB.

    Raises:
        FormatError: The file is missing, empty, corrupt, or mirrored by its EXIF orientation.
    """
    import cv2

    data = np.fromfile(str(path), dtype=np.uint8) if Path(path).is_file() else None
    if data is None:
        raise FormatError(path, None, "image file not found")
    if data.size == 0:
        raise FormatError(path, None, "image file is empty (0 bytes)")
    img = _decode(data, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise FormatError(path, None, "cannot decode image (corrupt or unsupported format)")
    return upright(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), path)


def upright(img: np.ndarray, path: os.PathLike | str) -> np.ndarray:
    """The decoded stored pixels of ``path`` -> the photo as displayed (EXIF orientation applied); a mirrored one is
    refused."""
    try:
        return orient_pixels(img, exif_orientation(path))
    except OrientationError as e:
        raise FormatError(path, None, str(e).split(": ", 1)[1]) from None
