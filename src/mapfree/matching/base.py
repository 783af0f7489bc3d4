"""The matcher interface: features per image, matches per pair, in original-image pixels."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

__all__ = ["Features", "Matches", "Matcher", "MatchCandidates", "CandidateMatches"]


@dataclass
class Features:
    """What a matcher extracts from one image; ``kpts`` in original pixels.

    ``data`` holds whatever the matcher's second stage needs (descriptors, tensors, the resized image
    for dense matchers); it is opaque to everyone else. Reference features are computed once per scene.
    """

    kpts: np.ndarray  # (N,2) float, original-image pixels
    image_size: tuple[int, int]  # (width, height) of the original image
    data: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.kpts)


@dataclass
class Matches:
    """Corresponding pixels: ``kpts0[i]`` in image 0 (reference) matches ``kpts1[i]`` in image 1 (query)."""

    kpts0: np.ndarray  # (N,2) float64
    kpts1: np.ndarray  # (N,2) float64
    scores: np.ndarray  # (N,) float, higher = more confident

    def __post_init__(self) -> None:
        self.kpts0 = np.asarray(self.kpts0, dtype=np.float64).reshape(-1, 2)
        self.kpts1 = np.asarray(self.kpts1, dtype=np.float64).reshape(-1, 2)
        self.scores = np.asarray(self.scores, dtype=np.float64).reshape(-1)
        if not (len(self.kpts0) == len(self.kpts1) == len(self.scores)):
            raise ValueError("kpts0, kpts1 and scores must have the same length")

    def __len__(self) -> int:
        return len(self.kpts0)

    @classmethod
    def empty(cls) -> Matches:
        return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))

    def subset(self, mask: np.ndarray) -> Matches:
        return Matches(self.kpts0[mask], self.kpts1[mask], self.scores[mask])


@dataclass
class MatchCandidates:
    """Every keypoint of both images with its metric depth, and a score for every pair of them: what a
    probabilistic solver draws correspondences from (MicKey's). Torch tensors on the matcher's device."""

    kpts0: Any  # (N0, 2) original-image pixels of image 0 (reference)
    kpts1: Any  # (N1, 2) of image 1 (query)
    depth0: Any  # (N0,) metres along the optical axis
    depth1: Any  # (N1,)
    scores: Any  # (N0, N1) >= 0, not normalised


@dataclass
class CandidateMatches(Matches):
    """Matches (the usual one-to-one correspondences) that also carry the scored candidates they were picked
    from; ``subset`` keeps only the matches."""

    candidates: MatchCandidates | None = None


@runtime_checkable
class Matcher(Protocol):
    """A named matcher. ``extract`` takes an (H,W,3) uint8 RGB image."""

    name: str

    def extract(self, image: np.ndarray) -> Features: ...

    def match(self, f0: Features, f1: Features) -> Matches: ...
