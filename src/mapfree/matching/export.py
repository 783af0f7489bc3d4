"""Correspondences between two image files with any registered matcher, and the ``.npz`` layout they are saved in
(the same keys for every matcher, so that a downstream tool reads SIFT's and SuperGlue's files alike)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..data.io import naming
from . import create, options_class, registry_key
from .base import Matches

__all__ = ["NPZ_KEYS", "PairMatches", "match_files", "save_npz", "load_npz", "resolve_name"]

#: Keys of a matches file, each with its meaning (written in this order).
NPZ_KEYS = {
    "kpts0": "(N,2) float32: x, y in image0's original pixels (pixel centres at integer coordinates)",
    "kpts1": "(N,2) float32: the corresponding x, y in image1's original pixels",
    "scores": "(N,) float32: the matcher's confidence per match, higher is better (its own scale)",
    "image0": "str: path of image0 as given",
    "image1": "str: path of image1 as given",
    "size0": "(2,) int32: width, height of image0",
    "size1": "(2,) int32: width, height of image1",
    "matcher": "str: the matcher's registry name",
    "seconds": "float64: wall time of feature extraction and matching (model loading excluded)",
}


@dataclass
class PairMatches:
    """What ``match_files`` found: the matches with the images they come from and what it cost."""

    matches: Matches
    image0: str
    image1: str
    size0: tuple[int, int]
    size1: tuple[int, int]
    matcher: str
    seconds: float
    load_seconds: float
    keypoints: tuple[int, int]  # candidate points per image (a dense matcher's grid cells)


def resolve_name(name: str) -> str:
    """The registry key of a matcher name (case and ``_``/``-`` as ``create`` accepts).

    Args:
        name: A matcher name.

    Returns:
        Its registry key.

    Raises:
        KeyError: An unknown name, with the nearest ones.
    """
    options_class(name)  # the registry's refusal of an unknown name, with the nearest ones
    return registry_key(name)


def match_files(image0: os.PathLike | str, image1: os.PathLike | str, matcher: str, **options: object) -> PairMatches:
    """Match two image files with a registered matcher.

    Args:
        image0: The first image.
        image1: The second image.
        matcher: A matcher name.
        **options: The matcher's options.

    Returns:
        The matches (original pixels) with the images, their sizes and the seconds it took.

    Raises:
        FormatError: An unreadable image (named).
        KeyError: An unknown matcher.
        MissingWeightsError: Its weights are neither local nor downloadable.
        OptionError: An option it does not have, or a bad value.
    """
    from ..data import read_image

    name = resolve_name(matcher)
    im0, im1 = read_image(image0), read_image(image1)
    t0 = time.perf_counter()
    mt = create(name, **options)
    t1 = time.perf_counter()
    f0, f1 = mt.extract(im0), mt.extract(im1)
    m = mt.match(f0, f1)
    t2 = time.perf_counter()
    return PairMatches(
        m,
        str(image0),
        str(image1),
        (im0.shape[1], im0.shape[0]),
        (im1.shape[1], im1.shape[0]),
        name,
        t2 - t1,
        t1 - t0,
        (len(f0), len(f1)),
    )


def save_npz(path: os.PathLike | str, r: PairMatches) -> Path:
    """Write matches with the keys of ``NPZ_KEYS`` (no pickled objects: ``np.load`` needs no ``allow_pickle``).

    Args:
        path: The file (``.npz`` is not appended).
        r: What ``match_files`` found.

    Returns:
        The path written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    m = r.matches
    arrays: dict[str, Any] = {
        "kpts0": m.kpts0.astype(np.float32),
        "kpts1": m.kpts1.astype(np.float32),
        "scores": m.scores.astype(np.float32),
        "image0": np.str_(r.image0),
        "image1": np.str_(r.image1),
        "size0": np.asarray(r.size0, np.int32),
        "size1": np.asarray(r.size1, np.int32),
        "matcher": np.str_(r.matcher),
        "seconds": np.float64(r.seconds),
    }
    assert list(arrays) == list(NPZ_KEYS)
    with naming(path), open(path, "wb") as f:  # np.savez would append .npz to a name without it
        np.savez(f, **arrays)
    return path


def load_npz(path: os.PathLike | str) -> dict[str, np.ndarray]:
    """A matches file as a dict of arrays.

    Args:
        path: A file written by ``save_npz``.

    Returns:
        ``NPZ_KEYS`` -> arrays (strings as 0-d str arrays: ``str(d["matcher"])``).
    """
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
