"""Relative-pose test pairs in the SuperGlue / LoFTR text format (ScanNet-1500, the paper's supplement).

One pair per line, fields separated by spaces::

    SCENE/color/frame-000100.jpg SCENE/color/frame-000250.jpg EXIF0 EXIF1 K0(9, row-major) K1(9) T_0to1(16)

(36 fields without the two EXIF rotations are accepted too). ``T_0to1`` maps camera-0 coordinates to
camera 1 (``X1 = R X0 + t``), i.e. the pose of image 1 relative to image 0 in mapfree's convention; ``K`` is
for the image as stored. Depth, when present, is ScanNet's ``SCENE/depth/frame-000100.png`` (uint16 mm).
Each malformed line raises ``FormatError`` naming the file and the line.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import Intrinsics, Pose
from .io import FormatError
from .scene import Frame

__all__ = ["ScanNetFrame", "PosePair", "read_pairs"]


@dataclass
class ScanNetFrame(Frame):
    """A ScanNet frame: ``…/color/NAME.jpg``; depth suffix ``depth`` reads ScanNet's ``…/depth/NAME.png``."""

    def depth_path(self, suffix: str) -> Path:
        if suffix == "depth" and self.image_path.parent.name == "color":
            return self.image_path.parent.parent / "depth" / f"{self.image_path.stem}.png"
        return super().depth_path(suffix)


@dataclass
class PosePair:
    """Two frames and the ground-truth pose of frame 1 relative to frame 0 (``X1 = R X0 + t``)."""

    frame0: ScanNetFrame
    frame1: ScanNetFrame
    T_0to1: Pose
    line: int

    @property
    def name(self) -> str:
        return f"{self.frame0.name} {self.frame1.name}"


def _image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from the file header only (no decoding); None when unreadable."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, ValueError):
        return None


def _intrinsics(values: list[float], size: tuple[int, int], path: Path, lineno: int, which: str) -> Intrinsics:
    K = np.array(values).reshape(3, 3)
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1]) and K[1, 0] == 0 and abs(K[0, 1]) < 1e-9):
        raise FormatError(path, lineno, f"{which} is not a pinhole camera matrix (fx, fy > 0, last row 0 0 1)")
    return Intrinsics.from_K(K, *size)


def read_pairs(path: os.PathLike | str, root: os.PathLike | str | None = None) -> list[PosePair]:
    """The pairs of a pair list; image paths are relative to ``root`` (default: the list's folder)."""
    path = Path(path)
    root = Path(root) if root is not None else path.parent
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FormatError(path, None, "pair list not found") from None
    except UnicodeDecodeError:
        raise FormatError(path, None, "not a text file") from None
    pairs = []
    for lineno, line in enumerate(text.splitlines(), 1):
        f = line.split()
        if not f or f[0].startswith("#"):
            continue
        if len(f) not in (36, 38):
            raise FormatError(
                path,
                lineno,
                f"expected 38 fields (img0 img1 exif0 exif1 K0 K1 T_0to1) or 36 without EXIF, found {len(f)}",
            )
        names, nums = f[:2], f[4:] if len(f) == 38 else f[2:]
        if len(f) == 38 and (f[2], f[3]) != ("0", "0"):
            raise FormatError(path, lineno, f"EXIF rotations {f[2]} {f[3]}: only unrotated pairs (0 0) are supported")
        try:
            v = [float(x) for x in nums]
        except ValueError:
            raise FormatError(path, lineno, "unparseable number") from None
        if not all(map(math.isfinite, v)):
            raise FormatError(path, lineno, "non-finite number")
        T = np.array(v[18:]).reshape(4, 4)
        R = T[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
            raise FormatError(path, lineno, "T_0to1 is not a rigid transform")
        frames = []
        for i, name in enumerate(names):
            img = root / name
            size = _image_size(img)
            if size is None:
                raise FormatError(path, lineno, f"image {img} is missing or unreadable")
            K = _intrinsics(v[9 * i : 9 * i + 9], size, path, lineno, f"K{i}")
            frames.append(ScanNetFrame(name, img, K))
        U, _, Vt = np.linalg.svd(R)
        pairs.append(PosePair(frames[0], frames[1], Pose(U @ Vt, T[:3, 3]), lineno))
    return pairs
