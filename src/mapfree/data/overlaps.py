"""``overlaps.npz`` of train scenes and pair sampling within overlap bounds."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .io import FormatError

__all__ = ["Overlaps", "read_overlaps", "write_overlaps"]


@dataclass
class Overlaps:
    """Frame pairs of a train scene with their visual overlap (``overlaps.npz``).

    Attributes:
        idxs: (M, 4) int ``seqA frameA seqB frameB`` per pair.
        overlaps: (M,) overlap of each pair, in [0, 1].
    """

    idxs: np.ndarray
    overlaps: np.ndarray

    def __len__(self) -> int:
        return len(self.overlaps)

    def within(self, min_overlap: float = 0.4, max_overlap: float = 0.8) -> np.ndarray:
        """Pairs whose overlap lies strictly inside the bounds (as the reference training code selects).

        Args:
            min_overlap: Lower bound, exclusive.
            max_overlap: Upper bound, exclusive.

        Returns:
            (K,) row indices into ``idxs``.
        """
        return np.flatnonzero((self.overlaps > min_overlap) & (self.overlaps < max_overlap))

    def sample(
        self, n: int, rng: np.random.Generator, min_overlap: float = 0.4, max_overlap: float = 0.8
    ) -> np.ndarray:
        """Draw training pairs uniformly, with replacement, among the pairs inside the bounds.

        Args:
            n: Number of pairs to draw.
            rng: Random generator.
            min_overlap: Lower bound, exclusive.
            max_overlap: Upper bound, exclusive.

        Returns:
            (n, 4) rows of ``idxs``; (0, 4) when no pair is inside the bounds.
        """
        ok = self.within(min_overlap, max_overlap)
        if len(ok) == 0:
            return np.zeros((0, 4), dtype=self.idxs.dtype)
        return self.idxs[ok[rng.integers(0, len(ok), size=n)]]


def read_overlaps(path: os.PathLike | str) -> Overlaps:
    """Read a scene's ``overlaps.npz`` (arrays ``idxs`` and ``overlaps``).

    Args:
        path: The file.

    Returns:
        The pairs; overlaps keep their stored float dtype (float32 in the release).

    Raises:
        FormatError: The file is missing, not an npz, lacks an array, or the shapes disagree.
    """
    try:
        with np.load(path) as z:
            idxs, ov = np.asarray(z["idxs"]), np.asarray(z["overlaps"])
    except FileNotFoundError:
        raise FormatError(path, None, "file not found") from None
    except KeyError as e:
        raise FormatError(path, None, f"missing array {e}") from None
    except Exception as e:  # corrupt zip / not an npz
        raise FormatError(path, None, f"cannot read npz ({e})") from None
    if idxs.ndim != 2 or idxs.shape[1] != 4 or len(idxs) != len(ov):
        raise FormatError(path, None, f"idxs must be (M,4) matching overlaps (M,), got {idxs.shape}, {ov.shape}")
    # Overlaps keep their stored dtype (float32 in the release): bounds then compare as the reference code does.
    return Overlaps(idxs.astype(np.int64), ov if np.issubdtype(ov.dtype, np.floating) else ov.astype(np.float64))


def write_overlaps(path: os.PathLike | str, overlaps: Overlaps) -> None:
    """Write an ``overlaps.npz`` (int32 indices, float32 overlaps, as the release stores them).

    Args:
        path: The file, overwritten.
        overlaps: The pairs.
    """
    np.savez(path, idxs=overlaps.idxs.astype(np.int32), overlaps=overlaps.overlaps.astype(np.float32))
