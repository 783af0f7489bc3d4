"""The public ``load_images(…, size=512)`` preprocessing, and the map from its pixels back to the original's.

Long side resized to 512 with PIL (LANCZOS when shrinking, BICUBIC otherwise), centre crop to multiples of 16
(a square image is cropped to 4:3 landscape), EXIF orientation applied, RGB scaled to [-1, 1]. Portrait images
stay portrait: the network takes any orientation. DUNE-MASt3R's recipe calls the same loader with
``size=518, patch_size=14, square_ok=True``: ``long_side``, ``patch`` and ``square_ok`` here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import PIL.Image
import torch
from PIL.ImageOps import exif_transpose

__all__ = ["Prepared", "prepare_image", "prepare_path", "resized_size", "crop_box"]

PATCH = 16


@dataclass(frozen=True)
class Prepared:
    """A network input and how its pixels sit in the original image.

    Attributes:
        tensor: (1, 3, H, W) float32 RGB in [-1, 1].
        original_size: (width, height) of the original image, pixels.
        resized_size: (width, height) after the resize, before the crop.
        crop: (left, top, right, bottom) of the crop in the resized image, pixels.
    """

    tensor: torch.Tensor
    original_size: tuple[int, int]  # (width, height)
    resized_size: tuple[int, int]  # (width, height) after the resize, before the crop
    crop: tuple[int, int, int, int]  # (left, top, right, bottom) in the resized image

    @property
    def true_shape(self) -> tuple[int, int]:
        """(H, W) of the network input."""
        return int(self.tensor.shape[2]), int(self.tensor.shape[3])

    def scale(self) -> tuple[float, float]:
        """(sx, sy) = resized size / original size."""
        return (self.resized_size[0] / self.original_size[0], self.resized_size[1] / self.original_size[1])

    def to_original(self, xy: np.ndarray) -> np.ndarray:
        """Map network-input pixels back to the original image (pixel centres at integers).

        Args:
            xy: (N, 2) pixel coordinates in the network input.

        Returns:
            (N, 2) pixel coordinates in the original image.
        """
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2) + np.array(self.crop[:2], dtype=np.float64)
        return (xy + 0.5) / np.asarray(self.scale()) - 0.5


def resized_size(width: int, height: int, long_side: int = 512) -> tuple[int, int]:
    """Size of an image resized to a long side, aspect kept.

    Args:
        width: Original width, pixels.
        height: Original height, pixels.
        long_side: Long side after the resize, pixels.

    Returns:
        (width, height) rounded to whole pixels.
    """
    s = max(width, height)
    return int(round(width * long_side / s)), int(round(height * long_side / s))


def crop_box(width: int, height: int, square_ok: bool = False, patch: int = PATCH) -> tuple[int, int, int, int]:
    """Centre crop of a resized image to multiples of the patch size (4:3 landscape when square).

    Args:
        width: Resized width, pixels.
        height: Resized height, pixels.
        square_ok: Keep a square image square instead of cropping it to 4:3.
        patch: The network's patch side, pixels (16; DUNE-MASt3R's 14).

    Returns:
        (left, top, right, bottom), pixels.
    """
    cx, cy = width // 2, height // 2
    halfw, halfh = ((2 * cx) // patch) * patch / 2, ((2 * cy) // patch) * patch / 2
    if not square_ok and width == height:
        halfh = 3 * halfw / 4
    return int(round(cx - halfw)), int(round(cy - halfh)), int(round(cx + halfw)), int(round(cy + halfh))


def prepare_image(img: PIL.Image.Image, long_side: int = 512, patch: int = PATCH, square_ok: bool = False) -> Prepared:
    """Preprocess an image as the public loader does (resize, centre crop, scale to [-1, 1]).

    Args:
        img: A PIL image, its orientation already applied.
        long_side: Long side after the resize, pixels.
        patch: The crop is a multiple of this, pixels.
        square_ok: Keep a square image square (else it is cropped to 4:3).

    Returns:
        The network input and its map back to the original pixels.
    """
    img = img.convert("RGB")
    w0, h0 = img.size
    size = resized_size(w0, h0, long_side)
    interp = PIL.Image.Resampling.LANCZOS if max(w0, h0) > long_side else PIL.Image.Resampling.BICUBIC
    resized = img.resize(size, interp)
    box = crop_box(*size, square_ok=square_ok, patch=patch)
    arr = np.array(resized.crop(box))  # a writable copy for torch
    t = torch.from_numpy(arr).permute(2, 0, 1).float().div(255)
    t = t.sub(0.5).div(0.5)
    return Prepared(t[None], (w0, h0), size, box)


def prepare_array(image: np.ndarray, long_side: int = 512, patch: int = PATCH, square_ok: bool = False) -> Prepared:
    """``prepare_image`` of an array.

    Args:
        image: (H, W, 3) uint8 RGB.
        long_side: Long side after the resize, pixels.
        patch: The crop is a multiple of this, pixels.
        square_ok: Keep a square image square.

    Returns:
        The network input and its map back to the original pixels.
    """
    return prepare_image(PIL.Image.fromarray(np.ascontiguousarray(image)), long_side, patch, square_ok)


def prepare_path(path: str | Path, long_side: int = 512, patch: int = PATCH, square_ok: bool = False) -> Prepared:
    """``prepare_image`` of a file, its EXIF orientation applied as the public loader does.

    Args:
        path: The image file.
        long_side: Long side after the resize, pixels.
        patch: The crop is a multiple of this, pixels.
        square_ok: Keep a square image square.

    Returns:
        The network input and its map back to the original pixels.
    """
    with PIL.Image.open(path) as im:
        return prepare_image(exif_transpose(im), long_side, patch, square_ok)
