"""Prepared anchors, what localizing against an anchor reuses, kept per API process in an LRU bounded in bytes.

An entry holds, per photo, what the method needs and nothing more: its features (keypoints, descriptors),
its depth at the working size (solvers sample it around keypoints, Procrustes refinement reads the whole
map), intrinsics and pose; for several photos the retrieval vocabulary and one global descriptor each. The
decoded photos are dropped once prepared. Each entry's size is measured by walking what it holds
(``deep_nbytes``), not estimated."""

from __future__ import annotations

import sys
import threading
from collections import OrderedDict
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field, fields, is_dataclass, replace
from typing import Any

import numpy as np

from ...estimate import Estimate
from ...geometry import Pose

#: An anchor photo's pixels once its features are extracted: nothing.
NO_PIXELS = np.zeros((0, 0, 3), np.uint8)


_ARRAY_HEADER = sys.getsizeof(np.empty(0)) - np.empty(0).nbytes  # an array object without its buffer


def _array_root(a: np.ndarray) -> np.ndarray:
    while isinstance(a.base, np.ndarray):
        a = a.base
    return a


def deep_nbytes(obj: Any, _seen: set | None = None, _depth: int = 0) -> int:
    """Bytes that ``obj`` keeps alive: NumPy buffers (a slice counts its whole base), torch tensor storages,
    bytes and strings, followed through containers, dataclasses and plain objects' attributes (each buffer
    once). Other Python objects are counted with ``sys.getsizeof``."""
    seen = set() if _seen is None else _seen
    if _depth > 50:
        return 0
    if isinstance(obj, np.ndarray):
        root = _array_root(obj)
        if id(root) in seen:
            return 0
        seen.add(id(root))
        return int(root.nbytes) + _ARRAY_HEADER
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(obj, torch.Tensor):
        storage = obj.untyped_storage()
        key = ("torch", storage.data_ptr(), storage.device.type)
        if key in seen:
            return 0
        seen.add(key)
        return int(storage.nbytes())
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    n = sys.getsizeof(obj)
    if isinstance(obj, (str, bytes, bytearray, int, float, bool, type(None))):
        return n
    if isinstance(obj, dict):
        return n + sum(deep_nbytes(k, seen, _depth + 1) + deep_nbytes(v, seen, _depth + 1) for k, v in obj.items())
    if isinstance(obj, (list, tuple, set, frozenset)):
        return n + sum(deep_nbytes(v, seen, _depth + 1) for v in obj)
    if is_dataclass(obj) and not isinstance(obj, type):
        return n + sum(deep_nbytes(getattr(obj, f.name, None), seen, _depth + 1) for f in fields(obj))
    if hasattr(obj, "__dict__") and not isinstance(obj, type):
        return n + deep_nbytes(vars(obj), seen, _depth + 1)
    return n


@dataclass
class PreparedPhoto:
    """One photo of an anchor, ready to match: the method's prepared reference without pixels (matching
    methods), or its ``View`` at the working size (method kinds that take a reference view as it is)."""

    reference: Any
    pose: Pose
    name: str


@dataclass
class PreparedAnchor:
    """Everything localizing against one version of an anchor reuses; ``nbytes``: what it keeps in memory."""

    photos: list[PreparedPhoto]
    describer: Any = None  # DenseVLAD fitted on the photos (several photos only)
    descriptors: np.ndarray | None = None  # one global descriptor per photo
    nbytes: int = field(default=0, compare=False)


def prepare_anchor(loc: Any, photos: Sequence[Any]) -> PreparedAnchor:
    """Prepare every photo (a ``photos.Photo``: a ``View`` at the working size with its ``pose``) with localizer
    ``loc``; with several photos learn the retrieval vocabulary on them (as ``ReferenceSet`` does) and describe
    each."""
    from ... import retrieval
    from ...relocalize import Anchor, View

    views = [replace(p, name=f"photo {i}") for i, p in enumerate(photos)]
    describer = descriptors = None
    if len(views) > 1:
        describer = retrieval.create("densevlad")
        descriptors = describer.fit_describe([v.image for v in views])
    out = []
    for v, p in zip(views, photos):
        ref = loc.prepare(v)  # a method without a reusable anchor (regression) keeps the photo itself
        if isinstance(ref, Anchor):
            ref = replace(ref, view=View(NO_PIXELS, v.intrinsics, None, name=v.name))
        out.append(PreparedPhoto(ref, p.pose, v.name))
    prepared = PreparedAnchor(out, describer, descriptors)
    prepared.nbytes = deep_nbytes(prepared)
    return prepared


def localize_prepared(loc: Any, prepared: PreparedAnchor, query: Any) -> Estimate:
    """World-to-camera pose of the ``query`` view in the anchor's frame: against its only photo, or against the
    most similar one (DenseVLAD) of several; ``Estimate.photo`` is that photo's position."""
    from ...relocalize import View
    from ...retrieval import retrieve

    i, sim = 0, None
    if prepared.descriptors is not None:
        order, sims = retrieve(prepared.describer.describe(query.image), prepared.descriptors, top=1)
        i, sim = int(order[0]), float(sims[0])
    photo = prepared.photos[i]
    if isinstance(photo.reference, View):
        loc.set_reference(photo.reference)
        est = loc.localize(query)
    else:
        est = loc.localize(query, photo.reference)
    if sim is not None:
        est.extras.update(reference=photo.name, retrieval_similarity=sim)
        if est.pose is not None:
            est.pose = est.pose @ photo.pose
    est.photo = i
    return est


class ByteLRU:
    """A thread-safe LRU whose entries have a size (``nbytes``) and an owner (the account whose request put
    them): while the total is over ``max_bytes``, the least recently used entry *of the owner holding the most
    bytes* is dropped, so that one account cannot evict everyone else's entries, only its own once it holds the
    most. An entry larger than the whole budget is not kept at all."""

    def __init__(self, max_bytes: int):
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[Hashable, tuple[Any, int, Hashable]] = OrderedDict()
        self._owned: dict[Hashable, int] = {}  # bytes per owner
        self._lock = threading.Lock()
        self.total = 0

    def get(self, key: Hashable) -> Any:
        with self._lock:
            item = self._items.get(key)
            if item is None:
                return None
            self._items.move_to_end(key)
            return item[0]

    def _pop(self, key: Hashable) -> None:
        _, n, owner = self._items.pop(key)
        self.total -= n
        self._owned[owner] -= n
        if not self._owned[owner]:
            del self._owned[owner]

    def put(self, key: Hashable, value: Any, nbytes: int, owner: Hashable = None) -> None:
        with self._lock:
            if key in self._items:
                self._pop(key)
            if nbytes > self.max_bytes:
                return
            self._items[key] = (value, nbytes, owner)
            self.total += nbytes
            self._owned[owner] = self._owned.get(owner, 0) + nbytes
            while self.total > self.max_bytes and self._items:
                heaviest = max(self._owned, key=self._owned.__getitem__)
                self._pop(next(k for k, item in self._items.items() if item[2] == heaviest))

    def owned(self, owner: Hashable) -> int:
        """Bytes held by ``owner``'s entries."""
        with self._lock:
            return self._owned.get(owner, 0)

    def drop(self, match) -> None:
        """Forget every entry whose key ``match(key)`` is true."""
        with self._lock:
            for k in [k for k in self._items if match(k)]:
                self._pop(k)

    def __len__(self) -> int:
        return len(self._items)
