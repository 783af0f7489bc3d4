"""``overlaps.npz`` of train scenes and pair sampling within overlap bounds."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .io import FormatError

__all__ = ["Overlaps", "read_overlaps", "write_overlaps"]


@dataclass
class Overlaps:
    """Pairs ``idxs (M,4) = seqA frameA seqB frameB`` with their overlap in [0,1]."""

    idxs: np.ndarray
    overlaps: np.ndarray

    def __len__(self) -> int:
        return len(self.overlaps)

    def within(self, min_overlap: float = 0.4, max_overlap: float = 0.8) -> np.ndarray:
        """Indices of pairs with ``min < overlap < max`` (strict, as in the reference training code)."""
        return np.flatnonzero((self.overlaps > min_overlap) & (self.overlaps < max_overlap))

    def sample(
        self, n: int, rng: np.random.Generator, min_overlap: float = 0.4, max_overlap: float = 0.8
    ) -> np.ndarray:
        """``n`` pair rows (M,4) drawn uniformly with replacement among pairs inside the bounds."""
        ok = self.within(min_overlap, max_overlap)
        if len(ok) == 0:
            return np.zeros((0, 4), dtype=self.idxs.dtype)
        return self.idxs[ok[rng.integers(0, len(ok), size=n)]]


def read_overlaps(path: os.PathLike | str) -> Overlaps:
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
    np.savez(path, idxs=overlaps.idxs.astype(np.int32), overlaps=overlaps.overlaps.astype(np.float32))
