"""``Relocalizer``: matcher x depth x solver for one reference-query pair, with the reference cached.

The reference's features and depth are computed once (``set_reference`` or ``prepare``) and reused for
every query, which is what makes a whole scene (or a service anchor) cheap.
"""

from __future__ import annotations

import logging
import os
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import cv2
import numpy as np

from ..data import Frame, read_image
from ..data.io import same_aspect
from ..data.orientation import exif_orientation, fit_intrinsics, orient_pixels
from ..estimate import Estimate
from ..geometry import Intrinsics
from ..matching.base import Features, Matcher, Matches
from .allocator import keep_heap_warm

if TYPE_CHECKING:
    from .batched import BatchOptions

log = logging.getLogger(__name__)

__all__ = ["View", "Anchor", "Localizer", "Relocalizer", "as_view", "ViewLike", "MIN_PARALLAX_PX"]

#: Median keypoint displacement (px) below which the query is seen from the reference's viewpoint (identity pose).
MIN_PARALLAX_PX = 0.5
#: Which depth maps each solver needs (anything else: both).
_DEPTH_NEEDS = {
    "essential": ("ref", "query"),
    "pnp": ("ref",),
    "procrustes": ("ref", "query"),
    "mickey": (),
}  # MicKey's solver lifts with the depths its matcher's candidates carry


@dataclass
class View:
    """One image ready for relocalization: pixels, intrinsics, and optionally a depth map or a Frame."""

    image: np.ndarray
    intrinsics: Intrinsics
    depth: np.ndarray | None = None
    frame: Frame | None = None
    name: str = ""
    #: EXIF orientation by which the frame's stored files (its intrinsics, depth maps) were turned upright.
    orientation: int = 1


ViewLike = View | Frame | tuple


def _read_image_any(image: Any) -> tuple[np.ndarray, Path | None]:
    if isinstance(image, (str, os.PathLike)):
        return read_image(image), Path(image)
    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=2)
    return arr, None


def _as_intrinsics(K: Any, image: np.ndarray) -> Intrinsics:
    if isinstance(K, Intrinsics):
        return K
    K = np.asarray(K, dtype=np.float64)
    h, w = image.shape[:2]
    if K.shape == (3, 3):
        return Intrinsics.from_K(K, w, h)
    if K.shape == (4,):
        return Intrinsics(*map(float, K), w, h)
    raise ValueError(f"intrinsics must be an Intrinsics, a 3x3 K or (fx, fy, cx, cy), got shape {K.shape}")


def as_view(x: ViewLike) -> View:
    """A ``View`` from a ``Frame`` or ``(image | path, Intrinsics | K | (fx,fy,cx,cy)[, depth])``."""
    if isinstance(x, View):
        return x
    if isinstance(x, Frame):
        image = x.image()
        K, _, turned = _upright(image, x.intrinsics, x.image_path, None)
        return View(image, K, None, x, x.name, turned)
    if isinstance(x, tuple) and len(x) in (2, 3):
        image, path = _read_image_any(x[0])
        depth = None if len(x) == 2 or x[2] is None else np.asarray(x[2], dtype=np.float32)
        K0 = _as_intrinsics(x[1], image)
        K, depth, turned = _upright(image, K0, path, depth)
        frame = Frame(path.name, path, K0) if path is not None else None  # its files keep the stored grid's K
        return View(image, K, depth, frame, path.name if path is not None else "", turned)
    raise TypeError(f"expected a Frame, a View or (image, intrinsics[, depth]); got {type(x).__name__}")


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


def _fit_depth(depth: np.ndarray | None, K: Intrinsics, owned: bool = False) -> np.ndarray | None:
    """Depth at the image size (nearest-neighbour resize keeps holes as holes); NaN/inf/negative -> 0.

    A new array, unless ``owned`` (the caller's fresh array: read from a file or predicted just now) and already
    clean, as every map read from a depth PNG is: it is then returned as is, not copied.
    """
    if depth is None:
        return None
    d = np.asarray(depth, dtype=np.float32)
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


def ahead(fn: Callable[[Any], Any], items: Iterable[Any], n: int) -> Iterator[Any]:
    """``fn(item)`` for every item, in order, with up to ``n`` of the next items computed in a background
    thread meanwhile (``n`` <= 0: in the calling thread)."""
    if n <= 0:
        yield from map(fn, items)
        return
    it = iter(items)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="mapfree-prefetch") as pool:
        pending: deque = deque(pool.submit(fn, x) for x in islice(it, n))
        while pending:
            done = pending.popleft().result()
            nxt = next(it, _END)
            if nxt is not _END:
                pending.append(pool.submit(fn, nxt))
            yield done


_END = object()


@dataclass
class _Prepared:
    """A query after the reference-independent stage (or the error that stopped it)."""

    view: View | None
    features: Features | None
    depth: np.ndarray | None
    timings: dict[str, float]
    error: str | None = None


def _error(e: Exception) -> str:
    log.warning("relocalization failed: %s", e, exc_info=log.isEnabledFor(logging.DEBUG))
    return f"error: {type(e).__name__}: {e}"


@dataclass
class Anchor:
    """A prepared reference: its view, features and depth, and what preparing it cost."""

    view: View
    features: Features
    depth: np.ndarray | None
    timings: dict[str, float] = field(default_factory=dict)


class Localizer(Protocol):
    """What every method kind builds (``Method.build()``): matching pipelines and regression models alike."""

    def set_reference(self, reference: ViewLike) -> Any: ...

    def localize(self, query: ViewLike) -> Estimate: ...

    def relocalize(self, reference: ViewLike, query: ViewLike) -> Estimate: ...


class Relocalizer:
    """Matcher x depth x solver. Components are names (built through their registries) or objects.

    ``relocalize(ref, query)`` for one pair; ``set_reference(ref)`` then ``localize(query)`` for many
    queries against one reference (its features and depth are computed once).
    """

    def __init__(
        self,
        matcher: str | Matcher = "sift",
        depth: str | Any = "none",
        solver: str | Any = "essential",
        *,
        matcher_opts: dict | None = None,
        solver_opts: dict | None = None,
        name: str = "",
    ) -> None:
        if isinstance(matcher, str):
            from .. import matching

            matcher = matching.create(matcher, **(matcher_opts or {}))
        if isinstance(depth, str):
            from .. import depth as depth_mod

            engine = getattr(matcher, "engine", None)  # a two-view network: its depth comes from the same passes
            same = depth in depth_mod.PAIR_MODELS and getattr(engine, "name", None) == depth
            depth = depth_mod.create(depth, **({"engine": engine} if same else {}))
        if isinstance(solver, str):
            from .. import solvers

            solver = solvers.create(solver, **(solver_opts or {}))
        keep_heap_warm()  # per-pair buffers stay in the heap instead of faulting in again (allocator.py)
        self.matcher, self.depth_source, self.solver = matcher, depth, solver
        self.name = name or f"{matcher.name}+{getattr(depth, 'name', 'depth')}+{solver.name}"
        self.anchor: Anchor | None = None

    @classmethod
    def from_method(cls, method: Any) -> Localizer:
        """Build a method by name, YAML path or ``Method`` (regression methods build their own kind)."""
        from .. import methods

        keep_heap_warm()  # also for the methods that build their own kind of localizer
        m = method if isinstance(method, methods.Method) else methods.get(method)
        return m.build()

    # ------------------------------------------------------------------ stages

    @property
    def metric(self) -> bool:
        return bool(getattr(self.depth_source, "metric", True))

    @property
    def pairwise_depth(self) -> bool:
        """Depth that comes from the pair (MASt3R's pointmaps): asked for after matching, in ``_solve``."""
        return bool(getattr(self.depth_source, "pairwise", False))

    def _depth(self, view: View) -> np.ndarray | None:
        if view.depth is not None:
            return _fit_depth(view.depth, view.intrinsics)
        if not self.metric or self.pairwise_depth:
            return None
        if view.frame is not None:
            d = self.depth_source.depth(view.frame)
            if view.orientation != 1 and d is not None and getattr(self.depth_source, "reads_files", False):
                d = orient_pixels(d, view.orientation)  # a stored map of a tagged photo: turned like its pixels
            return _fit_depth(d, view.intrinsics, owned=True)
        if hasattr(self.depth_source, "predict"):  # a network: predict from the pixels themselves
            return _fit_depth(
                self.depth_source.predict([view.image], [view.intrinsics.fx])[0], view.intrinsics, owned=True
            )
        return None

    def prepare(self, reference: ViewLike) -> Anchor:
        """Features and depth of a reference, without making it the current one (services keep many)."""
        view = as_view(reference)
        t0 = time.perf_counter()
        feats = self.matcher.extract(view.image)
        t1 = time.perf_counter()
        depth = self._depth(view)
        t2 = time.perf_counter()
        return Anchor(view, feats, depth, {"extract_ref": t1 - t0, "depth_ref": t2 - t1})

    def set_reference(self, reference: ViewLike | Anchor) -> Anchor:
        self.anchor = reference if isinstance(reference, Anchor) else self.prepare(reference)
        return self.anchor

    def relocalize(self, reference: ViewLike, query: ViewLike) -> Estimate:
        """Pose of ``query`` relative to ``reference``; timings include preparing the reference."""
        try:
            anchor = self.prepare(reference)
        except Exception as e:  # an unreadable or unusable reference is a "no estimate", like a bad query
            return Estimate.failure(f"reference: {_error(e)}")
        est = self.localize(query, anchor)
        est.timings["match"] = est.timings.get("match", 0.0) + anchor.timings["extract_ref"]
        est.timings["depth"] = est.timings.get("depth", 0.0) + anchor.timings["depth_ref"]
        est.timings["total"] = est.timings.get("total", 0.0) + sum(anchor.timings.values())
        return est

    def _anchor(self, anchor: Anchor | None) -> Anchor:
        anchor = anchor or self.anchor
        if anchor is None:
            raise RuntimeError("no reference: call set_reference(...) first or use relocalize(ref, query)")
        return anchor

    def _prepare_query(self, query: ViewLike) -> _Prepared:
        """Stage 1 (independent of the reference): read the query, extract features, get its depth."""
        t0 = time.perf_counter()
        try:
            view = as_view(query)
            t1 = time.perf_counter()
            feats = self.matcher.extract(view.image)
            t2 = time.perf_counter()
            depth = self._depth(view)
            t3 = time.perf_counter()
        except Exception as e:  # a bad frame must not stop a run; the reason says what happened
            return _Prepared(None, None, None, {"read": time.perf_counter() - t0}, _error(e))
        return _Prepared(view, feats, depth, {"read": t1 - t0, "extract": t2 - t1, "depth": t3 - t2})

    def _finish(self, anchor: Anchor, prep: _Prepared) -> Estimate:
        """Stage 2: match against the anchor and solve."""
        if prep.error is not None:
            return self.conclude(anchor, prep, None, 0.0)
        t0 = time.perf_counter()
        try:
            matches = self.matcher.match(anchor.features, prep.features)
        except Exception as e:
            prep = _Prepared(prep.view, prep.features, prep.depth, prep.timings, _error(e))
            matches = None
        return self.conclude(anchor, prep, matches, time.perf_counter() - t0)

    def conclude(self, anchor: Anchor, prep: _Prepared, matches: Matches | None, match_s: float) -> Estimate:
        """Stage 3: solve a matched query (thread-safe: the batched path runs it in a pool of solver threads)."""
        timings = dict(prep.timings)
        est = Estimate.failure(prep.error or "")
        if prep.error is None and matches is not None:
            try:
                t1 = time.perf_counter()
                est, pair_depth = self._solve(anchor, prep.view, matches, prep.depth, prep.features)
                timings["solve"] = time.perf_counter() - t1 - pair_depth
                timings["depth"] = timings.get("depth", 0.0) + pair_depth
                timings["match"] = timings.pop("extract", 0.0) + match_s  # extraction counts as matching time
            except Exception as e:
                est = Estimate.failure(_error(e))
        matches = matches if matches is not None else Matches.empty()
        timings["total"] = sum(v for k, v in timings.items() if k in ("read", "match", "extract", "depth", "solve"))
        est.timings = {**est.timings, **timings}
        est.extras.setdefault("matches", matches)
        est.extras.setdefault("num_matches", len(matches))
        return est

    def localize(self, query: ViewLike, anchor: Anchor | None = None) -> Estimate:
        """Pose of ``query`` relative to the anchor (default: the one given to ``set_reference``).

        Never raises for bad pixels or geometry: the answer is then an ``Estimate`` with ``pose=None``.
        """
        anchor = self._anchor(anchor)
        early = self._precheck(anchor)
        return early if early is not None else self._finish(anchor, self._prepare_query(query))

    def localize_many(
        self, queries: Iterable[ViewLike], anchor: Anchor | None = None, prefetch: int = 1
    ) -> Iterator[Estimate]:
        """``localize`` over many queries, in order; with ``prefetch`` > 0 the next queries are read and their
        features extracted in a background thread while the current one is matched and solved."""
        anchor = self._anchor(anchor)
        if self._precheck(anchor) is not None:  # nothing to extract: every query fails the same way
            for _ in queries:
                yield self._precheck(anchor)
            return
        yield from (self._finish(anchor, prep) for prep in ahead(self._prepare_query, queries, prefetch))

    def localize_batched(
        self, queries: Iterable[ViewLike], anchor: Anchor | None = None, options: BatchOptions | None = None
    ) -> Iterator[Estimate]:
        """``localize`` over many queries, in order, through the batched pipeline (``batched.py``): decoding
        in background threads, features and matches in batches on the device, solvers in a thread pool."""
        from .batched import BatchOptions, localize_batched

        o = options or BatchOptions()
        if self._precheck(self._anchor(anchor)) is not None:
            # A reference every query fails on alike: localize_many's path, the next queries decoded ahead.
            yield from self.localize_many(queries, anchor, prefetch=max(1, o.batch_size))
            return
        yield from localize_batched(self, self._anchor(anchor), queries, o)

    def _needs(self) -> tuple[str, ...]:
        if not self.metric:
            return ()
        return _DEPTH_NEEDS.get(getattr(self.solver, "name", ""), ("ref", "query"))

    def _precheck(self, anchor: Anchor) -> Estimate | None:
        """The failure every query of this anchor gets (a metric method without reference depth), else None."""
        if "ref" in self._needs() and anchor.depth is None and not self.pairwise_depth:
            return Estimate.failure("no depth for the reference image", total=0.0)
        return None

    def _solve(
        self,
        anchor: Anchor,
        view: View,
        matches: Matches,
        depth_q: np.ndarray | None,
        features_q: Features | None = None,
    ) -> tuple[Estimate, float]:
        """The estimate, and the seconds spent on depth from the pair (a two-view network's; counted as depth)."""
        flow = np.linalg.norm(matches.kpts1 - matches.kpts0, axis=1)
        if len(matches) and float(np.median(flow)) <= MIN_PARALLAX_PX:
            mode = getattr(getattr(self.solver, "options", None), "confidence", "inliers")
            return _same_viewpoint(flow, mode), 0.0
        needs = self._needs()
        depth_ref = anchor.depth
        if self.pairwise_depth and needs and (depth_ref is None or ("query" in needs and depth_q is None)):
            t0 = time.perf_counter()
            pair_ref, pair_q = self.depth_source.pair_depth(
                anchor.view.image,
                view.image,
                need_query="query" in needs and depth_q is None,
                features=(anchor.features, features_q),
            )
            depth_ref = depth_ref if depth_ref is not None else _fit_depth(pair_ref, anchor.view.intrinsics, owned=True)
            depth_q = depth_q if depth_q is not None else _fit_depth(pair_q, view.intrinsics, owned=True)
            pair_s = time.perf_counter() - t0
        else:
            pair_s = 0.0
        if "ref" in needs and depth_ref is None:
            return Estimate.failure("no depth for the reference image"), pair_s
        if "query" in needs and depth_q is None:
            return Estimate.failure("no depth for the query image"), pair_s
        est = self.solver.solve(matches, anchor.view.intrinsics, view.intrinsics, depth_ref, depth_q)
        if est.pose is not None and not self.metric:
            est.extras.setdefault("scale_free", True)
        return est, pair_s


def _same_viewpoint(flow: np.ndarray, mode: str) -> Estimate:
    """The query shows the scene from the reference's viewpoint (its keypoints have not moved): the identity
    pose, which needs no depth and no solver (an essential matrix is undefined without parallax, a rotation
    would have moved the keypoints). Inliers: the matches that stayed within a pixel, ranked like a solver's."""
    from ..geometry import Pose
    from ..solvers.confidence import choose, confidences

    n = int(np.count_nonzero(flow <= 2 * MIN_PARALLAX_PX))
    values = confidences(n, n / len(flow))
    return Estimate(Pose.identity(), choose(mode, values), n, extras={**values, "same_viewpoint": True})


def build_matching(method: Any) -> Relocalizer:
    """Factory of the ``matching`` method kind (registered with ``mapfree.methods``)."""
    return Relocalizer(
        method.matcher,
        method.depth,
        method.solver,
        matcher_opts=method.matcher_opts,
        solver_opts=method.solver_opts,
        name=method.name,
    )
