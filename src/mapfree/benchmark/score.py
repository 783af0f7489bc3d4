"""``evaluate``: score a submission against a split's ground truth, vectorised over every frame.

Two modes. ``compat="default"`` fixes the public evaluator's quirks: a missing scene costs exactly its
evaluated frames, a negative confidence is a per-line problem (line skipped), frames are matched by
name. ``compat="official"`` reproduces them, so numbers compare with the public leaderboard: a missing
scene adds *all* its ground-truth lines as failures, a negative confidence on a scored frame aborts,
frames are matched by number. On valid, complete submissions both modes agree with the public
evaluator to 1e-6.

``score`` is three steps: ``gather`` lays every evaluated frame out as ``Columns`` (its truth beside its
estimate), ``errors`` gives each estimated frame's three errors, and ``aggregate`` (``benchmark.scores``) turns
them into ``Scores``, for the whole split and for each scene.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import BinaryIO

import numpy as np

from .metrics import Thresholds, rotation_error_deg, translation_error, vcre
from .report import Report
from .scores import aggregate, aggregate_scenes, scene_medians
from .submission import (
    COMPAT_MODES,
    Problem,
    SceneEstimates,
    SubmissionLimits,
    from_estimates,
    read_submission,
)
from .truth import SceneTruth, load_truth

__all__ = [
    "evaluate",
    "score",
    "gather",
    "errors",
    "Columns",
    "aggregate",
    "aggregate_scenes",
    "scene_medians",
    "EvaluationError",
]


class EvaluationError(RuntimeError):
    """The evaluation cannot produce numbers (compat="official" aborts, or no ground truth)."""


def evaluate(
    submission: os.PathLike | str | bytes | BinaryIO | Mapping,
    dataset_root: os.PathLike | str | None = None,
    split: str = "val",
    compat: str = "default",
    gt_root: os.PathLike | str | None = None,
    *,
    truth: Mapping[str, SceneTruth] | None = None,
    limits: SubmissionLimits | None = None,
    thresholds: Thresholds = Thresholds(),
    track: str = "single",
) -> Report:
    """Score a submission against a split's ground truth (``mapfree evaluate``).

    Args:
        submission: A ZIP (path, bytes or binary file), or ``{scene: [(frame_name, Pose, confidence), ...]}``.
        dataset_root: The dataset folder; ground truth is read from ``dataset_root/SPLIT``.
        split: The split scored.
        compat: ``default`` (the public evaluator's quirks fixed) or ``official`` (reproduced).
        gt_root: Folder of private ground truth (``gt_root/SPLIT``), read instead of ``dataset_root``'s.
        truth: Ground truth already loaded by ``load_truth``, to score many submissions against one split.
        limits: Size limits of the ZIP.
        thresholds: Thresholds of the precision and AUC metrics.
        track: ``single``, or ``multi`` for the multi-frame leaderboard's frames (queries 9, 19, 29, …).

    Returns:
        The metrics, per-scene metrics, per-frame errors and every problem of the submission.

    Raises:
        ValueError: ``compat`` is unknown, or there is neither a dataset nor a ground-truth root.
        EvaluationError: ``compat="official"`` and the public evaluator would abort.
        FormatError: The ground truth is malformed.
    """
    if compat not in COMPAT_MODES:
        raise ValueError(f"compat must be one of {COMPAT_MODES}, got {compat!r}")
    truth = truth if truth is not None else load_truth(dataset_root, split, gt_root, track=track)
    expected = {s: t.frame_names for s, t in truth.items()}
    if isinstance(submission, Mapping):
        estimates, problems = from_estimates(submission, expected, compat)
    else:
        estimates, problems = read_submission(submission, expected, compat, limits)
    if compat == "official":
        fatal = [p for p in problems if p.fatal]
        if fatal:
            raise EvaluationError(f"the public evaluator aborts here: {fatal[0]}")
    return score(truth, estimates, problems, compat=compat, thresholds=thresholds, split=split, track=track)


def _match(t: SceneTruth, sel: np.ndarray, est: SceneEstimates, compat: str) -> np.ndarray:
    """Row of ``est`` for each selected evaluated frame, -1 where there is none."""
    if compat == "official":
        row_of = {k: i for i, k in enumerate(est.keys.tolist())}
        return np.array([row_of.get(k, -1) for k in t.keys[sel].tolist()], dtype=np.int64)
    row_of = {n: i for i, n in enumerate(est.names)}
    return np.array([row_of.get(t.names[i], -1) for i in np.flatnonzero(sel).tolist()], dtype=np.int64)


@dataclass
class Columns:
    """Every evaluated frame of every scene as columns, its ground truth beside its estimate (``gather``).

    Frames are grouped by scene, scenes sorted; M frames, S scenes.

    Attributes:
        scenes: The S scenes.
        bounds: (S + 1,) scene i is rows ``bounds[i]:bounds[i+1]``.
        extra: (S,) failures of each scene beyond its frames (``compat="official"``: a missing scene's other lines).
        scene: (M,) object, scene of each frame.
        frame: The M frame names.
        gt_q: (M, 4) true world-to-camera rotations, wxyz.
        gt_t: (M, 3) true translations, metres.
        K: (M, 4) float32 intrinsics fx, fy, cx, cy.
        width: (M,) image widths, pixels.
        height: (M,) image heights, pixels.
        q: (M, 4) estimated rotations; NaN where no estimate.
        t: (M, 3) estimated translations; NaN where no estimate.
        confidence: (M,) confidences; NaN where no estimate.
        line: (M,) line of each estimate in its file; 0 where none.
    """

    scenes: list[str]
    bounds: np.ndarray
    extra: np.ndarray
    scene: np.ndarray
    frame: list[str]
    gt_q: np.ndarray
    gt_t: np.ndarray
    K: np.ndarray
    width: np.ndarray
    height: np.ndarray
    q: np.ndarray
    t: np.ndarray
    confidence: np.ndarray
    line: np.ndarray

    @property
    def estimated(self) -> np.ndarray:
        """(M,) bool, the frames with an estimate."""
        return np.isfinite(self.confidence)


def _cat(parts: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(shape)


def gather(
    truth: Mapping[str, SceneTruth], estimates: Mapping[str, SceneEstimates], compat: str = "default"
) -> tuple[Columns, list[Problem]]:
    """The evaluated frames of every scene of ``truth`` as columns, each beside its estimate.

    Args:
        truth: Ground truth by scene.
        estimates: Estimates by scene.
        compat: ``default`` (queries matched by name) or ``official`` (every line matched by number).

    Returns:
        The columns, and a problem for each scene without estimates.
    """
    scenes = sorted(truth)
    sels, rows_of, extra, problems = [], [], [], []
    for scene in scenes:
        t = truth[scene]
        sel = np.ones(len(t.names), bool) if compat == "official" else t.is_query
        m, e, more = int(sel.sum()), estimates.get(scene), 0
        if e is None:
            rows = np.full(m, -1, dtype=np.int64)
            if compat == "official":  # the public evaluator counts every ground-truth line of a missing scene
                more = t.n_keys - m
            problems.append(Problem(scene, None, f"no estimates (pose_{scene}.txt missing): {m + more} failures"))
        else:
            rows = _match(t, sel, e, compat)
        sels.append(sel)
        rows_of.append(rows)
        extra.append(more)
    W = _cat([np.full(len(r), truth[s].width) for s, r in zip(scenes, rows_of)], (0,))
    H = _cat([np.full(len(r), truth[s].height) for s, r in zip(scenes, rows_of)], (0,))
    n = len(W)
    cols = Columns(
        scenes=scenes,
        bounds=np.concatenate([[0], np.cumsum([len(r) for r in rows_of])]).astype(np.int64),
        extra=np.array(extra, dtype=np.int64),
        scene=_cat([np.full(len(r), s, dtype=object) for s, r in zip(scenes, rows_of)], (0,)).astype(object),
        frame=[truth[s].names[i] for s, sel in zip(scenes, sels) for i in np.flatnonzero(sel).tolist()],
        gt_q=_cat([truth[s].q[sel] for s, sel in zip(scenes, sels)], (0, 4)),
        gt_t=_cat([truth[s].t[sel] for s, sel in zip(scenes, sels)], (0, 3)),
        K=_cat([truth[s].K[sel] for s, sel in zip(scenes, sels)], (0, 4)).astype(np.float32),
        width=W,
        height=H,
        q=np.full((n, 4), np.nan),
        t=np.full((n, 3), np.nan),
        confidence=np.full(n, np.nan),
        line=np.zeros(n, dtype=np.int64),
    )
    for scene, rows, lo in zip(scenes, rows_of, cols.bounds.tolist()):
        ok = rows >= 0
        if ok.any():
            e = estimates[scene]
            idx = lo + np.flatnonzero(ok)
            cols.q[idx], cols.t[idx] = e.q[rows[ok]], e.t[rows[ok]]
            cols.confidence[idx], cols.line[idx] = e.confidence[rows[ok]], e.lines[rows[ok]]
    return cols, problems


def errors(
    gt_q: np.ndarray,
    gt_t: np.ndarray,
    q: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    width: np.ndarray,
    height: np.ndarray,
    estimated: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The three errors of every estimated frame.

    Args:
        gt_q: (M, 4) true world-to-camera rotations, wxyz.
        gt_t: (M, 3) true translations, metres.
        q: (M, 4) estimated rotations.
        t: (M, 3) estimated translations.
        K: (M, 4) intrinsics fx, fy, cx, cy.
        width: (M,) image widths, pixels.
        height: (M,) image heights, pixels.
        estimated: (M,) bool, the frames with an estimate.

    Returns:
        (M,) translation errors (metres), rotation errors (degrees) and VCRE (pixels); NaN where no estimate.
    """
    te, re, ve = (np.full(len(estimated), np.nan) for _ in range(3))
    i = np.flatnonzero(estimated)
    if len(i):
        te[i] = translation_error(gt_q[i], gt_t[i], q[i], t[i])
        re[i] = rotation_error_deg(gt_q[i], q[i])
        ve[i] = vcre(gt_q[i], gt_t[i], q[i], t[i], K[i], width[i], height[i])
    return te, re, ve


def _official_abort(cols: Columns) -> None:
    """Raise where the public evaluator aborts: a negative confidence on a scored frame, or no estimate."""
    estimated = cols.estimated
    neg = np.flatnonzero(estimated & (cols.confidence < 0))
    if len(neg):
        i = neg[0]
        raise EvaluationError(
            f"{cols.scene[i]}:{cols.line[i]}: negative confidence on a scored frame; the public evaluator aborts "
            "the whole evaluation (compat='official')"
        )
    if not estimated.any():
        raise EvaluationError("submission does not have any valid pose estimates")


def score(
    truth: Mapping[str, SceneTruth],
    estimates: Mapping[str, SceneEstimates],
    problems: list[Problem] | None = None,
    compat: str = "default",
    thresholds: Thresholds = Thresholds(),
    split: str = "val",
    track: str = "single",
) -> Report:
    """Score parsed estimates: per-frame errors for every evaluated frame of every scene, then the aggregates.

    Args:
        truth: Ground truth by scene (``load_truth``).
        estimates: Estimates by scene (``read_submission``, ``from_estimates``).
        problems: Problems found while reading, carried into the report.
        compat: ``default`` or ``official`` (frames matched by number; missing scenes cost all their lines).
        thresholds: Thresholds of the precision and AUC metrics.
        split: The split, recorded in the report.
        track: The leaderboard whose frames ``truth`` holds, recorded in the report.

    Returns:
        The report.

    Raises:
        EvaluationError: ``compat="official"`` and a scored frame has a negative confidence, or no frame
            has an estimate.
    """
    cols, missing = gather(truth, estimates, compat)
    problems = [*(problems or []), *missing]
    estimated = cols.estimated
    unscored = _unscored_track_problem(estimates, int(estimated.sum()), track)
    if unscored is not None:
        problems.append(unscored)
    if compat == "official":
        _official_abort(cols)
    te, re, ve = errors(cols.gt_q, cols.gt_t, cols.q, cols.t, cols.K, cols.width, cols.height, estimated)
    medians = np.stack([scene_medians(x, cols.bounds, estimated) for x in (te, re, ve)], axis=1)  # (scenes, 3)
    extra = int(cols.extra.sum())
    metrics = aggregate(cols.bounds, te, re, ve, cols.confidence, estimated, extra, thresholds, medians)
    per_scene = aggregate_scenes(cols.bounds, te, re, ve, cols.confidence, estimated, cols.extra, thresholds, medians)
    return Report(
        metrics=metrics,
        per_scene=dict(zip(cols.scenes, per_scene)),
        scene=cols.scene.astype(str),
        frame=np.array(cols.frame, dtype=str),
        trans_err=te,
        rot_err=re,
        vcre=ve,
        confidence=cols.confidence,
        estimated=estimated,
        diagonal=np.hypot(cols.width, cols.height),
        problems=sorted(problems, key=lambda p: (p.scene or "", p.line or 0)),
        split=split,
        compat=compat,
        track=track,
        thresholds=thresholds,
        extra_failures=extra,
    )


def _unscored_track_problem(estimates: Mapping[str, SceneEstimates], matched: int, track: str) -> Problem | None:
    """A submission whose estimates are all for frames this track does not score (a multi-frame submission scored
    on the single-frame track, or the reverse) would score zero without a word: say so, and which track fits."""
    names = [n for e in estimates.values() for n in e.names]
    if matched or not names:
        return None
    numbers = [int(m.group(1)) for n in names if (m := re.search(r"(\d+)\.\w+$", n))]
    multi_like = bool(numbers) and all(k % 10 == 9 for k in numbers)
    single_like = bool(numbers) and all(k % 5 == 0 for k in numbers)
    hint = (
        "they are the multi-frame track's frames (9, 19, 29, ...): score it with --track multi"
        if track == "single" and multi_like
        else "they are the single-frame track's frames (every 5th): score it with --track single"
        if track == "multi" and single_like
        else "check the split and the frame names"
    )
    return Problem(
        None,
        None,
        f"none of the submission's {len(names)} estimates is for a frame the {track}-frame "
        f"track scores, so every frame counts as a failure; {hint}",
    )
