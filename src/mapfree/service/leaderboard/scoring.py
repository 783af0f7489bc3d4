"""The one place the service calls the benchmark core: score a stored ZIP, redact what ``test`` must hide,
render plots. Workers call ``score`` (uploads get only the cheap checks of ``zipcheck.check_submission_zip``)."""

from __future__ import annotations

import dataclasses
import math
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeGuard

import numpy as np

from ..config import Settings
from .disclosure import public_test_metrics

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

    from ...benchmark import Report

#: The benchmark's aggregate keys; for ``test`` nothing else leaves the server.
METRIC_KEYS = (
    "AUC @ VCRE < 90px",
    "Precision @ VCRE < 90px",
    "AUC @ Pose Error < (25.0cm, 5deg)",
    "Precision @ Pose Error < (25.0cm, 5deg)",
    "Average Median Translation Error",
    "Average Median Rotation Error",
    "Average Median Reprojection Error",
    "Estimates for % of frames",
)
#: Short names for URLs and table headers, in the leaderboard's column order (VCRE AUC first).
SHORT = {
    "vcre_auc": METRIC_KEYS[0],
    "vcre_prec": METRIC_KEYS[1],
    "pose_auc": METRIC_KEYS[2],
    "pose_prec": METRIC_KEYS[3],
    "med_trans": METRIC_KEYS[4],
    "med_rot": METRIC_KEYS[5],
    "med_vcre": METRIC_KEYS[6],
    "estimates": METRIC_KEYS[7],
}
#: Errors sort ascending, everything else descending.
LOWER_IS_BETTER = {"med_trans", "med_rot", "med_vcre"}
MAX_PROBLEMS = 50


class SubmissionRejected(ValueError):
    """The benchmark cannot score this submission at all (message names the problem)."""


def _finite(x: Any) -> Any:
    """JSON-safe copy: NaN/inf become None (PostgreSQL's JSON refuses NaN)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {str(k): _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if hasattr(x, "item") and getattr(x, "shape", None) == ():
        return _finite(x.item())
    return x


def _problems(report: Report) -> list[str]:
    return [str(p)[:500] for p in list(report.problems)[:MAX_PROBLEMS]]


def redact(report_dict: dict, problems: list[str], split: str) -> dict:
    """What may be stored and shown. For ``test`` only the aggregate metrics, coarsened (``disclosure.py``),
    and submission-format problems: no per-scene or per-frame numbers, so that responses do not reveal the
    private ground truth. The calibration figures of probabilities (ECE, Brier, reliability bins) are val-only
    too: their bins and precision per threshold would hand back per-frame pass/fail."""
    raw = report_dict.get("metrics", {}) or {}
    metrics = _finite({**{k: raw.get(k) for k in METRIC_KEYS}, **{str(k): v for k, v in raw.items()}})
    per_scene = _finite(report_dict.get("per_scene") or {})
    if split == "test":  # no medians, rounded (the threat model: disclosure.py)
        metrics, notes = public_test_metrics(metrics)
        return {"metrics": metrics, "problems": notes + problems}
    out = {"metrics": metrics, "problems": problems, "per_scene": per_scene}
    if report_dict.get("calibration"):
        out["calibration"] = _finite(report_dict["calibration"])
    return out


_TRUTH: dict[tuple, Any] = {}


def _truth(settings: Settings, split: str):
    """Ground truth of a split, loaded once per worker process (the dataset does not change under a server)."""
    from ...benchmark import load_truth

    gt_root = settings.gt_root if split == "test" else None
    key = (str(settings.data_root), str(gt_root), split)
    if key not in _TRUTH:
        _TRUTH[key] = load_truth(settings.data_root, split, gt_root)
    return _TRUTH[key]


def score(settings: Settings, split: str, zip_path: Path) -> tuple[dict, bytes | None]:
    """Evaluate one submission -> (redacted result, packed per-frame report for plots; None for ``test``)."""
    from ... import benchmark

    if settings.data_root is None:
        raise SubmissionRejected("the server has no dataset configured (--data)")
    if split == "test" and settings.gt_root is None:
        raise SubmissionRejected("the server has no private test ground truth configured (--gt)")
    lim = settings.limits  # the upload check's limits, enforced on what the entries really unpack to
    limits = benchmark.SubmissionLimits(
        max_zip_bytes=lim.max_submission_bytes,
        max_entries=lim.max_zip_entries,
        max_file_bytes=lim.max_zip_entry_bytes,
        max_total_bytes=lim.max_zip_uncompressed_bytes,
    )
    try:
        report = benchmark.evaluate(zip_path, settings.data_root, split, truth=_truth(settings, split), limits=limits)
    except (ValueError, OSError, KeyError, benchmark.EvaluationError) as e:
        raise SubmissionRejected(str(e).replace(str(zip_path), "submission.zip")) from None
    fatal = [p for p in report.problems if p.fatal]
    if fatal:
        raise SubmissionRejected(str(fatal[0]))
    if report.problems and not np.any(report.estimated):
        raise SubmissionRejected(
            "no valid pose line; expected 'seq1/frame_00000.jpg qw qx qy qz tx ty tz "
            f"confidence' (first problem: {report.problems[0]})"
        )
    result = redact(report.to_dict(), _problems(report), split)
    # Per-frame data would leak test ground truth: kept (for plots) only for public-GT splits.
    return result, (None if split == "test" else pack_report(report))


#: The figures of ``benchmark.plots.save_plots`` (rendered on first view, by the API process).
PLOT_NAMES = ("precision_ratio", "vcre_cdf", "scenes")


def _record(v: object) -> TypeGuard[DataclassInstance]:
    """Whether ``v`` is a dataclass instance (``dataclasses.is_dataclass`` is true of the classes too)."""
    return dataclasses.is_dataclass(v) and not isinstance(v, type)


def pack_report(report: Any) -> bytes:
    """A report as bytes without pickle: arrays in an .npz, everything else as JSON inside it."""
    import io
    import json

    import numpy as np

    # Any: numpy's stub matches a ``**`` mapping against savez's own keyword (allow_pickle: bool) too
    arrays: dict[str, Any] = {}
    rest: dict[str, Any] = {}
    for f in dataclasses.fields(report):
        v = getattr(report, f.name)
        if f.name == "metrics":  # the scores are stored by the public evaluator's names
            rest[f.name] = v.to_dict()
        elif f.name == "per_scene":
            rest[f.name] = {s: m.to_dict() for s, m in v.items()}
        elif isinstance(v, np.ndarray):
            arrays[f.name] = v.astype(str) if v.dtype == object else v
        elif _record(v):
            rest[f.name] = dataclasses.asdict(v)
        elif isinstance(v, list):
            rest[f.name] = [dataclasses.asdict(x) if _record(x) else x for x in v]
        else:
            rest[f.name] = v
    buf = io.BytesIO()
    np.savez_compressed(buf, __json__=np.frombuffer(json.dumps(_finite(rest)).encode(), np.uint8), **arrays)
    return buf.getvalue()


def _tuples(v: Any) -> Any:
    return tuple(_tuples(x) for x in v) if isinstance(v, list) else v


def unpack_report(data: bytes) -> Any:
    import io
    import json

    import numpy as np

    from ...benchmark import Problem, Report, Scores, Thresholds

    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        fields = {k: z[k] for k in z.files if k != "__json__"}
        rest = json.loads(z["__json__"].tobytes().decode())
    rest["problems"] = [Problem(**p) for p in rest.get("problems", [])]
    if "thresholds" in rest:
        rest["thresholds"] = Thresholds(**{k: _tuples(v) for k, v in rest["thresholds"].items()})
    rest["metrics"] = Scores.from_dict(rest.get("metrics", {}))
    rest["per_scene"] = {s: Scores.from_dict(m) for s, m in rest.get("per_scene", {}).items()}
    return Report(**fields, **rest)


def render_plots(report: Any) -> dict[str, bytes]:
    """The benchmark's figures as PNG bytes."""
    from ... import benchmark

    with tempfile.TemporaryDirectory(prefix="mapfree-plots-") as d:
        benchmark.save_plots(report, d, formats=("png",))
        return {p.stem[:64]: p.read_bytes() for p in sorted(Path(d).rglob("*.png"))[:12]}


def known_scenes(settings: Settings, split: str) -> set[str] | None:
    """Scene names of a split on this server (None when no dataset is configured)."""
    if settings.data_root is None or not (settings.data_root / split).is_dir():
        return None
    return {p.name for p in (settings.data_root / split).iterdir() if p.is_dir()}


def missing_ground_truth(settings: Settings) -> list[str]:
    """Test scenes of the dataset whose private ground truth (``gt_root/test/sNNNNN/poses.txt``) is missing: a
    submission for them could never be scored, so a server with any is refused at start."""
    scenes = known_scenes(settings, "test")
    if settings.gt_root is None or not scenes:
        return []
    return sorted(s for s in scenes if not (settings.gt_root / "test" / s / "poses.txt").is_file())


def check_ground_truth(settings: Settings) -> None:
    """``ValueError`` naming the test scenes without ground truth under ``gt_root`` (see ``missing_ground_truth``)."""
    missing = missing_ground_truth(settings)
    if missing:
        shown = ", ".join(missing[:20]) + (f" and {len(missing) - 20} more" if len(missing) > 20 else "")
        raise ValueError(
            f"the ground-truth folder {settings.gt_root} lacks {len(missing)} of the dataset's test "
            f"scenes ({shown}): expected {settings.gt_root}/test/SCENE/poses.txt for each"
        )
