"""MicKey's input: the image resized (OpenCV, bilinear) to 540x720 (W x H) whatever its shape, RGB / 255, no
mean or standard deviation; the intrinsics scaled by the same factors with the half-pixel rule (the public
``correct_intrinsic_scale``). The network then crops the bottom and right to multiples of 14 (532x714).

The Map-free photos are 540x720 portrait; other shapes are stretched to it, as the public code does.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ..geometry import to_original

__all__ = ["Prepared", "prepare_array", "scale_intrinsics", "INPUT_SIZE"]

#: (width, height) of the published models' input.
INPUT_SIZE = (540, 720)


@dataclass(frozen=True)
class Prepared:
    """One network input (3, H, W) float in [0, 1] and the size of the image it comes from."""

    tensor: torch.Tensor
    original_size: tuple[int, int]  # (width, height)

    @property
    def input_size(self) -> tuple[int, int]:
        return int(self.tensor.shape[2]), int(self.tensor.shape[1])

    def scale(self) -> tuple[float, float]:
        """(sx, sy) = network input / original."""
        return self.input_size[0] / self.original_size[0], self.input_size[1] / self.original_size[1]

    def to_original(self, xy: np.ndarray) -> np.ndarray:
        """Network-input pixels -> original-image pixels (pixel centres at integers in both)."""
        return to_original(xy, self.scale())


def prepare_array(image: np.ndarray, size: tuple[int, int] = INPUT_SIZE) -> Prepared:
    """An (H, W, 3) uint8 RGB image -> the network input at ``size`` (W, H)."""
    h, w = image.shape[:2]
    resized = image if (w, h) == tuple(size) else cv2.resize(image, tuple(size), interpolation=cv2.INTER_LINEAR)
    t = torch.from_numpy(np.ascontiguousarray(resized)).permute(2, 0, 1).float().div(255)
    return Prepared(t, (w, h))


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K for pixel coordinates x' = sx (x + 0.5) - 0.5, y' = sy (y + 0.5) - 0.5 (what a resize by (sx, sy) does)."""
    T = np.array([[sx, 0, sx / 2 - 0.5], [0, sy, sy / 2 - 0.5], [0, 0, 1]], dtype=np.float64)
    return T @ np.asarray(K, dtype=np.float64)
