"""RPR on synthetic data, end to end: held-out VCRE precision of a trained model vs the mean training pose.

Three steps, each skipped when its output exists: render the data (`mapfree synth`), train
(`mapfree train CONFIG`), then score every val query of the held-out scenes with the model and with the
constant mean relative pose of the same training pairs (chordal mean R, mean t). VCRE is measured on the
val images' own 540x720 intrinsics, as the benchmark does. Prints a table and writes OUT/heldout.json and
OUT/curves_vs_mean_pose.png.

    .venv/bin/python bench/rpr_synth.py --root data/rpr_synth --out runs/rpr_synth   # ~35 min on 2 CPU cores
    .venv/bin/python bench/rpr_synth.py --root data/rpr_synth --out runs/vp --set loss.virtual_points=1.0
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table


def _mapfree(*args: str) -> None:
    cmd = [sys.executable, "-m", "mapfree", *args]
    print("$ mapfree", " ".join(args), flush=True)
    subprocess.run(cmd, check=True)


def render(root: Path, train_scenes: int, val_scenes: int, seed: int, workers: int) -> None:
    """The held-out val split at the benchmark's 540x720 and many small train scenes at the network's 192x256."""
    if not (root / "val").is_dir():
        _mapfree(
            "synth",
            str(root),
            "--split",
            "val",
            "--scenes",
            str(val_scenes),
            "--queries",
            "30",
            "--seed",
            str(seed),
            "--workers",
            str(workers),
            "--quiet",
        )
    if not (root / "train").is_dir():
        _mapfree(
            "synth",
            str(root),
            "--split",
            "train",
            "--scenes",
            str(train_scenes),
            "--train-frames",
            "25",
            "--size",
            "192x256",
            "--no-mono",
            "--seed",
            str(seed),
            "--workers",
            str(workers),
            "--quiet",
        )


def evaluate(run: Path, root: Path) -> dict[str, dict[str, float]]:
    import torch
    import yaml

    from mapfree.rpr import load_method
    from mapfree.rpr.config import RPRConfig
    from mapfree.rpr.report import evaluate_pairs, mean_training_pose

    cfg = RPRConfig.from_dict(yaml.safe_load((run / "config.yaml").read_text()))
    R, t = mean_training_pose(root, cfg.data, epochs=3)
    method = load_method(run / "checkpoints" / "last.ckpt", device="cuda" if torch.cuda.is_available() else "cpu")
    return {
        "mean training pose": evaluate_pairs(None, root, cfg.data, constant=(R, t)),
        "model (last.ckpt)": evaluate_pairs(method.predict, root, cfg.data),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=Path("data/rpr_synth"), help="synthetic dataset root")
    ap.add_argument("--out", type=Path, default=Path("runs/rpr_synth"), help="training run folder")
    ap.add_argument("--config", default="R6D_t_cpu_synth", help="RPR config (name in configs/rpr or YAML path)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override for training")
    ap.add_argument("--train-scenes", type=int, default=400)
    ap.add_argument("--val-scenes", type=int, default=10)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--workers", type=int, default=2, help="processes rendering scenes")
    args = ap.parse_args()

    t0 = time.perf_counter()
    render(args.root, args.train_scenes, args.val_scenes, args.seed, args.workers)
    if not (args.out / "checkpoints" / "last.ckpt").is_file():
        extra = [a for kv in args.set for a in ("--set", kv)]
        _mapfree("train", args.config, "--data", str(args.root), "--out", str(args.out), "--no-progress", *extra)
    res = evaluate(args.out, args.root)
    (args.out / "heldout.json").write_text(json.dumps(res, indent=1))
    from mapfree.rpr.report import plot_curves

    png = plot_curves(
        args.out / "logs" / "metrics.csv",
        args.out / "curves_vs_mean_pose.png",
        args.config,
        {"mean training pose: VCRE prec": res["mean training pose"]["vcre_prec"]},
    )

    table = Table(title=f"held-out val ({int(res['model (last.ckpt)']['pairs'])} pairs): VCRE < 90 px")
    for col in ("", "VCRE prec", "VCRE AUC", "median VCRE px", "median t err m", "median R err deg"):
        table.add_column(col, justify="right" if col else "left")
    for name, m in res.items():
        table.add_row(
            name,
            f"{m['vcre_prec']:.3f}",
            f"{m['vcre_auc']:.3f}",
            f"{m['vcre_med']:.0f}",
            f"{m['trans_err_med']:.2f}",
            f"{m['rot_err_med']:.1f}",
        )
    Console(width=120).print(table)
    base, model = res["mean training pose"]["vcre_prec"], res["model (last.ckpt)"]["vcre_prec"]
    print(
        f"model / mean pose precision: {model / max(base, 1e-9):.2f}x; curves: {png}; "
        f"total {time.perf_counter() - t0:.0f} s"
    )


if __name__ == "__main__":
    main()
