"""The batched, pipelined path for many queries against one reference (what ``mapfree run`` uses on a GPU).

Three stages overlap: background threads decode query images and depth maps (OpenCV releases the GIL); the
calling thread extracts ``batch_size`` queries' features in one network pass and matches them in batches
against the cached reference features; a pool of threads runs the CPU solvers of one batch while the device
works on the next. Results come out in query order and equal ``Relocalizer.localize`` one pair at a time:
every matcher's batched entry points give each pair the result it gets alone.
"""

from __future__ import annotations

import os
import time
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from itertools import islice
from typing import Protocol

from ..depth.base import DepthSource, NetworkDepthSource
from ..estimate import Estimate
from ..localizer import BatchOptions
from ..matching.base import Features, Matcher, Matches
from .views import Anchor, PreparedQuery, ViewLike, as_view, error_reason, fit_depth, view_depth

__all__ = ["BatchOptions", "Stages", "localize_batched", "default_batch_size"]


class Stages(Protocol):
    """What the batched path drives (a ``Relocalizer``): its matcher, its depth source, and its last stage."""

    matcher: Matcher
    depth_source: DepthSource

    def conclude(self, anchor: Anchor, prep: PreparedQuery, matches: Matches | None, match_s: float) -> Estimate:
        """Solve one matched query (thread-safe: a pool of solver threads runs it)."""
        ...


def default_batch_size(matcher: Matcher) -> int:
    """Queries per device pass when the caller leaves it open.

    Args:
        matcher: The method's matcher.

    Returns:
        16 for a matcher on a GPU, 0 (the one-pair-at-a-time path) elsewhere.
    """
    return 16 if matcher.on_gpu else 0


def _depth_in_workers(source: DepthSource) -> bool:
    """Depth the decode workers can produce: everything but a network's, which runs on the device stage a batch
    at a time (``depth_many``)."""
    return not isinstance(source, NetworkDepthSource)


def _read(stages: Stages, query: ViewLike) -> PreparedQuery:
    """Decode one query and read its depth file (no network work): a decode worker's job."""
    t0 = time.perf_counter()
    try:
        view = as_view(query)
        t1 = time.perf_counter()
        if _depth_in_workers(stages.depth_source):  # a depth file is decoded here, beside its photo
            depth = view_depth(stages.depth_source, view)
        else:
            depth = fit_depth(view.depth, view.intrinsics)
        t2 = time.perf_counter()
    except Exception as e:  # a bad frame is a "no estimate" for that frame, never the end of the run
        return PreparedQuery(None, None, None, {"read": time.perf_counter() - t0}, error_reason(e))
    return PreparedQuery(view, None, depth, {"read": t1 - t0, "depth": t2 - t1})


def _network_depth(stages: Stages, batch: list[PreparedQuery]) -> None:
    """Depth from a network for the batch's frames in one ``depth_many`` call (cached on disk by the source)."""
    src = stages.depth_source
    todo = [
        (p, p.view, p.view.frame)
        for p in batch
        if p.error is None and p.depth is None and p.view is not None and p.view.frame is not None
    ]
    if not todo or not isinstance(src, NetworkDepthSource) or not src.metric:
        return
    t0 = time.perf_counter()
    deps = src.depth_many([frame for _, _, frame in todo])
    share = (time.perf_counter() - t0) / len(todo)
    for (p, view, _), d in zip(todo, deps):
        p.depth = fit_depth(d, view.intrinsics, owned=True)  # fresh from the network or its cache file
        p.timings["depth"] = p.timings.get("depth", 0.0) + share


def _extract(stages: Stages, batch: list[PreparedQuery]) -> None:
    """Features of the batch's readable queries in one ``extract_many`` call; if the batch fails (a bad
    image), each query is extracted alone so only the bad one fails."""
    ok = [(p, p.view) for p in batch if p.error is None and p.view is not None]
    if not ok:
        return
    t0 = time.perf_counter()
    matcher = stages.matcher
    feats: list[Features | None]
    try:
        feats = list(matcher.extract_many([view.image for _, view in ok]))
    except Exception:
        feats = []
        for p, view in ok:
            try:
                feats.append(matcher.extract(view.image))
            except Exception as e:
                p.error = error_reason(e)
                feats.append(None)
    share = (time.perf_counter() - t0) / len(ok)
    for (p, _), f in zip(ok, feats):
        p.features = f
        p.timings["extract"] = share


def _match(stages: Stages, anchor: Anchor, batch: list[PreparedQuery]) -> tuple[list[Matches | None], float]:
    """Matches of the batch's extracted queries against the anchor, all in one ``match_many`` call (one network
    pass for the matchers that batch); if it fails, each query is matched alone so only the bad one fails."""
    ok = [(i, f) for i, p in enumerate(batch) if p.error is None and (f := p.features) is not None]
    out: list[Matches | None] = [None] * len(batch)
    if not ok:
        return out, 0.0
    t0 = time.perf_counter()
    matcher = stages.matcher
    res: list[Matches] | None
    try:
        res = matcher.match_many(anchor.features, [f for _, f in ok], batch_size=len(ok))
    except Exception:
        res = None
    for j, (i, f) in enumerate(ok):
        if res is not None:
            out[i] = res[j]
            continue
        try:
            out[i] = matcher.match(anchor.features, f)
        except Exception as e:
            batch[i].error = error_reason(e)
    return out, (time.perf_counter() - t0) / len(ok)


def localize_batched(
    stages: Stages, anchor: Anchor, queries: Iterable[ViewLike], options: BatchOptions | None = None
) -> Iterator[Estimate]:
    """Estimates for ``queries`` in order (see the module docstring).

    Args:
        stages: The relocalizer (its reference precheck passed: every query needs the pipeline).
        anchor: The prepared reference.
        queries: ``as_view`` inputs (dataset frames, views, ``(image, K[, depth])``).
        options: Batch size and threads (default ``BatchOptions()``).

    Returns:
        One estimate per query, in order, each equal to what ``Relocalizer.localize`` gives it alone.
    """
    o = options or BatchOptions()
    size = max(1, o.batch_size)
    solvers = o.solve_workers or min(8, os.cpu_count() or 1)
    it = iter(queries)
    with (
        ThreadPoolExecutor(max(1, o.decode_workers), thread_name_prefix="mapfree-decode") as decode,
        ThreadPoolExecutor(solvers, thread_name_prefix="mapfree-solve") as solve,
    ):
        reading: deque[Future[PreparedQuery]] = deque(
            decode.submit(_read, stages, q) for q in islice(it, size * max(1, o.ahead))
        )
        solving: deque[Future[Estimate]] = deque()
        while reading:
            batch = [reading.popleft().result() for _ in range(min(size, len(reading)))]
            reading.extend(decode.submit(_read, stages, q) for q in islice(it, len(batch)))  # keep decoding ahead
            _network_depth(stages, batch)
            _extract(stages, batch)
            matches, match_s = _match(stages, anchor, batch)
            solving.extend(solve.submit(stages.conclude, anchor, p, m, match_s) for p, m in zip(batch, matches))
            # Hand out the previous batch's results while this one is being solved and the next one matched.
            while len(solving) > len(batch):
                yield solving.popleft().result()
        while solving:
            yield solving.popleft().result()
