"""The Map-free benchmark: exact scoring, submission ZIPs, reports and plots.

    from mapfree.benchmark import evaluate, format_table
    report = evaluate("submission.zip", "data/mapfree", split="val")
    print(format_table(report))

``benchmark`` depends only on ``geometry`` and ``data``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from .metrics import Thresholds, auc, precision_ratio_curve, rotation_error_deg, translation_error, vcre, virtual_points
from .report import METRIC_KEYS, Report, format_table
from .score import EvaluationError, aggregate, evaluate, score
from .scores import Acceptance, Scores
from .submission import Problem, SceneEstimates, SubmissionLimits, from_estimates, read_submission
from .truth import SceneTruth, load_scene_truth, load_truth
from .writing import write_submission

__all__ = [
    "evaluate",
    "score",
    "aggregate",
    "EvaluationError",
    "Report",
    "Scores",
    "Acceptance",
    "format_table",
    "METRIC_KEYS",
    "Thresholds",
    "auc",
    "precision_ratio_curve",
    "rotation_error_deg",
    "translation_error",
    "vcre",
    "virtual_points",
    "Problem",
    "SceneEstimates",
    "SubmissionLimits",
    "from_estimates",
    "read_submission",
    "write_submission",
    "SceneTruth",
    "load_scene_truth",
    "load_truth",
    "save_plots",
]


def save_plots(report: Report, outdir: os.PathLike | str, formats: Sequence[str] = ("png", "pdf")) -> list[Path]:
    """Write the paper-style figures of a report; imports matplotlib only when called.

    Args:
        report: The scores.
        outdir: Folder of the figures, created when missing.
        formats: File formats matplotlib writes, e.g. ``png``, ``pdf``.

    Returns:
        The files written, ``outdir/{precision_ratio,vcre_cdf,scenes}.FORMAT``.
    """
    from .plots import save_plots as _save

    return _save(report, outdir, formats)
