"""Depth maps stored beside the images (``frame.SUFFIX.png``, uint16 millimetres), and the scale-free ``none``."""

from __future__ import annotations

import cv2
import numpy as np

from ..data import Frame, check_depth_size

__all__ = ["FileDepth", "NoDepth"]


class FileDepth:
    """``files:SUFFIX``: reads ``frame.SUFFIX.png``; None when the frame has no such file."""

    metric = True
    reads_files = True  # its maps are stored like the photo's pixel grid (turned with a tagged photo)

    def __init__(self, suffix: str) -> None:
        if not suffix or "/" in suffix:
            raise ValueError(f"bad depth suffix {suffix!r} (expected e.g. 'dptkitti' or 'sensor')")
        self.suffix = suffix
        self.name = f"files:{suffix}"

    def depth(self, frame: Frame) -> np.ndarray | None:
        if not frame.has_depth(self.suffix):
            return None
        d = frame.depth(self.suffix)  # FormatError naming the file when it is corrupt
        w, h = frame.intrinsics.width, frame.intrinsics.height
        check_depth_size(frame.depth_path(self.suffix), d.shape, w, h)
        if d.shape != (h, w):  # a map stored at another resolution: nearest keeps invalid pixels invalid
            d = cv2.resize(d, (int(w), int(h)), interpolation=cv2.INTER_NEAREST)
        return d

    def depth_many(self, frames: list[Frame]) -> list[np.ndarray | None]:
        return [self.depth(f) for f in frames]


class NoDepth:
    """``none``: no depth at all; solvers then return poses up to scale (``metric`` is False)."""

    name = "none"
    metric = False

    def depth(self, frame: Frame) -> np.ndarray | None:
        return None

    def depth_many(self, frames: list[Frame]) -> list[np.ndarray | None]:
        return [None] * len(frames)
