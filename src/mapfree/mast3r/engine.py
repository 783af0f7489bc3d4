"""One network, shared by the ``mast3r``/``dust3r``/``dune-mast3r`` matcher and depth source, with one forward
pass per pair.

``encode(image)`` runs the encoder once per image (the reference's output is kept by whoever holds its
``Features``, so a new query only encodes itself); ``pair(ref, query)`` decodes the pair once and keeps what the
depth source needs (the reference's depth and confidence) until the solver asks for it. Caches are keyed on
the identity of the image arrays, so the matcher and the depth source meet on the same entries.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..runtime import resolve_device, steady_kernels
from .checkpoint import find_checkpoint, load_model
from .dune_checkpoint import find_dune_checkpoint, load_dune_model
from .model import Encoded, PairNetwork
from .preprocess import Prepared, prepare_array
from .published import DUNE_KINDS

__all__ = [
    "EncodedImage",
    "PairOutput",
    "PairEngine",
    "shared_engine",
    "find_network",
    "load_network",
    "PUBLISHED_SIZE",
    "BACKENDS",
]

#: How a network of the family runs: our PyTorch port, or the graphs of ``mapfree export`` in onnxruntime.
BACKENDS = ("torch", "onnxruntime")


@dataclass
class EncodedImage:
    """An image after preprocessing and the encoder, ready to be paired with any other.

    Attributes:
        prepared: The network input and how it maps back to the original pixels.
        encoded: The encoder's tokens.
        engine_id: ``id()`` of the engine that made it (its network and input size).
    """

    prepared: Prepared
    encoded: Encoded
    engine_id: int = 0  # id() of the engine that made it (its network and input size)


@dataclass
class PairOutput:
    """What one forward pass of (view 1, view 2) leaves for the matcher and the depth source, on the CPU.

    Maps are at the network input size; points are in metres for MASt3R's metric checkpoint, up to scale for
    DUSt3R.

    Attributes:
        pts1: (H1, W1, 3) view 1's points in its own camera frame.
        conf1: (H1, W1) their confidence.
        pts2: (H2, W2, 3) view 2's points in view 1's camera frame.
        conf2: (H2, W2) their confidence.
        desc1: (H1, W1, D) unit descriptors of view 1 (MASt3R); on the device when asked for.
        desc2: (H2, W2, D) unit descriptors of view 2.
        desc_conf1: (H1, W1) descriptor confidence of view 1.
        desc_conf2: (H2, W2) descriptor confidence of view 2.
        extras: Anything else a consumer attaches.
    """

    pts1: np.ndarray  # (H1, W1, 3) view 1's points in its own frame
    conf1: np.ndarray  # (H1, W1)
    pts2: np.ndarray  # (H2, W2, 3) view 2's points in view 1's frame
    conf2: np.ndarray
    desc1: np.ndarray | torch.Tensor | None = None  # (H1, W1, D) unit descriptors (MASt3R); on the device if asked
    desc2: np.ndarray | torch.Tensor | None = None
    desc_conf1: np.ndarray | None = None
    desc_conf2: np.ndarray | None = None
    extras: dict[str, Any] = field(default_factory=dict)

    def without_descriptors(self) -> PairOutput:
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
    """A loaded MASt3R/DUSt3R/DUNE-MASt3R network with its caches: one encoder pass per image, one decoder pass per pair.

    Thread-safe (the batched pipeline solves in a thread pool, the relocalizer reads the next query ahead):
    the lock guards the caches, not the network's passes. Get one with ``shared_engine``.

    Args:
        model: The network, on ``device``: ``AsymmetricModel`` in PyTorch or ``OnnxPairNetwork`` in onnxruntime.
        device: Where it runs.
        name: ``mast3r``, ``dust3r``, ``dune-mast3r`` or ``dune-mast3r-small``.
        long_side: Long side of the network input, pixels (512 for the published MASt3R/DUSt3R, 518 for
            DUNE-MASt3R); images are cropped to multiples of the network's patch.
        cache_pairs: Images and pairs kept in each cache.
    """

    def __init__(
        self,
        model: PairNetwork,
        device: torch.device,
        name: str = "mast3r",
        long_side: int = 512,
        cache_pairs: int = 32,
    ) -> None:
        self.model, self.device, self.name, self.long_side = model, device, name, long_side
        self._images = _IdentityCache(cache_pairs)
        self._pairs = _IdentityCache(cache_pairs)
        self._lock = threading.RLock()
        self.encodes = 0  # counters for tests and benchmarks
        self.forwards = 0

    def _prepare(self, image: np.ndarray) -> Prepared:
        """The public loader of this network: its size, its patch, squares kept or cropped to 4:3."""
        return prepare_array(image, self.long_side, self.model.cfg.patch_size, self.model.square_ok)

    @property
    def has_descriptors(self) -> bool:
        """Whether the network has MASt3R's descriptor head."""
        return self.model.cfg.has_descriptors

    def encode(self, image: np.ndarray) -> EncodedImage:
        """Preprocess and encode one image, cached on the array's identity.

        Args:
            image: (H, W, 3) uint8 RGB.

        Returns:
            The encoded image.
        """
        return self.encode_many([image])[0]

    def encode_many(self, images: Sequence[np.ndarray]) -> list[EncodedImage]:
        """``encode`` for several images: those of one network input size go through the encoder together.

        Args:
            images: (H, W, 3) uint8 RGB images.

        Returns:
            The encoded images, in order.
        """
        with self._lock:
            cached: list[EncodedImage | None] = [self._images.get(im) for im in images]
        todo = [i for i, hit in enumerate(cached) if hit is None]
        fresh: dict[int, EncodedImage] = {}
        preps = dict(zip(todo, _prepare_all([images[i] for i in todo], self._prepare)))
        for group in _groups(todo, lambda i: preps[i].true_shape):
            with torch.inference_mode(), steady_kernels():  # outside the lock: others may use the cache meanwhile
                enc = self.model.encode(torch.cat([preps[i].tensor for i in group]).to(self.device))
            for j, i in enumerate(group):
                fresh[i] = EncodedImage(
                    preps[i], Encoded(enc.tokens[j : j + 1], enc.positions[j : j + 1], enc.hw), id(self)
                )
        with self._lock:
            self.encodes += len(todo)
            for i in todo:
                self._images.put(fresh[i], images[i])
        return [hit if hit is not None else fresh[i] for i, hit in enumerate(cached)]

    def pair(self, first: EncodedImage, second: EncodedImage, descriptors: bool = False) -> PairOutput:
        """Decoders and heads on (first, second), once per pair; ``first`` is the frame of both pointmaps.

        The cache keeps points and confidences: the matcher asks first (``descriptors`` True: a fresh pass) and
        the depth source later finds the same pass's points here.

        Args:
            first: View 1, the frame of both point maps.
            second: View 2.
            descriptors: Return the descriptors too (never cached: a fresh pass unless the network has none).

        Returns:
            The pass's output on the CPU.
        """
        return self.pair_many(first, [second], descriptors)[0]

    def pair_many(
        self, first: EncodedImage, seconds: Sequence[EncodedImage], descriptors: bool = False, on_device: bool = False
    ) -> list[PairOutput]:
        """``pair`` of ``first`` with each of ``seconds``, batched: each pair's output as it is alone.

        The pairs whose second images share a size go through the decoders and heads as one batch (``first``'s
        tokens repeated).

        Args:
            first: View 1 of every pair.
            seconds: View 2 of each pair.
            descriptors: Return the descriptors too.
            on_device: Leave the descriptors on the network's device (the matcher searches them there).

        Returns:
            One output per pair, in order.
        """
        want_desc = descriptors and self.has_descriptors
        with self._lock:
            hits = [self._pairs.get(first, s) for s in seconds]
        cached: list[PairOutput | None] = [None if want_desc else h for h in hits]
        todo = [i for i, o in enumerate(cached) if o is None]
        fresh: dict[int, PairOutput] = {}
        for group in _groups(todo, lambda i: seconds[i].encoded.hw):
            b, e1 = len(group), first.encoded
            e1 = Encoded(e1.tokens.expand(b, -1, -1), e1.positions.expand(b, -1, -1), e1.hw)
            e2 = Encoded(
                torch.cat([seconds[i].encoded.tokens for i in group]),
                torch.cat([seconds[i].encoded.positions for i in group]),
                seconds[group[0]].encoded.hw,
            )
            with torch.inference_mode(), steady_kernels():
                r1, r2 = self.model.predict(e1, e2)
            host = {
                k: v.float().cpu().numpy()
                for k, v in (
                    ("pts1", r1["pts3d"]),
                    ("conf1", r1["conf"]),
                    ("pts2", r2["pts3d_in_other_view"]),
                    ("conf2", r2["conf"]),
                    ("desc_conf1", r1.get("desc_conf")),
                    ("desc_conf2", r2.get("desc_conf")),
                )
                if v is not None
            }
            desc = {k: r.get("desc") for k, r in (("desc1", r1), ("desc2", r2))}
            for j, i in enumerate(group):
                fresh[i] = PairOutput(
                    host["pts1"][j],
                    host["conf1"][j],
                    host["pts2"][j],
                    host["conf2"][j],
                    _desc_row(desc["desc1"], j, on_device),
                    _desc_row(desc["desc2"], j, on_device),
                    _row(host.get("desc_conf1"), j),
                    _row(host.get("desc_conf2"), j),
                )
        with self._lock:
            self.forwards += len(todo)
            for i in todo:
                self._pairs.put(fresh[i].without_descriptors(), first, seconds[i])
        return [o if o is not None else fresh[i] for i, o in enumerate(cached)]


def _prepare_all(images: Sequence[np.ndarray], prepare: Callable[[np.ndarray], Prepared]) -> list[Prepared]:
    """``prepare`` of each image; several at once in threads (PIL's resampling releases the GIL, and on a GPU
    this work is on the path between two network passes)."""
    if len(images) <= 1:
        return [prepare(im) for im in images]
    with ThreadPoolExecutor(min(4, len(images)), thread_name_prefix="mapfree-mast3r-prepare") as pool:
        return list(pool.map(prepare, images))


def _row(a: np.ndarray | None, j: int) -> np.ndarray | None:
    return None if a is None else a[j]


def _desc_row(t: Any, j: int, on_device: bool) -> Any:
    """Row ``j`` of a batch of descriptors: the tensor itself on the device, else a float32 array on the host."""
    return None if t is None else t[j] if on_device else t[j].float().cpu().numpy()


def _groups(indices: Sequence[int], key: Callable[[int], Hashable]) -> list[list[int]]:
    """``indices`` grouped by ``key`` (first-seen order of the groups and within them)."""
    groups: dict[Hashable, list[int]] = {}
    for i in indices:
        groups.setdefault(key(i), []).append(i)
    return list(groups.values())


_ENGINES: dict[tuple[str, str, str, int, str], PairEngine] = {}
_ENGINES_LOCK = threading.Lock()


#: Long side of the network input of each kind, pixels: the size its public recipe uses.
PUBLISHED_SIZE = {"mast3r": 512, "dust3r": 512, **{k: 518 for k in DUNE_KINDS}}


def find_network(kind: str, weights: str | Path | None = None) -> Path:
    """The checkpoint of a network of the family by the weights rule (the DUNE decoder file for DUNE kinds).

    Args:
        kind: ``mast3r``, ``dust3r``, ``dune-mast3r`` or ``dune-mast3r-small``.
        weights: A file (or hub folder) the user gave: then only there.

    Returns:
        The file or folder.

    Raises:
        MissingWeightsError: Not found.
    """
    return find_dune_checkpoint(kind, weights) if kind in DUNE_KINDS else find_checkpoint(kind, weights)


def load_network(kind: str, path: Path, device: torch.device | str = "cpu") -> PairNetwork:
    """Load a network of the family (a DUNE kind reads its decoder file and the encoder file it names).

    Args:
        kind: As ``find_network``.
        path: The checkpoint.
        device: Where to put it.

    Returns:
        The network in eval mode.

    Raises:
        ValueError: ``mast3r`` asked of a checkpoint without the descriptor head; see the loaders.
    """
    if kind in DUNE_KINDS:
        return load_dune_model(path, device)
    model = load_model(path, device)
    if kind == "mast3r" and not model.cfg.has_descriptors:  # DUSt3R runs on either kind of checkpoint
        raise ValueError(
            f"{path}: a {model.cfg.class_name} checkpoint has no descriptor head; "
            f"mast3r needs an AsymmetricMASt3R checkpoint"
        )
    return model


def shared_engine(
    kind: str,
    weights: str | Path | None = None,
    device: str | torch.device | None = None,
    long_side: int | None = None,
    backend: str = "torch",
    onnx: str | Path | None = None,
) -> PairEngine:
    """The one engine per (kind, checkpoint or graph, device, input size, backend): a method's matcher and depth
    source share it.

    The checkpoint (or graph) is found first, so a missing file fails before any image is read.

    Args:
        kind: ``mast3r``, ``dust3r``, ``dune-mast3r`` or ``dune-mast3r-small``.
        weights: The checkpoint (a ``.pth`` file or a hub folder; DUNE: the decoder file); found by the weights
            rule when None.
        device: Where to run; None and ``auto`` mean cuda when available.
        long_side: Long side of the network input, pixels; None: the published size (``PUBLISHED_SIZE``: 512,
            DUNE-MASt3R 518). Other sizes are for quick checks only.
        backend: ``torch`` (our PyTorch port) or ``onnxruntime`` (the graphs of ``mapfree export``).
        onnx: With ``onnxruntime``: the encoder graph ``NAME.onnx`` (default: ``KIND.onnx`` in the weights
            folders), its ``NAME.decoder.onnx`` beside it.

    Returns:
        The engine, loaded on first use.

    Raises:
        MissingWeightsError: No checkpoint (or graph) found.
        ValueError: ``mast3r`` asked of a checkpoint without the descriptor head; an unknown backend; a graph
            that cannot serve (``onnxgraph.GraphError``, one line).
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend {backend!r}: choose {' or '.join(BACKENDS)}")
    size = int(long_side) if long_side is not None else PUBLISHED_SIZE[kind]
    if backend == "onnxruntime":
        return _onnx_engine(kind, onnx, device, size)
    if onnx is not None:
        raise ValueError(f"onnx={onnx}: a graph is run by backend onnxruntime, not {backend}")
    path = find_network(kind, weights)
    dev = resolve_device(device)  # as the matcher and depth source resolve theirs: None/"auto" -> cuda if any
    key = (kind, str(path.resolve()), str(dev), size, backend)
    with _ENGINES_LOCK:
        if key not in _ENGINES:
            _ENGINES[key] = PairEngine(load_network(kind, path, dev), dev, kind, size)
        return _ENGINES[key]


def _onnx_engine(kind: str, onnx: str | Path | None, device: str | torch.device | None, long_side: int) -> PairEngine:
    """The engine of an exported graph pair run by onnxruntime (outputs on the CPU, whatever its provider)."""
    from .onnxgraph import OnnxPairNetwork, find_graph

    path = find_graph(kind, onnx)
    dev = resolve_device(device)
    key = (kind, str(path.resolve()), str(dev), long_side, "onnxruntime")
    with _ENGINES_LOCK:
        if key not in _ENGINES:
            net = OnnxPairNetwork(path, kind, long_side, dev)
            _ENGINES[key] = PairEngine(net, torch.device("cpu"), kind, long_side)
        return _ENGINES[key]
