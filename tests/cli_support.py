"""Helpers shared by the tests of what the commands print (a module the tests import, not a test module)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def one_line(capfd) -> tuple[str, str]:
    """(stdout, the only line of stderr); fails when stderr holds anything else (a traceback, a warning)."""
    out, err = capfd.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return out, lines[0]


def query_pair(synth: Path) -> tuple[str, str]:
    scene = synth / "val" / "s00000"
    return str(scene / "seq0" / "frame_00000.jpg"), str(scene / "seq1" / "frame_00005.jpg")


def mapfree_process(
    *args: object, env: dict[str, str] | None = None, timeout: float = 300
) -> subprocess.CompletedProcess:
    """``python -m mapfree ARGS`` as its own process, as a user runs it; ``env`` is added to this process's."""
    return subprocess.run(
        [sys.executable, "-m", "mapfree", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, **(env or {})},
    )


#: EXIF tags a phone writes: Orientation (main IFD); FocalLength, FocalLengthIn35mmFilm, FocalPlaneXResolution,
#: FocalPlaneResolutionUnit, PixelXDimension (Exif sub-IFD, 0x8769).
ORIENTATION, EXIF_IFD = 0x0112, 0x8769
FOCAL_LENGTH, FOCAL_35MM, FOCAL_PLANE_X_RES, FOCAL_PLANE_UNIT, PIXEL_X_DIM = 0x920A, 0xA405, 0xA20E, 0xA210, 0xA002


def stored_grid(upright, orientation: int):
    """The pixels a sensor stores for an upright photo (or depth map) that ``orientation`` turns upright."""
    import numpy as np

    from mapfree.data.orientation import ROTATIONS

    return np.ascontiguousarray(np.rot90(upright, ROTATIONS[orientation]))  # the inverse of orient_pixels


def phone_jpeg(dst, upright, orientation: int, tags: dict, scale: float = 1.0) -> None:
    """Write ``upright`` (H, W, 3 RGB) as a phone would, to a path or a binary file: its stored grid, the EXIF
    orientation that turns it upright and the focal ``tags`` of the Exif sub-IFD (Pillow's Exif API), optionally
    resized afterwards by ``scale``."""
    from PIL import Image

    img = Image.fromarray(stored_grid(upright, orientation))
    if scale != 1.0:
        img = img.resize((round(img.width * scale), round(img.height * scale)), Image.Resampling.LANCZOS)
    exif = Image.Exif()
    exif[ORIENTATION] = orientation
    exif.get_ifd(EXIF_IFD).update(tags)
    img.save(dst, format="JPEG", exif=exif, quality=95)
