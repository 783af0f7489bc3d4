"""Held-out evaluation of a trained RPR model against the mean-training-pose baseline, and loss-curve plots."""

from __future__ import annotations

import csv
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..data import Dataset
from .config import DataConfig
from .data import PairDataset, resolve_size, sample_pairs, val_pairs
from .metrics import pose_errors, summarize, vcre_px

__all__ = ["mean_training_pose", "evaluate_pairs", "plot_curves"]


def mean_training_pose(
    root: os.PathLike | str, cfg: DataConfig | None = None, epochs: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """The average relative pose of the training pairs: chordal mean rotation (SVD projection) and mean t."""
    cfg = cfg or DataConfig()
    scenes = Dataset(root).scenes("train")
    Rs, ts = [], []
    for e in range(epochs):
        for p in sample_pairs(
            scenes, cfg.pairs_per_scene, np.random.default_rng([cfg.seed, e]), cfg.min_overlap, cfg.max_overlap
        ):
            s = PairDataset([p], (1, 1)).scene(p.scene)
            pose0, pose1 = s.frame(p.name0).pose, s.frame(p.name1).pose
            if pose0 is None or pose1 is None:
                raise ValueError(f"{s.path}/poses.txt: no pose for {p.name0 if pose0 is None else p.name1}")
            rel = pose1.relative_to(pose0)
            Rs.append(rel.R)
            ts.append(rel.t)
    U, _, Vt = np.linalg.svd(np.mean(Rs, 0))
    R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return R, np.mean(ts, 0)


def evaluate_pairs(
    predict: Callable[[dict], dict] | None,
    root: os.PathLike | str,
    cfg: DataConfig,
    split: str = "val",
    every_query: int = 1,
    constant: tuple[np.ndarray, np.ndarray] | None = None,
    batch_size: int = 16,
) -> dict[str, float]:
    """Metrics over reference–query pairs of ``split`` for a ``predict(batch)`` function or a constant pose."""
    import torch
    from torch.utils.data import DataLoader

    scenes = Dataset(root).scenes(split)
    pairs = val_pairs(scenes, every_query)
    first = next(iter(scenes[0].frames.values()))
    size = resolve_size((first.intrinsics.width, first.intrinsics.height), cfg)
    cols: dict[str, list] = {"t": [], "r": [], "v": [], "c": []}
    for batch in DataLoader(PairDataset(pairs, size), batch_size=batch_size):
        Rg, tg = batch["R"].double().numpy(), batch["t"].double().numpy()
        if constant is not None:
            R = np.broadcast_to(constant[0], Rg.shape)
            t = np.broadcast_to(constant[1], tg.shape)
            conf = np.zeros(len(tg))
        elif predict is None:
            raise ValueError("evaluate_pairs needs a predict function or a constant pose")
        else:
            with torch.inference_mode():
                res = predict(batch)
            R, t, conf = res["R"], res["t"], res["confidence"]
        te, re = pose_errors(R, t, Rg, tg)
        cols["t"].append(te)
        cols["r"].append(re)
        cols["v"].append(vcre_px(R, t, Rg, tg, batch["K1_orig"].numpy(), batch["size1_orig"].numpy()))
        cols["c"].append(conf)
    t_err, r_err, v_err, conf = (np.concatenate(cols[k]) for k in "trvc")
    out = summarize(t_err, r_err, v_err, conf)
    out["pairs"] = float(len(pairs))
    return out


def _read_csv(path: Path) -> dict[str, list[tuple[float, float]]]:
    series: dict[str, list[tuple[float, float]]] = {}
    with open(path) as f:
        for row in csv.DictReader(f):
            step = float(row.get("step") or 0)
            for k, v in row.items():
                if k not in ("step", "epoch") and v not in ("", None):
                    series.setdefault(k, []).append((step, float(v)))
    return series


def plot_curves(
    metrics_csv: os.PathLike | str,
    out_png: os.PathLike | str,
    title: str = "",
    baselines: dict[str, float] | None = None,
) -> Path:
    """Loss curves (train per step, val per epoch) and validation VCRE precision/AUC from Lightning's CSV log.

    ``baselines``: label -> value drawn as dashed horizontal lines on the validation panel (e.g. the
    mean training pose's precision on the same pairs).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = _read_csv(Path(metrics_csv))
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4))
    for key, style in (
        ("train/loss", "-"),
        ("train/loss_rot", ":"),
        ("train/loss_trans", ":"),
        ("train/loss_vp", ":"),
        ("val/loss", "o-"),
        ("val/loss_pose", "s-"),
    ):
        if key in s:
            x, y = zip(*s[key])
            ax0.plot(x, y, style, label=key, ms=4)
    ax0.set_xlabel("step")
    ax0.set_ylabel("loss")
    ax0.set_title("losses" + (f" — {title}" if title else ""))
    for key in ("val/vcre_prec", "val/vcre_auc", "val/pose_prec"):
        if key in s:
            x, y = zip(*s[key])
            ax1.plot(x, y, "o-", label=key, ms=4)
    for i, (label, value) in enumerate((baselines or {}).items()):
        ax1.axhline(value, ls="--", lw=1, color=f"C{i + 3}", label=label)
    ax1.set_xlabel("step")
    ax1.set_ylim(0, 1)
    ax1.set_title("validation (VCRE < 90 px)")
    for ax in (ax0, ax1):
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
        else:  # a run shorter than the logging interval or than one epoch
            ax.text(0.5, 0.5, "nothing logged yet", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    out = Path(out_png)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
