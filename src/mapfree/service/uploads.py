"""Hostile-input gates for uploads: ZIP submissions and images. Each failure is an ``UploadError`` carrying the
HTTP status and a message that names the problem (never a 500)."""

from __future__ import annotations

import io
import math
import re
import zipfile
import zlib
from dataclasses import dataclass

import cv2
import numpy as np

from .config import Limits

ENTRY_RE = re.compile(r"^pose_(s\d{5})\.txt$")


class UploadError(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


@dataclass
class ZipInfo:
    scenes: list[str]
    uncompressed_bytes: int


def check_submission_zip(data: bytes, limits: Limits, split: str, known_scenes: set[str] | None) -> ZipInfo:
    """Structure checks on an uploaded submission before it is stored: a real ZIP, few entries, bounded
    uncompressed size and ratio (zip bombs), flat ``pose_sNNNNN.txt`` names only (no traversal), known scenes,
    UTF-8 text. Reads every entry through a bounded reader, so lying headers cannot inflate memory."""
    if len(data) > limits.max_submission_bytes:
        raise UploadError(413, f"submission is {len(data)} bytes; the limit is {limits.max_submission_bytes}")
    if not data:
        raise UploadError(400, "submission file is empty")
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
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
            raise UploadError(413, f"ZIP entry {name!r}: compression ratio {ratio:.0f}:1 looks like a zip bomb")
        total += info.file_size
        if total > limits.max_zip_uncompressed_bytes:
            raise UploadError(413, f"ZIP expands to more than {limits.max_zip_uncompressed_bytes} bytes (zip bomb?)")
        scenes.append(m.group(1))
    if not scenes:
        raise UploadError(422, "ZIP holds no pose_sNNNNN.txt files")
    # Headers can lie: read each entry with a hard cap, which also checks CRCs and text encoding.
    real = 0
    for info in infos:
        try:
            with zf.open(info) as f:
                while chunk := f.read(1 << 16):
                    real += len(chunk)
                    if real > limits.max_zip_uncompressed_bytes:
                        raise UploadError(413, f"ZIP entry {info.filename!r} expands beyond the declared size "
                                               f"(limit {limits.max_zip_uncompressed_bytes} bytes)")
                    try:
                        chunk.decode("utf-8")
                    except UnicodeDecodeError as e:
                        if e.start < len(chunk) - 4:  # a split multi-byte char at the chunk edge is fine
                            raise UploadError(422, f"ZIP entry {info.filename!r} is not UTF-8 text") from None
        except UploadError:
            raise
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError) as e:
            raise UploadError(422, f"ZIP entry {info.filename!r} is corrupt ({e})") from None
    return ZipInfo(sorted(scenes), real)


def decode_image(data: bytes, limits: Limits, what: str) -> np.ndarray:
    """Uploaded bytes -> (H,W,3) uint8 RGB. The header is read first, so that a decompression bomb is refused
    before decoding."""
    if not data:
        raise UploadError(400, f"{what}: empty file")
    if len(data) > limits.max_image_bytes:
        raise UploadError(413, f"{what}: {len(data)} bytes; the limit is {limits.max_image_bytes}")
    w, h = _image_size(data, what)
    if w * h > limits.max_image_pixels:
        raise UploadError(413, f"{what}: {w}x{h} pixels; the limit is {limits.max_image_pixels} pixels")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None or img.shape[0] != h or img.shape[1] != w:
        raise UploadError(422, f"{what}: corrupt or unsupported image (JPEG or PNG expected)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def decode_depth(data: bytes, limits: Limits, shape: tuple[int, int], what: str = "depth") -> np.ndarray:
    """A uint16 millimetre PNG of the image's size -> float32 metres."""
    if len(data) > limits.max_image_bytes:
        raise UploadError(413, f"{what}: {len(data)} bytes; the limit is {limits.max_image_bytes}")
    w, h = _image_size(data, what)
    if (h, w) != tuple(shape):
        raise UploadError(422, f"{what}: {w}x{h} but the image is {shape[1]}x{shape[0]}; they must match")
    d = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_ANYDEPTH)
    if d is None or d.ndim != 2:
        raise UploadError(422, f"{what}: not a single-channel depth PNG (uint16 millimetres)")
    return d.astype(np.float32) / 1000.0


def _image_size(data: bytes, what: str) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as im:
            if im.format not in ("JPEG", "PNG"):
                raise UploadError(422, f"{what}: {im.format} images are not accepted (JPEG or PNG expected)")
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
    if out["fx"] <= 0 or out["fy"] <= 0:
        raise UploadError(422, f"{what}: focal lengths must be positive")
    if not (-width <= out["cx"] <= 2 * width and -height <= out["cy"] <= 2 * height):
        raise UploadError(422, f"{what}: principal point ({out['cx']}, {out['cy']}) is far outside the image")
    out.update(width=int(width), height=int(height))
    return out
