"""The scores of a submission as a record, and their aggregation over frames grouped by scene.

``Scores`` holds typed fields (the three average medians, the ratio of frames estimated, the precision and AUC
at each threshold); read as a mapping it is the public evaluator's dict, keyed by its English sentences
(``METRIC_KEYS`` first, then the extra thresholds): the form of ``mapfree evaluate --json``, the text table and
every stored report. ``Scores.from_dict`` reads that form back.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import SupportsFloat

import numpy as np

from .metrics import Thresholds, auc, segment_auc

__all__ = ["METRIC_KEYS", "Acceptance", "Scores", "aggregate", "aggregate_scenes", "scene_medians"]

# The public evaluator's output keys, in its order.
METRIC_KEYS = (
    "Average Median Translation Error",
    "Average Median Rotation Error",
    "Average Median Reprojection Error",
    "Precision @ Pose Error < (25.0cm, 5deg)",
    "AUC @ Pose Error < (25.0cm, 5deg)",
    "Precision @ VCRE < 90px",
    "AUC @ VCRE < 90px",
    "Estimates for % of frames",
)

_PRECISION, _AUC = "Precision @ ", "AUC @ "


@dataclass(frozen=True)
class Acceptance:
    """Precision and AUC at one acceptance threshold.

    Attributes:
        name: The threshold as the public evaluator spells it (``Thresholds.pose_name``, ``Thresholds.vcre_name``),
            e.g. ``VCRE < 90px``.
        precision: Fraction of the evaluated frames accepted; None when undefined (no frame).
        auc: Area under the precision against ratio-of-confident-estimates curve; None when undefined.
    """

    name: str
    precision: float | None = None
    auc: float | None = None


def _value(v: SupportsFloat | None) -> float | None:
    """A metric's value: a float, or None for NaN, infinity or nothing."""
    if v is None:
        return None
    f = float(v)
    return f if math.isfinite(f) else None


@dataclass(frozen=True, eq=False)
class Scores(Mapping[str, "float | None"]):
    """The benchmark's metrics over a set of evaluated frames (a submission, or one scene of it).

    As a mapping it is the public evaluator's dict: ``METRIC_KEYS`` in its order (the headline pose and VCRE
    thresholds), then precision and AUC at the further thresholds. Two scores compare equal when their dicts do.

    Attributes:
        median_trans: Average over scenes of the median translation error, metres; None without an estimate.
        median_rot: The same for the rotation error, degrees.
        median_vcre: The same for the VCRE, pixels.
        estimated: Fraction of the evaluated frames with an estimate; None when there is no frame.
        pose: Precision and AUC at each pose threshold, the headline first.
        vcre: Precision and AUC at each VCRE threshold, the headline first.
    """

    median_trans: float | None = None
    median_rot: float | None = None
    median_vcre: float | None = None
    estimated: float | None = None
    pose: tuple[Acceptance, ...] = ()
    vcre: tuple[Acceptance, ...] = ()

    @cached_property
    def _english(self) -> dict[str, float | None]:
        out = dict(zip(METRIC_KEYS[:3], (self.median_trans, self.median_rot, self.median_vcre)))
        for a in (*self.pose[:1], *self.vcre[:1]):  # the headline pose and VCRE thresholds first
            out[_PRECISION + a.name], out[_AUC + a.name] = a.precision, a.auc
        out[METRIC_KEYS[7]] = self.estimated
        for a in (*self.pose[1:], *self.vcre[1:]):
            out[_PRECISION + a.name], out[_AUC + a.name] = a.precision, a.auc
        return out

    def to_dict(self) -> dict[str, float | None]:
        """The public evaluator's dict (a new one), for JSON and the stored reports."""
        return dict(self._english)

    def __getitem__(self, key: str) -> float | None:
        return self._english[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._english)

    def __len__(self) -> int:
        return len(self._english)

    @classmethod
    def from_dict(cls, metrics: Mapping[str, SupportsFloat | None]) -> Scores:
        """Read the public evaluator's dict back (a stored report); keys it does not know are ignored.

        Args:
            metrics: Values by the English names; NaN or None where undefined; missing keys read as None.

        Returns:
            The scores, thresholds in the order their keys come.
        """
        names: dict[str, list[str]] = {"pose": [], "vcre": []}
        for key in metrics:
            for prefix in (_PRECISION, _AUC):
                if key.startswith(prefix):
                    name = key[len(prefix) :]
                    family = names["vcre" if name.startswith("VCRE") else "pose"]
                    if name not in family:
                        family.append(name)

        def at(name: str) -> Acceptance:
            return Acceptance(name, _value(metrics.get(_PRECISION + name)), _value(metrics.get(_AUC + name)))

        trans, rot, reproj = (_value(metrics.get(k)) for k in METRIC_KEYS[:3])
        return cls(
            median_trans=trans,
            median_rot=rot,
            median_vcre=reproj,
            estimated=_value(metrics.get(METRIC_KEYS[7])),
            pose=tuple(at(n) for n in names["pose"]),
            vcre=tuple(at(n) for n in names["vcre"]),
        )


def _scores(
    medians: Iterable[SupportsFloat],
    precision: np.ndarray | list[float],
    areas: np.ndarray | list[float],
    est_ratio: SupportsFloat,
    thresholds: Thresholds,
) -> Scores:
    """Scores from the three mean medians and the (k,) precisions and areas, pose thresholds then VCRE's."""
    n = len(thresholds.pose)

    def at(i: int, name: str) -> Acceptance:
        return Acceptance(name, _value(precision[i]), _value(areas[i]))

    trans, rot, reproj = (_value(m) for m in medians)
    return Scores(
        median_trans=trans,
        median_rot=rot,
        median_vcre=reproj,
        estimated=_value(est_ratio),
        pose=tuple(at(i, Thresholds.pose_name(tm, rd)) for i, (tm, rd) in enumerate(thresholds.pose)),
        vcre=tuple(at(n + i, Thresholds.vcre_name(px)) for i, px in enumerate(thresholds.vcre)),
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


def _criteria(te: np.ndarray, re: np.ndarray, ve: np.ndarray, thresholds: Thresholds) -> np.ndarray:
    """(k, N) accepted, for every pose threshold then every VCRE threshold."""
    ok = [(te < tm) & (re < rd) for tm, rd in thresholds.pose] + [ve < px for px in thresholds.vcre]
    return np.array(ok, dtype=bool).reshape(len(ok), len(te))


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
) -> Scores:
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
        The scores (None where undefined).
    """
    est = np.flatnonzero(estimated)
    failures = int(len(estimated) - len(est) + extra_failures)
    total = len(est) + failures
    if medians is None:
        medians = np.stack([scene_medians(x, bounds, estimated) for x in (trans_err, rot_err, vcre_err)], axis=1)
    mean_medians = [np.mean(c[np.isfinite(c)]) if np.isfinite(c).any() else np.nan for c in medians.T]
    ok = _criteria(trans_err[est], rot_err[est], vcre_err[est], thresholds)
    if total == 0:
        return _scores(mean_medians, [np.nan] * len(ok), [np.nan] * len(ok), np.nan, thresholds)
    precision = ok.sum(axis=1) / total
    areas = np.asarray(auc(confidence[est], ok, failures)) if len(est) else np.zeros(len(ok))
    return _scores(mean_medians, precision, areas, len(est) / total, thresholds)


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
) -> list[Scores]:
    """``aggregate`` of every scene at once, vectorised over scenes.

    The arguments are ``aggregate``'s, except ``extra_failures``: (S,) failures of each scene beyond its
    frames, and ``medians``, required.

    Returns:
        The scores of each scene.
    """
    S = len(bounds) - 1
    est = np.flatnonzero(estimated)
    seg = np.repeat(np.arange(S), np.diff(bounds))[est]
    n_est = np.bincount(seg, minlength=S)
    failures = np.diff(bounds) - n_est + np.asarray(extra_failures)
    total = n_est + failures
    ok = _criteria(trans_err[est], rot_err[est], vcre_err[est], thresholds)
    with np.errstate(invalid="ignore", divide="ignore"):
        tp = np.array([np.bincount(seg, weights=o, minlength=S) for o in ok]).reshape(len(ok), S)
        precision = np.where(total > 0, tp / total, np.nan)
        ratio = np.where(total > 0, n_est / total, np.nan)
    areas = segment_auc(seg, confidence[est], ok, failures)
    areas[:, total == 0] = np.nan
    return [_scores(medians[j], precision[:, j], areas[:, j], ratio[j], thresholds) for j in range(S)]
