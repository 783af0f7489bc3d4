"""Relative-pose scores of image pairs (ScanNet-1500, as in the paper's supplement and SuperGlue/LoFTR).

Per pair: rotation error (geodesic, °), translation *direction* error (° — the smaller of the angle and its
supplement, as the SuperGlue evaluation does for up-to-scale essential-matrix poses), pose error = the max of
the two, and, for metric estimates, the translation error in metres. AUC @ 5/10/20° is the area under the
cumulative pose-error curve up to each threshold, normalised by it; a pair without an estimate has an
infinite error.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field

import numpy as np

from ..geometry import rotation_angle_deg
from .report import _clean

__all__ = [
    "AUC_THRESHOLDS",
    "RelPoseReport",
    "pose_auc",
    "relpose_errors",
    "relpose_report",
    "format_relpose",
    "cumulative_error_figure",
]

AUC_THRESHOLDS = (5.0, 10.0, 20.0)


def relpose_errors(R_gt: np.ndarray, t_gt: np.ndarray, R_est: np.ndarray, t_est: np.ndarray) -> tuple[np.ndarray, ...]:
    """(rotation °, translation direction °, metric translation m) for stacked (N,3,3)/(N,3) poses."""
    r = rotation_angle_deg(R_gt, R_est)
    n_gt, n_est = np.linalg.norm(t_gt, axis=1), np.linalg.norm(t_est, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.einsum("ni,ni->n", t_gt, t_est) / (n_gt * n_est)
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    ang = np.where(np.isfinite(ang), np.minimum(ang, 180.0 - ang), np.inf)  # no direction: infinitely wrong
    return r, ang, np.linalg.norm(t_gt - t_est, axis=1)


def pose_auc(errors: np.ndarray, thresholds=AUC_THRESHOLDS) -> list[float]:
    """Area under recall(error) from 0 to each threshold, divided by it (trapezoids; inf = never recalled)."""
    e = np.sort(np.asarray(errors, dtype=np.float64))
    n = len(e)
    out = []
    for th in thresholds:
        if n == 0:
            out.append(float("nan"))
            continue
        k = int(np.searchsorted(e, th, side="left"))
        x = np.r_[0.0, e[:k], th]
        y = np.r_[0.0, np.arange(1, k + 1) / n, k / n]
        out.append(float(np.sum(np.diff(x) * (y[1:] + y[:-1]) / 2) / th))
    return out


@dataclass
class RelPoseReport:
    """Per-pair errors (inf where no estimate; metric error NaN where the estimate has no scale) and summary."""

    pairs: list[str]
    rot_err: np.ndarray
    trans_dir_err: np.ndarray
    trans_err_m: np.ndarray
    estimated: np.ndarray
    metric: np.ndarray
    metrics: dict[str, float | None] = field(default_factory=dict)

    @property
    def pose_err(self) -> np.ndarray:
        return np.maximum(self.rot_err, self.trans_dir_err)

    def to_dict(self, pairs: bool = False) -> dict:
        out: dict = {"metrics": {k: _clean(v) for k, v in self.metrics.items()}}
        if pairs:
            out["pairs"] = [
                {
                    "pair": p,
                    "estimated": bool(e),
                    "rot_err": _clean(r),
                    "trans_dir_err": _clean(t),
                    "trans_err_m": _clean(m),
                }
                for p, e, r, t, m in zip(self.pairs, self.estimated, self.rot_err, self.trans_dir_err, self.trans_err_m)
            ]
        return out

    def to_json(self, pairs: bool = False) -> str:
        return json.dumps(self.to_dict(pairs), indent=2, allow_nan=False)


def relpose_report(names, R_gt, t_gt, R_est, t_est, metric) -> RelPoseReport:
    """Scores of N pairs; rows of ``R_est`` with NaN are pairs without an estimate."""
    n = len(names)
    R_gt, t_gt = np.asarray(R_gt, float).reshape(n, 3, 3), np.asarray(t_gt, float).reshape(n, 3)
    R_est, t_est = np.asarray(R_est, float).reshape(n, 3, 3), np.asarray(t_est, float).reshape(n, 3)
    est = np.all(np.isfinite(R_est.reshape(n, 9)), axis=1) & np.all(np.isfinite(t_est), axis=1)
    metric = np.asarray(metric, bool).reshape(n) & est
    r, a, m = (np.full(n, np.inf) for _ in range(3))
    if est.any():
        r[est], a[est], m[est] = relpose_errors(R_gt[est], t_gt[est], R_est[est], t_est[est])
    m[~metric] = np.nan
    report = RelPoseReport(list(names), r, a, m, est, metric)
    pe = report.pose_err
    aucs = pose_auc(pe)
    ok = lambda x: x[np.isfinite(x)]  # noqa: E731
    med = lambda x: float(np.median(ok(x))) if ok(x).size else None  # noqa: E731
    report.metrics = {
        **{f"AUC @ {th:g}°": v for th, v in zip(AUC_THRESHOLDS, aucs)},
        "Median rotation error (°)": med(r),
        "Median translation direction error (°)": med(a),
        "Median translation error (m)": med(m),
        "Precision @ (25 cm, 5°)": float(np.mean((np.nan_to_num(m, nan=np.inf) < 0.25) & (r < 5))) if n else None,
        "Estimates for % of pairs": float(est.mean()) if n else None,
        "Metric estimates for % of pairs": float(metric.mean()) if n else None,
        "Pairs": float(n),
    }
    return report


def format_relpose(report: RelPoseReport, title: str = "Relative pose") -> str:
    """A rich table of the summary metrics."""
    from rich.console import Console
    from rich.table import Table

    buf = io.StringIO()
    console = Console(file=buf, width=100, color_system=None)
    t = Table(title=title)
    t.add_column("metric")
    t.add_column("value", justify="right")
    for k, v in report.metrics.items():
        t.add_row(k, "—" if v is None or not math.isfinite(v) else (f"{v:.0f}" if k == "Pairs" else f"{v:.4f}"))
    console.print(t)
    return buf.getvalue()


def cumulative_error_figure(report: RelPoseReport):
    """Fraction of pairs with pose error (max of rotation and direction errors) below each value."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5, 4.2), dpi=120, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    e = np.sort(report.pose_err[np.isfinite(report.pose_err)])
    n = len(report.pairs)
    if len(e) and n:
        ax.step(np.r_[0.0, e], np.r_[0.0, np.arange(1, len(e) + 1) / n], where="post", label="pose error")
    for th in AUC_THRESHOLDS:
        ax.axvline(th, color="0.4", ls="--", lw=1)
    ax.set(
        xlim=(0, 2 * AUC_THRESHOLDS[-1]),
        ylim=(0, 1),
        xlabel="pose error: max(rotation, translation direction) (°)",
        ylabel="fraction of pairs",
        title="Cumulative pose error",
    )
    ax.grid(alpha=0.3)
    return fig
