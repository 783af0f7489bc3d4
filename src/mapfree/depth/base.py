"""The depth-source interface: a metric depth map for a frame, or None."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from ..data import Frame

__all__ = ["DepthSource"]


@runtime_checkable
class DepthSource(Protocol):
    """``depth(frame)`` -> (H,W) float32 metres at the frame's image size (0 = invalid), or None.

    ``metric`` is False for sources that give no usable scale (``none``): poses are then up to scale.
    """

    name: str
    metric: bool

    def depth(self, frame: Frame) -> np.ndarray | None: ...
