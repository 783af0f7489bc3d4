"""Depth maps stored beside the images (``frame.SUFFIX.png``, uint16 millimetres), and the scale-free ``none``."""

from __future__ import annotations

import cv2
import numpy as np

from ..data import Frame, check_depth_size
from .base import DepthSource, FileDepthSource

__all__ = ["FileDepth", "NoDepth"]


class FileDepth(FileDepthSource):
    """``files:SUFFIX``: reads ``frame.SUFFIX.png`` (uint16 millimetres); None when the frame has no such file.

    Args:
        suffix: The maps' suffix (``sensor``, ``dptkitti``): ``frame_00000.jpg`` -> ``frame_00000.sensor.png``.
    """

    def __init__(self, suffix: str) -> None:
        if not suffix or "/" in suffix:
            raise ValueError(f"bad depth suffix {suffix!r} (expected e.g. 'dptkitti' or 'sensor')")
        self.suffix = suffix
        self.name = f"files:{suffix}"

    def depth(self, frame: Frame) -> np.ndarray | None:
        """The frame's stored map at its image size (nearest-neighbour resize of a map stored at another size).

        Args:
            frame: A dataset frame.

        Returns:
            (H, W) float32 metres (0 = invalid), or None when the frame has no ``SUFFIX`` map.

        Raises:
            FormatError: The file is not a readable depth PNG, or of another aspect ratio (the message names it).
        """
        if not frame.has_depth(self.suffix):
            return None
        d = frame.depth(self.suffix)  # FormatError naming the file when it is corrupt
        w, h = frame.intrinsics.width, frame.intrinsics.height
        check_depth_size(frame.depth_path(self.suffix), d.shape, w, h)
        if d.shape != (h, w):  # a map stored at another resolution: nearest keeps invalid pixels invalid
            d = cv2.resize(d, (int(w), int(h)), interpolation=cv2.INTER_NEAREST)
        return d


class NoDepth(DepthSource):
    """``none``: no depth at all; solvers then return poses up to scale (``metric`` is False)."""

    name = "none"
    metric = False

    def depth(self, frame: Frame) -> np.ndarray | None:
        """None: this source has no depth.

        Args:
            frame: Any frame.

        Returns:
            None.
        """
        return None
