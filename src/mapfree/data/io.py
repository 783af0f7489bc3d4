"""Readers and writers for the Map-free text, depth and overlap files.

Every reader names the file and the line of the first malformed entry it meets (``FormatError``).
Lines whose first field contains ``#`` are comments.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
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
    "write_image",
    "naming",
    "read_image",
    "MAX_PIXELS",
    "MIN_SIDE",
    "image_size_problem",
    "pixel_problem",
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
    with naming(path):
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
    with naming(path):
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
        OSError: The file could not be written.
    """
    d = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    mm = np.rint(d * 1000.0)
    mm[(mm < 0) | (mm > 65535)] = 0
    write_image(path, mm.astype(np.uint16))


@contextmanager
def naming(path: os.PathLike | str) -> Iterator[None]:
    """Writes in the block that fail without a file name (``write`` on a full disk, ``ENOSPC``) raise the error
    again naming ``path``, so the one line a command prints says which output could not be written.

    Args:
        path: The output the block writes.

    Raises:
        OSError: The block's, with ``filename`` set to ``path`` when it had none.
    """
    try:
        yield
    except OSError as e:
        if e.filename is not None or e.errno is None:
            raise
        raise OSError(e.errno, e.strerror or os.strerror(e.errno), os.fsdecode(path)) from e


def write_image(path: os.PathLike | str, pixels: np.ndarray, params: Sequence[int] = ()) -> None:
    """Write an image file: encoded in memory by OpenCV (the format from the name's suffix), written by Python.

    OpenCV's own ``imwrite`` crashes the process on a file name that is not valid UTF-8; Python's ``open`` takes
    any name the system does (``mapfree synth $'out_\\xff'``).

    Args:
        path: The file (``.png``, ``.jpg``, ``.jpeg`` …), overwritten; its folder must exist.
        pixels: (H, W, 3) uint8 **BGR** (OpenCV's order), (H, W) uint8 or uint16 grey.
        params: ``cv2.imencode`` parameters (e.g. ``[cv2.IMWRITE_JPEG_QUALITY, 95]``).

    Raises:
        OSError: The format cannot be encoded, or the file cannot be written (naming the file).
    """
    import cv2

    suffix = Path(path).suffix.lower() or ".png"
    try:
        ok, buf = cv2.imencode(suffix, pixels, list(params))
    except cv2.error:
        ok, buf = False, None
    if not ok or buf is None:
        raise OSError(f"{os.fsdecode(path)}: could not encode the image as {suffix.lstrip('.').upper()}")
    with naming(path), open(path, "wb") as f:
        f.write(buf.tobytes())


#: The pixel budget of an image (50 megapixels, e.g. 8660 x 5773): a larger one is refused before it is decoded.
#: A 108 MP photo decoded and matched at its size takes tens of GB; ``$MAPFREE_MAX_PIXELS`` sets another budget.
MAX_PIXELS = 50_000_000
MAX_PIXELS_ENV = "MAPFREE_MAX_PIXELS"
#: The smallest side of an image any matcher can use, pixels.
MIN_SIDE = 8


def max_pixels() -> int:
    """The pixel budget: ``$MAPFREE_MAX_PIXELS`` when it is a positive integer, else ``MAX_PIXELS``."""
    value = os.environ.get(MAX_PIXELS_ENV, "")
    return int(value) if value.isdigit() and int(value) > 0 else MAX_PIXELS


def image_size_problem(data: bytes | np.ndarray) -> str | None:
    """Why an encoded image is refused before decoding it: more pixels than the budget (``max_pixels``), or a
    side under ``MIN_SIDE``; read from its header alone (Pillow), so a huge image costs no memory here.

    Args:
        data: The file's bytes.

    Returns:
        None for a usable size or a header Pillow cannot read (the decoder words that); else the reason.
    """
    import warnings

    from PIL import Image, UnidentifiedImageError

    budget = max_pixels()
    try:
        with warnings.catch_warnings():  # Pillow's own DecompressionBombWarning: this function words it
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data if isinstance(data, bytes) else data.tobytes())) as im:
                w, h = im.size
    except Image.DecompressionBombError:
        return f"more than {2 * (Image.MAX_IMAGE_PIXELS or 0) / 1e6:.0f} megapixels, over the {budget / 1e6:g}-megapixel budget"
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        return None
    return pixel_problem(w, h)


def pixel_problem(w: int, h: int) -> str | None:
    """Why a ``w`` x ``h`` image is refused (over ``max_pixels()``, a side under ``MIN_SIDE``), or None."""
    budget = max_pixels()
    if w * h > budget:
        return (
            f"{w}x{h} is {w * h / 1e6:.1f} megapixels, over the {budget / 1e6:g}-megapixel budget: downscale it "
            f"(the intrinsics with it), or raise ${MAX_PIXELS_ENV}"
        )
    if min(w, h) < MIN_SIDE:
        return f"{w}x{h} pixels: too small (both sides must be >= {MIN_SIDE})"
    return None


def read_image(path: os.PathLike | str) -> np.ndarray:
    """Read an image as displayed: decoded, then turned upright by its EXIF orientation.

    Args:
        path: The image file (any format OpenCV decodes), at most ``max_pixels()`` pixels (50 MP) and at least
            ``MIN_SIDE`` pixels a side.

    Returns:
        (H, W, 3) uint8 RGB.

    Raises:
        FormatError: The file is missing, empty, corrupt, too large or too small (before decoding it), or
            mirrored by its EXIF orientation.
    """
    import cv2

    data = np.fromfile(str(path), dtype=np.uint8) if Path(path).is_file() else None
    if data is None:
        raise FormatError(path, None, "image file not found")
    if data.size == 0:
        raise FormatError(path, None, "image file is empty (0 bytes)")
    problem = image_size_problem(data)
    if problem:
        raise FormatError(path, None, problem)
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
