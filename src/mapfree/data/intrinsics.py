"""Intrinsics of a photo nobody calibrated: from its EXIF tags, or a stated default field of view.

One convention for the whole project (``mapfree build`` reads scans with it, ``mapfree relocalize``, ``mapfree
match`` and the relocalization service read single photos with it): the 35 mm-equivalent focal length
``FocalLengthIn35mmFilm`` refers to the **long side** of a 36 x 24 mm full frame, so

    f_px = f35 / 36 mm x max(W, H)

for a photo of W x H pixels; without it, ``FocalLength`` (mm) with the sensor's pixel density
``FocalPlaneXResolution`` / ``FocalPlaneResolutionUnit`` gives ``f_px = FocalLength x pixels per mm``, scaled by the
stored width over ``PixelXDimension`` when the photo was resized after capture. The principal point is the
image centre ``((W - 1) / 2, (H - 1) / 2)`` (pixel centres at integers). The focal is found for the stored pixel
grid and turned with it by the EXIF orientation, so the intrinsics are those of the upright photo every reader
of ours returns.

Without any of these tags the default camera has a 64° field of view across the long side (a 28.8 mm-equivalent
lens, ``f = 0.8 x max(W, H)``: phones' main cameras are 24-28 mm-equivalent); a metric pose then rests on it.
"""

from __future__ import annotations

import io
import math
import os
from dataclasses import dataclass

from ..geometry import Intrinsics
from .orientation import ROTATIONS, orient_intrinsics

__all__ = [
    "FULL_FRAME_LONG_SIDE_MM",
    "DEFAULT_FOCAL_35MM",
    "EXIF_FOCAL_RANGE",
    "SOURCES",
    "ResolvedIntrinsics",
    "focal_from_35mm",
    "default_fov_deg",
    "exif_focal",
    "exif_intrinsics",
    "default_intrinsics",
    "check_principal_point",
]

#: The long side of a 36 x 24 mm full frame, the reference of 35 mm-equivalent focal lengths.
FULL_FRAME_LONG_SIDE_MM = 36.0
#: The default camera: a 28.8 mm-equivalent lens, f = 0.8 x the long side, 64° across it.
DEFAULT_FOCAL_35MM = 28.8
#: Where a photo's intrinsics came from, in the order they are looked for.
SOURCES = ("given", "exif", "estimated", "default")
#: EXIF focal lengths outside this range (times the long side: 3.6-3600 mm-equivalent) are junk tags, skipped.
EXIF_FOCAL_RANGE = (0.1, 100.0)
#: The principal point may lie this far outside the image (in image sizes) before it is refused as a typo.
PRINCIPAL_POINT_MARGIN = 0.5

# EXIF tags (Exif sub-IFD, 0x8769)
_EXIF_IFD = 0x8769
_ORIENTATION = 0x0112
_FOCAL_LENGTH = 0x920A
_FOCAL_35MM = 0xA405
_FOCAL_PLANE_X_RES = 0xA20E
_FOCAL_PLANE_UNIT = 0xA210
_PIXEL_X_DIMENSION = 0xA002
#: FocalPlaneResolutionUnit -> millimetres per unit (2: inch, the EXIF default; 3: cm; 4: mm; 5: µm).
_UNIT_MM = {1: 25.4, 2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


@dataclass(frozen=True)
class ResolvedIntrinsics:
    """A photo's intrinsics and where they came from.

    Attributes:
        intrinsics: Of the upright photo, at its full size.
        source: ``given``, ``exif``, ``estimated`` or ``default`` (``SOURCES``).
        detail: What they were found from, for people (``FocalLengthIn35mmFilm 26 mm``).
    """

    intrinsics: Intrinsics
    source: str
    detail: str = ""

    def to_dict(self) -> dict:
        """JSON-ready: ``source``, ``fx fy cx cy`` (pixels), ``width height`` and ``detail``."""
        k = self.intrinsics
        return {
            "source": self.source,
            "fx": k.fx,
            "fy": k.fy,
            "cx": k.cx,
            "cy": k.cy,
            "width": k.width,
            "height": k.height,
            "detail": self.detail,
        }


def focal_from_35mm(f35_mm: float, width: int, height: int) -> float:
    """Focal length in pixels of a 35 mm-equivalent focal length (the project's one convention).

    Args:
        f35_mm: 35 mm-equivalent focal length, millimetres.
        width: Image width, pixels.
        height: Image height, pixels.

    Returns:
        ``f35 / 36 mm x max(width, height)``, pixels.
    """
    return float(f35_mm) / FULL_FRAME_LONG_SIDE_MM * max(width, height)


def default_fov_deg() -> float:
    """Field of view of the default camera across the photo's long side, degrees (64.0)."""
    return math.degrees(2 * math.atan(FULL_FRAME_LONG_SIDE_MM / 2 / DEFAULT_FOCAL_35MM))


def _rational(value: object) -> float | None:
    try:
        v = float(value)  # type: ignore[arg-type]  # Pillow's IFDRational, int or float
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def exif_focal(source: bytes | os.PathLike | str) -> tuple[float, int, int, int, str] | None:
    """The focal length an image's EXIF tags give, for its stored pixel grid.

    Args:
        source: The image file, or its bytes.

    Returns:
        ``(f_px, stored width, stored height, orientation, detail)``, or None when the file has no usable focal tag
        (none, or one giving a focal outside ``EXIF_FOCAL_RANGE``) or cannot be read.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(source) if isinstance(source, (bytes, bytearray)) else source) as im:
            width, height = im.size
            exif = im.getexif()
            sub = exif.get_ifd(_EXIF_IFD)
            orientation = int(exif.get(_ORIENTATION, 1))
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, TypeError):
        return None
    lo, hi = EXIF_FOCAL_RANGE[0] * max(width, height), EXIF_FOCAL_RANGE[1] * max(width, height)
    f35 = _rational(sub.get(_FOCAL_35MM))
    if f35 is not None and lo <= (f := focal_from_35mm(f35, width, height)) < hi:
        return f, width, height, orientation, f"FocalLengthIn35mmFilm {f35:g} mm"
    f_mm, density = _rational(sub.get(_FOCAL_LENGTH)), _rational(sub.get(_FOCAL_PLANE_X_RES))
    try:
        unit = _UNIT_MM.get(int(sub.get(_FOCAL_PLANE_UNIT, 2) or 2))
    except (TypeError, ValueError):
        unit = None
    if f_mm is None or density is None or unit is None:
        return None
    f = f_mm * density / unit  # FocalPlaneXResolution: pixels per unit along the width the camera wrote
    captured = _rational(sub.get(_PIXEL_X_DIMENSION))
    if captured is not None and captured not in (width, height):  # resized since capture: the density was
        f *= width / captured  # for the width the camera wrote
    if not lo <= f < hi:
        return None
    return f, width, height, orientation, f"FocalLength {f_mm:g} mm, FocalPlaneXResolution {density:g} per unit"


def exif_intrinsics(source: bytes | os.PathLike | str) -> Intrinsics | None:
    """Pinhole intrinsics from a photo's EXIF focal length (principal point at the centre), for the photo as
    displayed (its EXIF orientation applied, as every reader of ours does).

    Args:
        source: The image file, or its bytes.

    Returns:
        The intrinsics of the upright photo at its full size; None without a usable focal tag, or for a mirrored
        or invalid orientation.
    """
    found = exif_focal(source)
    if found is None or found[3] not in ROTATIONS:
        return None
    f, width, height, orientation, _ = found
    return orient_intrinsics(Intrinsics(f, f, (width - 1) / 2, (height - 1) / 2, width, height), orientation)


def default_intrinsics(width: int, height: int) -> Intrinsics:
    """The default camera for a photo of this (upright) size: ``DEFAULT_FOCAL_35MM``, centred.

    Args:
        width: Image width, pixels.
        height: Image height, pixels.

    Returns:
        ``f = 0.8 x max(width, height)``, principal point at the centre.
    """
    f = focal_from_35mm(DEFAULT_FOCAL_35MM, width, height)
    return Intrinsics(f, f, (width - 1) / 2, (height - 1) / 2, int(width), int(height))


def check_principal_point(cx: float, cy: float, width: int, height: int, what: str) -> None:
    """Refuse a principal point far outside the image (a typo, or intrinsics of another photo).

    Args:
        cx: Principal point x, pixels.
        cy: Principal point y, pixels.
        width: Image width, pixels.
        height: Image height, pixels.
        what: The option or field, named in the error.

    Raises:
        ValueError: ``cx`` outside ``[-0.5 W, 1.5 W]`` or ``cy`` outside ``[-0.5 H, 1.5 H]``.
    """
    m = PRINCIPAL_POINT_MARGIN
    for name, v, size in (("cx", cx, width), ("cy", cy, height)):
        if not -m * size <= v <= (1 + m) * size:
            raise ValueError(
                f"{what}: principal point {name} = {v:g} is far outside the {width}x{height} image "
                f"(allowed {-m * size:g} to {(1 + m) * size:g}; the image centre is {(size - 1) / 2:g})"
            )
