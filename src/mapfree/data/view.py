"""One image ready for relocalization: ``View``, and ``as_view`` that makes one from whatever a localizer accepts.

A view is a dataset frame or an upload alike, upright, with the intrinsics of its upright pixels. ``ViewLike`` is
what every localizer takes as a query or a reference (``mapfree.localizer``): a ``View``, a dataset ``Frame`` or
``(image | path, intrinsics[, depth])``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..geometry import Intrinsics, Pose
from .intrinsics import ResolvedIntrinsics
from .io import read_image
from .orientation import exif_orientation, fit_intrinsics, orient_pixels
from .scene import Frame

__all__ = ["View", "ViewLike", "as_view", "as_intrinsics", "upright_view"]


@dataclass
class View:
    """One image ready for relocalization.

    Attributes:
        image: (H, W, 3) uint8 RGB, upright.
        intrinsics: Of the upright pixels.
        depth: (H, W) metric depth (metres, 0 = invalid) handed over with the image, or None.
        frame: The dataset frame it was read from (its depth files are found through it), or None.
        name: For messages and journals.
        orientation: The EXIF orientation by which the frame's stored files (its intrinsics, depth maps) were
            turned upright (1: none).
        pose: World-to-camera pose when known (a mapping image that serves as a reference among K), else None.
        intrinsics_source: Where the intrinsics came from: ``given``, ``exif``, ``estimated`` or ``default``.
        intrinsics_detail: What they were found from, for people (``FocalLengthIn35mmFilm 26 mm``).
    """

    image: np.ndarray
    intrinsics: Intrinsics
    depth: np.ndarray | None = None
    frame: Frame | None = None
    name: str = ""
    orientation: int = 1
    pose: Pose | None = None
    intrinsics_source: str = "given"
    intrinsics_detail: str = ""

    @property
    def resolved(self) -> ResolvedIntrinsics:
        """The intrinsics with where they came from (``to_dict()`` is what the CLI and the service report)."""
        return ResolvedIntrinsics(self.intrinsics, self.intrinsics_source, self.intrinsics_detail)


#: What ``as_view`` accepts: a ``View``, a ``Frame`` or ``(image | path, Intrinsics | K | (fx, fy, cx, cy)[, depth])``.
ViewLike = View | Frame | tuple


def _read_image_any(image: Any) -> tuple[np.ndarray, Path | None]:
    if isinstance(image, (str, os.PathLike)):
        return read_image(image), Path(image)
    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=2)
    return arr, None


def as_intrinsics(K: Any, image: np.ndarray) -> Intrinsics:
    """Intrinsics given as an ``Intrinsics``, a 3x3 K or ``(fx, fy, cx, cy)`` in pixels, for ``image``'s size.

    Raises:
        ValueError: Intrinsics of another shape.
    """
    if isinstance(K, Intrinsics):
        return K
    K = np.asarray(K, dtype=np.float64)
    h, w = image.shape[:2]
    if K.shape == (3, 3):
        return Intrinsics.from_K(K, w, h)
    if K.shape == (4,):
        fx, fy, cx, cy = map(float, K)
        return Intrinsics(fx, fy, cx, cy, w, h)
    raise ValueError(f"intrinsics must be an Intrinsics, a 3x3 K or (fx, fy, cx, cy), got shape {K.shape}")


def as_view(x: ViewLike) -> View:
    """A ``View`` of a frame or an image with its intrinsics.

    Args:
        x: A ``View`` (returned as is), a ``Frame``, or ``(image, intrinsics[, depth])`` with the image an
            (H, W, 3) uint8 RGB array or a path, the intrinsics an ``Intrinsics``, a 3x3 K or ``(fx, fy, cx, cy)``
            in pixels, and the depth an (H, W) map in metres. A path's EXIF orientation turns the pixels upright,
            and the intrinsics and depth given for its stored grid with them.

    Returns:
        The view.

    Raises:
        TypeError: ``x`` is none of these.
        ValueError: Intrinsics of another shape.
    """
    if isinstance(x, View):
        return x
    if isinstance(x, Frame):
        image = x.image()
        K, _, turned = _upright(image, x.intrinsics, x.image_path, None)
        return View(image, K, None, x, x.name, turned)
    if isinstance(x, tuple) and len(x) in (2, 3):
        image, path = _read_image_any(x[0])
        depth = None if len(x) == 2 or x[2] is None else np.asarray(x[2], dtype=np.float32)
        return upright_view(image, path, as_intrinsics(x[1], image), depth)
    raise TypeError(f"expected a Frame, a View or (image, intrinsics[, depth]); got {type(x).__name__}")


def upright_view(
    image: np.ndarray,
    path: Path | None,
    K0: Intrinsics,
    depth: np.ndarray | None,
    source: str = "given",
    detail: str = "",
) -> View:
    """The view of an image (read from ``path``, or None), ``K0`` and ``depth`` given for its stored pixel grid:
    the EXIF orientation of ``path`` turns them with the pixels; ``source`` and ``detail`` say where ``K0`` came
    from."""
    K, depth, turned = _upright(image, K0, path, depth)
    frame = Frame(path.name, path, K0) if path is not None else None  # its files keep the stored grid's K
    return View(image, K, depth, frame, path.name if path is not None else "", turned, None, source, detail)


def _upright(
    image: np.ndarray, K: Intrinsics, path: Path | None, depth: np.ndarray | None
) -> tuple[Intrinsics, np.ndarray | None, int]:
    """Intrinsics and depth for the upright pixels of an image file: given for its stored grid (a tagged phone
    photo), they are turned with it. Returns them and the orientation applied to them (1: none)."""
    o = exif_orientation(path) if path is not None else 1
    if o == 1:
        return K, depth, 1
    h, w = image.shape[:2]
    K2 = fit_intrinsics(K, w, h, o, str(path))
    if K2 is K:
        return K, depth, 1
    return K2, (orient_pixels(depth, o) if depth is not None else None), o
