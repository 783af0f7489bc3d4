"""Ground truth of a split as the public evaluator sees it: evaluated frames, poses, float32 intrinsics.

Frames are keyed by their number (``int(name[-9:-4])``) in insertion order: a later line with the same
number replaces the value but keeps the first line's position, so the reference ``seq0/frame_00000.jpg``
gives its slot to ``seq1/frame_00000.jpg``; lines with a zero quaternion (private test poses) are
skipped; every 5th position is evaluated. Intrinsics are keyed the same way (the last line wins), held
in float32, and the image size comes from the last line of ``intrinsics.txt``.

The multi-frame track (``track="multi"``) evaluates instead the queries its leaderboard scores: linear
index 9, 19, 29, … of the ``seq1`` frames sorted by number (``mapfree.data.multiframe_bursts``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from ..data import Dataset, FormatError, frame_number, multiframe_bursts
from ..data.io import iter_records
from .tables import scan_table

__all__ = ["SceneTruth", "load_scene_truth", "load_truth", "EVERY", "TRACKS"]

EVERY = 5  # 1-in-5 subsampling of the query list
TRACKS = ("single", "multi")  # the leaderboards: one query frame, or a burst of 9 with device poses
_ZERO = 1e-8  # a quaternion this short is "zero" (the public evaluator's np.isclose(norm, 0))


class FrameNames:
    """The frame names of a scene, for membership tests; the full set is only decoded when a name is not
    one of the evaluated frames (a submission holding just the scored frames never pays for it)."""

    def __init__(self, evaluated: list[str], load_all):
        self._evaluated = frozenset(evaluated)
        self._load_all = load_all
        self._all: frozenset[str] | None = None

    @property
    def all(self) -> frozenset[str]:
        if self._all is None:
            self._all = frozenset(self._load_all())
        return self._all

    def __contains__(self, name: object) -> bool:
        return name in self._evaluated or name in self.all

    def issuperset(self, names) -> bool:
        names = names if isinstance(names, (set, frozenset)) else set(names)
        return self._evaluated.issuperset(names) or self.all.issuperset(names)

    def __iter__(self):
        return iter(self.all)

    def __len__(self) -> int:
        return len(self.all)


@dataclass
class SceneTruth:
    """The evaluated frames of one scene, in the public evaluator's order.

    Attributes:
        scene: Scene name.
        names: (m) name of each evaluated frame (the last line with its number).
        keys: (m,) frame numbers.
        q: (m, 4) true world-to-camera quaternions ``w x y z``.
        t: (m, 3) true translations, metres.
        K: (m, 4) float32 ``fx fy cx cy``, pixels.
        width: Image width from the last line of ``intrinsics.txt``, pixels.
        height: Image height, pixels.
        n_keys: Distinct frame numbers with a valid pose (the public evaluator's missing-scene penalty).
        frame_names: Every frame named in ``poses.txt`` (set-like, decoded lazily).
    """

    scene: str
    names: list[str]  # name of each evaluated frame (the last line with its number)
    keys: np.ndarray  # (m,) frame numbers
    q: np.ndarray  # (m,4) world-to-camera wxyz
    t: np.ndarray  # (m,3)
    K: np.ndarray  # (m,4) float32 fx fy cx cy
    width: float  # from the last line of intrinsics.txt
    height: float
    n_keys: int  # distinct frame numbers with a valid pose: the public evaluator's missing-scene penalty
    frame_names: FrameNames  # every frame named in poses.txt (a set-like, decoded lazily)

    @cached_property
    def is_query(self) -> np.ndarray:
        """Evaluated frames that are real queries (``seq1/``); the reference only slips in when a scene's
        ``seq1`` has no frame 0 (the public evaluator then scores the reference as a query)."""
        return np.array([n.startswith("seq1/") for n in self.names], dtype=bool)


def _dict_order(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distinct keys in first-insertion order, index of the last line holding each of them)."""
    if len(keys) == 0:
        return keys, keys
    uniq, first = np.unique(keys, return_index=True)
    _, last_rev = np.unique(keys[::-1], return_index=True)
    last = len(keys) - 1 - last_rev
    order = np.argsort(first, kind="stable")
    return uniq[order], last[order]


def _poses_slow(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    names, keys, rows = [], [], []
    for lineno, name, v in iter_records(path, 7):
        if np.linalg.norm(v[:4]) <= _ZERO:
            continue  # private ground truth (all-zero line), skipped like the public evaluator does
        try:
            keys.append(frame_number(name))
        except ValueError:
            raise FormatError(path, lineno, f"frame name {name!r} has no number at [-9:-4]") from None
        names.append(name)
        rows.append(v)
    return names, np.array(keys, dtype=np.int64), np.array(rows, dtype=np.float64).reshape(-1, 7)


def _intrinsics_slow(path: Path) -> tuple[np.ndarray, np.ndarray]:
    keys, rows = [], []
    for lineno, name, v in iter_records(path, 6):
        try:
            keys.append(frame_number(name))
        except ValueError:
            raise FormatError(path, lineno, f"frame name {name!r} has no number at [-9:-4]") from None
        rows.append(v)
    return np.array(keys, dtype=np.int64), np.array(rows, dtype=np.float64).reshape(-1, 6)


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise FormatError(path, None, "ground-truth file not found") from None


def _load_poses(path: Path, every: int):
    """(names, keys, q, t, n_keys, all names) of the evaluated frames."""
    table = scan_table(_read(path), 7)
    if table is not None:
        ukeys, last = _dict_order(table.keys)
        rows = last[::every]
        vals, bad = table.values(rows)
        ok = not bad.any() and np.all(np.isfinite(vals)) and np.all(np.linalg.norm(vals[:, :4], axis=1) > _ZERO)
        if ok:
            names = table.names(rows)
            return names, ukeys[::every], vals[:, :4], vals[:, 4:], len(ukeys), FrameNames(names, table.names)
    names, keys, vals = _poses_slow(path)  # exact errors, and zero-quaternion lines skipped
    ukeys, last = _dict_order(keys)
    rows = last[::every]
    evaluated = [names[i] for i in rows]
    return evaluated, ukeys[::every], vals[rows, :4], vals[rows, 4:], len(ukeys), FrameNames(evaluated, lambda: names)


def _load_poses_multi(path: Path):
    """(names, keys, q, t, n_keys, all names) of the queries the multi-frame track scores."""
    names, keys, vals = _poses_slow(path)
    last = {n: i for i, n in enumerate(names)}  # the public loader keys poses by name: the last line wins
    rows = np.array([last[q] for q, _ in multiframe_bursts(names)], dtype=np.int64)
    evaluated = [names[i] for i in rows]
    n_keys = len(np.unique(keys))
    return evaluated, keys[rows], vals[rows, :4], vals[rows, 4:], n_keys, FrameNames(evaluated, lambda: names)


def _load_intrinsics(path: Path, keys: np.ndarray) -> tuple[np.ndarray, float, float]:
    """float32 (fx fy cx cy) for each key (last line with that number wins) and W, H of the last line."""
    table = scan_table(_read(path), 6)
    if table is not None and len(table):
        ukeys, last = _dict_order(table.keys)
        sorter = np.argsort(ukeys)
        pos = sorter[np.minimum(np.searchsorted(ukeys, keys, sorter=sorter), len(ukeys) - 1)]
        if np.all(ukeys[pos] == keys):
            vals, bad = table.values(last[pos], ncols=4)
            size, bad_size = table.values(np.array([len(table) - 1]))
            if not (bad.any() or bad_size.any()) and np.all(np.isfinite(vals)) and np.all(np.isfinite(size)):
                return vals.astype(np.float32), float(size[0, 4]), float(size[0, 5])
    ikeys, vals = _intrinsics_slow(path)
    if len(ikeys) == 0:
        raise FormatError(path, None, "no intrinsics")
    by_key = {k: i for i, k in enumerate(ikeys.tolist())}  # last line wins
    missing = [k for k in keys.tolist() if k not in by_key]
    if missing:
        raise FormatError(path, None, f"no intrinsics for frame number(s) {missing[:5]}")
    rows = np.array([by_key[k] for k in keys.tolist()], dtype=np.int64)
    return vals[rows, :4].astype(np.float32), float(vals[-1, 4]), float(vals[-1, 5])


def load_scene_truth(
    poses_path: os.PathLike | str,
    intrinsics_path: os.PathLike | str,
    scene: str | None = None,
    every: int = EVERY,
    track: str = "single",
) -> SceneTruth:
    """Read one scene's ground truth (``poses.txt`` + ``intrinsics.txt``) for the single- or multi-frame track.

    Args:
        poses_path: The scene's ``poses.txt``.
        intrinsics_path: The scene's ``intrinsics.txt``.
        scene: Scene name; the parent folder's name when None.
        every: Stride of the scored queries of the single-frame track.
        track: ``single`` or ``multi``.

    Returns:
        The evaluated frames with their poses and intrinsics.

    Raises:
        ValueError: ``track`` is unknown.
        FormatError: A file is malformed, or the image size is not positive.
    """
    if track not in TRACKS:
        raise ValueError(f"track must be one of {TRACKS}, got {track!r}")
    poses_path, intrinsics_path = Path(poses_path), Path(intrinsics_path)
    load = _load_poses(poses_path, every) if track == "single" else _load_poses_multi(poses_path)
    names, keys, q, t, n_keys, all_names = load
    K, W, H = _load_intrinsics(intrinsics_path, keys)
    if not (W > 0 and H > 0):
        raise FormatError(intrinsics_path, None, "image size must be positive")
    return SceneTruth(scene or poses_path.parent.name, names, keys, q, t, K, W, H, n_keys, all_names)


def load_truth(
    dataset_root: os.PathLike | str | None,
    split: str = "val",
    gt_root: os.PathLike | str | None = None,
    track: str = "single",
) -> dict[str, SceneTruth]:
    """Ground truth of every scene of a split, by scene name.

    Args:
        dataset_root: The dataset folder.
        split: The split.
        gt_root: Folder of ``SPLIT/sNNNNN/poses.txt`` (+ ``intrinsics.txt``) with private poses; its scenes
            define the split, and intrinsics missing there are read from ``dataset_root``.
        track: ``single`` (every 5th query) or ``multi`` (the multi-frame leaderboard's queries 9, 19, …).

    Returns:
        Ground truth by scene name.

    Raises:
        ValueError: Neither root is given.
        FileNotFoundError: A root or the split's scenes do not exist.
        FormatError: A file is malformed, or every pose is hidden (the public test split without
            ``gt_root``).
    """
    if gt_root is not None:
        root = Path(gt_root)
    elif dataset_root is not None:
        root = Path(dataset_root)
    else:
        raise ValueError("need a dataset root or a ground-truth root")
    if gt_root is not None and not root.is_dir():
        raise FileNotFoundError(f"ground-truth root {root} (--gt-root) does not exist")
    if dataset_root is not None and not Path(dataset_root).is_dir():
        raise FileNotFoundError(f"dataset root {dataset_root} (--dataset) does not exist")
    names = Dataset(root).scene_names(split)
    if not names:
        raise FileNotFoundError(f"{root / split}: no scenes")
    out: dict[str, SceneTruth] = {}
    for name in names:
        d = root / split / name
        intr = d / "intrinsics.txt"
        if not intr.is_file() and dataset_root is not None:
            intr = Path(dataset_root) / split / name / "intrinsics.txt"
        truth = load_scene_truth(d / "poses.txt", intr, name, track=track)
        out[name] = truth
    if all(t.n_keys == 0 for t in out.values()):
        raise FormatError(
            root / split,
            None,
            "no ground-truth poses (all-zero lines, as in the public test split): pass the private ground truth with --gt-root DIR (in Python: gt_root=DIR)",
        )
    return out
