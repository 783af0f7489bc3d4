"""The batched, pipelined path for many queries against one reference (what ``mapfree run`` uses on a GPU).

Three stages overlap: background threads decode query images and depth maps (OpenCV releases the GIL); the
calling thread extracts ``batch_size`` queries' features in one network pass and matches them in batches
against the cached reference features; a pool of threads runs the CPU solvers of one batch while the device
works on the next. Results come out in query order and equal ``Relocalizer.localize`` one pair at a time:
every matcher's batched entry points give each pair the result it gets alone.
"""

from __future__ import annotations

import inspect
import os
import time
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from itertools import islice
from typing import TYPE_CHECKING

from ..estimate import Estimate
from ..matching.base import Features, Matches

if TYPE_CHECKING:
    from .pipeline import Anchor, Relocalizer, ViewLike, _Prepared

__all__ = ["BatchOptions", "localize_batched", "default_batch_size"]


@dataclass
class BatchOptions:
    """``batch_size`` queries per device pass; ``decode_workers`` threads read images and depth ahead (up to
    ``ahead`` batches); ``solve_workers`` threads run the solvers (default: the cores, at most 8)."""

    batch_size: int = 16
    decode_workers: int = 4
    solve_workers: int | None = None
    ahead: int = 2


def default_batch_size(matcher: object) -> int:
    """16 for a matcher on a GPU, 0 (the one-pair-at-a-time path) elsewhere."""
    device = getattr(matcher, "device", None)
    return 16 if getattr(device, "type", "cpu") == "cuda" else 0


def _depth_in_workers(source: object) -> bool:
    """Depth the decode workers can produce: files (``reads_files``) and sources without a batched network pass.
    Depth networks (``depth_many``) run on the device stage, a batch at a time."""
    return bool(getattr(source, "reads_files", False)) or not hasattr(source, "depth_many")


def _read(loc: Relocalizer, query: ViewLike) -> _Prepared:
    """Decode one query and read its depth file (no network work): a decode worker's job."""
    from .pipeline import _error, _fit_depth, _Prepared, as_view

    t0 = time.perf_counter()
    try:
        view = as_view(query)
        t1 = time.perf_counter()
        depth = None
        if _depth_in_workers(loc.depth_source):  # a depth file is decoded here, beside its photo
            depth = loc._depth(view)
        elif view.depth is not None:
            depth = _fit_depth(view.depth, view.intrinsics)
        t2 = time.perf_counter()
    except Exception as e:  # a bad frame is a "no estimate" for that frame, never the end of the run
        return _Prepared(None, None, None, {"read": time.perf_counter() - t0}, _error(e))
    return _Prepared(view, None, depth, {"read": t1 - t0, "depth": t2 - t1})


def _network_depth(loc: Relocalizer, batch: list[_Prepared]) -> None:
    """Depth from a network for the batch's frames in one ``depth_many`` call (cached on disk by the source)."""
    from .pipeline import _fit_depth

    src = loc.depth_source
    todo = [p for p in batch if p.error is None and p.depth is None and p.view.frame is not None]
    if not todo or _depth_in_workers(src) or not loc.metric:
        return
    t0 = time.perf_counter()
    deps = src.depth_many([p.view.frame for p in todo])
    share = (time.perf_counter() - t0) / len(todo)
    for p, d in zip(todo, deps):
        p.depth = _fit_depth(d, p.view.intrinsics, owned=True)  # fresh from the network or its cache file
        p.timings["depth"] = p.timings.get("depth", 0.0) + share


def _extract(loc: Relocalizer, batch: list[_Prepared]) -> None:
    """Features of the batch's readable queries in one ``extract_many`` call; if the batch fails (a bad
    image), each query is extracted alone so only the bad one fails."""
    from .pipeline import _error

    ok = [p for p in batch if p.error is None]
    if not ok:
        return
    t0 = time.perf_counter()
    many = getattr(loc.matcher, "extract_many", None)
    try:
        feats: list[Features] = (
            many([p.view.image for p in ok]) if many else [loc.matcher.extract(p.view.image) for p in ok]
        )
    except Exception:
        feats = []
        for p in ok:
            try:
                feats.append(loc.matcher.extract(p.view.image))
            except Exception as e:
                p.error = _error(e)
                feats.append(None)  # type: ignore[arg-type]
    share = (time.perf_counter() - t0) / len(ok)
    for p, f in zip(ok, feats):
        p.features = f
        p.timings["extract"] = share


def _match(loc: Relocalizer, anchor: Anchor, batch: list[_Prepared]) -> tuple[list[Matches | None], float]:
    """Matches of the batch's extracted queries against the anchor, all in one network pass where the
    matcher's ``match_many`` takes a ``batch_size``."""
    from .pipeline import _error

    ok = [i for i, p in enumerate(batch) if p.error is None and p.features is not None]
    out: list[Matches | None] = [None] * len(batch)
    if not ok:
        return out, 0.0
    t0 = time.perf_counter()
    many = getattr(loc.matcher, "match_many", None)
    try:
        kw = {"batch_size": len(ok)} if many and "batch_size" in inspect.signature(many).parameters else {}
        res = many(anchor.features, [batch[i].features for i in ok], **kw) if many else None
    except Exception:
        res = None
    for j, i in enumerate(ok):
        if res is not None:
            out[i] = res[j]
            continue
        try:
            out[i] = loc.matcher.match(anchor.features, batch[i].features)
        except Exception as e:
            batch[i].error = _error(e)
    return out, (time.perf_counter() - t0) / len(ok)


def localize_batched(
    loc: Relocalizer, anchor: Anchor, queries: Iterable[ViewLike], options: BatchOptions | None = None
) -> Iterator[Estimate]:
    """Estimates for ``queries`` in order (see the module docstring); ``loc`` must have passed its precheck."""
    o = options or BatchOptions()
    size = max(1, o.batch_size)
    solvers = o.solve_workers or min(8, os.cpu_count() or 1)
    it = iter(queries)
    with (
        ThreadPoolExecutor(max(1, o.decode_workers), thread_name_prefix="mapfree-decode") as decode,
        ThreadPoolExecutor(solvers, thread_name_prefix="mapfree-solve") as solve,
    ):
        reading: deque[Future] = deque(decode.submit(_read, loc, q) for q in islice(it, size * max(1, o.ahead)))
        solving: deque[Future] = deque()
        while reading:
            batch = [reading.popleft().result() for _ in range(min(size, len(reading)))]
            reading.extend(decode.submit(_read, loc, q) for q in islice(it, len(batch)))  # keep decoding ahead
            _network_depth(loc, batch)
            _extract(loc, batch)
            matches, match_s = _match(loc, anchor, batch)
            solving.extend(solve.submit(loc.conclude, anchor, p, m, match_s) for p, m in zip(batch, matches))
            # Hand out the previous batch's results while this one is being solved and the next one matched.
            while len(solving) > len(batch):
                yield solving.popleft().result()
        while solving:
            yield solving.popleft().result()
