"""Microsoft 7-Scenes in its own layout, as ``Frame`` objects the rest of mapfree understands.

```
ROOT/SCENE/TrainSplit.txt, TestSplit.txt   # "sequence1" lines: which seq-XX folders map and which query
ROOT/SCENE/seq-01/frame-000000.color.png   # RGB, 640x480
                  frame-000000.depth.png   # uint16 millimetres, 65535 (and 0) = no measurement
                  frame-000000.pose.txt    # 4x4 camera-to-world matrix (metres)
```
Poses are turned into mapfree's world-to-camera convention. Every malformed file raises ``FormatError``
naming it. Depth is read with the suffix ``depth`` (methods ``*_depth``, e.g. ``sift_pnp_depth``).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import Intrinsics, Pose
from .io import FormatError, read_depth, read_image
from .scene import Frame

__all__ = ["SCENES", "COLOR_CAMERA", "SevenScenesFrame", "SevenScenesScene", "SevenScenes", "read_matrix_pose"]

SCENES = ("chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs")
#: fx fy cx cy of the Kinect colour camera as commonly calibrated for 7-Scenes (the dataset ships none);
#: the image size is read from the images.
COLOR_CAMERA = (525.0, 525.0, 320.0, 240.0)
_SEQ_RE = re.compile(r"^seq-(\d+)$")
_SPLIT_RE = re.compile(r"^sequence(\d+)$")
_INVALID_MM = 65535


def read_matrix_pose(path: os.PathLike | str) -> Pose:
    """Read a 7-Scenes pose file into mapfree's convention.

    Args:
        path: A ``.pose.txt``: a 4x4 camera-to-world matrix, metres.

    Returns:
        The world-to-camera pose, its rotation re-orthonormalised.

    Raises:
        FormatError: The file is missing or not a rigid 4x4 transform.
    """
    path = Path(path)
    try:
        rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    except FileNotFoundError:
        raise FormatError(path, None, "pose file not found") from None
    except UnicodeDecodeError:
        raise FormatError(path, None, "not a text file") from None
    if len(rows) != 4 or any(len(r) != 4 for r in rows):
        raise FormatError(
            path, None, f"expected a 4x4 matrix, found {len(rows)} line(s) of {[len(r) for r in rows]} values"
        )
    try:
        T = np.array(rows, dtype=np.float64)
    except ValueError:
        raise FormatError(path, None, "unparseable number in the pose matrix") from None
    if not np.all(np.isfinite(T)):
        raise FormatError(path, None, "non-finite number in the pose matrix")
    R = T[:3, :3]
    if (
        np.abs(R.T @ R - np.eye(3)).max() > 1e-2
        or np.linalg.det(R) < 0
        or not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6)
    ):
        raise FormatError(path, None, "not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    U, _, Vt = np.linalg.svd(R)
    return Pose(U @ Vt, T[:3, 3]).inverse()


@dataclass
class SevenScenesFrame(Frame):
    """A 7-Scenes frame: depth beside the colour image as ``frame-NNNNNN.SUFFIX.png`` (native: ``depth``)."""

    def depth_path(self, suffix: str) -> Path:
        """``frame-NNNNNN.SUFFIX.png`` beside the colour image, whether or not it exists."""
        return self.image_path.with_name(self.image_path.name.replace(".color.png", f".{suffix}.png"))

    def depth(self, suffix: str) -> np.ndarray:
        """(H, W) float32 depth in metres; 0 where invalid, the Kinect's 65535 "no measurement" included."""
        d = read_depth(self.depth_path(suffix))
        d[d >= _INVALID_MM / 1000.0] = 0.0  # the Kinect's "no measurement"
        return d


@dataclass
class SevenScenesScene:
    """One scene folder; ``frames("train")`` are the mapping frames, ``frames("test")`` the queries."""

    path: Path
    camera: tuple[float, float, float, float] = COLOR_CAMERA

    def __post_init__(self) -> None:
        self.path = Path(self.path)

    @property
    def name(self) -> str:
        """Scene name, e.g. ``chess``."""
        return self.path.name

    def all_sequences(self) -> list[str]:
        """Every ``seq-XX`` folder of the scene, sorted."""
        return sorted(p.name for p in self.path.iterdir() if p.is_dir() and _SEQ_RE.match(p.name))

    def sequences(self, split: str) -> list[str]:
        """The sequences of a split, as the scene's ``TrainSplit.txt`` or ``TestSplit.txt`` lists them.

        Args:
            split: ``train`` (mapping) or ``test`` (queries).

        Returns:
            ``seq-XX`` folder names.

        Raises:
            ValueError: ``split`` is neither.
            FormatError: The split file is missing, malformed, or names a missing folder.
        """
        if split not in ("train", "test"):
            raise ValueError(f"split must be 'train' or 'test', got {split!r}")
        f = self.path / f"{split.capitalize()}Split.txt"
        if not f.is_file():
            raise FormatError(f, None, "split file not found (7-Scenes scenes list their sequences there)")
        out = []
        for lineno, line in enumerate(f.read_text().splitlines(), 1):
            s = line.strip()
            if not s:
                continue
            m = _SPLIT_RE.match(s)
            if not m:
                raise FormatError(f, lineno, f"expected 'sequenceN', found {s!r}")
            seq = f"seq-{int(m.group(1)):02d}"
            if not (self.path / seq).is_dir():
                raise FormatError(f, lineno, f"sequence folder {self.path / seq} does not exist")
            out.append(seq)
        return out

    def frames(self, split: str, stride: int = 1) -> list[SevenScenesFrame]:
        """The frames of a split's sequences, in order, with their poses (read now).

        Args:
            split: ``train`` or ``test``.
            stride: Keep every ``stride``-th frame of each sequence.

        Returns:
            The frames; intrinsics from ``camera`` and the size of the first image.

        Raises:
            ValueError: ``split`` is unknown or ``stride < 1``.
            FormatError: A sequence without images, or a malformed pose or split file.
        """
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        out = []
        for seq in self.sequences(split):
            images = sorted((self.path / seq).glob("frame-*.color.png"))
            if not images:
                raise FormatError(self.path / seq, None, "no frame-NNNNNN.color.png images")
            h, w = read_image(images[0]).shape[:2]
            K = Intrinsics(*self.camera, w, h)
            for img in images[::stride]:
                pose = read_matrix_pose(img.with_name(img.name.replace(".color.png", ".pose.txt")))
                out.append(SevenScenesFrame(f"{seq}/{img.name}", img, K, pose))
        return out


class SevenScenes:
    """A 7-Scenes root: one folder per scene (``chess``, ``fire``, …) holding ``seq-XX`` folders."""

    def __init__(self, root: os.PathLike | str, camera: tuple[float, float, float, float] = COLOR_CAMERA) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"7-Scenes root {self.root} does not exist")
        if len(camera) != 4 or not all(np.isfinite(camera)) or camera[0] <= 0 or camera[1] <= 0:
            raise ValueError(f"camera must be fx fy cx cy with positive focal lengths, got {camera}")
        fx, fy, cx, cy = (float(c) for c in camera)
        self.camera = (fx, fy, cx, cy)

    def scene_names(self) -> list[str]:
        return sorted(
            p.name
            for p in self.root.iterdir()
            if p.is_dir() and any(_SEQ_RE.match(c.name) for c in p.iterdir() if c.is_dir())
        )

    def scene(self, name: str) -> SevenScenesScene:
        p = self.root / name
        if not p.is_dir():
            raise FileNotFoundError(f"{p}: no such 7-Scenes scene (have: {', '.join(self.scene_names()) or 'none'})")
        return SevenScenesScene(p, self.camera)
