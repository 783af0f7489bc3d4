"""Photos at the size the methods work at: a decoded upload is downscaled (long side at most ``max_side``)
before any method sees it, so that what a request allocates is bounded by the work, not by the upload (SIFT,
for one, upsamples its input: a 4096x4096 photo made it allocate gigabytes). Intrinsics follow the
half-pixel-centre rule and depth maps are resized nearest-neighbour, so poses stay metric and unchanged."""

from __future__ import annotations

from dataclasses import replace
from typing import TypeVar

import cv2
import numpy as np

from ...geometry import Intrinsics
from ...relocalize import View
from ..config import Limits

#: The default long side (``Limits.work_max_side``).
DEFAULT_MAX_SIDE = Limits.work_max_side


def work_scale(width: int, height: int, max_side: int) -> float:
    """The factor that brings the long side down to ``max_side`` (1.0 when it fits already, or no cap)."""
    long = max(width, height)
    return 1.0 if max_side <= 0 or long <= max_side else max_side / long


def fit_image(
    image: np.ndarray, K: Intrinsics, depth: np.ndarray | None, max_side: int
) -> tuple[np.ndarray, Intrinsics, np.ndarray | None]:
    """``(image, K, depth)`` with the long side at most ``max_side`` -> the same, downscaled (area filter for
    the pixels, nearest neighbour for depth so that holes stay holes); unchanged when it fits."""
    h, w = image.shape[:2]
    s = work_scale(w, h, max_side)
    if s == 1.0:
        return image, K, depth
    nw, nh = max(1, round(w * s)), max(1, round(h * s))
    small = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA)
    K2 = K.resized(nw, nh)  # per-axis factors nw/w, nh/h: the pixel grid actually produced
    d2 = None if depth is None else cv2.resize(np.asarray(depth, np.float32), (nw, nh), interpolation=cv2.INTER_NEAREST)
    return small, K2, d2


ViewT = TypeVar("ViewT", bound=View)


def fit_photo(photo: ViewT, max_side: int) -> ViewT:
    """A ``View`` (``image``, ``intrinsics``, ``depth``) at the working size: the one place photos are brought
    to it, for uploads, stored photos and the localizers alike (unchanged when it fits)."""
    image, K, depth = fit_image(photo.image, photo.intrinsics, photo.depth, max_side)
    return photo if image is photo.image else replace(photo, image=image, intrinsics=K, depth=depth)
