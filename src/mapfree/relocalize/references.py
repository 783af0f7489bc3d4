"""K reference images of a place (paper §5.1, Fig. 4b): chosen among mapping images, retrieved per query.

``ReferenceSet.build(mapping_frames, k=10)`` describes every mapping image with a global descriptor
(DenseVLAD, vocabulary learned on those images), keeps the K most representative by K-means, and answers
``localize(localizer, query)``: retrieve the most similar reference(s), relocalize against it with the
method, and return the query pose in the frame of the references' poses. ``mode="triangulation"`` is the
paper's depth-free baseline: up-to-scale relative poses to the two most similar references, whose known
poses fix the metric scale (``mapfree.solvers.triangulation``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal, get_args

import numpy as np

from .. import retrieval
from ..data import Frame, Scene
from ..estimate import Estimate
from ..geometry import Pose
from ..localizer import Localizer, QueryLocalizer
from ..methods import Method, get
from ..retrieval import retrieve
from ..solvers.essential import EssentialSolver
from ..solvers.triangulation import triangulate_pose
from .pipeline import Relocalizer, build_localizer
from .views import View, ViewLike, ahead, as_view

log = logging.getLogger(__name__)

__all__ = [
    "MODES",
    "ReferenceMode",
    "ReferenceOptions",
    "ReferenceSet",
    "ReferencedLocalizer",
    "mapping_frames",
    "scene_references",
    "check_scene_references",
    "ReferenceSpec",
    "reference_spec",
]

#: How K references answer a query: the most similar one's pose (``retrieval``) or the poses against several of
#: them triangulated (``triangulation``, depth-free).
ReferenceMode = Literal["retrieval", "triangulation"]
MODES: tuple[ReferenceMode, ...] = get_args(ReferenceMode)


@dataclass
class ReferenceOptions:
    """How references are chosen and used. ``top``: references tried per query (the most confident wins)."""

    k: int = 1
    mode: ReferenceMode = "retrieval"
    top: int = 1
    descriptor: str = "densevlad"
    descriptor_opts: dict = field(default_factory=dict)
    max_fit_images: int = 200  # the vocabulary is learned on at most this many (evenly spaced) mapping images
    seed: int = 0

    def __post_init__(self) -> None:
        if self.k < 1:
            raise ValueError(f"the number of references must be >= 1, got {self.k}")
        if self.mode not in MODES:
            raise ValueError(f"reference mode must be one of {MODES}, got {self.mode!r}")
        if self.mode == "triangulation" and self.k < 2:
            raise ValueError("pose triangulation needs K >= 2 references")
        if self.top < 1:
            raise ValueError(f"top must be >= 1, got {self.top}")


def _pose_of(item: ViewLike, pose: Pose | None) -> Pose:
    """The given pose, else the item's own (a ``Frame``'s, a ``View``'s or its frame's)."""
    if pose is None and isinstance(item, Frame):
        pose = item.pose
    elif pose is None and isinstance(item, View):
        pose = item.pose if item.pose is not None else item.frame.pose if item.frame is not None else None
    if pose is None:
        name = item.name if isinstance(item, (Frame, View)) else item
        raise ValueError(f"mapping image {name!r} has no pose: every reference needs one")
    return pose


class ReferenceSet:
    """The chosen references of one place: views, world-to-camera poses, global descriptors."""

    def __init__(
        self,
        views: list[View],
        poses: list[Pose],
        descriptors: np.ndarray | None,
        describer: Any,
        options: ReferenceOptions,
        mapping_size: int,
        indices: np.ndarray,
    ) -> None:
        self.views, self.poses, self.descriptors, self.describer = views, poses, descriptors, describer
        self.options, self.mapping_size, self.indices = options, mapping_size, indices
        self._anchors: dict[tuple[int, int], Any] = {}
        self.timings: dict[str, float] = {}

    def __len__(self) -> int:
        return len(self.views)

    @property
    def names(self) -> list[str]:
        return [v.name for v in self.views]

    @classmethod
    def build(
        cls,
        mapping: Sequence[ViewLike],
        poses: Sequence[Pose | None] | None = None,
        options: ReferenceOptions | None = None,
        **overrides: Any,
    ) -> ReferenceSet:
        """Choose ``k`` references among ``mapping`` (Frames with poses, Views, or (image, K[, depth]) with
        ``poses``). Every image is read once to describe it; only the chosen ones are kept in memory."""

        o = replace(options or ReferenceOptions(), **overrides) if overrides else (options or ReferenceOptions())
        mapping = list(mapping)
        if not mapping:
            raise ValueError("no mapping images to choose references from")
        pose_list = [_pose_of(m, poses[i] if poses is not None else None) for i, m in enumerate(mapping)]
        t0 = time.perf_counter()
        if len(mapping) == 1 or o.k >= len(mapping) and o.mode == "retrieval" and o.top >= len(mapping):
            chosen, G, describer = np.arange(len(mapping)), None, None  # nothing to choose or retrieve
        else:
            describer = retrieval.create(o.descriptor, **o.descriptor_opts)
            fit_idx = np.unique(
                np.linspace(0, len(mapping) - 1, min(len(mapping), o.max_fit_images)).round().astype(int)
            )
            describer.fit(as_view(mapping[i]).image for i in fit_idx)
            G = np.stack([describer.describe(as_view(m).image) for m in mapping])
            chosen = retrieval.select_references(G, o.k, seed=o.seed)
            G = G[chosen]
        views = [as_view(mapping[i]) for i in chosen]
        out = cls(views, [pose_list[i] for i in chosen], G, describer, o, len(mapping), chosen)
        out.timings["choose"] = time.perf_counter() - t0
        return out

    # ------------------------------------------------------------------ per query

    def ranked(self, view: View) -> tuple[np.ndarray, np.ndarray]:
        """Reference indices, most similar first, with their similarities (all 1 when nothing to retrieve)."""
        if self.descriptors is None:
            return np.arange(len(self)), np.ones(len(self))

        return retrieve(self.describer.describe(view.image), self.descriptors, top=len(self))

    def _anchor(self, loc: Localizer[Any], i: int) -> Any:
        """The localizer's anchor of reference ``i``, prepared once (a method without one keeps the view)."""
        key = (id(loc), i)
        if key not in self._anchors:
            self._anchors[key] = loc.prepare(self.views[i])
        return self._anchors[key]

    def _relative(self, loc: Localizer[Any], view: View, i: int) -> Estimate:
        """Pose of the query relative to reference ``i`` with the localizer's own method."""
        return loc.localize(view, self._anchor(loc, i))

    def localize(self, loc: Localizer[Any], query: ViewLike) -> Estimate:
        """World-to-camera pose of ``query`` in the frame of the references' poses (never raises on bad input)."""
        t0 = time.perf_counter()
        try:
            view = as_view(query)
            order, sims = self.ranked(view)
        except Exception as e:
            log.warning("query failed: %s", e)
            return Estimate.failure(f"error: {type(e).__name__}: {e}")
        t_retrieve = time.perf_counter() - t0
        if self.options.mode == "triangulation":
            est = self._triangulate(loc, view, order[:2], sims[:2])
        else:
            est = self._retrieve(loc, view, order[: self.options.top], sims)
        est.timings["retrieve"] = t_retrieve
        est.timings["total"] = est.timings.get("total", 0.0) + t_retrieve
        return est

    def _retrieve(self, loc: Localizer[Any], view: View, order: np.ndarray, sims: np.ndarray) -> Estimate:
        best: Estimate | None = None
        for rank, i in enumerate(order):
            est = self._relative(loc, view, int(i))
            est.extras.update(reference=self.views[i].name, reference_rank=rank, retrieval_similarity=float(sims[rank]))
            if est.pose is not None:
                est.pose = est.pose @ self.poses[i]
            if best is None or (est.ok and (not best.ok or est.confidence > best.confidence)):
                best = est
        assert best is not None
        return best

    def _triangulate(self, loc: Localizer[Any], view: View, order: np.ndarray, sims: np.ndarray) -> Estimate:
        if not isinstance(loc, Relocalizer):
            return Estimate.failure("pose triangulation needs a matching method (matcher + essential matrix)")
        matcher = loc.matcher
        px = loc.solver.options.ransac_threshold_px if isinstance(loc.solver, EssentialSolver) else 3.0
        solver = EssentialSolver(ransac_threshold_px=px, allow_unscaled=True)
        t0 = time.perf_counter()
        qf = matcher.extract(view.image)
        rel, refs, weights, names = [], [], [], []
        for i in order:
            anchor = self._anchor(loc, int(i))
            est = solver.solve(matcher.match(anchor.features, qf), anchor.view.intrinsics, view.intrinsics, None, None)
            names.append(self.views[i].name)
            if est.pose is None:
                return Estimate.failure(
                    f"pose triangulation: no relative pose to {self.views[i].name}: {est.reason}",
                    total=time.perf_counter() - t0,
                )
            rel.append(est.pose)
            refs.append(self.poses[i])
            weights.append(max(est.inliers, 1))
        out = triangulate_pose(refs, rel, weights)
        out.extras.update(reference=names[0], references=",".join(names), retrieval_similarity=float(sims[0]))
        out.timings["total"] = time.perf_counter() - t0
        return out


def _view_or_query(query: ViewLike) -> ViewLike:
    """The query decoded to a ``View`` ahead of retrieval; unchanged when that fails, so that the reference
    set reports the failure exactly as ``localize`` does."""
    try:
        return as_view(query)
    except Exception:
        return query


class ReferencedLocalizer(QueryLocalizer):
    """Any method's localizer bound to a ``ReferenceSet``: ``localize(query)`` retrieves, then relocalizes, and
    returns the query pose in the frame of the references' poses. K references are always a ``ReferenceSet``
    apart from the localizer (which stays a one-reference localizer): ``mapfree run --references K`` binds each
    scene's set here; the service keeps one set per anchor and calls ``set.localize(loc, query)`` with whichever
    pooled localizer is free."""

    def __init__(self, localizer: Localizer[Any], references: ReferenceSet) -> None:
        self.localizer, self.references = localizer, references

    @classmethod
    def build(
        cls,
        localizer: Localizer[Any] | str | Method,
        mapping: Sequence[ViewLike],
        k: int = 1,
        poses: Sequence[Pose | None] | None = None,
        **options: Any,
    ) -> ReferencedLocalizer:
        """``localizer`` (a built localizer, or a method name, path or ``Method``) bound to ``k`` references
        chosen among ``mapping`` (Frames with poses, or views with ``poses``); ``options``: ``ReferenceOptions``
        fields, e.g. ``mode="triangulation"`` (the depth-free baseline) or ``top``."""
        loc = localizer if isinstance(localizer, Localizer) else build_localizer(localizer)
        return cls(loc, ReferenceSet.build(mapping, poses, k=k, **options))

    def localize(self, query: ViewLike) -> Estimate:
        """World-to-camera pose of ``query`` in the frame of the references' poses (never raises on bad input)."""
        return self.references.localize(self.localizer, query)

    def check_available(self) -> None:
        """The bound localizer's check (a depth network that can be neither found nor downloaded)."""
        self.localizer.check_available()

    def localize_many(self, queries: Iterable[ViewLike], prefetch: int = 1) -> Iterator[Estimate]:
        """``localize`` over many queries, in order, the next ``prefetch`` decoded in a background thread."""
        yield from (self.localize(v) for v in ahead(_view_or_query, queries, prefetch))


def mapping_frames(scene: Scene, seq: str = "seq0") -> list[Frame]:
    """The frames of a Map-free scene's mapping scan that have a pose (val/test: the reference and any
    other ``seq0`` frames; the world frame is the reference camera)."""
    return [f for n, f in scene.frames.items() if n.startswith(f"{seq}/") and f.pose is not None]


def scene_references(scene: Scene, k: int, mode: ReferenceMode = "retrieval", **options: Any) -> ReferenceSet:
    """``ReferenceSet`` of a Map-free scene's ``seq0`` frames; K is capped by the frames there are."""
    frames = mapping_frames(scene)
    if not frames:
        raise ValueError(f"{scene.path}: no seq0 frame with a pose to use as a reference")
    if mode == "triangulation" and len(frames) < 2:
        raise ValueError(f"{scene.path}: pose triangulation needs >= 2 posed seq0 frames, found {len(frames)}")
    return ReferenceSet.build(frames, options=ReferenceOptions(k=min(k, len(frames)), mode=mode, **options))


#: Key of ``Method.options`` holding ``{"k": K, "mode": ..., "top": ...}`` for ``mapfree run --references K``.
REFERENCES_OPTION = "references"


@dataclass(frozen=True)
class ReferenceSpec:
    """What ``mapfree run --references K`` asks of a method (``Method.options["references"]``).

    Attributes:
        k: References per scene.
        mode: ``retrieval`` or ``triangulation``.
        top: References tried per query (the most confident wins).
    """

    k: int = 1
    mode: ReferenceMode = "retrieval"
    top: int = 1


def reference_spec(method: Method) -> ReferenceSpec | None:
    """The K-references request a method carries (``with_references``), or None for one reference per scene.

    Args:
        method: The method.

    Returns:
        Its ``ReferenceSpec``, or None.
    """
    spec = method.options.get(REFERENCES_OPTION)
    if not spec:
        return None
    return ReferenceSpec(int(spec.get("k", 1)), spec.get("mode", "retrieval"), int(spec.get("top", 1)))


def with_references(method: str | Method, k: int, mode: ReferenceMode = "retrieval", top: int = 1) -> Method:
    """The method run against K references per scene; K = 1 leaves it unchanged.

    Stored in ``options`` so that a run's journal header records it and ``--resume`` checks it.

    Args:
        method: A name, a YAML path or a ``Method``.
        k: References per scene.
        mode: ``retrieval`` or ``triangulation``.
        top: References tried per query.

    Returns:
        The method, renamed ``NAME+K{k}`` (``-triangulation``).

    Raises:
        ValueError: Values ``ReferenceOptions`` refuses.
    """
    m = method if isinstance(method, Method) else get(method)
    ReferenceOptions(k=k, mode=mode, top=top)  # validate early, with a clear message
    if k == 1 and mode == "retrieval":
        return m
    spec = {"k": int(k), "mode": mode, "top": int(top)}
    suffix = f"+K{k}" + ("-triangulation" if mode == "triangulation" else "")
    return replace(m, name=m.name + suffix, options={**m.options, REFERENCES_OPTION: spec})


def check_scene_references(scenes: Sequence[Scene], method: Method) -> None:
    """Refuse up front a K no scene can honour: K references need K posed ``seq0`` frames in every scene (else
    the run would quietly use fewer), triangulation needs two.

    Args:
        scenes: The run's scenes.
        method: The method (``with_references``).

    Raises:
        ValueError: Naming the scenes short of frames.
    """
    spec = reference_spec(method)
    if spec is None:
        return
    k, mode = spec.k, spec.mode
    need = max(k, 2) if mode == "triangulation" else k
    short = [(s.name, len(mapping_frames(s))) for s in scenes]
    short = [(n, c) for n, c in short if c < need]
    if short:
        listed = ", ".join(f"{n} ({c})" for n, c in short[:5])
        listed += f" and {len(short) - 5} more" if len(short) > 5 else ""
        what = "pose triangulation needs" if mode == "triangulation" else f"--references {k} needs"
        raise ValueError(
            f"{what} {need} posed seq0 (mapping) frames per scene; these scenes have fewer: {listed}. "
            f"Use --references {min(c for _, c in short) or 1} or fewer, or leave those scenes out "
            f"with --scenes"
        )


def bind_scene_references(
    loc: Localizer[Any], scene: Scene, method: Method, ref_pose: Pose
) -> tuple[QueryLocalizer, Pose]:
    """The localizer a scene's queries go to, and the pose its estimates are relative to.

    Args:
        loc: The method's localizer, its reference set to the scene's.
        scene: The scene.
        method: The method (``with_references``).
        ref_pose: The scene reference's world-to-camera pose.

    Returns:
        ``(loc, ref_pose)`` for one reference; else the localizer bound to the scene's K references, whose
        estimates are already in the world frame, and the identity.
    """
    spec = reference_spec(method)
    if spec is None:
        return loc, ref_pose
    refs = scene_references(scene, spec.k, spec.mode, top=spec.top)
    return ReferencedLocalizer(loc, refs), Pose.identity()


def localize_with_references(
    method: str | Method,
    mapping: Sequence[ViewLike],
    queries: Sequence[ViewLike],
    k: int,
    mode: ReferenceMode = "retrieval",
    top: int = 1,
    progress: bool = False,
    localizer: Localizer[Any] | None = None,
) -> tuple[ReferenceSet, list[Estimate]]:
    """Choose ``k`` references among ``mapping`` and localize every query with ``method`` (a name, path,
    ``Method`` or, through ``localizer``, an already built one); estimates are world-to-camera poses in the
    frame of the mapping poses. A bad query is a failed estimate, never an exception."""
    bound = ReferencedLocalizer.build(localizer if localizer is not None else method, mapping, k, mode=mode, top=top)
    it: Iterable = queries
    if progress:
        from tqdm import tqdm

        it = tqdm(queries, desc=f"K={k}", unit="frame", dynamic_ncols=True)
    return bound.references, [bound.localize(q) for q in it]


def relocalize_pairs(
    method: str | Method, pairs: Sequence[tuple[ViewLike, ViewLike]], progress: bool = False
) -> list[Estimate]:
    """Pose of the second image of each pair relative to the first (``X1 = R X0 + t``), one method for all.

    An Ess.Mat method without depth (``*_emat_none``) returns its up-to-scale pose (``Method.build``): the
    angular scores of a pair benchmark do not need the scale."""
    loc = build_localizer(method)
    it: Iterable = pairs
    if progress:
        from tqdm import tqdm

        it = tqdm(pairs, desc="pairs", unit="pair", dynamic_ncols=True)
    out = []
    for a, b in it:
        try:
            out.append(loc.relocalize(a, b))
        except Exception as e:  # other method kinds: a bad pair is a failure, not the end of the run
            out.append(Estimate.failure(f"error: {type(e).__name__}: {e}"))
    return out
