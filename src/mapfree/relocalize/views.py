"""What one photo is on its way through a method, and the per-query state the one-pair and the batched paths share.

``View`` is one image ready for relocalization (a dataset frame or an upload alike); ``as_view`` makes one from a
``Frame`` or ``(image | path, intrinsics[, depth])`` (both from ``mapfree.data.view``, re-exported here),
``photo_view`` / ``photo_views`` from a photo file whose intrinsics may be unknown (given, else EXIF, else the
method's estimate, else the default camera). ``Anchor`` is a prepared reference, ``PreparedQuery`` a query after its
reference-independent stage. ``fit_depth`` and ``view_depth`` bring a depth map to a view's pixels.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np

from ..data import read_image
from ..data.intrinsics import (
    check_principal_point,
    default_fov_deg,
    default_intrinsics,
    exif_focal,
)
from ..data.io import same_aspect
from ..data.orientation import displayed_size, exif_orientation, orient_pixels
from ..data.view import View, ViewLike, as_intrinsics, as_view, upright_view
from ..depth.base import DepthSource, FileDepthSource, NetworkDepthSource, PairDepthSource
from ..geometry import Intrinsics
from ..localizer import error_reason
from ..matching.base import Features, FocalEstimator, Matcher

__all__ = [
    "View",
    "ViewLike",
    "as_view",
    "photo_view",
    "photo_views",
    "default_warning",
    "Anchor",
    "PreparedQuery",
    "fit_depth",
    "view_depth",
    "error_reason",
    "ahead",
]


def _centred(f: float, width: int, height: int) -> Intrinsics:
    return Intrinsics(f, f, (width - 1) / 2, (height - 1) / 2, width, height)


def _resolve(
    image: np.ndarray, path: Path, given: Any, matcher: Matcher | None, other: np.ndarray | None, what: str
) -> tuple[Intrinsics, str, str]:
    """``(K of the stored grid or of the upright photo, source, detail)`` of one photo, in the documented order."""
    h, w = image.shape[:2]
    if given is not None:
        K = as_intrinsics(given, image)
        check_principal_point(K.cx, K.cy, K.width, K.height, what)
        return K, "given", ""
    sw, sh = displayed_size(w, h, exif_orientation(path))  # the stored grid: a quarter turn is its own inverse
    found = exif_focal(path)
    if found is not None:
        return _centred(found[0], sw, sh), "exif", found[4]
    if isinstance(matcher, FocalEstimator):  # the capability is declared by the matcher's class
        f = matcher.estimate_focal(image, other)
        if f is not None:  # of the upright photo, centred: the same focal for the stored grid
            return (
                _centred(f, sw, sh),
                "estimated",
                f"the method's pointmap: {2 * np.degrees(np.arctan(max(w, h) / 2 / f)):.1f}° across the long side",
            )
    K = default_intrinsics(sw, sh)
    return K, "default", f"{default_fov_deg():.0f}° across the long side, f = {K.fx:g} px"


def photo_view(
    path: str | os.PathLike,
    intrinsics: Any = None,
    depth: np.ndarray | None = None,
    matcher: Matcher | None = None,
    other: np.ndarray | None = None,
    what: str | None = None,
) -> View:
    """A ``View`` of a photo file, its intrinsics given or found.

    The intrinsics are, in this order: ``intrinsics`` when given (for the stored pixel grid or the upright photo,
    as ``as_view`` takes them); the photo's EXIF focal length (``mapfree.data.intrinsics``: 35 mm-equivalent, or
    focal length with the sensor's pixel density); the focal of the ``matcher``'s pointmap when it declares
    that it estimates one (``FocalEstimator``: MASt3R, DUSt3R); the default
    camera (64° across the long side). The principal point of the last three is the image centre, and the
    EXIF orientation turns them with the pixels. ``View.intrinsics_source`` says which it was.

    Args:
        path: The photo (JPEG or PNG).
        intrinsics: An ``Intrinsics``, a 3x3 K or ``(fx, fy, cx, cy)`` in pixels, or None.
        depth: (H, W) metres for the stored grid, or None.
        matcher: The method's matcher (its focal estimate is used when it is a ``FocalEstimator``), or None.
        other: The other photo of the pair, for the estimate (upright (H, W, 3) uint8 RGB); None: the photo alone.
        what: The option or field the given intrinsics came from, named in errors (default: the path).

    Returns:
        The view, upright, with ``intrinsics_source`` and ``intrinsics_detail`` set.

    Raises:
        FormatError: The file is missing or not a readable photo.
        ValueError: Given intrinsics of another size, or a principal point far outside the image.
    """
    path = Path(path)
    return _photo_view(read_image(path), path, intrinsics, depth, matcher, other, what or str(path))


def _photo_view(
    image: np.ndarray,
    path: Path,
    intrinsics: Any,
    depth: np.ndarray | None,
    matcher: Matcher | None,
    other: np.ndarray | None,
    what: str,
) -> View:
    K0, source, detail = _resolve(image, path, intrinsics, matcher, other, what)
    d = None if depth is None else np.asarray(depth, dtype=np.float32)
    return upright_view(image, path, K0, d, source, detail)


def photo_views(
    reference: str | os.PathLike,
    query: str | os.PathLike,
    intrinsics: tuple[Any, Any] = (None, None),
    depths: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
    matcher: Matcher | None = None,
    what: tuple[str | None, str | None] = (None, None),
) -> tuple[View, View]:
    """``photo_view`` of a pair: the matcher's focal estimate (when one is needed) sees each photo with the other.

    Args:
        reference: The reference photo.
        query: The query photo.
        intrinsics: Given intrinsics of each, or None.
        depths: (H, W) metres of each (for the stored grid), or None.
        matcher: The method's matcher (its focal estimate is used when it is a ``FocalEstimator``), or None.
        what: The options the given intrinsics came from, named in errors.

    Returns:
        The two views.
    """
    paths = (Path(reference), Path(query))
    images = [read_image(p) for p in paths]
    return (
        _photo_view(images[0], paths[0], intrinsics[0], depths[0], matcher, images[1], what[0] or str(paths[0])),
        _photo_view(images[1], paths[1], intrinsics[1], depths[1], matcher, images[0], what[1] or str(paths[1])),
    )


def default_warning(view: View) -> str | None:
    """The warning line for a view on the default camera (None for any other source)."""
    if view.intrinsics_source != "default":
        return None
    return (
        f"{view.name}: no intrinsics given, no focal length in its EXIF and none estimated by the method: the default "
        f"camera, {view.intrinsics_detail}; the metric scale of the pose rests on it"
    )


def fit_depth(depth: np.ndarray | None, K: Intrinsics, owned: bool = False) -> np.ndarray | None:
    """A depth map at the image's size, invalid values as 0.

    A map at another resolution of the same aspect ratio is resized (nearest neighbour: holes stay holes).

    Args:
        depth: (h, w) metres, or None.
        K: The image's intrinsics (its ``width`` and ``height``).
        owned: The caller's fresh array (read from a file or predicted just now): when it is already clean, as
            every map read from a depth PNG is, it is returned as is instead of copied.

    Returns:
        (K.height, K.width) float32 metres, NaN/inf/negative replaced by 0; None for None.

    Raises:
        ValueError: Not 2-D, or another aspect ratio than the image's.
    """
    if depth is None:
        return None
    d: np.ndarray = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth map must be 2-D, got shape {d.shape}")
    if d.shape != (K.height, K.width):
        if not same_aspect(d.shape, K.width, K.height):
            raise ValueError(
                f"depth map is {d.shape[1]}x{d.shape[0]} but the image is {K.width}x{K.height}: another "
                f"aspect ratio, so not this image's map (a map at another resolution is resized)"
            )
        d = cv2.resize(d, (K.width, K.height), interpolation=cv2.INTER_NEAREST)
    # min >= 0 and max < inf: no NaN (it would be the min), no negative, no infinity: nothing to replace.
    if (owned or d is not depth) and d.size and d.min() >= 0 and d.max() < np.inf:
        return d
    return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)


def view_depth(source: DepthSource, view: View) -> np.ndarray | None:
    """The depth map of one view, before any matching.

    The view's own map when it came with one; else, for a metric source that does not need the pair, the source's
    map of the view's frame (a stored map of an EXIF-turned photo turned with it), or a network's prediction from
    the pixels of a view without a frame.

    Args:
        source: The method's depth source.
        view: The image.

    Returns:
        (H, W) float32 metres at the view's size (0 = invalid), or None (no depth, or depth from the pair).
    """
    if view.depth is not None:
        return fit_depth(view.depth, view.intrinsics)
    if not source.metric or isinstance(source, PairDepthSource):
        return None
    if view.frame is not None:
        d = source.depth(view.frame)
        if view.orientation != 1 and d is not None and isinstance(source, FileDepthSource):
            d = orient_pixels(d, view.orientation)  # a stored map of a tagged photo: turned like its pixels
        return fit_depth(d, view.intrinsics, owned=True)
    if isinstance(source, NetworkDepthSource):  # a network: predict from the pixels themselves
        return fit_depth(source.predict([view.image], [view.intrinsics.fx])[0], view.intrinsics, owned=True)
    return None


@dataclass
class Anchor:
    """A prepared reference: what every query against it reuses.

    Attributes:
        view: The reference image.
        features: Its matcher features.
        depth: (H, W) metres, or None (no depth, or depth that comes with each pair).
        timings: Seconds spent preparing it (``extract_ref``, ``depth_ref``).
    """

    view: View
    features: Features
    depth: np.ndarray | None
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class PreparedQuery:
    """A query after the reference-independent stage (reading, features, depth), or the error that stopped it.

    Attributes:
        view: The decoded query (None when reading failed).
        features: Its matcher features (None until extracted, or when extraction failed).
        depth: (H, W) metres, or None.
        timings: Seconds per stage so far (``read``, ``extract``, ``depth``).
        error: Why the query failed (``error: Type: message``), or None.
    """

    view: View | None
    features: Features | None
    depth: np.ndarray | None
    timings: dict[str, float]
    error: str | None = None


T = TypeVar("T")
R = TypeVar("R")


def ahead(fn: Callable[[T], R], items: Iterable[T], n: int) -> Iterator[R]:
    """``fn(item)`` for every item, in order, with up to ``n`` of the next items computed in a background thread
    meanwhile.

    Args:
        fn: What to compute per item (reading and decoding a query).
        items: The items.
        n: How many to compute ahead; 0 or less: everything in the calling thread.

    Returns:
        ``fn``'s results, in the items' order.
    """
    if n <= 0:
        yield from map(fn, items)
        return
    it = iter(items)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="mapfree-prefetch") as pool:
        pending: deque[Future[R]] = deque(pool.submit(fn, x) for x in islice(it, n))
        while pending:
            done = pending.popleft().result()
            pending.extend(pool.submit(fn, x) for x in islice(it, 1))
            yield done
