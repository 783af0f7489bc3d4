"""The depth-source interfaces: a metric depth map for a frame, for a pair of images, or from a network.

Every source is a ``DepthSource``; what else it can do is declared by the base class it derives from, so the
relocalization pipeline asks the right question of each without probing:

- ``FileDepthSource``: maps stored beside the photos, read where the photos are decoded; stored on the photo's
  pixel grid, so they are turned with a photo whose EXIF orientation turns it upright;
- ``NetworkDepthSource``: a network that predicts depth from pixels (``predict``), in batches (``depth_many``);
  ``check_available`` says up front when it can be neither found nor downloaded;
- ``PairDepthSource``: depth that comes with a pair of images (``pair_depth``), asked for after matching.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..data import Frame

__all__ = ["DepthSource", "FileDepthSource", "NetworkDepthSource", "PairDepthSource"]


class DepthSource(ABC):
    """A source of metric depth maps for frames.

    Attributes:
        name: The spec a user types (``files:sensor``, ``dav2-indoor``, ``mast3r``, ``none``).
        metric: False for a source that gives no usable scale (``none``): poses are then up to scale.
    """

    name: str = ""
    metric: bool = True

    @abstractmethod
    def depth(self, frame: Frame) -> np.ndarray | None:
        """The depth map of one frame.

        Args:
            frame: A dataset frame (its image path and intrinsics).

        Returns:
            (H, W) float32 metres at the frame's image size, 0 where invalid; None when the source has none.
        """

    def depth_many(self, frames: Sequence[Frame]) -> list[np.ndarray | None]:
        """``depth`` of several frames, in order (network sources predict them in batches).

        Args:
            frames: Dataset frames.

        Returns:
            One map (or None) per frame, as ``depth`` gives it.
        """
        return [self.depth(frame) for frame in frames]

    def check_available(self) -> None:  # noqa: B027 - an optional hook, a no-op unless overridden
        """Raise now, with a clear message, when the source could not produce depth (a network that is neither
        on this machine nor downloadable); nothing to check for most sources."""


class FileDepthSource(DepthSource):
    """Depth maps stored beside the photos (read by the decode workers of the batched pipeline). They are stored
    on the photo's stored pixel grid: a photo turned upright by its EXIF orientation has its map turned alike."""


class NetworkDepthSource(DepthSource):
    """A network that predicts metric depth from pixels; ``depth_many`` runs it in batches."""

    @abstractmethod
    def predict(self, images: Sequence[np.ndarray], focals: Sequence[float | None] | None = None) -> list[np.ndarray]:
        """Metric depth of same-size images.

        Args:
            images: (H, W, 3) uint8 RGB images, all of one size.
            focals: Each image's focal length fx in pixels (networks that take it, e.g. Depth Pro), or None.

        Returns:
            One (H, W) float32 map in metres per image, 0 where invalid.
        """


class PairDepthSource(DepthSource):
    """Depth that depends on both images of a pair (a two-view network's pointmaps, MicKey's keypoints): the
    relocalizer asks for it after matching, with the matcher's features. ``depth`` of a frame alone is None."""

    def depth(self, frame: Frame) -> None:
        """No depth from one frame alone: see ``pair_depth``.

        Args:
            frame: Any frame.

        Returns:
            None.
        """
        return None

    @abstractmethod
    def pair_depth(
        self,
        reference: np.ndarray,
        query: np.ndarray,
        need_query: bool = True,
        features: tuple[Any, Any] = (None, None),
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Depth of both images of a pair.

        Args:
            reference: (H0, W0, 3) uint8 RGB reference image.
            query: (H1, W1, 3) uint8 RGB query image.
            need_query: Whether the query's map is needed (a PnP solver lifts the reference only).
            features: The matcher's ``Features`` of both images, whose network outputs are reused when they come
                from this source's network.

        Returns:
            (reference map (H0, W0), query map (H1, W1) or None) in metres, float32, 0 where invalid.
        """
