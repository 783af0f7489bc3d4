"""Confidences for ranking estimates: the paper's inlier count, and a score that ranks better.

The paper ranks by the number of inliers. That count grows with the number of matches, not with how
consistent the geometry is: 300 inliers out of 2000 matches whose depths disagree on the scale rank
above 80 clean ones. Our ``score`` keeps the count but multiplies it by the *agreement ratios* of the
robust steps, each in [0, 1]:

    Ess.Mat + D.Scale:  score = scale_inliers * (E inliers / matches) * (scale inliers / depth-valid inliers)
    PnP, Procrustes:    score = inliers * (inliers / matches with valid depth)

So a solution that many matches support *and* that a large fraction of them agree with ranks first.
On realmini-dev (SIFT, sensor depth, all 84 queries with depth) it raises ``AUC @ VCRE < 90px`` from
0.796 to 0.830 (Ess.Mat, OpenCV), 0.845 to 0.870 (Ess.Mat, poselib) and 0.869 to 0.891 (PnP, poselib).
Both numbers are stored in ``Estimate.extras`` (``confidence_inliers``, ``confidence_score``) so one run
can be scored with either.
"""

from __future__ import annotations

import math
from typing import Literal, get_args

__all__ = ["ConfidenceMode", "CONFIDENCE_MODES", "combined_score", "confidences", "choose"]

#: Which confidence a solver reports: ``inliers`` (the paper's) or ``score`` (``combined_score``).
ConfidenceMode = Literal["inliers", "score"]
CONFIDENCE_MODES: tuple[ConfidenceMode, ...] = get_args(ConfidenceMode)


def combined_score(inliers: int, *ratios: float) -> float:
    """Our ranking confidence: the inlier count times the agreement ratios of the robust steps.

    Args:
        inliers: Inlier count.
        *ratios: Agreement ratios, each clipped to [0, 1].

    Returns:
        ``inliers * prod(ratios)``; 0 for a non-finite ratio.
    """
    score = float(max(int(inliers), 0))
    for r in ratios:
        r = float(r)
        if not math.isfinite(r):
            return 0.0
        score *= min(max(r, 0.0), 1.0)
    return score


def confidences(inliers: int, *ratios: float) -> dict[str, float]:
    """Both confidences of an estimate, keyed as they are stored in ``Estimate.extras``.

    Args:
        inliers: Inlier count.
        *ratios: Agreement ratios in [0, 1].

    Returns:
        ``{"confidence_inliers": …, "confidence_score": …}``.
    """
    return {"confidence_inliers": float(max(int(inliers), 0)), "confidence_score": combined_score(inliers, *ratios)}


def choose(mode: str, values: dict[str, float]) -> float:
    """The confidence named by ``mode``.

    Args:
        mode: ``inliers`` (the paper's) or ``score`` (ours).
        values: What ``confidences`` returns.

    Returns:
        That confidence.

    Raises:
        ValueError: An unknown mode.
    """
    if mode not in CONFIDENCE_MODES:
        raise ValueError(f"confidence must be one of {CONFIDENCE_MODES}, got {mode!r}")
    return values[f"confidence_{mode}"]
