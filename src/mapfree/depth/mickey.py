"""``mickey`` depth: the metric depth MicKey predicts for each of its keypoints, as sparse depth maps.

Each image's map is zero except at its keypoints' pixels (original image size, the keypoint rounded to the
nearest pixel, as the solvers' nearest-pixel depth look-up reads it back), so our PnP, Procrustes and Ess.Mat
solvers run on MicKey's own geometry. Depths come with the matcher's features: the source asks after matching
(``pairwise``) and reads them from the features it is handed, running the network itself only on an image whose
features come from another matcher.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..matching.base import Features
from ..mickey.engine import MickeyEngine, MickeyImage, MickeyNetworkOptions, engine_for
from .base import PairDepthSource

__all__ = ["MickeyDepth", "MickeyDepthOptions", "sparse_depth_map"]

#: The depth source's options: those of the network (checkpoint, weights, dinov2, config, fp16, device), as the
#: ``mickey`` matcher's, so that both share one network.
MickeyDepthOptions = MickeyNetworkOptions


def sparse_depth_map(out: MickeyImage) -> np.ndarray:
    """MicKey's keypoints' depths as a sparse map.

    Args:
        out: MicKey's output for one image.

    Returns:
        (H, W) float32 at the original size: each keypoint's depth (metres) at its nearest pixel, 0 elsewhere and
        where the depth is not a positive finite number. Where two keypoints share a pixel the higher-scored wins.
    """
    w, h = out.original_size
    k = out.keypoints
    xy = np.rint(out.xy_original().cpu().numpy()).astype(np.int64)
    z = k.depth[0].float().cpu().numpy()
    order = np.argsort(k.score[0].float().cpu().numpy(), kind="stable")  # ascending: the best written last
    xy, z = xy[order], z[order]
    ok = (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h) & np.isfinite(z) & (z > 0)
    d = np.zeros((h, w), np.float32)
    d[xy[ok, 1], xy[ok, 0]] = z[ok]
    return d


class MickeyDepth(PairDepthSource):
    """Depth of MicKey's keypoints of both images of a pair.

    Args:
        engine: The matcher's network; else the shared one for the options.
        options: ``MickeyDepthOptions`` (the network's: checkpoint, weights, dinov2, config, fp16, device), checked
            as every component's are.
        **overrides: Single options over ``options``.
    """

    name = "mickey"

    def __init__(
        self, engine: MickeyEngine | None = None, options: MickeyDepthOptions | None = None, **overrides: object
    ) -> None:
        self.options = MickeyDepthOptions.build(overrides, owner="depth network 'mickey'", base=options)
        self.engine = engine if engine is not None else engine_for(self.options)

    def _map(self, image: np.ndarray, features: Any) -> np.ndarray:
        if isinstance(features, Features):
            out = features.data.get("mickey")
            if isinstance(out, MickeyImage):
                return sparse_depth_map(out)
            if len(features) == 0:  # a blank image: no keypoints, no depth
                return np.zeros(features.image_size[::-1], np.float32)
        return sparse_depth_map(self.engine.extract([image])[0])

    def pair_depth(
        self,
        reference: np.ndarray,
        query: np.ndarray,
        need_query: bool = True,
        features: tuple[Any, Any] = (None, None),
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Sparse depth maps of both images of a pair.

        Args:
            reference: (H0, W0, 3) uint8 RGB.
            query: (H1, W1, 3) uint8 RGB.
            need_query: Whether the query's map is needed.
            features: The matcher's features of both images: MicKey's are read (no network pass), others' images are
                run through the network.

        Returns:
            (reference map (H0, W0), query map (H1, W1) or None), float32 metres (0 off the keypoints).
        """
        d_ref = self._map(reference, features[0])
        return d_ref, self._map(query, features[1]) if need_query else None
