"""EXIF orientation: turning a photo upright and its intrinsics (and depth map) with it.

Phones store the sensor's pixel grid and a tag saying how to turn it for display. We always work on the photo as
displayed (upright), so that learned matchers and regressors see what they were trained on, and a pose refers to
the upright camera. Intrinsics and depth maps sized like the stored grid (e.g. from the phone's calibration) are
turned with the pixels. Pixel centres are at integer coordinates (the half-pixel convention of ``Intrinsics``), so
flipping a width-W axis maps ``u -> W - 1 - u``. Mirrored orientations (2, 4, 5, 7) have no pinhole camera that
takes the mirrored picture, so they are refused.
"""

from __future__ import annotations

import io
import os

import numpy as np

from ..geometry import Intrinsics

__all__ = [
    "UPRIGHT",
    "ROTATIONS",
    "OrientationError",
    "check_orientation",
    "exif_orientation",
    "orient_pixels",
    "orient_intrinsics",
    "camera_rotation",
    "displayed_size",
    "fit_intrinsics",
]

UPRIGHT = 1
#: Orientations we handle -> quarter turns clockwise that make the stored grid upright.
ROTATIONS = {1: 0, 6: 1, 3: 2, 8: 3}
_MIRRORED = {2, 4, 5, 7}
_EXIF_ORIENTATION = 0x0112


class OrientationError(ValueError):
    """A photo whose EXIF orientation we cannot honour (mirrored, or not 1-8)."""


def check_orientation(orientation: int, what: str = "image") -> int:
    """Accept an EXIF orientation we handle (1, 3, 6, 8), refuse the others in one line.

    Args:
        orientation: The EXIF orientation tag.
        what: The photo, named in the error.

    Returns:
        ``orientation``.

    Raises:
        OrientationError: A mirrored orientation (2, 4, 5, 7) or one outside 1-8.
    """
    if orientation in ROTATIONS:
        return orientation
    if orientation in _MIRRORED:
        raise OrientationError(
            f"{what}: EXIF orientation {orientation} is a mirrored photo, which no pinhole "
            "camera takes; re-save it unmirrored (orientations 1, 3, 6 and 8 are supported)"
        )
    raise OrientationError(f"{what}: invalid EXIF orientation {orientation} (1-8 expected)")


def exif_orientation(source: bytes | os.PathLike | str) -> int:
    """The EXIF orientation tag of an image.

    Args:
        source: The image file, or its bytes.

    Returns:
        The tag; 1 (upright) when there is none or it cannot be read.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(source) if isinstance(source, (bytes, bytearray)) else source) as im:
            value = im.getexif().get(_EXIF_ORIENTATION, UPRIGHT)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        return UPRIGHT
    try:
        return int(value)
    except (TypeError, ValueError):
        return UPRIGHT


def orient_pixels(arr: np.ndarray, orientation: int) -> np.ndarray:
    """Turn a stored pixel grid (an image or a depth map) upright.

    Args:
        arr: (H, W) or (H, W, C) grid as stored.
        orientation: The file's EXIF orientation.

    Returns:
        The upright grid; ``arr`` itself when nothing changes.

    Raises:
        OrientationError: A mirrored or invalid orientation.
    """
    k = ROTATIONS[check_orientation(orientation)]
    return np.ascontiguousarray(np.rot90(arr, -k)) if k else arr  # rot90 turns counter-clockwise


def displayed_size(width: int, height: int, orientation: int) -> tuple[int, int]:
    """Size of a stored grid once turned upright.

    Args:
        width: Stored width, pixels.
        height: Stored height, pixels.
        orientation: The file's EXIF orientation.

    Returns:
        (width, height) of the upright photo.

    Raises:
        OrientationError: A mirrored or invalid orientation.
    """
    return (height, width) if ROTATIONS[check_orientation(orientation)] % 2 else (width, height)


def orient_intrinsics(K: Intrinsics, orientation: int) -> Intrinsics:
    """Turn intrinsics of the stored grid into those of the upright photo.

    A quarter turn swaps the axes: the new x is the old y, read from the far edge for a clockwise turn.

    Args:
        K: Intrinsics of the stored grid.
        orientation: The file's EXIF orientation.

    Returns:
        Intrinsics of the upright photo.

    Raises:
        OrientationError: A mirrored or invalid orientation.
    """
    k = ROTATIONS[check_orientation(orientation)]
    W, H = K.width, K.height
    if k == 0:
        return K
    if k == 1:  # clockwise: u' = H-1-v, v' = u
        return Intrinsics(K.fy, K.fx, H - 1 - K.cy, K.cx, H, W)
    if k == 2:  # half turn: u' = W-1-u, v' = H-1-v
        return Intrinsics(K.fx, K.fy, W - 1 - K.cx, H - 1 - K.cy, W, H)
    return Intrinsics(K.fy, K.fx, K.cy, W - 1 - K.cx, H, W)  # counter-clockwise: u' = v, v' = W-1-u


def camera_rotation(orientation: int) -> np.ndarray:
    """Rotation from the stored camera to the upright one, about the optical axis.

    A world-to-camera pose of the stored camera becomes ``R @ pose`` for the upright camera.

    Args:
        orientation: The file's EXIF orientation.

    Returns:
        (3, 3) R with ``X_upright = R X_stored`` in camera coordinates.

    Raises:
        OrientationError: A mirrored or invalid orientation.
    """
    k = ROTATIONS[check_orientation(orientation)]
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][k]  # cos, sin of k quarter turns
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)


def fit_intrinsics(K: Intrinsics, width: int, height: int, orientation: int, what: str = "image") -> Intrinsics:
    """Intrinsics for an upright photo, whether they were given for the stored grid or for the upright photo.

    ``K`` is turned when it is sized like the stored grid, kept when sized like the upright photo only (where
    both sizes agree, a half turn or a square photo, the stored grid's is assumed, as phone calibrations give it).

    Args:
        K: The given intrinsics.
        width: Width of the upright photo, pixels.
        height: Height of the upright photo, pixels.
        orientation: The file's EXIF orientation.
        what: The photo, named in errors.

    Returns:
        Intrinsics of the upright photo.

    Raises:
        OrientationError: A mirrored or invalid orientation.
        ValueError: ``K`` has neither size.
    """
    k = ROTATIONS[check_orientation(orientation, what)]
    stored = (height, width) if k % 2 else (width, height)
    if (K.width, K.height) == stored:
        return orient_intrinsics(K, orientation)
    if (K.width, K.height) == (width, height):
        return K
    raise ValueError(
        f"{what}: the photo is {width}x{height} (EXIF orientation {orientation} applied) but its "
        f"intrinsics say {K.width}x{K.height}"
    )
