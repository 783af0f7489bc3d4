"""Writing a submission ZIP: atomically, with reproducible bytes, never a line the reader would refuse."""

from __future__ import annotations

import os
import re
import tempfile
import zipfile
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from ..data.io import naming, publish
from ..geometry import Pose
from .submission import Problem

__all__ = ["write_submission", "ZIP_DATE"]

ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # entries' timestamp in a written submission (the ZIP epoch): reproducible bytes


def write_submission(
    path: os.PathLike | str, estimates: Mapping[str, Iterable[tuple[str, Pose | None, float]]]
) -> list[Problem]:
    """Write a submission ZIP (``pose_sNNNNN.txt`` per scene), atomically and with reproducible bytes.

    Frames without a pose are left out (they count as failures); non-finite poses or confidences and
    negative confidences are never written: they are skipped and returned as problems.

    Args:
        path: The ZIP, replaced when it exists.
        estimates: ``{scene: [(frame_name, world-to-camera Pose | None, confidence), ...]}``.

    Returns:
        The estimates skipped, one problem each.

    Raises:
        ValueError: A scene name is not ``sNNNNN``.
    """
    path = Path(path)
    skipped: list[Problem] = []
    files: dict[str, str] = {}
    for scene in sorted(estimates):
        if not re.fullmatch(r"s\d{5}", scene):
            raise ValueError(f"scene name {scene!r} is not sNNNNN")
        lines = []
        for name, pose, conf in estimates[scene]:
            if pose is None:
                continue
            if any(c.isspace() for c in name) or not name:
                skipped.append(Problem(scene, None, f"{name!r}: frame names cannot be empty or contain spaces"))
                continue
            conf = float(conf)
            if not pose.is_finite() or not np.isfinite(conf):
                skipped.append(Problem(scene, None, f"{name}: non-finite pose or confidence, not written"))
                continue
            if conf < 0:
                skipped.append(Problem(scene, None, f"{name}: negative confidence {conf}, not written"))
                continue
            q, t = pose.qt()
            lines.append(name + " " + " ".join(repr(float(v)) for v in (*q, *t, conf)) + "\n")
        files[f"pose_{scene}.txt"] = "".join(lines)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name, suffix=".part", dir=path.parent)
    try:
        with naming(path), os.fdopen(fd, "wb") as fh, zipfile.ZipFile(fh, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for name, text in files.items():  # a fixed timestamp: the same estimates give the same bytes
                info = zipfile.ZipInfo(name, date_time=ZIP_DATE)
                info.external_attr = 0o644 << 16  # -rw-r--r-- when unpacked
                zf.writestr(info, text, compress_type=zipfile.ZIP_DEFLATED)
        publish(tmp, path)  # 0644 as every other output, not mkstemp's 0600
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return skipped
