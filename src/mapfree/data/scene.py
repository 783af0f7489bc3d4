"""The Map-free dataset layout: ``Dataset`` -> ``Scene`` -> ``Frame``, all lazy.

A scene's text files are parsed on first use and its images and depth maps only when asked for,
so that scenes with tens of thousands of frames cost nothing until touched.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ..geometry import Intrinsics, Pose, quat_to_rotmat
from .io import FormatError, PoseTable, depth_path_for, read_depth, read_image, read_intrinsics, read_poses
from .overlaps import Overlaps, read_overlaps

__all__ = ["Frame", "Scene", "Dataset", "SPLITS", "REFERENCE_NAME", "frame_number", "scored_query_names"]

SPLITS = ("train", "val", "test")
REFERENCE_NAME = "seq0/frame_00000.jpg"
_SCENE_RE = re.compile(r"^s\d{5}$")


def frame_number(name: str) -> int:
    """The number in a frame name, as the public evaluator reads it (``int(name[-9:-4])``).

    Args:
        name: Frame name like ``seq1/frame_00012.jpg``.

    Returns:
        The frame number (12).
    """
    return int(name[-9:-4])


def scored_query_names(pose_names: Sequence[str], every: int = 5) -> list[str]:
    """Names of the frames the benchmark scores, from a scene's ``poses.txt`` order.

    Frames are keyed by their number; a later name with the same number replaces the value but keeps the
    first position (so ``seq1/frame_00000.jpg`` takes the reference's slot); every ``every``-th position counts.

    Args:
        pose_names: Frame names in ``poses.txt`` order.
        every: Stride of the scored positions (5 for the single-frame track).

    Returns:
        The scored frame names, in that order.
    """
    by_key: dict[int, str] = {}
    for n in pose_names:
        by_key[frame_number(n)] = n
    return list(by_key.values())[::every]


@dataclass
class Frame:
    """One image of a scene, with its own intrinsics (phones refocus) and, when known, its pose.

    Attributes:
        name: Frame name relative to the scene, e.g. ``seq1/frame_00012.jpg``.
        image_path: The image file.
        intrinsics: The frame's intrinsics.
        pose: World-to-camera pose in the scene's frame (val/test: the reference camera's), or None when unknown.
    """

    name: str
    image_path: Path
    intrinsics: Intrinsics
    pose: Pose | None = None

    def image(self) -> np.ndarray:
        """The image as (H, W, 3) uint8 RGB, upright (see ``read_image``)."""
        return read_image(self.image_path)

    def depth_path(self, suffix: str) -> Path:
        """The depth map file of one source (``frame_00012.SUFFIX.png``), whether or not it exists.

        Args:
            suffix: Depth source name, e.g. ``dptkitti``.

        Returns:
            The path.
        """
        return depth_path_for(self.image_path, suffix)

    def has_depth(self, suffix: str) -> bool:
        """Whether the depth map of one source exists.

        Args:
            suffix: Depth source name.

        Returns:
            True when the file is there.
        """
        return self.depth_path(suffix).is_file()

    def depth(self, suffix: str) -> np.ndarray:
        """Read the depth map of one source.

        Args:
            suffix: Depth source name.

        Returns:
            (H, W) float32 depth in metres; 0 where invalid.

        Raises:
            FormatError: The map is missing or unreadable.
        """
        return read_depth(self.depth_path(suffix))

    @property
    def seq(self) -> str:
        """Sequence folder of the frame (``seq0`` is the reference, ``seq1`` the queries)."""
        return self.name.split("/")[0]


@dataclass
class Scene:
    """One scene folder ``ROOT/split/sNNNNN``; its files are read on first use.

    Attributes:
        path: The scene folder.
        split: ``train``, ``val`` or ``test``; the parent folder's name when not given.
    """

    path: Path
    split: str = ""
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.path = Path(self.path)
        if not self.split:
            self.split = self.path.parent.name

    @property
    def name(self) -> str:
        """Scene name, e.g. ``s00460``."""
        return self.path.name

    @cached_property
    def intrinsics(self) -> dict[str, Intrinsics]:
        """Intrinsics by frame name, from ``intrinsics.txt``."""
        return read_intrinsics(self.path / "intrinsics.txt")

    @cached_property
    def poses(self) -> PoseTable | None:
        """Ground-truth poses (None when the scene has no ``poses.txt``)."""
        p = self.path / "poses.txt"
        return read_poses(p) if p.is_file() else None

    @cached_property
    def device_poses(self) -> PoseTable | None:
        """Poses tracked by the capture device (``poses_device.txt``), or None when the scene has none."""
        p = self.path / "poses_device.txt"
        return read_poses(p) if p.is_file() else None

    @cached_property
    def overlaps(self) -> Overlaps | None:
        """Frame-pair overlaps (``overlaps.npz``, train scenes), or None when the scene has none."""
        p = self.path / "overlaps.npz"
        return read_overlaps(p) if p.is_file() else None

    @cached_property
    def frames(self) -> dict[str, Frame]:
        """All frames, in ``intrinsics.txt`` order, with their poses where ``poses.txt`` has them."""
        pose_of: dict[str, Pose | None] = {}
        table = self.poses
        if table is not None:
            valid = np.linalg.norm(table.q, axis=1) > 0  # all-zero lines: private ground truth
            R = np.zeros((len(table), 3, 3))
            R[valid] = quat_to_rotmat(table.q[valid])  # one vectorised call, not one per frame
            pose_of = {n: Pose(R[i], table.t[i]) if valid[i] else None for i, n in enumerate(table.names)}
        return {n: Frame(n, self.path / n, k, pose_of.get(n)) for n, k in self.intrinsics.items()}

    def frame(self, name: str) -> Frame:
        """One frame by name.

        Args:
            name: Frame name, e.g. ``seq1/frame_00012.jpg``.

        Returns:
            The frame.

        Raises:
            FormatError: ``intrinsics.txt`` has no such frame.
        """
        try:
            return self.frames[name]
        except KeyError:
            raise FormatError(self.path / "intrinsics.txt", None, f"no intrinsics for frame {name!r}") from None

    def frame_by_seq_number(self, seq: int, number: int) -> Frame:
        """One frame by sequence and number (the indices of ``overlaps.npz``).

        Args:
            seq: Sequence index (``seqN``).
            number: Frame number (``frame_NNNNN.jpg``).

        Returns:
            The frame.

        Raises:
            FormatError: ``intrinsics.txt`` has no such frame.
        """
        return self.frame(f"seq{seq}/frame_{number:05d}.jpg")

    @property
    def reference(self) -> Frame:
        """The reference image of a val/test scene (``seq0/frame_00000.jpg``)."""
        return self.frame(REFERENCE_NAME)

    @property
    def queries(self) -> list[Frame]:
        """Every query frame (``seq1/*``), in file order."""
        return [f for n, f in self.frames.items() if n.startswith("seq1/")]

    def scored_queries(self) -> list[Frame]:
        """The queries the benchmark scores (every 5th), in file order.

        Returns:
            The scored query frames.

        Raises:
            FormatError: A scored query has no intrinsics (the evaluator needs them too).
        """
        order = self.poses.names if self.poses is not None else list(self.intrinsics)
        return [self.frame(n) for n in scored_query_names(order) if n.startswith("seq1/")]


class Dataset:
    """A Map-free root folder holding ``train/``, ``val/`` and ``test/`` scene folders.

    Args:
        root: The folder.

    Raises:
        FileNotFoundError: ``root`` does not exist or is a file.
    """

    def __init__(self, root: os.PathLike | str):
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(
                f"dataset root {self.root} " + ("is a file, not a folder" if self.root.exists() else "does not exist")
            )

    def splits(self) -> list[str]:
        """The splits present, in train, val, test order."""
        return [s for s in SPLITS if (self.root / s).is_dir()]

    def scene_names(self, split: str) -> list[str]:
        """Names of the scene folders (``sNNNNN``) of a split, sorted.

        Args:
            split: ``train``, ``val`` or ``test``.

        Returns:
            The scene names.

        Raises:
            FileNotFoundError: The split folder does not exist.
        """
        d = self.root / split
        if not d.is_dir():
            raise FileNotFoundError(f"{d}: no such split (have: {', '.join(self.splits()) or 'none'})")
        return sorted(p.name for p in d.iterdir() if p.is_dir() and _SCENE_RE.match(p.name))

    def scenes(self, split: str) -> list[Scene]:
        """The scenes of a split, sorted by name (nothing read yet).

        Args:
            split: ``train``, ``val`` or ``test``.

        Returns:
            The scenes.

        Raises:
            FileNotFoundError: The split folder does not exist.
        """
        return [Scene(self.root / split / n, split) for n in self.scene_names(split)]

    def scene(self, split: str, name: str) -> Scene:
        """One scene.

        Args:
            split: ``train``, ``val`` or ``test``.
            name: Scene name, e.g. ``s00460``.

        Returns:
            The scene (nothing read yet).

        Raises:
            FileNotFoundError: The scene folder does not exist.
        """
        p = self.root / split / name
        if not p.is_dir():
            raise FileNotFoundError(f"{p}: no such scene")
        return Scene(p, split)

    def __iter__(self) -> Iterator[Scene]:
        for s in self.splits():
            yield from self.scenes(s)
