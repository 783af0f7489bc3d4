"""The Map-free benchmark: exact scoring, submission ZIPs, reports and plots.

    from mapfree.benchmark import evaluate, format_table
    report = evaluate("submission.zip", "data/mapfree", split="val")
    print(format_table(report))

``benchmark`` depends only on ``geometry`` and ``data``.
"""

from .metrics import Thresholds, auc, precision_ratio_curve, rotation_error_deg, translation_error, vcre, virtual_points
from .report import METRIC_KEYS, Report, format_table
from .score import EvaluationError, aggregate, evaluate, score
from .submission import Problem, SceneEstimates, SubmissionLimits, from_estimates, read_submission, write_submission
from .truth import SceneTruth, load_scene_truth, load_truth

__all__ = [
    "evaluate",
    "score",
    "aggregate",
    "EvaluationError",
    "Report",
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


def save_plots(report, outdir, formats=("png", "pdf")):
    """Write the paper-style figures of a report (see ``mapfree.benchmark.plots``); imports matplotlib lazily."""
    from .plots import save_plots as _save

    return _save(report, outdir, formats)
