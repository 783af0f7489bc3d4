"""What a ``test`` result may say without revealing the private ground truth: the threat model, and the code that
holds it.

**Threat model.** An account may submit any pose for any frame, in any combination, and read what the server
publishes; it gets ``Settings.test_daily_limit`` test evaluations per 24 h (5 by default), which is the whole
budget of what it may learn about the test split. What one test evaluation may reveal:

* no per-scene or per-frame number, no plot (those stay with val, whose ground truth is public);
* no statistic that is a *continuous* function of one frame's error. Every median is one: the submitter chooses
  every estimate, so it can place all frames but one far above (1e5 m away) or far below (the identity pose)
  a probe, and the published median *is* the probe's private error, whatever the split's size or coverage.
  Three such evaluations (a probe 100 m along x, y and z) used to place one frame's camera centre to 6 mm,
  rounding to 1 cm or not. So test results publish **no median errors** (translation, rotation, reprojection):
  ``None``, with a note;
* no figure that depends on the submitter's ordering of its frames. Every AUC is one: it is the area under
  precision over the submitter's confidence ranking, so seven chosen frames with confidences 7..1 (the rest
  left out, or put 1e5 m away) give one (precision, AUC) pair per pass/fail pattern of the seven, even rounded
  to 0.001: exact pass/fail of each chosen frame under each threshold in one evaluation. So test results
  publish **no AUC** (``None``, with a note) and boards rank test by precision (``TEST_RANK_BY``);
* what remains are **counts** of the submitted frames under each fixed threshold (the precisions: count /
  frames of the split) and the fraction estimated (the submitter's own choice). They are symmetric in the
  frames: exchanging which frames pass, at the same count, changes nothing published. With E frames estimated
  one evaluation reveals at most log2(E + 1) bits per threshold (four thresholds: two nested pose pairs, two
  nested VCRE radii), and of any one frame only "is the true pose within the threshold of the pose I sent?".
  Finding a frame from such answers needs about (volume searched / volume of the threshold ball)
  evaluations: a 10 m cube against a 25 cm ball is ~64,000 of them, 35 years at 5 a day;
* every number is rounded to what a leaderboard shows (``DECIMALS``).

A real method is still ranked on a figure of the benchmark (VCRE precision, pose precision) on test; val results
keep every number, the AUCs and medians included.
"""

from __future__ import annotations

from typing import Any

MEDIAN_KEYS = ("Average Median Translation Error", "Average Median Rotation Error", "Average Median Reprojection Error")
#: Decimals kept per metric (metres, degrees, pixels); every other metric (fractions, AUCs): ``DEFAULT_DECIMALS``.
DECIMALS = dict(zip(MEDIAN_KEYS, (2, 1, 1)))
DEFAULT_DECIMALS = 3
#: The note a test result carries in its problems, saying why its medians are empty.
MEDIANS_NOTE = (
    "median errors are not published for test: a median over estimates the submitter chooses can be "
    "made to equal one frame's private error; the leaderboard ranks test by VCRE and pose precision"
)


#: The note a test result carries in its problems, saying why its AUCs are empty.
AUC_NOTE = (
    "AUCs are not published for test: an AUC over the submitter's confidence ranking of a few chosen frames "
    "says which of them passed; test results show counts of frames under each threshold (precisions), and "
    "test boards rank by them"
)
#: What a test board ranks by when asked for an AUC (withheld on test): the precision at the same threshold.
TEST_RANK_BY = {"vcre_auc": "vcre_prec", "pose_auc": "pose_prec"}


def withheld(key: str) -> bool:
    """Whether a metric is withheld from test results: every median, and every AUC (of any threshold)."""
    return key in MEDIAN_KEYS or key.startswith("AUC @")


def coarsen(metrics: dict[str, Any]) -> dict[str, Any]:
    """Every number rounded to leaderboard precision (idempotent; ``None`` stays ``None``)."""
    return {
        k: round(float(v), DECIMALS.get(k, DEFAULT_DECIMALS))
        if isinstance(v, (int, float)) and not isinstance(v, bool)
        else v
        for k, v in metrics.items()
    }


def without_withheld(metrics: dict[str, Any]) -> dict[str, Any]:
    """``metrics`` with every median error and every AUC emptied (``None``) and every number rounded: what a test
    result shows, also for results stored before medians and AUCs were withheld."""
    return coarsen({k: None if withheld(k) else v for k, v in metrics.items()})


def public_test_metrics(metrics: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """(the metrics a test result shows, notes for its owner): medians and AUCs withheld, the rest rounded."""
    return without_withheld({**{k: None for k in MEDIAN_KEYS}, **metrics}), [MEDIANS_NOTE, AUC_NOTE]
