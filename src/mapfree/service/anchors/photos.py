"""An uploaded photo read once: decoded, turned upright by its EXIF orientation, with the intrinsics and depth the
client gave for the stored pixel grid turned with it; then brought to the working size (``worksize.py``). Every
endpoint that takes a photo reads it here, so that each is decoded at its full size exactly once."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...data.orientation import displayed_size, orient_intrinsics, orient_pixels
from ..config import Limits
from .decode import decode_depth, decode_photo, parse_intrinsics
from .localizers import Photo, intrinsics_of
from .worksize import fit_image

_FIELDS = ("fx", "fy", "cx", "cy")


def stored_shape(upright: np.ndarray, orientation: int) -> tuple[int, int]:
    """(rows, cols) of the stored grid of an upright photo: what the client's intrinsics and depth describe."""
    w, h = displayed_size(upright.shape[1], upright.shape[0], orientation)  # a quarter turn is its own size swap
    return h, w


def upright_intrinsics(intr: dict, orientation: int) -> dict:
    """Checked intrinsics of the stored grid (``parse_intrinsics``) -> those of the upright photo."""
    if orientation == 1:
        return intr
    k = orient_intrinsics(intrinsics_of(intr), orientation)
    return {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "width": k.width, "height": k.height}


@dataclass
class UprightPhoto:
    """A decoded upload at its full size, upright: RGB pixels, checked intrinsics (a dict, as stored) and the
    EXIF orientation the file had."""

    image: np.ndarray
    intrinsics: dict
    orientation: int

    @property
    def stored_shape(self) -> tuple[int, int]:
        """(rows, cols) of the file's stored grid: what the client's intrinsics and depth describe."""
        return stored_shape(self.image, self.orientation)

    def depth(self, data: bytes, lim: Limits, what: str = "depth") -> np.ndarray:
        """A depth map uploaded for the stored grid (``decode_depth``), turned upright like the photo."""
        return orient_pixels(decode_depth(data, lim, self.stored_shape, what), self.orientation)

    def fit(self, max_side: int, depth: np.ndarray | None = None) -> Photo:
        """The photo (and its upright ``depth``) at the working size: what a method sees."""
        image, K, d = fit_image(self.image, intrinsics_of(self.intrinsics), depth, max_side)
        return Photo(image, K, d)


def read_photo(data: bytes, lim: Limits, fields: dict, what: str = "image", intr_what: str = "intrinsics",
               guess: bool = False) -> UprightPhoto:
    """Uploaded bytes and the client's ``fx fy cx cy`` for the stored grid -> the upright photo and its checked
    intrinsics. ``guess``: all four left empty means focal 0.8 x the long side, centred (the web form)."""
    image, orientation = decode_photo(data, lim, what)
    h, w = stored_shape(image, orientation)
    if guess and all(str(fields.get(k, "")).strip() == "" for k in _FIELDS):
        f = 0.8 * max(w, h)
        fields = {"fx": f, "fy": f, "cx": (w - 1) / 2, "cy": (h - 1) / 2}
    return UprightPhoto(image, upright_intrinsics(parse_intrinsics(fields, w, h, intr_what), orientation), orientation)
