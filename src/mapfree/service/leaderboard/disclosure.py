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
* only counts of frames under fixed thresholds (precisions, and AUCs over the submitter's confidence ranking):
  for one frame, one evaluation answers "is the true pose within the threshold of the pose I sent?" (25 cm and
  5° for the pose metrics, 90 px VCRE). Finding a frame from such answers needs about (volume searched / volume
  of the threshold ball) evaluations: a 10 m cube against a 25 cm ball is ~64,000 of them, 35 years at 5 a day;
* every number is rounded to what a leaderboard shows (``DECIMALS``).

A real method is still ranked on what the benchmark ranks by (VCRE AUC and precision, pose AUC and precision);
val results keep every number.
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
    "made to equal one frame's private error; the leaderboard ranks test by VCRE and pose AUC and "
    "precision"
)


def coarsen(metrics: dict[str, Any]) -> dict[str, Any]:
    """Every number rounded to leaderboard precision (idempotent; ``None`` stays ``None``)."""
    return {
        k: round(float(v), DECIMALS.get(k, DEFAULT_DECIMALS))
        if isinstance(v, (int, float)) and not isinstance(v, bool)
        else v
        for k, v in metrics.items()
    }


def without_medians(metrics: dict[str, Any]) -> dict[str, Any]:
    """``metrics`` with every median error emptied (``None``) and every number rounded: what a test result shows,
    also for results stored before medians were withheld."""
    return coarsen({**metrics, **{k: None for k in MEDIAN_KEYS if k in metrics}})


def public_test_metrics(metrics: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """(the metrics a test result shows, notes for its owner): medians withheld, the rest rounded."""
    return without_medians({**{k: None for k in MEDIAN_KEYS}, **metrics}), [MEDIANS_NOTE]
