"""Hostile-input gates for uploads: ZIP submissions and images. Each failure is an ``UploadError`` carrying the
HTTP status and a message that names the problem (never a 500)."""

from __future__ import annotations

import io
import math
import re
import unicodedata
import zipfile
import zlib
from dataclasses import dataclass
from typing import BinaryIO

import cv2
import numpy as np

from ..data.orientation import orient_pixels
from .config import Limits
from .exif import photo_orientation

ENTRY_RE = re.compile(r"^pose_(s\d{5})\.txt$")
#: A focal length beyond this many times the image's longest side is not a camera (a ~0.6 degree field of view).
MAX_FOCAL_FACTOR = 100
#: Smallest focal length, per pixel of the longest side: 0.1 is a 157-degree field of view across it, past any
#: pinhole lens (fisheyes need another camera model); 0.5 px or 1e-300 are unit mistakes, not cameras.
MIN_FOCAL_FACTOR = 0.1


class UploadError(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


@dataclass
class ZipInfo:
    scenes: list[str]
    uncompressed_bytes: int  # as the ZIP directory declares them
    zip_bytes: int  # the upload itself


#: How much of each entry the upload check decompresses (the start of the file: encoding, corrupt streams).
SNIFF_BYTES = 4096


def check_submission_zip(data: bytes | BinaryIO, limits: Limits, split: str,
                         known_scenes: set[str] | None) -> ZipInfo:
    """The cheap checks an upload gets before it is stored, in bounded time and memory: a real ZIP (its central
    directory), few entries, flat ``pose_sNNNNN.txt`` names only (no traversal), known scenes, declared sizes
    within the per-entry and total limits and a sane ratio (zip bombs), and the first few kB of each entry
    decompressed (UTF-8 text, a readable stream). Parsing the pose lines is left to the workers."""
    f = io.BytesIO(data) if isinstance(data, (bytes, bytearray)) else data
    f.seek(0, io.SEEK_END)
    size = f.tell()
    f.seek(0)
    if size > limits.max_submission_bytes:
        raise UploadError(413, f"submission is {size} bytes; the limit is {limits.max_submission_bytes}")
    if not size:
        raise UploadError(400, "submission file is empty")
    try:
        zf = zipfile.ZipFile(f)
        infos = zf.infolist()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, EOFError) as e:
        raise UploadError(400, f"submission is not a valid ZIP archive ({e})") from None
    if len(infos) > limits.max_zip_entries:
        raise UploadError(413, f"ZIP has {len(infos)} entries; the limit is {limits.max_zip_entries}")
    total, scenes = 0, []
    for info in infos:
        name = info.filename
        if info.is_dir():
            raise UploadError(422, f"ZIP entry {name!r}: folders are not allowed; put pose_sNNNNN.txt at the root")
        if name.startswith(("/", "\\")) or ".." in name or "/" in name or "\\" in name or ":" in name:
            raise UploadError(422, f"ZIP entry {name!r}: paths are not allowed (path traversal); "
                                   "entries must be pose_sNNNNN.txt at the root")
        m = ENTRY_RE.match(name)
        if not m:
            raise UploadError(422, f"ZIP entry {name!r}: expected a name like pose_s00460.txt")
        if info.flag_bits & 0x1:
            raise UploadError(422, f"ZIP entry {name!r} is encrypted")
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise UploadError(422, f"ZIP entry {name!r}: unsupported compression (use deflate or store)")
        if m.group(1) in scenes:
            raise UploadError(422, f"ZIP entry {name!r} appears twice")
        if known_scenes is not None and m.group(1) not in known_scenes:
            raise UploadError(422, f"ZIP entry {name!r}: scene {m.group(1)} is not in the {split} split")
        ratio = info.file_size / max(info.compress_size, 1)
        if info.file_size > (1 << 20) and ratio > limits.max_zip_ratio:
            raise UploadError(413, f"ZIP entry {name!r}: compression ratio {ratio:.0f}:1 looks like a zip bomb "
                                   f"(the limit is {limits.max_zip_ratio:g}:1)")
        if info.file_size > limits.max_zip_entry_bytes:
            raise UploadError(413, f"ZIP entry {name!r} unpacks to {info.file_size} bytes; the per-file limit is "
                                   f"{limits.max_zip_entry_bytes} bytes")
        total += info.file_size
        if total > limits.max_zip_uncompressed_bytes:
            raise UploadError(413, f"ZIP unpacks to more than the total limit of {limits.max_zip_uncompressed_bytes} "
                                   "bytes (zip bomb?)")
        scenes.append(m.group(1))
    if not scenes:
        raise UploadError(422, "ZIP holds no pose_sNNNNN.txt files")
    for info in infos:
        _sniff(zf, info)
    return ZipInfo(sorted(scenes), total, size)


def _sniff(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> None:
    """Decompress the start of one entry: a corrupt stream or a binary file is refused now. Headers that lie
    about the size are caught too (the stream ends early and its CRC fails); the workers' reader enforces the
    size limits on the whole entry."""
    try:
        with zf.open(info) as f:
            head = f.read(SNIFF_BYTES)
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError) as e:
        raise UploadError(422, f"ZIP entry {info.filename!r} is corrupt ({e})") from None
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as e:
        if e.start < len(head) - 4 or len(head) < SNIFF_BYTES:  # a multi-byte char cut at the edge is fine
            raise UploadError(422, f"ZIP entry {info.filename!r} is not UTF-8 text") from None


def decode_image(data: bytes, limits: Limits, what: str) -> np.ndarray:
    """``decode_photo`` without the orientation."""
    return decode_photo(data, limits, what)[0]


def decode_photo(data: bytes, limits: Limits, what: str) -> tuple[np.ndarray, int]:
    """Uploaded bytes -> (H,W,3) uint8 RGB upright (its EXIF orientation applied; a mirrored photo is refused),
    and that orientation. The header is read first, so that a decompression bomb is refused before decoding."""
    if not data:
        raise UploadError(400, f"{what}: empty file")
    if len(data) > limits.max_image_bytes:
        raise UploadError(413, f"{what}: {len(data)} bytes; the limit is {limits.max_image_bytes}")
    w, h = _image_size(data, what)
    if w * h > limits.max_image_pixels:
        raise UploadError(413, f"{what}: {w}x{h} pixels; the limit is {limits.max_image_pixels} pixels")
    orientation = photo_orientation(data, what)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None or img.shape[0] != h or img.shape[1] != w:
        raise UploadError(422, f"{what}: corrupt or unsupported image (JPEG or PNG expected)")
    return orient_pixels(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), orientation), orientation


def decode_depth(data: bytes, limits: Limits, shape: tuple[int, int], what: str = "depth") -> np.ndarray:
    """A single-channel uint16 millimetre PNG of the image's size -> float32 metres. Anything else (a JPEG, an
    8-bit or colour PNG) is refused: read as millimetres it would be a silently wrong metric scale."""
    if len(data) > limits.max_image_bytes:
        raise UploadError(413, f"{what}: {len(data)} bytes; the limit is {limits.max_image_bytes}")
    w, h = _image_size(data, what, formats=("PNG",))
    if (h, w) != tuple(shape):
        raise UploadError(422, f"{what}: {w}x{h} but the image is {shape[1]}x{shape[0]}; they must match")
    d = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if d is None or d.shape[:2] != (h, w):
        raise UploadError(422, f"{what}: corrupt PNG")
    if d.ndim != 2 or d.dtype != np.uint16:
        got = f"{8 * d.dtype.itemsize}-bit, {1 if d.ndim == 2 else d.shape[2]} channel(s)"
        raise UploadError(422, f"{what}: must be a single-channel 16-bit PNG (uint16 millimetres); got {got}")
    return d.astype(np.float32) / 1000.0


def check_name(name: str | None, max_chars: int, what: str = "name") -> str:
    """A display name: trimmed, bounded, without control or invisible formatting characters (U+202E and other
    bidirectional overrides would let a name display as something it is not)."""
    name = (name or "").strip()
    if len(name) > max_chars:
        raise UploadError(422, f"{what} is longer than {max_chars} characters")
    bad = next((c for c in name if unicodedata.category(c) in ("Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp")), None)
    if bad is not None:
        raise UploadError(422, f"{what} contains a control or formatting character (U+{ord(bad):04X})")
    return name


def _image_size(data: bytes, what: str, formats: tuple[str, ...] = ("JPEG", "PNG")) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as im:
            if im.format not in formats:
                raise UploadError(422, f"{what}: {im.format} images are not accepted ({' or '.join(formats)} "
                                       "expected)")
            return im.size
    except UploadError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise UploadError(422, f"{what}: not a readable image ({type(e).__name__})") from None
    except Image.DecompressionBombError:
        raise UploadError(413, f"{what}: image too large (decompression bomb)") from None


def parse_intrinsics(values: dict, width: int, height: int, what: str = "intrinsics") -> dict:
    """fx, fy, cx, cy (pixels of the uploaded image) -> a checked dict with the image's width and height."""
    out = {}
    for k in ("fx", "fy", "cx", "cy"):
        v = values.get(k)
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise UploadError(422, f"{what}: {k} must be a number, got {v!r}") from None
        if not math.isfinite(f):
            raise UploadError(422, f"{what}: {k} must be finite")
        out[k] = f
    fmin, fmax = MIN_FOCAL_FACTOR * max(width, height), MAX_FOCAL_FACTOR * max(width, height)
    if not (fmin <= out["fx"] < fmax and fmin <= out["fy"] < fmax):
        raise UploadError(422, f"{what}: focal lengths must lie between {fmin:g} and {fmax:g} px "
                               f"({MIN_FOCAL_FACTOR} to {MAX_FOCAL_FACTOR} x the image's longest side, {max(width, height)} "
                               f"px; in pixels, not millimetres); got fx={out['fx']:g}, fy={out['fy']:g}")
    if not (0 <= out["cx"] <= width and 0 <= out["cy"] <= height):
        raise UploadError(422, f"{what}: principal point ({out['cx']:g}, {out['cy']:g}) must lie inside the "
                               f"{width}x{height} image")
    out.update(width=int(width), height=int(height))
    return out


#: How far a photo of an anchor may be from the anchor's first camera (metres): one place, not a city.
MAX_POSE_METRES = 1000.0


def parse_pose(text: str | None, what: str = "pose") -> list[float]:
    """``"qw qx qy qz tx ty tz"`` (world-to-camera, Map-free ``poses.txt`` order; commas allowed) -> the seven
    numbers with the quaternion normalised. A quaternion far from unit length or a translation beyond
    ``MAX_POSE_METRES`` is refused: it almost always means the values are in another order or unit."""
    parts = (text or "").replace(",", " ").split()
    if len(parts) != 7:
        raise UploadError(422, f"{what}: expected 7 numbers 'qw qx qy qz tx ty tz' (world-to-camera from the "
                               f"anchor's first photo, metres), got {len(parts)}")
    try:
        v = [float(p) for p in parts]
    except ValueError:
        raise UploadError(422, f"{what}: not a number in {text.strip()[:80]!r}") from None
    if not all(math.isfinite(x) for x in v):
        raise UploadError(422, f"{what}: every value must be finite")
    n = math.sqrt(sum(x * x for x in v[:4]))
    if abs(n - 1.0) > 0.01:
        raise UploadError(422, f"{what}: the quaternion (qw qx qy qz) must have unit length, got {n:.4g}")
    if math.sqrt(sum(x * x for x in v[4:])) > MAX_POSE_METRES:
        raise UploadError(422, f"{what}: the translation is over {MAX_POSE_METRES:g} m from the anchor's first "
                               "photo (metres expected)")
    return [x / n for x in v[:4]] + v[4:]
