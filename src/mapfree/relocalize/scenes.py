"""One scene's frames relocalized, the same wherever they run (a local pool worker, a Ray worker, this process):
the method built once per process and bound to the scene's reference, the frames' journal records and figures.

``run.py`` drives a split over these locally, ``distributed.py`` on a Ray cluster; both import from here and
neither from the other.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..benchmark.html import frame_figure_path
from ..calibration import calibration_for
from ..data import Scene
from ..estimate import Estimate
from ..geometry import Pose
from ..localizer import Localizer, QueryLocalizer
from ..methods import Method
from ..viz import FIGURE_MAX_SIDE, FIGURE_QUALITY, estimate_figure, jpeg_bytes
from ..viz import save_figure as save_jpeg
from .allocator import keep_heap_warm
from .batched import BatchOptions
from .journal import FrameRecord
from .references import bind_scene_references, reference_spec

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- the method bound to a scene


_LOCALIZERS: dict[str, Localizer[Any]] = {}


def _method_key(method: Method) -> str:
    return json.dumps(method.to_dict(), sort_keys=True)


def built_localizer(method: Method) -> Localizer[Any]:
    """One built method per worker process (matchers load weights once); ``open_scene`` binds it to one scene's
    reference at a time."""
    key = _method_key(method)
    if key not in _LOCALIZERS:
        _LOCALIZERS[key] = method.build()
    return _LOCALIZERS[key]


@dataclass
class FrameResult:
    """One computed frame as a worker hands it over: its journal record and, with ``--viz``, its figure (JPEG)."""

    record: FrameRecord
    figure: bytes | None = None


@dataclass
class SceneReference:
    """A scene with the method bound to its reference(s), set up once for all the frames a worker computes
    there; ``error`` says why the reference failed (then every frame fails with that reason)."""

    scene: Scene
    localizer: QueryLocalizer | None
    ref_pose: Pose
    error: str = ""
    _image: np.ndarray | None = field(default=None, repr=False)

    def ref_image(self) -> np.ndarray:
        """The reference image, decoded once for all the scene's figures (``--viz``)."""
        if self._image is None:
            self._image = self.scene.reference.image()
        return self._image


def open_scene(method: Method, scene_path: str) -> SceneReference:
    """The built method (one per process) bound to the reference of the scene at ``scene_path``."""
    scene = Scene(Path(scene_path))
    ref_pose = Pose.identity()
    try:
        loc = built_localizer(method)
        ref = scene.reference
        ref_pose = ref.pose if ref.pose is not None else Pose.identity()
        loc.set_reference(ref)
        bound, ref_pose = bind_scene_references(loc, scene, method, ref_pose)  # --references K (references.py)
    except Exception as e:  # the whole scene fails cleanly; each frame says why
        return SceneReference(scene, None, ref_pose, f"reference failed: {type(e).__name__}: {e}")
    return SceneReference(scene, bound, ref_pose)


def scene_results(
    ref: SceneReference, method: Method, frames: Sequence[str], batch_size: int | None = None, figures: bool = False
) -> Iterator[FrameResult]:
    """Relocalize ``frames`` of a scene against its reference, one ``FrameResult`` per frame in order (the same
    wherever it runs: a pool worker, a Ray worker, this process). ``figures``: draw each one (``--viz``)."""
    scene = ref.scene
    if ref.localizer is None:
        for name in frames:
            yield FrameResult(FrameRecord.of(scene.name, name, Estimate.failure(ref.error), None))
        return
    calibration = calibration_for(method.name, method.options)
    for name, est in zip(frames, estimates(ref.localizer, scene, frames, batch_size)):
        if calibration is not None and est.p_correct is None:  # a cascade's estimates come with their own
            calibration.apply(est)
        # Relative pose (query w.r.t. reference) -> world-to-camera in the scene's frame.
        world = est.pose @ ref.ref_pose if est.pose is not None else None
        picture = None
        if figures:
            fig = frame_figure(scene, name, est, world, method, ref.ref_image)
            picture = None if fig is None else jpeg_bytes(fig, FIGURE_MAX_SIDE, FIGURE_QUALITY)
        yield FrameResult(FrameRecord.of(scene.name, name, est, world), picture)


def save_figure(viz_dir: os.PathLike | str | None, result: FrameResult) -> None:
    """Write a frame's figure where ``--viz`` puts it (``frame_figure_path``); a failed write is logged only."""
    if viz_dir is None or result.figure is None:
        return
    path = frame_figure_path(viz_dir, result.record.scene, result.record.frame)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(result.figure)
    except OSError as e:  # a figure is a by-product: the frame's result is journaled already
        log.warning("no figure for %s %s: %s", result.record.scene, result.record.frame, e)


def frame_figure(
    scene: Scene,
    frame: str,
    est: Estimate,
    world: Pose | None,
    method: Method,
    ref_image: Callable[[], np.ndarray] | None = None,
) -> np.ndarray | None:
    """One frame's figure for ``run --viz`` (matches + AR check against the scene's reference image, ground truth
    when the split has it). Methods that relocalize against other references than the scene's
    (``--references K``) get the AR check alone: their matches are with another image. A figure that cannot be
    drawn is logged, never raised. ``ref_image``: the reference image's reader, when the caller caches it."""

    try:
        ref, query = scene.reference, scene.frame(frame)
        ref_pose = ref.pose if ref.pose is not None else Pose.identity()
        rel = world @ ref_pose.inverse() if world is not None else None
        gt = query.pose @ ref_pose.inverse() if query.pose is not None and ref.pose is not None else None
        other = reference_spec(method) is not None  # matched with another reference than the scene's
        shown = Estimate(
            rel,
            est.confidence,
            est.inliers,
            est.reason,
            extras={} if other else est.extras,
            matches=None if other else est.matches,
        )
        thr = float(method.solver_opts.get("ransac_threshold_px", 3.0))  # the inlier colours of the figure
        return estimate_figure(
            (ref_image or ref.image)(),
            query.image(),
            ref.intrinsics,
            query.intrinsics,
            shown,
            gt,
            threshold_px=thr,
            title=f"{scene.name} {frame}  {method.name}",
        )
    except Exception as e:  # a figure is a by-product: the frame's result is journaled already
        log.warning("no figure for %s %s: %s", scene.name, frame, e)
        return None


def write_frame_figure(
    viz_dir: Path,
    scene: Scene,
    frame: str,
    est: Estimate,
    world: Pose | None,
    method: Method,
    ref_image: Callable[[], np.ndarray] | None = None,
) -> Path | None:
    """Draw one frame's figure (``frame_figure``) into ``frame_figure_path(viz_dir, …)``; None when it could not
    be drawn or written (logged, never raised)."""

    fig = frame_figure(scene, frame, est, world, method, ref_image)
    if fig is None:
        return None
    try:
        return save_jpeg(frame_figure_path(viz_dir, scene.name, frame), fig)
    except OSError as e:
        log.warning("no figure for %s %s: %s", scene.name, frame, e)
        return None


def estimates(
    loc: QueryLocalizer, scene: Scene, frames: Sequence[str], batch_size: int | None = None
) -> Iterator[Estimate]:
    """Estimates in frame order: through the batched path when ``batch_size`` > 0 (``None``: the localizer's
    default, 16 for a matcher on a GPU), else one query at a time with the next one prefetched where supported."""
    size = loc.default_batch_size() if batch_size is None else batch_size
    queries = [scene.frame(n) for n in frames]
    if size > 0:
        yield from loc.localize_batched(queries, options=BatchOptions(batch_size=size))
    else:
        yield from loc.localize_many(queries)


def set_threads(threads: int) -> None:
    """A worker's share of the cores: ``threads`` for OpenMP/BLAS, OpenCV and torch."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    import cv2

    cv2.setNumThreads(threads)
    try:
        import torch

        torch.set_num_threads(threads)
    except ImportError:
        pass


# --------------------------------------------------------------------------- process set-up


def set_up_worker(threads: int) -> None:
    """What a worker process sets once when it starts, before any frame: its share of the cores
    (``set_threads``) and glibc's heap kept warm between frames (``allocator.keep_heap_warm``)."""
    set_threads(threads)
    keep_heap_warm()


@contextmanager
def sigint_ignored() -> Iterator[None]:
    """Ctrl-C ignored inside the block (main thread only: elsewhere signals cannot be set)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def check_available(m: Method, keep: bool = True) -> None:
    """Build ``m`` here and check its depth network can be loaded: weights or a model that are neither on this
    machine nor downloadable are one clear error before any work, not a run in which every frame fails.

    Args:
        m: The method.
        keep: This process relocalizes the frames itself, so the built method is kept for them (else dropped,
            leaving the memory to the worker processes).
    """
    loc = built_localizer(m)
    if not keep:
        _LOCALIZERS.pop(_method_key(m), None)
    check_depth_source(loc)


def check_depth_source(loc: QueryLocalizer) -> None:
    """Raise the clear error of a localizer's depth network that can be neither found nor downloaded (nothing
    for a method without one): ``loc.check_available()``."""
    loc.check_available()
