"""The result of an evaluation: headline metrics, per-scene metrics, per-frame errors and problems."""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field

import numpy as np

from .metrics import Thresholds
from .reliability import Reliability, is_probability, reliability
from .scores import METRIC_KEYS, Scores
from .submission import Problem

__all__ = ["Report", "format_table", "METRIC_KEYS", "NOT_PROBABILITIES"]

#: What a report says instead of calibration figures when the confidences are not probabilities.
NOT_PROBABILITIES = (
    "the confidences are not probabilities (some outside [0, 1]): no calibration figures; submit p_correct "
    "(mapfree run --confidence calibrated) to judge them as probabilities"
)


def _clean(v):
    """JSON-safe value: NaN/inf -> None, numpy scalars -> Python."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


@dataclass
class Report:
    """Scores of one submission; per-frame arrays cover every evaluated frame (NaN where no estimate).

    Attributes:
        metrics: The headline metrics; as a mapping, by the public evaluator's names (``METRIC_KEYS``).
        per_scene: The same metrics for each scene.
        scene: (M,) scene of each evaluated frame.
        frame: (M,) frame name.
        trans_err: (M,) translation error, metres.
        rot_err: (M,) rotation error, degrees.
        vcre: (M,) virtual correspondence reprojection error, pixels.
        confidence: (M,) submitted confidence.
        estimated: (M,) bool, whether the frame has a usable estimate.
        diagonal: (M,) image diagonal, pixels.
        problems: What was wrong with the submission, each naming its file and line.
        split: The split scored.
        compat: ``default``, or ``official`` (the public evaluator's behaviour, quirks included).
        track: ``single`` or ``multi``: the leaderboard whose frames were scored.
        thresholds: The thresholds of the precision and AUC metrics.
        extra_failures: Failures beyond the evaluated frames (``compat="official"``: missing scenes).
    """

    metrics: Scores
    per_scene: dict[str, Scores]
    scene: np.ndarray  # (M,) scene of each evaluated frame
    frame: np.ndarray  # (M,) frame name
    trans_err: np.ndarray  # (M,) metres
    rot_err: np.ndarray  # (M,) degrees
    vcre: np.ndarray  # (M,) pixels
    confidence: np.ndarray  # (M,)
    estimated: np.ndarray  # (M,) bool
    diagonal: np.ndarray  # (M,) image diagonal in pixels
    problems: list[Problem] = field(default_factory=list)
    split: str = "val"
    compat: str = "default"
    track: str = "single"  # leaderboard whose frames were scored: "single" or "multi" (the multi-frame track)
    thresholds: Thresholds = field(default_factory=Thresholds)
    extra_failures: int = 0  # failures beyond the evaluated frames (compat="official": missing scenes)

    def calibration(self) -> Reliability | None:
        """How well the confidences work as the probability that VCRE is under the benchmark's first threshold
        (90 px), on the frames with an estimate: ECE (10 bins), Brier score, precision at p >= 0.5, 0.8, 0.9.

        Returns:
            The figures, or None when the confidences are not probabilities (one outside [0, 1], or no estimate).
        """
        est = self.estimated
        if not est.any() or not is_probability(self.confidence[est]):
            return None
        return reliability(self.confidence[est], self.vcre[est] < self.thresholds.vcre[0])

    @property
    def fatal(self) -> bool:
        """Whether a problem made the submission unscorable (the public evaluator would abort)."""
        return any(p.fatal for p in self.problems)

    def to_dict(self, frames: bool = False) -> dict:
        """JSON-ready form: split, compat, track, metrics, per-scene metrics, problems (NaN becomes None).

        Args:
            frames: Add one entry per evaluated frame with its errors.

        Returns:
            The report as plain dicts and lists.
        """
        out = {
            "split": self.split,
            "compat": self.compat,
            "track": self.track,
            "metrics": {k: _clean(v) for k, v in self.metrics.items()},
            "per_scene": {s: {k: _clean(v) for k, v in m.items()} for s, m in self.per_scene.items()},
            "problems": [
                {"scene": p.scene, "line": p.line, "reason": p.reason, "fatal": p.fatal} for p in self.problems
            ],
        }
        cal = self.calibration()
        out["calibration"] = (
            {"probabilities": True, **cal.to_dict()}
            if cal is not None
            else {"probabilities": False, "note": NOT_PROBABILITIES}
        )
        if frames:
            out["frames"] = [
                {
                    "scene": str(s),
                    "frame": str(f),
                    "estimated": bool(e),
                    "trans_err": _clean(te),
                    "rot_err": _clean(re),
                    "vcre": _clean(v),
                    "confidence": _clean(c),
                }
                for s, f, e, te, re, v, c in zip(
                    self.scene, self.frame, self.estimated, self.trans_err, self.rot_err, self.vcre, self.confidence
                )
            ]
        return out

    def to_json(self, indent: int | None = 2, frames: bool = False) -> str:
        """The report as JSON text (``mapfree evaluate --json``).

        Args:
            indent: JSON indentation; None for one line.
            frames: Add one entry per evaluated frame with its errors.

        Returns:
            Strict JSON (no NaN).
        """
        return json.dumps(self.to_dict(frames), indent=indent, allow_nan=False)


def _fmt(key: str, v) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "—"
    if key.endswith("Translation Error"):
        return f"{v:.3f} m"
    if key.endswith("Rotation Error"):
        return f"{v:.2f}°"
    if key.endswith("Reprojection Error"):
        return f"{v:.1f} px"
    if key.startswith("Estimates"):
        return f"{100 * v:.1f} %"
    return f"{v:.4f}"


def format_table(report: Report, per_scene: bool = False, width: int = 100, max_problems: int = 50) -> str:
    """A readable text rendering (rich tables) of the metrics, for a terminal or a log.

    Args:
        report: The scores.
        per_scene: Add a table of the metrics of each scene.
        width: Characters per line.
        max_problems: Problems listed (``Report.problems`` and ``to_json`` hold them all).

    Returns:
        Plain text, no colour codes.
    """
    from rich.console import Console
    from rich.table import Table

    buf = io.StringIO()
    console = Console(file=buf, width=width, force_terminal=False, color_system=None)
    n = len(report.estimated)
    title = (
        f"Map-free benchmark — {report.split}, {len(report.per_scene)} scenes, "
        f"{n} evaluated frames, {int(report.estimated.sum())} estimated"
        + (f", {report.track}-frame track" if report.track != "single" else "")
    )
    console.print(title, markup=False, highlight=False)
    table = Table()
    table.add_column("metric")
    table.add_column("value", justify="right")
    for k, v in report.metrics.items():
        table.add_row(k, _fmt(k, v))
    console.print(table)
    if report.compat != "default":
        console.print(f"compatibility mode: {report.compat} (public evaluator's quirks reproduced)")
    if per_scene and report.per_scene:
        keys = [
            ("Estimates for % of frames", "est."),
            ("Average Median Translation Error", "med. t"),
            ("Average Median Rotation Error", "med. R"),
            ("Average Median Reprojection Error", "med. VCRE"),
            (METRIC_KEYS[3], "prec. pose"),
            (METRIC_KEYS[5], "prec. VCRE"),
            (METRIC_KEYS[6], "AUC VCRE"),
        ]
        st = Table(title="per scene", title_justify="left")
        st.add_column("scene")
        for _, label in keys:
            st.add_column(label, justify="right")
        for s, m in report.per_scene.items():
            st.add_row(s, *[_fmt(k, m.get(k)) for k, _ in keys])
        console.print(st)
    cal = report.calibration()
    if cal is None:
        console.print(f"calibration: {NOT_PROBABILITIES}", markup=False, highlight=False)
    else:
        console.print(format_calibration(cal, report.thresholds.vcre[0]), markup=False, highlight=False)
    if report.problems:
        console.print(f"{len(report.problems)} problem(s):")
        for p in report.problems[:max_problems]:
            console.print(f"  {'FATAL ' if p.fatal else ''}{p}", markup=False, highlight=False)
        if len(report.problems) > max_problems:
            console.print(f"  … {len(report.problems) - max_problems} more (see --json)")
    return buf.getvalue()


def format_calibration(cal: Reliability, px: float) -> str:
    """One paragraph of calibration figures (``mapfree evaluate``'s table, ``mapfree calibrate``).

    Args:
        cal: The figures.
        px: The VCRE threshold the probabilities are judged against.

    Returns:
        Text lines: ECE and Brier, then the precision of the frames accepted at each level.
    """
    lines = [
        f"calibration (confidence read as P(VCRE < {px:g} px), {cal.frames} estimated frames): "
        f"ECE {cal.ece:.3f}, Brier {cal.brier:.3f}"
    ]
    for level, prec in cal.precision.items():
        shown = "—" if prec is None else f"{100 * prec:.1f} %"
        lines.append(f"  accepted at p >= {level:g}: {cal.accepted[level]} frames, precision {shown}")
    return "\n".join(lines)
