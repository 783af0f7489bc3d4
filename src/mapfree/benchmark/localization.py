"""Visual localisation scores (7-Scenes, paper Fig. 4b): world poses of query frames against ground truth.

Built from per-frame arrays into the same ``Report`` as the Map-free benchmark (so ``format_table``,
``save_plots`` and ``to_json`` apply), with thresholds relative to the image: VCRE < 10 % (and 5 %) of the
diagonal, and the usual 7-Scenes pose thresholds. ``comparison_figures`` overlays several runs (K = 1 vs
K = 10 references): precision against the ratio of confident estimates at VCRE < 10 %, and the VCRE CDF.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .metrics import Thresholds, precision_ratio_curve
from .report import Report
from .score import errors
from .scores import aggregate, aggregate_scenes, scene_medians

__all__ = ["localization_thresholds", "localization_report", "comparison_figures", "save_comparison"]


def localization_thresholds(width: int, height: int) -> Thresholds:
    """(5 cm, 5°) and (25 cm, 5°) pose thresholds; VCRE at 10 % and 5 % of the image diagonal."""
    diag = float(np.hypot(width, height))
    return Thresholds(pose=((0.05, 5), (0.25, 5)), vcre=(round(0.1 * diag, 1), round(0.05 * diag, 1)))


def localization_report(
    scene: Sequence[str],
    frame: Sequence[str],
    q_gt: np.ndarray,
    t_gt: np.ndarray,
    q_est: np.ndarray,
    t_est: np.ndarray,
    confidence: np.ndarray,
    K: np.ndarray,
    width: np.ndarray,
    height: np.ndarray,
    thresholds: Thresholds | None = None,
    split: str = "test",
) -> Report:
    """Scores of N query frames (world-to-camera ``q``/``t``; NaN rows of ``q_est`` = no estimate).

    ``K`` (N,4) fx fy cx cy; frames must be grouped by ``scene`` (contiguous) for the per-scene medians.
    """
    scenes = np.asarray(scene, dtype=str)
    n = len(scenes)
    q_gt, t_gt = np.asarray(q_gt, float).reshape(n, 4), np.asarray(t_gt, float).reshape(n, 3)
    q_est, t_est = np.asarray(q_est, float).reshape(n, 4), np.asarray(t_est, float).reshape(n, 3)
    conf = np.asarray(confidence, float).reshape(n)
    W, H = np.asarray(width, float).reshape(n), np.asarray(height, float).reshape(n)
    starts = np.flatnonzero(np.r_[True, scenes[1:] != scenes[:-1]]) if n else np.zeros(0, np.int64)
    names = scenes[starts]
    if len(set(names.tolist())) != len(names):
        raise ValueError("the frames of each scene must be contiguous")
    bounds = np.append(starts, n).astype(np.int64)
    estimated = np.all(np.isfinite(q_est), axis=1) & np.all(np.isfinite(t_est), axis=1) & np.isfinite(conf)
    estimated &= np.linalg.norm(np.nan_to_num(q_est), axis=1) > 0
    th = thresholds or localization_thresholds(int(np.median(W)) if n else 640, int(np.median(H)) if n else 480)
    te, re, ve = errors(q_gt, t_gt, q_est, t_est, np.asarray(K, np.float32), W, H, estimated)
    medians = np.stack([scene_medians(x, bounds, estimated) for x in (te, re, ve)], axis=1)
    metrics = aggregate(bounds, te, re, ve, conf, estimated, 0, th, medians)
    per_scene = dict(
        zip(
            names.tolist(),
            aggregate_scenes(bounds, te, re, ve, conf, estimated, np.zeros(len(names), np.int64), th, medians),
        )
    )
    return Report(
        metrics=metrics,
        per_scene=per_scene,
        scene=scenes,
        frame=np.asarray(frame, dtype=str),
        trans_err=te,
        rot_err=re,
        vcre=ve,
        confidence=np.where(estimated, conf, np.nan),
        estimated=estimated,
        diagonal=np.hypot(W, H),
        split=split,
        thresholds=th,
    )


def comparison_figures(reports: Mapping[str, Report]) -> dict:
    """Two figures over several runs: precision vs ratio at VCRE < 10 % of the diagonal, and the VCRE CDF."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figs = {}
    for key in ("precision_ratio", "vcre_cdf"):
        fig = Figure(figsize=(5.5, 4.2), dpi=120, layout="constrained")
        FigureCanvasAgg(fig)
        figs[key] = fig
    ax_p, ax_c = figs["precision_ratio"].add_subplot(), figs["vcre_cdf"].add_subplot()
    xmax = 0.0
    for label, r in reports.items():
        est = r.estimated
        px = r.thresholds.vcre[0]
        ratio, prec = precision_ratio_curve(r.confidence[est], r.vcre[est] < px, int((~est).sum()))
        if len(ratio):
            area = float(np.sum(np.diff(np.r_[np.float32(0), ratio]) * prec))
            ax_p.step(np.r_[0.0, ratio], np.r_[prec[0], prec], where="pre", label=f"{label} (AUC {area:.3f})")
        else:
            ax_p.plot([], [], label=f"{label} (no estimates)")
        v = np.sort(r.vcre[est])
        total = len(est)
        if len(v) and total:
            ax_c.step(np.r_[0.0, v], np.r_[0.0, np.arange(1, len(v) + 1) / total], where="post", label=label)
        diag = float(np.median(r.diagonal)) if len(r.diagonal) else 800.0
        xmax = max(xmax, 0.3 * diag)
    some = next(iter(reports.values()), None)
    if some is not None and len(some.diagonal):
        diag = float(np.median(some.diagonal))
        for frac, style in ((0.05, "--"), (0.10, "-")):
            ax_c.axvline(
                frac * diag, color="0.3", ls=style, lw=1, label=f"{frac:.0%} of diagonal ({frac * diag:.0f} px)"
            )
    ax_p.set(
        xlim=(0, 1),
        ylim=(0, 1.02),
        xlabel="ratio of confident estimates (frames kept / all frames)",
        ylabel="precision (VCRE < 10 % of diagonal)",
        title="Precision as the confidence threshold is lowered",
    )
    ax_c.set(
        xlim=(0, xmax or 1),
        ylim=(0, 1),
        xlabel="VCRE (px)",
        ylabel="fraction of query frames",
        title="Cumulative distribution of VCRE",
    )
    ax_p.grid(alpha=0.3)
    ax_p.legend(loc="lower left", fontsize=8)
    ax_c.grid(alpha=0.3)
    ax_c.legend(loc="lower right", fontsize=8)
    return figs


def save_comparison(reports: Mapping[str, Report], outdir: os.PathLike | str, formats=("png", "pdf")) -> list[Path]:
    """``comparison_figures`` as ``outdir/compare_{precision_ratio,vcre_cdf}.{png,pdf}``."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, fig in comparison_figures(reports).items():
        for fmt in formats:
            p = outdir / f"compare_{name}.{fmt}"
            fig.savefig(p)
            paths.append(p)
    return paths
