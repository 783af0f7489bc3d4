"""Small helpers shared by the matchers: resizing with the half-pixel rule, tensors, mutual NN.

torch is imported by the helpers that use it, not here: SIFT (OpenCV only) shares the image helpers, and a SIFT
command then starts without loading torch (a second or more of every ``mapfree`` call)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .base import Features

if TYPE_CHECKING:
    import torch

__all__ = [
    "check_image",
    "resize_for_matching",
    "matching_size",
    "image_tensor",
    "mutual_nearest",
    "autocast",
    "is_textureless",
    "checked_or_blank",
    "inside",
]


def check_image(image: np.ndarray) -> np.ndarray:
    """Validate an RGB image (a grey one is promoted).

    Args:
        image: (H, W, 3) or (H, W) uint8, at least 8x8.

    Returns:
        (H, W, 3) uint8, contiguous.

    Raises:
        ValueError: Another shape or dtype.
    """
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] < 8 or image.shape[1] < 8:
        raise ValueError(f"expected an (H,W,3) RGB image of at least 8x8 pixels, got shape {image.shape}")
    if image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {image.dtype}")
    return np.ascontiguousarray(image)


def resize_for_matching(
    image: np.ndarray, max_size: int | None = None, multiple: int = 1
) -> tuple[np.ndarray, tuple[float, float]]:
    """Resize so that the long side is at most ``max_size`` and both sides are multiples of ``multiple``.

    Args:
        image: (H, W, C) image.
        max_size: Long-side cap (None: none).
        multiple: Both sides become multiples of it.

    Returns:
        The image and the scale ``(sx, sy)`` = new size / old size (``mapfree.geometry.to_original`` undoes it).
    """
    h, w = image.shape[:2]
    nw, nh = matching_size(w, h, max_size, multiple)
    if (nw, nh) == (w, h):
        return image, (1.0, 1.0)
    interp = cv2.INTER_AREA if nw < w else cv2.INTER_LINEAR
    return cv2.resize(image, (nw, nh), interpolation=interp), (nw / w, nh / h)


def matching_size(width: int, height: int, max_size: int | None = None, multiple: int = 1) -> tuple[int, int]:
    """The size ``resize_for_matching`` resizes an image to.

    Args:
        width: Image width, pixels.
        height: Image height, pixels.
        max_size: Long-side cap (None: none).
        multiple: Both sides become multiples of it.

    Returns:
        (width, height).
    """
    s = 1.0 if not max_size or max(height, width) <= max_size else max_size / max(height, width)
    nw = max(multiple, int(round(width * s / multiple)) * multiple)
    nh = max(multiple, int(round(height * s / multiple)) * multiple)
    return nw, nh


def image_tensor(image: np.ndarray, device: torch.device, gray: bool = False) -> torch.Tensor:
    """An image as a network input.

    Args:
        image: (H, W, 3) uint8 RGB.
        device: Where the tensor goes.
        gray: Convert to grey first.

    Returns:
        (1, C, H, W) float32 in [0, 1] (C = 1 or 3).
    """
    import torch

    if gray:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)[..., None]
    t = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None]
    return t.to(device=device, dtype=torch.float32) / 255.0


def mutual_nearest(
    desc0: torch.Tensor, desc1: torch.Tensor, min_sim: float = -1.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mutual nearest neighbours of L2-normalised descriptors.

    Args:
        desc0: (N0, D) unit descriptors.
        desc1: (N1, D) unit descriptors.
        min_sim: Pairs of a cosine similarity not above it are dropped.

    Returns:
        (M,) indices into ``desc0``, (M,) into ``desc1`` and (M,) cosine similarities.
    """
    import torch

    if len(desc0) == 0 or len(desc1) == 0:
        e = torch.zeros(0, dtype=torch.long, device=desc0.device)
        return e, e, torch.zeros(0, device=desc0.device)
    sim = desc0 @ desc1.t()
    best01 = sim.argmax(dim=1)
    best10 = sim.argmax(dim=0)
    idx0 = torch.arange(len(desc0), device=desc0.device)
    keep = best10[best01] == idx0
    s = sim[idx0, best01]
    keep &= s > min_sim
    return idx0[keep], best01[keep], s[keep]


@contextlib.contextmanager
def autocast(device: torch.device, enabled: bool) -> Iterator[None]:
    """Mixed precision on CUDA when enabled; a no-op elsewhere (CPU half kernels are slow or missing).

    Args:
        device: The network's device.
        enabled: Whether to use it.

    Returns:
        A context manager.
    """
    if enabled and device.type == "cuda":
        import torch

        with torch.autocast("cuda", dtype=torch.float16):
            yield
    else:
        yield


def is_textureless(image: np.ndarray, min_std: float = 1.0) -> bool:
    """Whether an image is (nearly) constant: nothing in it can be matched, so matchers return no features.

    Dense matchers would otherwise pair arbitrary cells of a blank image whose descriptors all tie.

    Args:
        image: (H, W, 3) uint8 RGB.
        min_std: Grey-level standard deviation below which the image is blank.

    Returns:
        True for a blank image.
    """
    return float(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).std()) < min_std


def checked_or_blank(image: np.ndarray) -> tuple[np.ndarray, Features | None]:
    """``check_image(image)``, and the empty feature set to return for it when it is textureless.

    Args:
        image: (H, W, 3) uint8 RGB.

    Returns:
        The checked image, and empty ``Features`` for a blank image (else None).
    """
    image = check_image(image)
    if is_textureless(image):
        return image, Features(np.zeros((0, 2)), (image.shape[1], image.shape[0]), {"empty": True})
    return image, None


def inside(kpts: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Which keypoints lie on the image (pixel centres at integers: [-0.5, W-0.5] x [-0.5, H-0.5]).

    Args:
        kpts: (N, 2) pixels.
        image_size: (width, height).

    Returns:
        (N,) bool mask.
    """
    w, h = image_size
    k = np.asarray(kpts).reshape(-1, 2)
    return (k[:, 0] >= -0.5) & (k[:, 0] <= w - 0.5) & (k[:, 1] >= -0.5) & (k[:, 1] <= h - 0.5)
