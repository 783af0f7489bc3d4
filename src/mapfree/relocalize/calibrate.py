"""``mapfree calibrate``: a method's estimates of every frame with ground truth, turned into a ``Calibration``.

The estimates come from a run's journal (``journal.Journal``: each frame's signals and world pose), either one the
user already has or one this module writes by running the method on every query of the split.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..benchmark.metrics import rotation_error_deg, translation_error, vcre
from ..calibration import CALIBRATION_OPTION, Calibration, CalibrationError, fit
from ..data import Dataset
from ..estimate import Signals
from ..methods import Method, get
from .cascade import CASCADE, STAGE_CALIBRATIONS
from .journal import Journal
from .run import run_split

__all__ = ["JournalFrames", "journal_frames", "calibration_frames", "calibrate", "with_calibration"]


@dataclass
class JournalFrames:
    """The estimated frames of a journal that have ground truth, with their errors.

    Attributes:
        method: The method's name (the journal header's).
        signals: Each frame's signals.
        confidence: (N,) each frame's own confidence.
        vcre: (N,) VCRE, pixels.
        trans_err: (N,) metres.
        rot_err: (N,) degrees.
        stage: (N) the cascade stage that answered (empty for other methods).
        failed: Frames with ground truth but no estimate.
        p_correct: (N,) each frame's journaled ``p_correct`` (NaN where none).
    """

    method: str
    signals: list[Signals]
    confidence: np.ndarray
    vcre: np.ndarray
    trans_err: np.ndarray
    rot_err: np.ndarray
    stage: list[str]
    failed: int
    p_correct: np.ndarray


def journal_frames(journal: os.PathLike | str, root: os.PathLike | str, split: str) -> JournalFrames:
    """Read a run's journal and score each estimated frame against the split's ground truth.

    Args:
        journal: The run's ``*.journal.jsonl``.
        root: The dataset folder.
        split: The split the run relocalized.

    Returns:
        The frames with an estimate and ground truth.

    Raises:
        CalibrationError: No journal, or no frame of it has ground truth.
    """
    read = Journal.read(journal)
    if read.header is None:
        raise CalibrationError(f"{journal} is no run journal (no header line)")
    scenes = {s.name: s for s in Dataset(root).scenes(split)}
    rows: list[tuple[Any, ...]] = []
    failed = 0
    for r in read.frames:
        scene = scenes.get(r.scene)
        if scene is None:
            continue
        ref, frame = scene.reference, scene.frame(r.frame)
        if frame.pose is None or ref.pose is None:
            continue
        if not r.ok:
            failed += 1
            continue
        q, t = frame.pose.qt()
        K = frame.intrinsics
        p_correct = np.nan if r.p_correct is None else r.p_correct
        rows.append(
            (r.signals, r.confidence, q, t, r.q, r.t, [K.fx, K.fy, K.cx, K.cy, K.width, K.height], r.stage, p_correct)
        )
    if not rows and not failed:
        raise CalibrationError(
            f"the {split} split of {root} has no ground-truth poses for the frames of {journal}: calibrate on a "
            f"split with poses (val, or your own data)"
        )
    n = len(rows)
    arr = lambda i, w: np.array([r[i] for r in rows], dtype=np.float64).reshape(n, w)  # noqa: E731
    q_gt, t_gt, q_est, t_est, k = arr(2, 4), arr(3, 3), arr(4, 4), arr(5, 3), arr(6, 6)
    return JournalFrames(
        method=str(read.header.method.get("name", "")),
        signals=[r[0] for r in rows],
        confidence=np.array([r[1] for r in rows], dtype=np.float64),
        vcre=vcre(q_gt, t_gt, q_est, t_est, k[:, :4].astype(np.float32), k[:, 4], k[:, 5]),
        trans_err=translation_error(q_gt, t_gt, q_est, t_est),
        rot_err=rotation_error_deg(q_gt, q_est),
        stage=[r[7] for r in rows],
        failed=failed,
        p_correct=np.array([r[8] for r in rows], dtype=np.float64),
    )


def _has_truth(root: os.PathLike | str, split: str) -> bool:
    for scene in Dataset(root).scenes(split):
        if scene.reference.pose is not None and any(f.pose is not None for f in scene.queries):
            return True
    return False


def _concat(parts: Sequence[JournalFrames]) -> JournalFrames:
    return JournalFrames(
        method=parts[0].method,
        signals=[s for p in parts for s in p.signals],
        confidence=np.concatenate([p.confidence for p in parts]),
        vcre=np.concatenate([p.vcre for p in parts]),
        trans_err=np.concatenate([p.trans_err for p in parts]),
        rot_err=np.concatenate([p.rot_err for p in parts]),
        stage=[s for p in parts for s in p.stage],
        failed=sum(p.failed for p in parts),
        p_correct=np.concatenate([p.p_correct for p in parts]),
    )


def calibration_frames(
    roots: Sequence[os.PathLike | str],
    split: str,
    method: Method,
    *,
    journals: Sequence[os.PathLike | str] | None = None,
    run_outputs: Sequence[os.PathLike | str] | None = None,
    **run_options: Any,
) -> JournalFrames:
    """A method's estimates of every query with ground truth of one split of each dataset, with their errors.

    Args:
        roots: Dataset folders.
        split: A split with ground-truth poses in each.
        method: The method.
        journals: One journal of a run of ``method`` per dataset, read instead of running it.
        run_outputs: One submission path per dataset where the method runs (its journal beside it; an earlier
            run there is resumed).
        **run_options: Passed to ``run_split`` (``workers``, ``progress``, ``batch_size``).

    Returns:
        The frames of all the datasets.

    Raises:
        CalibrationError: A split without scenes or ground truth, a journal of another method.
    """
    parts = []
    for i, root in enumerate(roots):
        if not Dataset(root).scenes(split):
            raise CalibrationError(f"the {split} split of {root} holds no scenes")
        if not _has_truth(root, split):
            raise CalibrationError(
                f"the {split} split of {root} has no ground-truth poses (the test split hides them): calibrate on "
                f"val or on your own data with poses"
            )
        if journals is not None:
            journal: os.PathLike | str = journals[i]
        elif run_outputs is not None:
            journal = run_split(
                root, split, method, run_outputs[i], all_frames=True, resume=True, **run_options
            ).journal
        else:
            raise ValueError("give the journals to read or the run outputs to run the method into")
        frames = journal_frames(journal, root, split)
        if frames.method != method.name:
            raise CalibrationError(f"{journal} is a run of method {frames.method!r}, not {method.name!r}")
        parts.append(frames)
    return _concat(parts)


def calibrate(
    roots: Sequence[os.PathLike | str],
    split: str,
    method: str | Method,
    *,
    journals: Sequence[os.PathLike | str] | None = None,
    run_outputs: Sequence[os.PathLike | str] | None = None,
    **run_options: Any,
) -> Calibration:
    """Fit a method's calibration on every query with ground truth of a split of one or more datasets.

    Args:
        roots: Dataset folders.
        split: A split with ground-truth poses (``val``, or your own).
        method: The method (a name, YAML path or ``Method``).
        journals: One journal of a run of ``method`` per dataset, read instead of running it.
        run_outputs: One submission path per dataset where the method runs (resumed when run before).
        **run_options: Passed to ``run_split`` (``workers``, ``progress``, ``batch_size``).

    Returns:
        The calibration (``save`` it).

    Raises:
        CalibrationError: A split without ground truth, too few frames, one class only, a journal of another
            method.
    """
    m = method if isinstance(method, Method) else get(method)
    frames = calibration_frames(roots, split, m, journals=journals, run_outputs=run_outputs, **run_options)
    where = " + ".join(f"{Path(r).name}/{split}" for r in roots)
    return fit(m.name, frames.signals, frames.confidence.tolist(), frames.vcre, frames.trans_err, frames.rot_err, where)


def with_calibration(method: str | Method, paths: Sequence[os.PathLike | str]) -> Method:
    """The method whose estimates get ``p_correct`` from calibration files (``mapfree run --calibration``).

    A cascade takes one file per stage (each file names its method); another method takes one.

    Args:
        method: The method (a name, YAML path or ``Method``).
        paths: Calibration files.

    Returns:
        The method with the files in its options.

    Raises:
        CalibrationError: A file that cannot be read, is for another method (or no stage of the cascade), or
            more than one file for a method that is not a cascade.
    """
    m = method if isinstance(method, Method) else get(method)
    if not paths:
        return m
    if m.kind == CASCADE:
        stages = [str(s) for s in m.options.get("stages", [])]
        files: dict[str, str] = {}
        for p in paths:
            cal = Calibration.load(p)
            if cal.method not in stages:
                raise CalibrationError(
                    f"calibration {p} is for method {cal.method!r}, which is no stage of cascade {m.name!r} "
                    f"(stages: {', '.join(stages)})"
                )
            files[cal.method] = str(Path(p).resolve())
        return replace(m, options={**m.options, STAGE_CALIBRATIONS: files})
    if len(paths) > 1:
        raise CalibrationError(
            f"--calibration given {len(paths)} times: method {m.name!r} takes one (a cascade one per stage)"
        )
    Calibration.load(paths[0], m.name)
    return replace(m, options={**m.options, CALIBRATION_OPTION: str(Path(paths[0]).resolve())})
