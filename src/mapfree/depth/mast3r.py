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
    """A network-resolution depth map at the original image's size.

    Args:
        z: (h, w) depths at the network's resolution, metres.
        conf: (h, w) confidences.
        prep: How the image was resized and cropped for the network.
        min_conf: Depths with a lower confidence are dropped.

    Returns:
        (H, W) float32 metres at the original size (nearest pixel; 0 outside the crop, where z <= 0, or below
        ``min_conf``).
    """
    z = np.where((z > 0) & np.isfinite(z) & (conf >= min_conf), z, 0).astype(np.float32)
    w0, h0 = prep.original_size
    sx, sy = prep.scale()
    mx = ((np.arange(w0, dtype=np.float64) + 0.5) * sx - 0.5 - prep.crop[0]).astype(np.float32)
    my = ((np.arange(h0, dtype=np.float64) + 0.5) * sy - 0.5 - prep.crop[1]).astype(np.float32)
    map_x, map_y = np.meshgrid(mx, my)
    return cv2.remap(z, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


class Mast3rDepth(PairDepthSource):
    """Depth of both images of a pair from MASt3R's (or DUSt3R's) own metric pointmaps.

    Args:
        kind: ``mast3r``, ``dust3r``, ``dune-mast3r`` or ``dune-mast3r-small``.
        weights: A checkpoint file or folder (default: the published file in the weights folders).
        device: The network's device (None: CUDA when available).
        min_conf: Depths of a lower confidence are 0.
        long_side: The network's input size (None: the published one, 512 or DUNE-MASt3R's 518).
        engine: The matcher's network (same checkpoint and input size), else the shared one.
    """

    def __init__(
        self,
        kind: str = "mast3r",
        weights: str | None = None,
        device: str | None = None,
        min_conf: float = 0.0,
        long_side: int | None = None,
        engine: PairEngine | None = None,
    ) -> None:
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
        """Depth of both images of a pair.

        The reference's is the z of view 1's points in its own frame (the pass the matcher ran); the query's comes
        from the symmetric pass (decoders and heads only: both images are encoded already).

        Args:
            reference: (H0, W0, 3) uint8 RGB.
            query: (H1, W1, 3) uint8 RGB.
            need_query: Whether the query's map is needed (PnP needs the reference's only: one pass per pair).
            features: The matcher's features of both images, whose encodings are reused when they are this engine's.

        Returns:
            (reference map (H0, W0), query map (H1, W1) or None), float32 metres.
        """
        ref, q = self._encoded(reference, features[0]), self._encoded(query, features[1])
        fwd = self.engine.pair(ref, q)
        d_ref = depth_at_original(fwd.pts1[..., 2], fwd.conf1, ref.prepared, self.min_conf)
        if not need_query:
            return d_ref, None
        back = self.engine.pair(q, ref)
        return d_ref, depth_at_original(back.pts1[..., 2], back.conf1, q.prepared, self.min_conf)
