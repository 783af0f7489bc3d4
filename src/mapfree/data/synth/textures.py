"""Real-photo textures (scikit-image's bundled samples) packed into one mip-mapped atlas.

All textures are square ``size × size`` tiles; each is stored with its mip levels side by side and a
reflect-padded border, so that one ``cv2.remap`` per mip level textures a whole frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

__all__ = ["PHOTOS", "SURFACES", "GROUNDS", "TextureAtlas", "load_atlas"]

# Photos for the "place of interest" (sculpture faces, murals, posters) and repeating surface materials.
PHOTOS = (
    "astronaut",
    "coffee",
    "chelsea",
    "rocket",
    "motorcycle",
    "immunohistochemistry",
    "camera",
    "coins",
    "moon",
)
SURFACES = ("brick", "gravel", "grass", "page", "text")
# Softer (lower-contrast) variants of the ground materials: pavement seen from eye height is not all edges.
GROUNDS = ("brick~soft", "gravel~soft", "grass~soft")
_SOFT_CONTRAST = 0.6
_PAD = 2


_FILES = {
    "astronaut": "astronaut.png",
    "coffee": "coffee.png",
    "chelsea": "chelsea.png",
    "rocket": "rocket.jpg",
    "motorcycle": "motorcycle_left.png",
    "immunohistochemistry": "ihc.png",
    "camera": "camera.png",
    "coins": "coins.png",
    "moon": "moon.png",
    "brick": "brick.png",
    "gravel": "gravel.png",
    "grass": "grass.png",
    "page": "page.png",
    "text": "text.png",
}


def _load(name: str) -> np.ndarray:
    """One scikit-image sample photo as (H,W,3) uint8 RGB (read straight from the installed package)."""
    if name.endswith("~soft"):
        img = _load(name.split("~")[0]).astype(np.float32)
        mean = img.mean(axis=(0, 1), keepdims=True)
        return np.clip(mean + _SOFT_CONTRAST * (img - mean), 0, 255).astype(np.uint8)
    import skimage.data
    from PIL import Image

    path = Path(skimage.data.__file__).parent / _FILES[name]
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except OSError as e:
        raise FileNotFoundError(f"{path}: scikit-image sample image unreadable (needed for textures): {e}") from None


def _square(img: np.ndarray, size: int) -> np.ndarray:
    """Centre-crop to a square and resize to ``size``."""
    h, w = img.shape[:2]
    s = min(h, w)
    y0, x0 = (h - s) // 2, (w - s) // 2
    return cv2.resize(img[y0 : y0 + s, x0 : x0 + s], (size, size), interpolation=cv2.INTER_AREA)


@dataclass(frozen=True)
class TextureAtlas:
    """Textures with mip levels in one image; ``offsets[tex, level] = (x0, y0)`` of that level's first texel."""

    image: np.ndarray  # (H,W,3) uint8 RGB
    names: tuple[str, ...]
    size: int  # texels per side at level 0
    levels: int
    offsets: np.ndarray  # (T, L, 2) float32

    def index(self, name: str) -> int:
        return self.names.index(name)


def _build(names: tuple[str, ...], size: int, levels: int) -> TextureAtlas:
    row_w = sum((size >> k) + 2 * _PAD for k in range(levels))
    row_h = size + 2 * _PAD
    atlas = np.zeros((row_h * len(names), row_w, 3), np.uint8)
    offsets = np.zeros((len(names), levels, 2), np.float32)
    for i, name in enumerate(names):
        level = _square(_load(name), size)
        x = 0
        for k in range(levels):
            s = size >> k
            if k:
                level = cv2.resize(level, (s, s), interpolation=cv2.INTER_AREA)
            padded = cv2.copyMakeBorder(level, _PAD, _PAD, _PAD, _PAD, cv2.BORDER_REFLECT)
            atlas[i * row_h : i * row_h + s + 2 * _PAD, x : x + s + 2 * _PAD] = padded
            offsets[i, k] = (x + _PAD, i * row_h + _PAD)
            x += s + 2 * _PAD
    return TextureAtlas(atlas, names, size, levels, offsets)


@lru_cache(maxsize=4)
def load_atlas(size: int = 512, levels: int = 7) -> TextureAtlas:
    """The atlas of every photo and surface texture (cached per process)."""
    if size < 8 or size & (size - 1):
        raise ValueError(f"texture size must be a power of two >= 8, got {size}")
    levels = min(levels, int(np.log2(size)) - 1)
    return _build(PHOTOS + SURFACES + GROUNDS, size, levels)
