"""DenseVLAD (Torii et al., CVPR 2015), the global descriptor the paper uses to pick and retrieve references.

Dense RootSIFT on a regular grid at several patch sizes (kornia), aggregated with VLAD over a small vocabulary that
is learned (K-means) on the mapping images of the place itself; residuals are intra-normalised per visual
word, then signed-square-rooted and L2-normalised, so that the dot product of two descriptors is their
cosine similarity.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from ..matching.sift import squared_distances
from ..matching.utils import check_image, resize_for_matching

if TYPE_CHECKING:
    import torch

__all__ = ["DenseVLADOptions", "DenseVLAD", "dense_rootsift"]


@dataclass
class DenseVLADOptions:
    """Grid and vocabulary settings of DenseVLAD (a coarser grid than the original 2 px stride: CPU).

    Attributes:
        max_size: Long side of the image the grid is laid on, pixels.
        stride: Grid spacing, pixels at ``max_size``.
        bin_sizes: SIFT spatial bin widths (2, 3, 4: patches of 8, 12 and 16 pixels).
        words: Vocabulary size; the descriptor has ``words * 128`` dimensions.
        max_train_descriptors: Dense descriptors sampled to learn the vocabulary.
        seed: Seed of the sampling and of K-means.

    Raises:
        ValueError: A setting is out of range.
    """

    max_size: int = 320  # long side of the image the grid is laid on
    stride: int = 4  # grid spacing, pixels (at max_size)
    bin_sizes: tuple[int, ...] = (2, 3, 4)  # SIFT spatial bin widths: patches of 8, 12 and 16 pixels
    words: int = 32  # vocabulary size; the descriptor has words x 128 dimensions
    max_train_descriptors: int = 40_000  # subsample of dense descriptors the vocabulary is learned from
    seed: int = 0

    def __post_init__(self) -> None:
        if self.max_size < 16 or self.stride < 1 or not self.bin_sizes or min(self.bin_sizes) < 1:
            raise ValueError("max_size >= 16, stride >= 1 and bin sizes >= 1 are required")
        if self.words < 1 or self.max_train_descriptors < self.words:
            raise ValueError("words must be >= 1 and max_train_descriptors >= words")


_SIFT_CACHE: dict[tuple[int, int], torch.nn.Module] = {}


def dense_rootsift(image: np.ndarray, options: DenseVLADOptions | None = None) -> np.ndarray:
    """Dense RootSIFT on a regular grid at every patch size (kornia's dense SIFT): DenseVLAD's local features.

    Args:
        image: (H, W, 3) uint8 RGB.
        options: Grid settings; the defaults when None.

    Returns:
        (N, 128) float32 unit descriptors; flat patches (no gradient at all) are dropped.

    Raises:
        ValueError: The image is too small for the smallest patch.
    """
    import torch
    from kornia.feature import DenseSIFTDescriptor

    o = options or DenseVLADOptions()
    small, _ = resize_for_matching(check_image(image), o.max_size)
    gray = torch.from_numpy(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY))[None, None].float() / 255.0
    out = []
    with torch.inference_mode():
        for b in o.bin_sizes:
            if 4 * b > min(gray.shape[-2:]):
                continue
            key = (b, o.stride)
            if key not in _SIFT_CACHE:
                _SIFT_CACHE[key] = DenseSIFTDescriptor(spatial_bin_size=b, stride=o.stride, rootsift=True)
            d = _SIFT_CACHE[key](gray)  # (1,128,h,w)
            out.append(d[0].flatten(1).T.numpy())
    if not out:
        raise ValueError(f"image of {gray.shape[-1]}x{gray.shape[-2]} pixels is too small for dense SIFT")
    desc = np.concatenate(out).astype(np.float32)
    return np.ascontiguousarray(desc[np.linalg.norm(desc, axis=1) > 0.5])  # RootSIFT has unit norm; flat: ~0


class DenseVLAD:
    """DenseVLAD global image descriptor, with a vocabulary learned on the place's own mapping images.

    ``fit`` learns the vocabulary; ``describe`` gives each image a unit vector whose dot products are cosine
    similarities.

    Args:
        options: Settings; built from ``overrides`` when None.
        **overrides: ``DenseVLADOptions`` fields, used when ``options`` is None.
    """

    name = "densevlad"

    def __init__(self, options: DenseVLADOptions | None = None, **overrides: Any) -> None:
        self.options = options or DenseVLADOptions(**overrides)
        self.centers: np.ndarray | None = None  # (words, 128)

    @property
    def dim(self) -> int:
        """Length of a descriptor, ``words * 128``."""
        return self.options.words * 128

    def fit(self, images: Iterable[np.ndarray]) -> DenseVLAD:
        """Learn the vocabulary by K-means on dense RootSIFT of a place's mapping images.

        Args:
            images: (H, W, 3) uint8 RGB images, at least one.

        Returns:
            This descriptor, fitted.

        Raises:
            ValueError: No image, or no descriptor to learn from.
        """
        self._fit_dense([dense_rootsift(im, self.options) for im in images])
        return self

    def fit_describe(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """``fit(images)`` then ``describe_many(images)``, computing each image's dense descriptors once.

        Args:
            images: (H, W, 3) uint8 RGB images, at least one.

        Returns:
            (N, dim) float32 descriptors, one row per image.
        """
        dense = [dense_rootsift(im, self.options) for im in images]
        self._fit_dense(dense)
        return np.stack([self._aggregate(d) for d in dense])

    def _fit_dense(self, descs: list[np.ndarray]) -> None:
        from sklearn.cluster import MiniBatchKMeans

        if not descs:
            raise ValueError("DenseVLAD.fit needs at least one image")
        rng = np.random.default_rng(self.options.seed)
        per_image = max(1, self.options.max_train_descriptors // len(descs))
        sample = np.concatenate([d[rng.permutation(len(d))[:per_image]] for d in descs])
        words = min(self.options.words, len(sample))
        if words < 1:
            raise ValueError("no descriptors to learn a vocabulary from")
        km = MiniBatchKMeans(n_clusters=words, random_state=self.options.seed, n_init=3, batch_size=4096)
        centers = km.fit(sample).cluster_centers_.astype(np.float32)
        if words < self.options.words:  # pad so every descriptor keeps the configured dimension
            centers = np.vstack([centers, np.full((self.options.words - words, 128), np.inf, np.float32)])
        self.centers = centers

    def describe(self, image: np.ndarray) -> np.ndarray:
        """The descriptor of one image.

        Args:
            image: (H, W, 3) uint8 RGB.

        Returns:
            (dim,) float32 with unit L2 norm; all zeros for a blank image.

        Raises:
            RuntimeError: The vocabulary was not learned (call ``fit`` first).
        """
        return self._aggregate(dense_rootsift(image, self.options))

    def _aggregate(self, desc: np.ndarray) -> np.ndarray:
        if self.centers is None:
            raise RuntimeError("DenseVLAD has no vocabulary: call fit(mapping_images) first")
        finite = np.isfinite(self.centers[:, 0])
        vlad = np.zeros(self.centers.shape, np.float32)
        if len(desc):
            word = np.flatnonzero(finite)[squared_distances(desc, self.centers[finite]).argmin(axis=1)]
            onehot = np.zeros((len(desc), len(vlad)), np.float32)
            onehot[np.arange(len(desc)), word] = 1.0
            counts = np.bincount(word, minlength=len(vlad))[finite].astype(np.float32)
            vlad[finite] = (onehot.T @ desc)[finite] - counts[:, None] * self.centers[finite]  # sum of residuals
        norms = np.linalg.norm(vlad, axis=1, keepdims=True)
        vlad = np.divide(vlad, norms, out=np.zeros_like(vlad), where=norms > 0)  # intra-normalisation
        v = vlad.ravel()
        v = np.sign(v) * np.sqrt(np.abs(v))
        n = np.linalg.norm(v)
        return (v / n if n > 0 else v).astype(np.float32)

    def describe_many(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """``describe`` of each image, stacked.

        Args:
            images: (H, W, 3) uint8 RGB images.

        Returns:
            (N, dim) float32; (0, dim) for no image.
        """
        return np.stack([self.describe(im) for im in images]) if len(images) else np.zeros((0, self.dim), np.float32)
