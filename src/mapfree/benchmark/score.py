"""``evaluate``: score a submission against a split's ground truth, vectorised over every frame.

Two modes. ``compat="default"`` fixes the public evaluator's quirks: a missing scene costs exactly its
evaluated frames, a negative confidence is a per-line problem (line skipped), frames are matched by
name. ``compat="official"`` reproduces them, so numbers compare with the public leaderboard: a missing
scene adds *all* its ground-truth lines as failures, a negative confidence on a scored frame aborts,
frames are matched by number. On valid, complete submissions both modes agree with the public
evaluator to 1e-6.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from typing import BinaryIO

import numpy as np

from .metrics import Thresholds, auc, rotation_error_deg, segment_auc, translation_error, vcre
from .report import METRIC_KEYS, Report
from .submission import (
    COMPAT_MODES,
    Problem,
    SceneEstimates,
    SubmissionLimits,
    from_estimates,
    read_submission,
)
from .truth import SceneTruth, load_truth

__all__ = ["evaluate", "score", "aggregate", "aggregate_scenes", "scene_medians", "EvaluationError"]


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
    scenes: list[np.ndarray] = []
    frames: list[str] = []
    q_parts: list[np.ndarray] = []
    t_parts: list[np.ndarray] = []
    K_parts: list[np.ndarray] = []
    W_parts: list[np.ndarray] = []
    H_parts: list[np.ndarray] = []
    est_rows: list[np.ndarray] = []
    est_of: list[str] = []
    extra: dict[str, int] = {}
    problems = list(problems or [])
    for scene in sorted(truth):
        t = truth[scene]
        sel = np.ones(len(t.names), bool) if compat == "official" else t.is_query
        m = int(sel.sum())
        e = estimates.get(scene)
        if e is None:
            rows = np.full(m, -1, dtype=np.int64)
            cost = m
            if compat == "official":  # the public evaluator counts every ground-truth line of a missing scene
                extra[scene] = t.n_keys - m
                cost = t.n_keys
            problems.append(Problem(scene, None, f"no estimates (pose_{scene}.txt missing): {cost} failures"))
        else:
            rows = _match(t, sel, e, compat)
        scenes.append(np.full(m, scene, dtype=object))
        frames.extend(t.names[i] for i in np.flatnonzero(sel).tolist())
        q_parts.append(t.q[sel])
        t_parts.append(t.t[sel])
        K_parts.append(t.K[sel])
        W_parts.append(np.full(m, t.width))
        H_parts.append(np.full(m, t.height))
        est_rows.append(rows)
        est_of.append(scene)
    cat = lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape)  # noqa: E731
    scene_arr = cat(scenes, (0,)).astype(object)
    gt_q, gt_t, K = cat(q_parts, (0, 4)), cat(t_parts, (0, 3)), cat(K_parts, (0, 4)).astype(np.float32)
    W, H = cat(W_parts, (0,)), cat(H_parts, (0,))
    n = len(scene_arr)
    q_est, t_est, conf = np.full((n, 4), np.nan), np.full((n, 3), np.nan), np.full(n, np.nan)
    lines = np.zeros(n, dtype=np.int64)
    offset = 0
    for scene, rows in zip(est_of, est_rows):
        ok = rows >= 0
        if ok.any():
            e = estimates[scene]
            idx = offset + np.flatnonzero(ok)
            q_est[idx], t_est[idx] = e.q[rows[ok]], e.t[rows[ok]]
            conf[idx], lines[idx] = e.confidence[rows[ok]], e.lines[rows[ok]]
        offset += len(rows)
    estimated = np.isfinite(conf)
    unscored = _unscored_track_problem(estimates, int(estimated.sum()), track)
    if unscored is not None:
        problems.append(unscored)
    if compat == "official":
        neg = np.flatnonzero(estimated & (conf < 0))
        if len(neg):
            i = neg[0]
            raise EvaluationError(
                f"{scene_arr[i]}:{lines[i]}: negative confidence on a scored frame; the public evaluator aborts "
                "the whole evaluation (compat='official')"
            )
        if not estimated.any():
            raise EvaluationError("submission does not have any valid pose estimates")
    te, re, ve = (np.full(n, np.nan) for _ in range(3))
    i = np.flatnonzero(estimated)
    te[i] = translation_error(gt_q[i], gt_t[i], q_est[i], t_est[i])
    re[i] = rotation_error_deg(gt_q[i], q_est[i])
    ve[i] = vcre(gt_q[i], gt_t[i], q_est[i], t_est[i], K[i], W[i], H[i])
    bounds = np.concatenate([[0], np.cumsum([len(r) for r in est_rows])]).astype(np.int64)
    medians = np.stack([scene_medians(x, bounds, estimated) for x in (te, re, ve)], axis=1)  # (scenes, 3)
    metrics = aggregate(bounds, te, re, ve, conf, estimated, sum(extra.values()), thresholds, medians)
    extra_each = np.array([extra.get(s, 0) for s in est_of], dtype=np.int64)
    scene_metrics = aggregate_scenes(bounds, te, re, ve, conf, estimated, extra_each, thresholds, medians)
    per_scene = dict(zip(est_of, scene_metrics))
    return Report(
        metrics=metrics,
        per_scene=per_scene,
        scene=scene_arr.astype(str),
        frame=np.array(frames, dtype=str),
        trans_err=te,
        rot_err=re,
        vcre=ve,
        confidence=conf,
        estimated=estimated,
        diagonal=np.hypot(W, H),
        problems=sorted(problems, key=lambda p: (p.scene or "", p.line or 0)),
        split=split,
        compat=compat,
        track=track,
        thresholds=thresholds,
        extra_failures=sum(extra.values()),
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


def scene_medians(values: np.ndarray, bounds: np.ndarray, estimated: np.ndarray) -> np.ndarray:
    """Median over the estimated frames of each scene, all scenes in one sort (same numbers as ``np.median``).

    Args:
        values: (M,) per-frame values, frames grouped by scene.
        bounds: (S + 1,) scene i is ``bounds[i]:bounds[i+1]``.
        estimated: (M,) bool, frames that count.

    Returns:
        (S,) medians; NaN for a scene without an estimated frame.
    """
    n = len(bounds) - 1
    seg = np.repeat(np.arange(n), np.diff(bounds))[estimated]
    v = values[estimated]
    order = np.lexsort((v, seg))
    v = v[order]
    counts = np.bincount(seg, minlength=n)
    starts = np.cumsum(counts) - counts
    has = counts > 0
    out = np.full(n, np.nan)
    lo, hi = (starts + (counts - 1) // 2)[has], (starts + counts // 2)[has]
    out[has] = (v[lo] + v[hi]) / 2
    return out


def _criteria(te: np.ndarray, re: np.ndarray, ve: np.ndarray, thresholds: Thresholds):
    """(names, (k, N) accepted) for every pose threshold then every VCRE threshold."""
    names = [Thresholds.pose_name(tm, rd) for tm, rd in thresholds.pose]
    names += [Thresholds.vcre_name(px) for px in thresholds.vcre]
    ok = [(te < tm) & (re < rd) for tm, rd in thresholds.pose] + [ve < px for px in thresholds.vcre]
    return names, np.array(ok, dtype=bool).reshape(len(names), len(te))


def _as_dict(medians, precision, areas, est_ratio, names, n_pose) -> dict[str, float | None]:
    """Metric dict in the public evaluator's key order, then the extra thresholds; NaN -> None."""
    val = lambda v: float(v) if v is not None and np.isfinite(v) else None  # noqa: E731
    out = {key: val(m) for key, m in zip(METRIC_KEYS[:3], medians)}
    for i in (0, n_pose):  # the headline pose and VCRE thresholds first
        out[f"Precision @ {names[i]}"] = val(precision[i])
        out[f"AUC @ {names[i]}"] = val(areas[i])
    out["Estimates for % of frames"] = val(est_ratio)
    for i in [j for j in range(len(names)) if j not in (0, n_pose)]:
        out[f"Precision @ {names[i]}"] = val(precision[i])
        out[f"AUC @ {names[i]}"] = val(areas[i])
    return out


def aggregate(
    bounds: np.ndarray,
    trans_err: np.ndarray,
    rot_err: np.ndarray,
    vcre_err: np.ndarray,
    confidence: np.ndarray,
    estimated: np.ndarray,
    extra_failures: int = 0,
    thresholds: Thresholds = Thresholds(),
    medians: np.ndarray | None = None,
) -> dict[str, float | None]:
    """The benchmark's metrics over evaluated frames grouped by scene.

    "Average Median" = median per scene over its estimated frames, mean over scenes with an estimate;
    precision and AUC count every evaluated frame (plus ``extra_failures``) in the denominator.

    Args:
        bounds: (S + 1,) scene i is ``bounds[i]:bounds[i+1]``.
        trans_err: (M,) translation errors, metres.
        rot_err: (M,) rotation errors, degrees.
        vcre_err: (M,) VCRE, pixels.
        confidence: (M,) confidences.
        estimated: (M,) bool, frames with an estimate.
        extra_failures: Failures beyond the M frames.
        thresholds: Thresholds of the precision and AUC metrics.
        medians: (S, 3) per-scene medians of the three errors, when already computed.

    Returns:
        The metrics by the public evaluator's names (None where undefined).
    """
    est = np.flatnonzero(estimated)
    failures = int(len(estimated) - len(est) + extra_failures)
    total = len(est) + failures
    if medians is None:
        medians = np.stack([scene_medians(x, bounds, estimated) for x in (trans_err, rot_err, vcre_err)], axis=1)
    mean_medians = [np.mean(c[np.isfinite(c)]) if np.isfinite(c).any() else np.nan for c in medians.T]
    names, ok = _criteria(trans_err[est], rot_err[est], vcre_err[est], thresholds)
    if total == 0:
        return _as_dict(mean_medians, [np.nan] * len(names), [np.nan] * len(names), np.nan, names, len(thresholds.pose))
    precision = ok.sum(axis=1) / total
    areas = auc(confidence[est], ok, failures) if len(est) else np.zeros(len(names))
    return _as_dict(mean_medians, precision, areas, len(est) / total, names, len(thresholds.pose))


def aggregate_scenes(
    bounds: np.ndarray,
    trans_err: np.ndarray,
    rot_err: np.ndarray,
    vcre_err: np.ndarray,
    confidence: np.ndarray,
    estimated: np.ndarray,
    extra_failures: np.ndarray,
    thresholds: Thresholds,
    medians: np.ndarray,
) -> list[dict[str, float | None]]:
    """``aggregate`` of every scene at once (same keys), vectorised over scenes.

    The arguments are ``aggregate``'s, except ``extra_failures``: (S,) failures of each scene beyond its
    frames, and ``medians``, required.

    Returns:
        One metrics dict per scene.
    """
    S = len(bounds) - 1
    est = np.flatnonzero(estimated)
    seg = np.repeat(np.arange(S), np.diff(bounds))[est]
    n_est = np.bincount(seg, minlength=S)
    failures = np.diff(bounds) - n_est + np.asarray(extra_failures)
    total = n_est + failures
    names, ok = _criteria(trans_err[est], rot_err[est], vcre_err[est], thresholds)
    with np.errstate(invalid="ignore", divide="ignore"):
        tp = np.array([np.bincount(seg, weights=o, minlength=S) for o in ok]).reshape(len(names), S)
        precision = np.where(total > 0, tp / total, np.nan)
        ratio = np.where(total > 0, n_est / total, np.nan)
    areas = segment_auc(seg, confidence[est], ok, failures)
    areas[:, total == 0] = np.nan
    n_pose = len(thresholds.pose)
    return [_as_dict(medians[j], precision[:, j], areas[:, j], ratio[j], names, n_pose) for j in range(S)]
