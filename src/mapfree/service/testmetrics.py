"""What a ``test`` result may say without revealing the private ground truth.

Submitting one frame at the identity pose used to return that frame's true distance from the reference to 12
digits (``Average Median Translation Error``), and its rotation angle: a few such probes place a frame. A
median over the estimated frames of a scene is exactly one frame's error when one frame is estimated, and
close to one when few are. So for ``test``:

* the median errors are withheld (``None``, with a note) unless at least ``MIN_SCENE_COVERAGE`` of the frames
  of every scene are estimated: a median then sits among at least half of a scene's frames, the spread of a
  scene, not a frame; a real method estimates (nearly) every frame, and leaderboards need nothing else;
* every number is rounded to what a leaderboard shows (``DECIMALS``): 1 cm, 0.1°, 0.1 px, 0.001 of a
  precision or AUC. The one bit a single-frame probe still gets from a precision (under a threshold or not)
  is bounded by the daily test limit.
"""

from __future__ import annotations

from typing import Any

#: Fraction of a scene's frames that must be estimated for the median errors to be published (test only).
MIN_SCENE_COVERAGE = 0.5
MEDIAN_KEYS = ("Average Median Translation Error", "Average Median Rotation Error",
               "Average Median Reprojection Error")
#: Decimals kept per metric (metres, degrees, pixels); every other metric (fractions, AUCs): ``DEFAULT_DECIMALS``.
DECIMALS = dict(zip(MEDIAN_KEYS, (2, 1, 1)))
DEFAULT_DECIMALS = 3


def coarsen(metrics: dict[str, Any]) -> dict[str, Any]:
    """Every number rounded to leaderboard precision (idempotent; ``None`` stays ``None``)."""
    return {k: round(float(v), DECIMALS.get(k, DEFAULT_DECIMALS)) if isinstance(v, (int, float))
            and not isinstance(v, bool) else v for k, v in metrics.items()}


def thin_scenes(per_scene: dict[str, dict]) -> list[str]:
    """Scenes where fewer than ``MIN_SCENE_COVERAGE`` of the frames are estimated."""
    return sorted(s for s, m in per_scene.items()
                  if (m or {}).get("Estimates for % of frames") is None
                  or m["Estimates for % of frames"] < MIN_SCENE_COVERAGE)


def public_test_metrics(metrics: dict[str, Any], per_scene: dict[str, dict]) -> tuple[dict[str, Any], list[str]]:
    """(the metrics a test result shows, notes for its owner): medians withheld below the coverage, then all
    rounded (``coarsen``)."""
    out, notes = dict(metrics), []
    thin = thin_scenes(per_scene)
    if thin:
        for k in MEDIAN_KEYS:
            out[k] = None
        notes.append(f"median errors withheld: fewer than {MIN_SCENE_COVERAGE:.0%} of the frames estimated in "
                     f"{len(thin)} of {len(per_scene)} test scene(s) (a median over so few frames would reveal the "
                     "private ground truth of single frames)")
    return coarsen(out), notes
