"""The matcher interface: features per image, matches per pair, in original-image pixels."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    import torch

__all__ = [
    "Features",
    "Matches",
    "Matcher",
    "BatchedMatcher",
    "FocalEstimator",
    "MatchCandidates",
    "CandidateMatches",
    "SharedNetwork",
]


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
        """No matches.

        Returns:
            Matches of length 0.
        """
        return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))

    def subset(self, mask: np.ndarray) -> Matches:
        """The matches a mask (or an index array) selects.

        Args:
            mask: (N,) bool mask or indices.

        Returns:
            The selected matches.
        """
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


class SharedNetwork(Protocol):
    """A network a matcher runs that can serve another part too: MASt3R's pair engine gives the pair's depth,
    MicKey's its keypoints' depths. ``name`` is the depth source it serves (``mast3r``, ``dust3r``, ``mickey``)."""

    name: str


class Matcher(ABC):
    """A named matcher: features per image, matches per pair, keypoints in original-image pixels.

    Subclasses implement ``extract`` and ``match``. ``extract_many`` and ``match_many`` loop over them; the
    matchers that batch on their device (LightGlue, XFeat, MASt3R, MicKey) derive from ``BatchedMatcher`` instead,
    each pair getting the result it gets alone. Callers (the batched pipeline) always call the batched forms.

    Attributes:
        name: The registry name (``"aliked-lightglue"``).
        device: The torch device its network runs on; None for a matcher without one (SIFT).
        engine: The network it runs when that network serves a depth source too (``SharedNetwork``), else None.
    """

    name: str = ""
    device: torch.device | None = None
    engine: SharedNetwork | None = None

    @abstractmethod
    def extract(self, image: np.ndarray) -> Features:
        """Features of one image (computed once for a reference and reused for every query).

        Args:
            image: (H, W, 3) uint8 RGB.

        Returns:
            Keypoints in the image's own pixels and whatever ``match`` needs.
        """

    @abstractmethod
    def match(self, f0: Features, f1: Features) -> Matches:
        """Correspondences between two images' features.

        Args:
            f0: Features of image 0 (the reference).
            f1: Features of image 1 (the query).

        Returns:
            ``kpts0[i]`` in image 0 matching ``kpts1[i]`` in image 1, original pixels.
        """

    def extract_many(self, images: Sequence[np.ndarray]) -> list[Features]:
        """``extract`` of several images, in order (one network pass for the matchers that batch).

        Args:
            images: (H, W, 3) uint8 RGB images.

        Returns:
            One ``Features`` per image.
        """
        return [self.extract(image) for image in images]

    def match_many(self, f0: Features, f1s: Sequence[Features], batch_size: int | None = None) -> list[Matches]:
        """``match(f0, f1)`` for each of ``f1s``, in order.

        Args:
            f0: Features of the reference image.
            f1s: Features of the query images.
            batch_size: Pairs per network pass for the matchers that batch (None: their own default).

        Returns:
            One ``Matches`` per query, each equal to what ``match`` gives that pair alone.
        """
        return [self.match(f0, f1) for f1 in f1s]

    @property
    def on_gpu(self) -> bool:
        """Whether the matcher's network runs on a CUDA device."""
        return self.device is not None and self.device.type == "cuda"

    @classmethod
    def runs_offline(cls, **args: Any) -> bool:
        """Whether the matcher can be built on this machine now without a download (``matching.available()``).

        Args:
            **args: The keyword arguments its registry entry gives the class (``features="aliked"``).

        Returns:
            True unless its weights or packages are missing; a matcher that needs nothing keeps this default.
        """
        return True


class BatchedMatcher(Matcher):
    """A matcher whose batched forms are its implementation: ``extract`` is ``extract_many`` of one image and
    ``match`` is ``match_many`` of one pair, so the two always agree.

    Subclasses implement ``extract_many`` and ``match_many``; ``match_many`` may still call a ``match`` of its own
    for the modes that do not batch (XFeat's sparse and semi-dense modes).
    """

    def extract(self, image: np.ndarray) -> Features:
        return self.extract_many([image])[0]

    def match(self, f0: Features, f1: Features) -> Matches:
        return self.match_many(f0, [f1])[0]

    @abstractmethod
    def extract_many(self, images: Sequence[np.ndarray]) -> list[Features]: ...

    @abstractmethod
    def match_many(self, f0: Features, f1s: Sequence[Features], batch_size: int | None = None) -> list[Matches]: ...


class FocalEstimator(ABC):
    """A matcher whose network tells each photo's focal length by itself (MASt3R and DUSt3R: the focal that
    best explains a photo's own pointmap, principal point at the centre, as their authors estimate it).

    A matcher derives from both ``Matcher`` and this to declare the capability; photos with neither given
    intrinsics nor EXIF focal tags then take the estimate instead of the default field of view.
    """

    @abstractmethod
    def estimate_focal(self, image: np.ndarray, other: np.ndarray | None = None) -> float | None:
        """The focal length of ``image`` from the network's pass over (``image``, ``other``).

        Args:
            image: (H, W, 3) uint8 RGB, upright.
            other: The pair's other photo (its overlap steadies the pointmap); None: ``image`` paired with
                itself, as DUSt3R does for a single photo.

        Returns:
            The focal length in pixels of ``image`` at its own size (fx = fy, principal point at the centre), or
            None when the network gives no usable pointmap (a blank photo).
        """
