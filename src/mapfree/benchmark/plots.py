"""The paper's evaluation figures for a ``Report`` (matplotlib, Agg canvas, PNG and PDF).

- ``precision_ratio``: precision against the ratio of confident estimates kept, for the pose and VCRE
  thresholds (the area under each curve is its AUC);
- ``vcre_cdf``: cumulative distribution of VCRE over every evaluated frame, with lines at 1, 5 and 10 %
  of the image diagonal;
- ``scenes``: per scene, median rotation vs median translation error, coloured by VCRE precision.
No pyplot: figures draw on their own Agg canvas, so nothing global changes.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import LogFormatter

from .metrics import precision_ratio_curve
from .report import Report

__all__ = [
    "FIGURES",
    "figures_of",
    "reliability_figure",
    "save_plots",
    "precision_ratio_figure",
    "vcre_cdf_figure",
    "scene_scatter_figure",
]


class _PlainLogFormatter(LogFormatter):
    """Log-axis labels as plain numbers (0.3, 20); matplotlib picks which minor ticks to label from the span:
    all of them under half a decade, a subset under two, none beyond, so a narrow axis is never left bare."""

    _sublabels: set[float] | None  # matplotlib's own, set by LogFormatter.set_locs

    def _num_to_string(self, x, vmin, vmax):
        return f"{x:g}"

    def set_locs(self, locs=None):
        # Over more than a decade matplotlib labels 2, 3, 4 and 6 of each: 0.3 and 0.4 then overlap on a
        # figure-sized axis. 2 and 5 keep every decade labelled without touching.
        super().set_locs(locs)
        if self.axis is None:  # matplotlib sets the axis before it asks for labels
            return
        lo, hi = sorted(self.axis.get_view_interval())
        if self._sublabels is not None and len(self._sublabels) > 3 and lo > 0 and np.log10(hi / lo) > 1:
            self._sublabels = {1, 2, 5}


def _figure(size=(5.5, 4.2)) -> Figure:
    fig = Figure(figsize=size, dpi=120, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _failures(report: Report) -> int:
    return int((~report.estimated).sum() + report.extra_failures)


def precision_ratio_figure(report: Report) -> Figure:
    """Precision vs ratio of confident estimates for each pose and VCRE threshold."""
    fig = _figure()
    ax = fig.add_subplot()
    est = report.estimated
    conf = report.confidence[est]
    th = report.thresholds
    curves = [(f"VCRE < {px:g} px", report.vcre[est] < px) for px in th.vcre]
    curves += [
        (f"pose < {tm * 100:g} cm, {rd:g}°", (report.trans_err[est] < tm) & (report.rot_err[est] < rd))
        for tm, rd in th.pose
    ]
    colors = {"VCRE": "tab:blue", "pose": "tab:orange"}
    seen: set[str] = set()
    for label, ok in curves:
        kind = label.split()[0]
        style = "-" if kind not in seen else "--"
        seen.add(kind)
        ratio, prec = precision_ratio_curve(conf, ok, _failures(report))
        if len(ratio) == 0:
            ax.plot([], [], style, color=colors[kind], label=f"{label} (no estimates)")
            continue
        area = float(np.sum(np.diff(np.r_[np.float32(0), ratio]) * prec))
        ax.step(
            np.r_[0.0, ratio],
            np.r_[prec[0], prec],
            where="pre",
            ls=style,
            color=colors[kind],
            label=f"{label}  (AUC {area:.3f})",
        )
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("ratio of confident estimates (frames kept / all frames)")
    ax.set_ylabel("precision")
    ax.set_title("Precision as the confidence threshold is lowered")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    return fig


def vcre_cdf_figure(report: Report) -> Figure:
    """Fraction of all evaluated frames (failures included) with VCRE below each value."""
    fig = _figure()
    ax = fig.add_subplot()
    total = len(report.estimated) + report.extra_failures
    v = np.sort(report.vcre[report.estimated])
    diag = float(np.median(report.diagonal)) if len(report.diagonal) else 900.0
    xmax = max(1.5 * 0.1 * diag, float(np.percentile(v, 90)) if len(v) else 0.0)
    if len(v) and total:
        ax.step(
            np.r_[0.0, v], np.r_[0.0, np.arange(1, len(v) + 1) / total], where="post", color="tab:blue", label="VCRE"
        )
    for frac, style in ((0.01, ":"), (0.05, "--"), (0.10, "-")):
        ax.axvline(frac * diag, color="0.3", ls=style, lw=1, label=f"{frac:.0%} of diagonal ({frac * diag:.0f} px)")
    if abs(report.thresholds.vcre[0] - 0.1 * diag) > 0.5:  # images other than 540x720
        ax.axvline(
            report.thresholds.vcre[0],
            color="tab:red",
            lw=1,
            alpha=0.6,
            label=f"benchmark threshold ({report.thresholds.vcre[0]:g} px)",
        )
    ax.set_xlim(0, xmax)
    ax.set_ylim(0, 1.0)
    ax.set_xlabel("VCRE (px)")
    ax.set_ylabel("fraction of evaluated frames")
    ax.set_title("Cumulative distribution of VCRE")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    return fig


def scene_scatter_figure(report: Report) -> Figure:
    """Per scene: median rotation vs median translation error, coloured by VCRE precision."""
    fig = _figure((5.8, 4.4))
    ax = fig.add_subplot()
    rows = [
        (m.median_rot, m.median_trans, (m.vcre[0].precision if m.vcre else None) or 0.0)
        for m in report.per_scene.values()
        if m.median_rot is not None
    ]
    if rows:
        r, t, p = (np.array(c, dtype=float) for c in zip(*rows))
        sc = ax.scatter(
            np.maximum(r, 1e-2),
            np.maximum(t, 1e-3),
            c=p,
            cmap="viridis",
            vmin=0,
            vmax=1,
            s=28,
            edgecolors="k",
            linewidths=0.4,
        )
        fig.colorbar(sc, ax=ax, label=f"precision (VCRE < {report.thresholds.vcre[0]:g} px)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_major_formatter(_PlainLogFormatter(labelOnlyBase=False))
            axis.set_minor_formatter(_PlainLogFormatter(labelOnlyBase=False, minor_thresholds=(2, 0.5)))
    else:
        ax.text(0.5, 0.5, "no estimates", ha="center", va="center", transform=ax.transAxes)
    tm, rd = report.thresholds.pose[0]
    ax.axvline(rd, color="0.4", ls="--", lw=1)
    ax.axhline(tm, color="0.4", ls="--", lw=1)
    ax.set_xlabel("median rotation error (°)")
    ax.set_ylabel("median translation error (m)")
    missing = [s for s, m in report.per_scene.items() if m.median_rot is None]
    if missing:  # a scene without a single estimate has no point: say so instead of dropping it silently
        names = ", ".join(missing[:4]) + (f" and {len(missing) - 4} more" if len(missing) > 4 else "")
        ax.text(
            0.99,
            0.01,
            f"no estimates: {names}",
            ha="right",
            va="bottom",
            fontsize=8,
            color="tab:red",
            transform=ax.transAxes,
        )
    ax.set_title(f"Per-scene median errors ({len(rows)} of {len(report.per_scene)} scenes)")
    ax.grid(alpha=0.3, which="both")
    return fig


def reliability_figure(report: Report) -> Figure:
    """Reliability diagram: per probability bin, the fraction of frames right against the mean probability
    (on the diagonal for perfectly calibrated probabilities), with each bin's frame count.

    Raises:
        ValueError: The confidences are not probabilities (``Report.calibration`` is None).
    """
    cal = report.calibration()
    if cal is None:
        raise ValueError("the confidences are not probabilities: no reliability diagram")
    return reliability_diagram({"submission": cal}, f"VCRE < {report.thresholds.vcre[0]:g} px")


def reliability_diagram(curves: dict, what: str) -> Figure:
    """Reliability diagram of one or more sets of probabilities.

    Args:
        curves: ``{label: Reliability}``.
        what: What the probabilities are of (axis label).

    Returns:
        The figure.
    """
    fig = _figure()
    ax = fig.add_subplot()
    ax.plot([0, 1], [0, 1], color="0.5", lw=1, ls=":", label="perfect calibration")
    for label, cal in curves.items():
        filled = cal.bin_count > 0
        ax.plot(
            cal.bin_p[filled],
            cal.bin_right[filled],
            "o-",
            label=f"{label}: ECE {cal.ece:.3f}, Brier {cal.brier:.3f} ({cal.frames} frames)",
        )
        for x, y, c in zip(cal.bin_p[filled], cal.bin_right[filled], cal.bin_count[filled]):
            ax.annotate(str(int(c)), (x, y), textcoords="offset points", xytext=(4, -10), fontsize=7)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("predicted probability (bin mean)")
    ax.set_ylabel(f"fraction of frames with {what}")
    ax.set_title("Reliability diagram (numbers: frames per bin)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return fig


#: The evaluation figures: (file stem, caption, maker), for ``save_plots`` and the HTML report.
FIGURES = (
    ("precision_ratio", "precision against ratio", precision_ratio_figure),
    ("vcre_cdf", "VCRE distribution", vcre_cdf_figure),
    ("scenes", "per-scene errors", scene_scatter_figure),
)
_RELIABILITY = ("reliability", "reliability diagram", reliability_figure)


def figures_of(report: Report) -> tuple:
    """The figures a report has: ``FIGURES``, and the reliability diagram when its confidences are probabilities.

    Args:
        report: The report.

    Returns:
        ``(file stem, caption, maker)`` tuples.
    """
    return (*FIGURES, _RELIABILITY) if report.calibration() is not None else FIGURES


def save_plots(report: Report, outdir: os.PathLike | str, formats: Sequence[str] = ("png", "pdf")) -> list[Path]:
    """``mapfree.benchmark.save_plots``: each of ``FIGURES`` as ``outdir/NAME.FORMAT``, the files returned."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, _, make in figures_of(report):
        fig = make(report)
        for fmt in formats:
            p = outdir / f"{name}.{fmt}"
            fig.savefig(p)
            paths.append(p)
    return paths
