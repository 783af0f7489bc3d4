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
    """One network input and the size of the image it comes from.

    Attributes:
        tensor: (3, H, W) float32 RGB in [0, 1].
        original_size: (width, height) of the original image, pixels.
    """

    tensor: torch.Tensor
    original_size: tuple[int, int]  # (width, height)

    @property
    def input_size(self) -> tuple[int, int]:
        """(width, height) of the network input, pixels."""
        return int(self.tensor.shape[2]), int(self.tensor.shape[1])

    def scale(self) -> tuple[float, float]:
        """(sx, sy) = network input size / original size."""
        return self.input_size[0] / self.original_size[0], self.input_size[1] / self.original_size[1]

    def to_original(self, xy: np.ndarray) -> np.ndarray:
        """Map network-input pixels back to the original image (pixel centres at integers in both).

        Args:
            xy: (N, 2) pixel coordinates in the network input.

        Returns:
            (N, 2) pixel coordinates in the original image.
        """
        return to_original(xy, self.scale())


def prepare_array(image: np.ndarray, size: tuple[int, int] = INPUT_SIZE) -> Prepared:
    """Resize an image to the network input (bilinear, aspect not kept, as the public code does).

    Args:
        image: (H, W, 3) uint8 RGB.
        size: (width, height) of the network input, pixels.

    Returns:
        The network input and the original size.
    """
    h, w = image.shape[:2]
    resized = image if (w, h) == tuple(size) else cv2.resize(image, tuple(size), interpolation=cv2.INTER_LINEAR)
    t = torch.from_numpy(np.ascontiguousarray(resized)).permute(2, 0, 1).float().div(255)
    return Prepared(t, (w, h))


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics after a resize by (sx, sy), half-pixel rule: ``x' = sx (x + 0.5) - 0.5``.

    Args:
        K: (3, 3) calibration matrix of the original image.
        sx: Horizontal scale factor.
        sy: Vertical scale factor.

    Returns:
        (3, 3) calibration matrix of the resized image.
    """
    T = np.array([[sx, 0, sx / 2 - 0.5], [0, sy, sy / 2 - 0.5], [0, 0, 1]], dtype=np.float64)
    return T @ np.asarray(K, dtype=np.float64)
