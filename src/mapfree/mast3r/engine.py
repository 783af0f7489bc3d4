"""One network, shared by the ``mast3r``/``dust3r`` matcher and depth source, with one forward pass per pair.

``encode(image)`` runs the encoder once per image (the reference's output is kept by whoever holds its
``Features``, so a new query only encodes itself); ``pair(ref, query)`` decodes the pair once and keeps what the
depth source needs (the reference's depth and confidence) until the solver asks for it. Caches are keyed on
the identity of the image arrays, so the matcher and the depth source meet on the same entries.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..matching.utils import resolve_device
from .checkpoint import find_checkpoint, load_model
from .model import AsymmetricModel, Encoded
from .preprocess import Prepared, prepare_array

__all__ = ["EncodedImage", "PairOutput", "PairEngine", "shared_engine"]


@dataclass
class EncodedImage:
    """An image after preprocessing and the encoder."""

    prepared: Prepared
    encoded: Encoded
    engine_id: int = 0  # id() of the engine that made it (its network and input size)


@dataclass
class PairOutput:
    """What one forward pass of (view 1, view 2) leaves for the matcher and the depth source, on the CPU."""

    pts1: np.ndarray  # (H1, W1, 3) view 1's points in its own frame
    conf1: np.ndarray  # (H1, W1)
    pts2: np.ndarray  # (H2, W2, 3) view 2's points in view 1's frame
    conf2: np.ndarray
    desc1: np.ndarray | None = None  # (H1, W1, D) unit descriptors (MASt3R)
    desc2: np.ndarray | None = None
    desc_conf1: np.ndarray | None = None
    desc_conf2: np.ndarray | None = None
    extras: dict[str, Any] = field(default_factory=dict)

    def without_descriptors(self) -> "PairOutput":
        """What the cache keeps (the depth source's part): two 24-D maps are 90% of a pair's output."""
        return PairOutput(self.pts1, self.conf1, self.pts2, self.conf2)


class _IdentityCache:
    """A small LRU keyed on the identity of objects (weakly held, so a recycled id never hits a dead entry)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._items: OrderedDict[tuple[int, ...], tuple[tuple[weakref.ref, ...], Any]] = OrderedDict()

    def get(self, *objs: Any) -> Any:
        key = tuple(map(id, objs))
        hit = self._items.get(key)
        if hit is None or any(r() is not o for r, o in zip(hit[0], objs)):
            return None
        self._items.move_to_end(key)
        return hit[1]

    def put(self, value: Any, *objs: Any) -> None:
        self._items[tuple(map(id, objs))] = (tuple(weakref.ref(o) for o in objs), value)
        self._items.move_to_end(tuple(map(id, objs)))
        while len(self._items) > self.size:
            self._items.popitem(last=False)


class PairEngine:
    """A loaded network with its caches. Thread-safe (the batched pipeline solves in a thread pool, the
    relocalizer reads the next query ahead): the lock guards the caches, not the network's passes."""

    def __init__(self, model: AsymmetricModel, device: torch.device, name: str = "mast3r", long_side: int = 512,
                 cache_pairs: int = 32) -> None:
        self.model, self.device, self.name, self.long_side = model, device, name, long_side
        self._images = _IdentityCache(cache_pairs)
        self._pairs = _IdentityCache(cache_pairs)
        self._lock = threading.RLock()
        self.encodes = 0  # counters for tests and benchmarks
        self.forwards = 0

    @property
    def has_descriptors(self) -> bool:
        return self.model.cfg.has_descriptors

    def encode(self, image: np.ndarray) -> EncodedImage:
        """(H, W, 3) uint8 RGB -> preprocessed and encoded (cached on the array's identity)."""
        with self._lock:
            hit = self._images.get(image)
        if hit is not None:
            return hit
        prep = prepare_array(image, self.long_side)
        with torch.inference_mode():  # outside the lock: another thread may use the cache meanwhile
            enc = self.model.encode(prep.tensor.to(self.device))
        out = EncodedImage(prep, enc, id(self))
        with self._lock:
            self.encodes += 1
            self._images.put(out, image)
        return out

    def pair(self, first: EncodedImage, second: EncodedImage, descriptors: bool = False) -> PairOutput:
        """Decoders and heads on (first, second), once per pair; ``first`` is the frame of both pointmaps.

        The cache keeps points and confidences: the matcher asks first (``descriptors`` True: a fresh pass) and
        the depth source later finds the same pass's points here."""
        with self._lock:
            hit = self._pairs.get(first, second)
        if hit is not None and not (descriptors and self.has_descriptors):
            return hit
        with torch.inference_mode():
            r1, r2 = self.model.predict(first.encoded, second.encoded)

        def cpu(t: torch.Tensor | None) -> np.ndarray | None:
            return None if t is None else t[0].float().cpu().numpy()

        out = PairOutput(cpu(r1["pts3d"]), cpu(r1["conf"]), cpu(r2["pts3d_in_other_view"]), cpu(r2["conf"]),
                         cpu(r1.get("desc")), cpu(r2.get("desc")), cpu(r1.get("desc_conf")), cpu(r2.get("desc_conf")))
        with self._lock:
            self.forwards += 1
            self._pairs.put(out.without_descriptors(), first, second)
        return out


_ENGINES: dict[tuple[str, str, str, int], PairEngine] = {}
_ENGINES_LOCK = threading.Lock()


def shared_engine(kind: str, weights: str | Path | None = None, device: str | torch.device | None = None,
                  long_side: int = 512) -> PairEngine:
    """The one engine per (kind, checkpoint, device, input size): a method's matcher and depth source share it.

    The checkpoint is found first, so a missing file fails before any image is read. ``long_side`` 512 is the
    published models' input; smaller sizes are for quick checks only."""
    path = find_checkpoint(kind, weights)
    dev = resolve_device(device)  # as the matcher and depth source resolve theirs: None/"auto" -> cuda if any
    key = (kind, str(path.resolve()), str(dev), int(long_side))
    with _ENGINES_LOCK:
        if key not in _ENGINES:
            model = load_model(path, dev)
            if kind == "mast3r" and not model.cfg.has_descriptors:  # DUSt3R runs on either kind of checkpoint
                raise ValueError(f"{path}: a {model.cfg.class_name} checkpoint has no descriptor head; "
                                 f"mast3r needs an AsymmetricMASt3R checkpoint")
            _ENGINES[key] = PairEngine(model, dev, kind, int(long_side))
        return _ENGINES[key]
