"""``mast3r`` / ``dust3r`` depth: the metric pointmaps of the same forward pass that gave the matches.

A pair source (``pairwise``): depth depends on both images, so the relocalizer asks after matching with
``pair_depth(reference, query)``. The reference's depth is the z of view 1's points in its own frame (the
pass reference -> query, the one the matcher ran). The query's depth is needed only by solvers that lift the
query too (Ess.Mat's scale, Procrustes): the network gives the query's points in the *reference's* frame, so
its own-frame depth comes from the symmetric pass query -> reference (decoders and heads only: both images are
already encoded), z of view 1's points. PnP needs the reference's depth only: one forward per pair.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..mast3r.engine import EncodedImage, PairEngine, shared_engine
from ..mast3r.preprocess import Prepared
from ..matching.base import Features
from .base import PairDepthSource

__all__ = ["Mast3rDepth", "depth_at_original"]


def depth_at_original(z: np.ndarray, conf: np.ndarray, prep: Prepared, min_conf: float = 0.0) -> np.ndarray:
    """A network-resolution depth map -> the original image's size (nearest pixel; 0 outside the crop, where
    z <= 0 or the confidence is below ``min_conf``)."""
    z = np.where((z > 0) & np.isfinite(z) & (conf >= min_conf), z, 0).astype(np.float32)
    w0, h0 = prep.original_size
    sx, sy = prep.scale()
    mx = ((np.arange(w0, dtype=np.float64) + 0.5) * sx - 0.5 - prep.crop[0]).astype(np.float32)
    my = ((np.arange(h0, dtype=np.float64) + 0.5) * sy - 0.5 - prep.crop[1]).astype(np.float32)
    map_x, map_y = np.meshgrid(mx, my)
    return cv2.remap(z, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


class Mast3rDepth(PairDepthSource):
    """Depth of both images of a pair from MASt3R's (or DUSt3R's) own metric pointmaps."""

    def __init__(
        self,
        kind: str = "mast3r",
        weights: str | None = None,
        device: str | None = None,
        min_conf: float = 0.0,
        long_side: int = 512,
        engine: PairEngine | None = None,
    ) -> None:
        """``engine``: the matcher's (same network, same checkpoint and input size), else the shared one."""
        self.name = kind
        self.min_conf = min_conf
        self.engine = engine if engine is not None else shared_engine(kind, weights, device, long_side)

    def _encoded(self, image: np.ndarray, features: Any) -> EncodedImage:
        """The matcher's encoding when its features carry this engine's (a cached reference is never encoded
        again), else the engine's own (cached on the image)."""
        enc = features.data.get("encoded") if isinstance(features, Features) else None
        if isinstance(enc, EncodedImage) and enc.engine_id == id(self.engine):
            return enc
        return self.engine.encode(image)

    def pair_depth(
        self,
        reference: np.ndarray,
        query: np.ndarray,
        need_query: bool = True,
        features: tuple[Any, Any] = (None, None),
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """(reference depth, query depth or None) in metres at each image's original size. ``features``: the
        matcher's features of both images, whose encodings are reused when they come from this engine."""
        ref, q = self._encoded(reference, features[0]), self._encoded(query, features[1])
        fwd = self.engine.pair(ref, q)
        d_ref = depth_at_original(fwd.pts1[..., 2], fwd.conf1, ref.prepared, self.min_conf)
        if not need_query:
            return d_ref, None
        back = self.engine.pair(q, ref)
        return d_ref, depth_at_original(back.pts1[..., 2], back.conf1, q.prepared, self.min_conf)
