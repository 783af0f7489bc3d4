"""Uploaded photos, depth maps, intrinsics and poses checked and decoded: each failure is an ``UploadError`` naming the
problem (never a 500)."""

from __future__ import annotations

import io
import math
from dataclasses import asdict, astuple, dataclass

import cv2
import numpy as np

from ...data.orientation import orient_pixels
from ...geometry import Intrinsics
from ..config import Limits
from ..inputs import UploadError
from .exif import photo_orientation

#: A focal length beyond this many times the image's longest side is not a camera (a ~0.6 degree field of view).
MAX_FOCAL_FACTOR = 100


#: Smallest focal length, per pixel of the longest side: 0.1 is a 157-degree field of view across it, past any
#: pinhole lens (fisheyes need another camera model); 0.5 px or 1e-300 are unit mistakes, not cameras.
MIN_FOCAL_FACTOR = 0.1


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


def _image_size(data: bytes, what: str, formats: tuple[str, ...] = ("JPEG", "PNG")) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as im:
            if im.format not in formats:
                raise UploadError(422, f"{what}: {im.format} images are not accepted ({' or '.join(formats)} expected)")
            return im.size
    except UploadError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise UploadError(422, f"{what}: not a readable image ({type(e).__name__})") from None
    except Image.DecompressionBombError:
        raise UploadError(413, f"{what}: image too large (decompression bomb)") from None


@dataclass(frozen=True)
class IntrinsicsForm:
    """A request's four intrinsics fields as sent, in pixels of the uploaded image's stored grid: numbers (the
    API's form fields), text (a web page's), or None (left out). They become an ``Intrinsics`` once the photo's
    size is known (``parse_intrinsics``); all four left out, the photo's EXIF or the default camera is taken
    (``photos.read_upload``)."""

    fx: str | float | None = None
    fy: str | float | None = None
    cx: str | float | None = None
    cy: str | float | None = None

    def empty(self) -> bool:
        """Whether all four were left out (None, or empty text)."""
        return all(v is None or str(v).strip() == "" for v in astuple(self))


def parse_intrinsics(values: IntrinsicsForm, width: int, height: int, what: str = "intrinsics") -> Intrinsics:
    """fx, fy, cx, cy as sent (pixels of the uploaded image) -> checked ``Intrinsics`` of a ``width`` x ``height``
    image; each problem an ``UploadError`` naming ``what`` and the field."""
    out = {}
    for k, v in asdict(values).items():
        if v is None:
            raise UploadError(422, f"{what}: {k} must be a number, got None")
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise UploadError(422, f"{what}: {k} must be a number, got {v!r}") from None
        if not math.isfinite(f):
            raise UploadError(422, f"{what}: {k} must be finite")
        out[k] = f
    fmin, fmax = MIN_FOCAL_FACTOR * max(width, height), MAX_FOCAL_FACTOR * max(width, height)
    if not (fmin <= out["fx"] < fmax and fmin <= out["fy"] < fmax):
        raise UploadError(
            422,
            f"{what}: focal lengths must lie between {fmin:g} and {fmax:g} px "
            f"({MIN_FOCAL_FACTOR} to {MAX_FOCAL_FACTOR} x the image's longest side, {max(width, height)} "
            f"px; in pixels, not millimetres); got fx={out['fx']:g}, fy={out['fy']:g}",
        )
    if not (0 <= out["cx"] <= width and 0 <= out["cy"] <= height):
        raise UploadError(
            422, f"{what}: principal point ({out['cx']:g}, {out['cy']:g}) must lie inside the {width}x{height} image"
        )
    return Intrinsics(out["fx"], out["fy"], out["cx"], out["cy"], int(width), int(height))


#: How far a photo of an anchor may be from the anchor's first camera (metres): one place, not a city.
MAX_POSE_METRES = 1000.0


def parse_pose(text: str | None, what: str = "pose") -> list[float]:
    """``"qw qx qy qz tx ty tz"`` (world-to-camera, Map-free ``poses.txt`` order; commas allowed) -> the seven
    numbers with the quaternion normalised. A quaternion far from unit length or a translation beyond
    ``MAX_POSE_METRES`` is refused: it almost always means the values are in another order or unit."""
    text = text or ""
    parts = text.replace(",", " ").split()
    if len(parts) != 7:
        raise UploadError(
            422,
            f"{what}: expected 7 numbers 'qw qx qy qz tx ty tz' (world-to-camera from the "
            f"anchor's first photo, metres), got {len(parts)}",
        )
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
        raise UploadError(
            422,
            f"{what}: the translation is over {MAX_POSE_METRES:g} m from the anchor's first photo (metres expected)",
        )
    return [x / n for x in v[:4]] + v[4:]
