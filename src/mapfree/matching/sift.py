"""OpenCV SIFT with RootSIFT descriptors and Lowe's ratio test (the paper's SIFT baseline)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .base import Features, Matches
from .utils import check_image, resize_for_matching, to_original

__all__ = ["SIFTOptions", "SIFTMatcher", "root_sift", "squared_distances", "two_nearest"]


@dataclass
class SIFTOptions:
    """Defaults = the paper's SIFT row (SPEC §4): 2048 features, RootSIFT, ratio 0.8, at 540x720."""

    max_features: int = 2048
    ratio: float = 0.8
    root_sift: bool = True
    mutual: bool = False  # also require the match to be the best in the other direction
    max_size: int | None = None  # long-side cap for extraction; None = native resolution
    device: str | None = None  # accepted for a uniform API; OpenCV SIFT runs on the CPU


def root_sift(desc: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    """RootSIFT (Arandjelović & Zisserman 2012): L1-normalise, then square-root, so L2 = Hellinger."""
    desc = desc.astype(np.float32)
    desc /= desc.sum(axis=1, keepdims=True) + eps
    return np.sqrt(desc)


def squared_distances(d0: np.ndarray, d1: np.ndarray) -> np.ndarray:
    """All pairwise squared L2 distances by one matrix product (|a|^2 + |b|^2 - 2 a.b), clipped at 0."""
    sq = (d0 * d0).sum(1)[:, None] + (d1 * d1).sum(1)[None, :] - 2.0 * (d0 @ d1.T)
    return np.maximum(sq, 0.0, out=sq)


def two_nearest(sq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest column of each row and the L2 distances (N,2) to the nearest and second nearest.

    Exact, like OpenCV's brute-force ``knnMatch(k=2)``, but several times faster on CPU (BLAS product, then two
    row scans instead of a per-row selection). ``sq`` is left unchanged.
    """
    rows = np.arange(len(sq))
    nearest = sq.argmin(axis=1)
    d1 = sq[rows, nearest]
    sq[rows, nearest] = np.inf
    d2 = sq.min(axis=1)
    sq[rows, nearest] = d1
    return nearest, np.sqrt(np.stack([d1, d2], axis=1))


class SIFTMatcher:
    """``sift``: CPU only (OpenCV); ``extract`` is separable so reference features are computed once."""

    name = "sift"

    def __init__(self, options: SIFTOptions | None = None, **overrides: object) -> None:
        self.options = options or SIFTOptions(**overrides)  # type: ignore[arg-type]
        self._sift = cv2.SIFT_create(nfeatures=self.options.max_features)

    def extract(self, image: np.ndarray) -> Features:
        image = check_image(image)
        small, scale = resize_for_matching(image, self.options.max_size)
        gray = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
        kps, desc = self._sift.detectAndCompute(gray, None)
        if desc is None or len(kps) == 0:
            desc, xy = np.zeros((0, 128), np.float32), np.zeros((0, 2))
        else:
            xy = np.array([k.pt for k in kps], dtype=np.float64)
            # OpenCV may return more than nfeatures when responses tie at the cut.
            desc, xy = desc[: self.options.max_features], xy[: self.options.max_features]
        if self.options.root_sift:
            desc = root_sift(desc)
        size = (image.shape[1], image.shape[0])
        return Features(to_original(xy, scale), size, {"descriptors": np.ascontiguousarray(desc, np.float32)})

    def match(self, f0: Features, f1: Features) -> Matches:
        d0, d1 = f0.data["descriptors"], f1.data["descriptors"]
        if len(d0) < 2 or len(d1) < 2:
            return Matches.empty()
        sq = squared_distances(d0, d1)
        i1, dist = two_nearest(sq)
        ratio = dist[:, 0] / np.maximum(dist[:, 1], 1e-12)
        keep = ratio < self.options.ratio
        if self.options.mutual:
            keep &= np.argmin(sq, axis=0)[i1] == np.arange(len(d0))
        i0 = np.flatnonzero(keep)
        return Matches(f0.kpts[i0], f1.kpts[i1[i0]], 1.0 - ratio[keep])

    def extract_many(self, images: Sequence[np.ndarray]) -> list[Features]:
        return [self.extract(im) for im in images]

    def match_many(self, f0: Features, f1s: Sequence[Features]) -> list[Matches]:
        return [self.match(f0, f1) for f1 in f1s]
