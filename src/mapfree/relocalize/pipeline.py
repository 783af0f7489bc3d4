"""``Relocalizer``: matcher x depth x solver for one reference-query pair, with the reference cached.

The reference's features and depth are computed once (``set_reference`` or ``prepare``) and reused for
every query, which is what makes a whole scene (or a service anchor) cheap.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from .. import depth as depth_mod
from .. import matching, methods, solvers
from ..calibration import CALIBRATION_OPTION, Calibrated, Calibration
from ..depth.base import DepthSource, PairDepthSource
from ..estimate import Estimate
from ..geometry import Pose
from ..localizer import Localizer
from ..matching.base import Features, Matcher, Matches
from ..methods import Method
from ..solvers.base import DepthNeed, Solver
from ..solvers.confidence import choose, confidences
from .batched import BatchOptions, default_batch_size, localize_batched
from .views import Anchor, PreparedQuery, View, ViewLike, ahead, as_view, error_reason, fit_depth, view_depth

__all__ = [
    "View",
    "Anchor",
    "Localizer",
    "Relocalizer",
    "as_view",
    "ViewLike",
    "MIN_PARALLAX_PX",
    "build_localizer",
    "build_matching",
]

#: Median keypoint displacement (px) below which the query is seen from the reference's viewpoint (identity pose).
MIN_PARALLAX_PX = 0.5
_NO_REFERENCE_DEPTH = "no depth for the reference image"


class Relocalizer(Localizer[Anchor]):
    """Matcher x depth x solver: the localizer of a ``matching`` method.

    ``relocalize(ref, query)`` for one pair; ``set_reference(ref)`` then ``localize(query)`` for many queries against
    one reference (its features and depth are computed once); ``prepare(ref)`` and ``localize(query, anchor)`` to
    keep many references.

    Args:
        matcher: A matcher name (``matching.create``) or a ``Matcher``.
        depth: A depth spec (``depth.create``: ``files:sensor``, ``none``, ``dav2-indoor``, ``mast3r``) or a
            ``DepthSource``. A pair network named like the matcher's network shares it (one forward pass per pair).
        solver: A solver name (``solvers.create``) or a ``Solver``.
        matcher_opts: Options of a matcher given by name.
        solver_opts: Options of a solver given by name.
        name: The method's name (default: ``matcher+depth+solver``).
    """

    def __init__(
        self,
        matcher: str | Matcher = "sift",
        depth: str | DepthSource = "none",
        solver: str | Solver = "essential",
        *,
        matcher_opts: dict[str, Any] | None = None,
        solver_opts: dict[str, Any] | None = None,
        name: str = "",
    ) -> None:
        if isinstance(matcher, str):
            matcher = matching.create(matcher, **(matcher_opts or {}))
        if isinstance(depth, str):
            engine = matcher.engine  # a two-view network: its depth comes from the same passes
            same = depth in depth_mod.PAIR_MODELS and engine is not None and engine.name == depth
            depth = depth_mod.create(depth, **({"engine": engine} if same else {}))
        if isinstance(solver, str):
            solver = solvers.create(solver, **(solver_opts or {}))
        self.matcher: Matcher = matcher
        self.depth_source: DepthSource = depth
        self.solver: Solver = solver
        self.name = name or f"{matcher.name}+{depth.name}+{solver.name}"
        self.anchor: Anchor | None = None

    @classmethod
    def from_method(cls, method: str | Method) -> Relocalizer:
        """The localizer of a ``matching`` method (``build_localizer`` builds any kind, and a calibrated one).

        Args:
            method: A name, a YAML path or a ``Method`` of kind ``matching``.

        Returns:
            Its ``Relocalizer``.

        Raises:
            ValueError: A method of another kind, or one that carries a calibration file (``mapfree run
                --calibration``): ``build_localizer`` returns those.
        """
        m = method if isinstance(method, methods.Method) else methods.get(method)
        if m.kind != "matching" or m.options.get(CALIBRATION_OPTION):
            what = f"a {m.kind} method" if m.kind != "matching" else "calibrated"
            raise ValueError(
                f"method {m.name!r} is {what}: its localizer is no Relocalizer; build it with "
                f"mapfree.relocalize.build_localizer({m.name!r})"
            )
        localizer = m.build()
        if not isinstance(localizer, Relocalizer):  # a ``register_kind`` of its own for matching methods
            raise ValueError(f"method {m.name!r} builds a {type(localizer).__name__}, not a Relocalizer")
        return localizer

    # ------------------------------------------------------------------ stages

    @property
    def metric(self) -> bool:
        """Whether its poses are metric (a depth source with a scale)."""
        return self.depth_source.metric

    @property
    def pairwise_depth(self) -> bool:
        """Depth that comes from the pair (MASt3R's pointmaps): asked for after matching, in ``_solve``."""
        return isinstance(self.depth_source, PairDepthSource)

    @property
    def depth_needs(self) -> tuple[DepthNeed, ...]:
        """The images a pair needs depth of: the solver's needs, none for a method without a scale."""
        return self.solver.depth_needs if self.metric else ()

    def default_batch_size(self) -> int:
        """16 when the matcher runs on a GPU (the batched path), else 0."""
        return default_batch_size(self.matcher)

    def check_available(self) -> None:
        """Raise the clear error of a depth network that can be neither found nor downloaded."""
        self.depth_source.check_available()

    def prepare(self, reference: ViewLike) -> Anchor:
        """Features and depth of a reference, without making it the current one (services keep many).

        Args:
            reference: A ``ViewLike``.

        Returns:
            The anchor, with the seconds spent on it (``extract_ref``, ``depth_ref``).
        """
        view = as_view(reference)
        t0 = time.perf_counter()
        feats = self.matcher.extract(view.image)
        t1 = time.perf_counter()
        depth = view_depth(self.depth_source, view)
        t2 = time.perf_counter()
        return Anchor(view, feats, depth, {"extract_ref": t1 - t0, "depth_ref": t2 - t1})

    def set_reference(self, reference: ViewLike | Anchor) -> Anchor:
        """Make ``reference`` (a ``ViewLike`` or a prepared ``Anchor``) the one ``localize(query)`` answers against.

        Returns:
            Its anchor.
        """
        self.anchor = reference if isinstance(reference, Anchor) else self.prepare(reference)
        return self.anchor

    def relocalize(self, reference: ViewLike, query: ViewLike) -> Estimate:
        """Pose of ``query`` relative to ``reference``; timings include preparing the reference.

        Args:
            reference: A ``ViewLike``.
            query: A ``ViewLike``.

        Returns:
            The estimate; an unreadable reference is a "no estimate" (``reference: error: …``), like a bad query.
        """
        try:
            anchor = self.prepare(reference)
        except Exception as e:  # an unreadable or unusable reference is a "no estimate", like a bad query
            return Estimate.failure(f"reference: {error_reason(e)}")
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

    def _prepare_query(self, query: ViewLike) -> PreparedQuery:
        """Stage 1 (independent of the reference): read the query, extract features, get its depth."""
        t0 = time.perf_counter()
        try:
            view = as_view(query)
            t1 = time.perf_counter()
            feats = self.matcher.extract(view.image)
            t2 = time.perf_counter()
            depth = view_depth(self.depth_source, view)
            t3 = time.perf_counter()
        except Exception as e:  # a bad frame must not stop a run; the reason says what happened
            return PreparedQuery(None, None, None, {"read": time.perf_counter() - t0}, error_reason(e))
        return PreparedQuery(view, feats, depth, {"read": t1 - t0, "extract": t2 - t1, "depth": t3 - t2})

    def _finish(self, anchor: Anchor, prep: PreparedQuery) -> Estimate:
        """Stage 2: match against the anchor and solve."""
        if prep.error is not None or prep.features is None:
            return self.conclude(anchor, prep, None, 0.0)
        t0 = time.perf_counter()
        matches: Matches | None
        try:
            matches = self.matcher.match(anchor.features, prep.features)
        except Exception as e:
            prep = PreparedQuery(prep.view, prep.features, prep.depth, prep.timings, error_reason(e))
            matches = None
        return self.conclude(anchor, prep, matches, time.perf_counter() - t0)

    def conclude(self, anchor: Anchor, prep: PreparedQuery, matches: Matches | None, match_s: float) -> Estimate:
        """Stage 3: solve a matched query (thread-safe: the batched path runs it in a pool of solver threads).

        Args:
            anchor: The prepared reference.
            prep: The query after stage 1 (or its error).
            matches: Its matches with the reference (None when matching failed).
            match_s: Seconds spent matching it.

        Returns:
            The estimate, with the timings of every stage and its ``matches``.
        """
        timings = dict(prep.timings)
        est = Estimate.failure(prep.error or "")
        if prep.error is None and prep.view is not None and matches is not None:
            try:
                t1 = time.perf_counter()
                est, pair_depth = self._solve(anchor, prep.view, matches, prep.depth, prep.features)
                timings["solve"] = time.perf_counter() - t1 - pair_depth
                timings["depth"] = timings.get("depth", 0.0) + pair_depth
                timings["match"] = timings.pop("extract", 0.0) + match_s  # extraction counts as matching time
            except Exception as e:
                est = Estimate.failure(error_reason(e))
        matches = matches if matches is not None else Matches.empty()
        if est.ok and est.signals.learned_confidence is None and len(matches):
            est.signals.learned_confidence = float(np.median(matches.scores))
        timings["total"] = sum(v for k, v in timings.items() if k in ("read", "match", "extract", "depth", "solve"))
        est.timings = {**est.timings, **timings}
        if est.matches is None:
            est.matches = matches
        est.extras.setdefault("num_matches", len(matches))
        return est

    def localize(self, query: ViewLike, anchor: Anchor | None = None) -> Estimate:
        """Pose of ``query`` relative to the anchor (default: the one given to ``set_reference``).

        Never raises for bad pixels or geometry: the answer is then an ``Estimate`` with ``pose=None``.

        Args:
            query: A ``ViewLike``.
            anchor: A prepared reference (``prepare``), or None for the current one.

        Returns:
            The estimate.
        """
        anchor = self._anchor(anchor)
        early = self._precheck(anchor)
        if early is not None:
            return Estimate.failure(early, total=0.0)
        return self._finish(anchor, self._prepare_query(query))

    def localize_many(
        self, queries: Iterable[ViewLike], anchor: Anchor | None = None, prefetch: int = 1
    ) -> Iterator[Estimate]:
        """``localize`` over many queries, in order; with ``prefetch`` > 0 the next queries are read and their
        features extracted in a background thread while the current one is matched and solved.

        Args:
            queries: The queries.
            anchor: A prepared reference, or None for the current one.
            prefetch: Queries prepared ahead (0: none).

        Returns:
            One estimate per query.
        """
        anchor = self._anchor(anchor)
        early = self._precheck(anchor)
        if early is not None:  # nothing to extract: every query fails the same way
            for _ in queries:
                yield Estimate.failure(early, total=0.0)
            return
        yield from (self._finish(anchor, prep) for prep in ahead(self._prepare_query, queries, prefetch))

    def localize_batched(
        self, queries: Iterable[ViewLike], *, anchor: Anchor | None = None, options: BatchOptions | None = None
    ) -> Iterator[Estimate]:
        """``localize`` over many queries, in order, through the batched pipeline (``batched.py``): decoding
        in background threads, features and matches in batches on the device, solvers in a thread pool.

        Args:
            queries: The queries.
            anchor: A prepared reference, or None for the current one.
            options: Batch size and threads (default ``BatchOptions()``).

        Returns:
            One estimate per query, each as ``localize`` gives it.
        """
        o = options or BatchOptions()
        if self._precheck(self._anchor(anchor)) is not None:
            # A reference every query fails on alike: localize_many's path, the next queries decoded ahead.
            yield from self.localize_many(queries, anchor, prefetch=max(1, o.batch_size))
            return
        yield from localize_batched(self, self._anchor(anchor), queries, o)

    def _precheck(self, anchor: Anchor) -> str | None:
        """Why every query of this anchor fails (a metric method without reference depth), else None."""
        if "ref" in self.depth_needs and anchor.depth is None and not self.pairwise_depth:
            return _NO_REFERENCE_DEPTH
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
            return _same_viewpoint(flow, self.solver.confidence_mode), 0.0
        needs = self.depth_needs
        depth_ref = anchor.depth
        src = self.depth_source
        pair_s = 0.0
        if isinstance(src, PairDepthSource) and needs and (depth_ref is None or ("query" in needs and depth_q is None)):
            t0 = time.perf_counter()
            pair_ref, pair_q = src.pair_depth(
                anchor.view.image,
                view.image,
                need_query="query" in needs and depth_q is None,
                features=(anchor.features, features_q),
            )
            depth_ref = depth_ref if depth_ref is not None else fit_depth(pair_ref, anchor.view.intrinsics, owned=True)
            depth_q = depth_q if depth_q is not None else fit_depth(pair_q, view.intrinsics, owned=True)
            pair_s = time.perf_counter() - t0
        if "ref" in needs and depth_ref is None:
            return Estimate.failure(_NO_REFERENCE_DEPTH), pair_s
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
    n = int(np.count_nonzero(flow <= 2 * MIN_PARALLAX_PX))
    values = confidences(n, n / len(flow))
    return Estimate(Pose.identity(), choose(mode, values), n, extras={**values, "same_viewpoint": True})


def build_localizer(method: str | Method, calibration: str | os.PathLike | Calibration | None = None) -> Localizer[Any]:
    """Any method's localizer: a ``Relocalizer`` for a matching method, a regression network's or a cascade's for
    those kinds, wrapped in ``mapfree.calibration.Calibrated`` with a calibration.

    Args:
        method: A name, a YAML path or a ``Method``.
        calibration: A calibration of the method (``mapfree calibrate``: a file or a ``Calibration``): every
            estimate then carries ``p_correct``. Default: the file in the method's options
            (``mapfree run --calibration``), else none (``mapfree.calibration.shipped`` names a preset's).

    Returns:
        The method's localizer.

    Raises:
        CalibrationError: A calibration file that cannot be used for this method.
    """
    m = method if isinstance(method, methods.Method) else methods.get(method)
    if calibration is not None and not isinstance(calibration, Calibration):
        calibration = Calibration.load(calibration, m.name)
    elif calibration is None and m.options.get(CALIBRATION_OPTION):
        calibration = Calibration.load(m.options[CALIBRATION_OPTION], m.name)
    localizer: Localizer[Any] = m.build()
    return localizer if calibration is None else Calibrated(localizer, calibration)


def build_matching(method: Method) -> Relocalizer:
    """The localizer of a ``matching`` method (the factory of that kind in ``mapfree.methods``' kind table).

    Args:
        method: A ``Method`` of kind ``matching``.

    Returns:
        Its ``Relocalizer``.
    """
    return Relocalizer(
        method.matcher,
        method.depth,
        method.solver,
        matcher_opts=method.matcher_opts,
        solver_opts=method.solver_opts,
        name=method.name,
    )
