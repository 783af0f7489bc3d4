"""``mapfree train CONFIG``: train a relative pose regression network with PyTorch Lightning."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import HelpFormatter, fail


def _devices(v: str):
    return v if v == "auto" or "," in v else int(v)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "train",
        help="train a relative pose regression (RPR) network",
        description="Train an RPR network on a Map-free root (train/ with overlaps.npz, val/ for validation). "
        "CONFIG is a YAML file or a name in configs/rpr (e.g. 3d3d, rot6d_trans: the public release's 12 "
        "configurations, or R6D_t_cpu_synth). Writes OUT/checkpoints/"
        "{best,last}.ckpt, OUT/logs/metrics.csv and OUT/tensorboard/. Multi-GPU / multi-node: "
        "--devices N --num-nodes M --strategy ddp (on a cluster, launch one process per device, e.g. with srun).",
        epilog="examples:\n"
        "  mapfree train 3d3d --data data/mapfree --out runs/3d3d\n"
        "  mapfree train 3d3d --data data/mapfree --out runs/3d3d --resume runs/3d3d/checkpoints/last.ckpt\n"
        "  mapfree train 3d3d --data data/mapfree --init 3d3d.ckpt --set train.lr=1e-5   # fine-tune\n"
        "  mapfree train rot6d_trans --data data/mapfree --devices 4 --strategy ddp --precision bf16-mixed\n"
        "  mapfree train R6D_t_cpu_synth --data data/synth --max-steps 20 --set data.batch_size=2   # smoke test\n",
        formatter_class=HelpFormatter,
    )
    p.add_argument("config", help="YAML config path or name in configs/rpr")
    p.add_argument("--data", type=Path, help="dataset root (overrides data.root)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: runs/rpr/<config name>)")
    p.add_argument(
        "--devices", type=_devices, default="auto", help="devices per node: N, 'auto' or a list '0,1' (default: auto)"
    )
    p.add_argument("--num-nodes", type=int, default=1, help="number of nodes (DDP; default: 1)")
    p.add_argument(
        "--strategy", default="auto", help="Lightning strategy: auto, ddp, ddp_spawn, fsdp, … (default: auto)"
    )
    p.add_argument("--accelerator", default="auto", help="auto, cpu, gpu, mps, … (default: auto: a GPU when present)")
    p.add_argument("--precision", default=None, help="32-true, bf16-mixed, 16-mixed (default: the config's)")
    p.add_argument("--max-epochs", type=int, default=None, help="override train.max_epochs")
    p.add_argument("--max-steps", type=int, default=None, help="stop after this many optimizer steps")
    p.add_argument("--resume", type=Path, default=None, help="checkpoint to resume (e.g. OUT/checkpoints/last.ckpt)")
    p.add_argument(
        "--init",
        type=Path,
        default=None,
        help="start from these weights: a published Map-free checkpoint (e.g. 3d3d.ckpt) or one of ours "
        "(train.init); a fresh run, unlike --resume",
    )
    p.add_argument(
        "--freeze",
        choices=("none", "encoder", "pose"),
        default=None,
        help="train.freeze: encoder (fixed encoder) or pose (only the uncertainty head trains: a confidence "
        "on top of a loaded model; needs model.uncertainty=true)",
    )
    p.add_argument("--channels-last", action="store_true", help="NHWC memory format (train.channels_last)")
    p.add_argument("--sync-batchnorm", action="store_true", help="synchronise BatchNorm statistics across devices")
    p.add_argument("--limit-val-batches", type=float, default=None, help="fraction (<=1) or number of val batches")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set data.batch_size=4 --set model.warping=false",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # The config and the flags are checked before Lightning is imported (seconds, and its banner lines): a typo
    # in the command line is answered at once.
    from ..rpr.config import apply_overrides, load_config, resolve_config

    try:
        path = resolve_config(args.config)
        cfg = load_config(path)
        overrides = list(args.overrides)
        if args.data is not None:
            overrides.append(f"data.root={args.data}")
        if args.channels_last:
            overrides.append("train.channels_last=true")
        if args.init is not None:
            if not args.init.is_file():
                raise FileNotFoundError(f"--init checkpoint {args.init} not found")
            overrides.append(f"train.init={args.init}")
        if args.freeze is not None:
            overrides.append(f"train.freeze={args.freeze}")
        cfg = apply_overrides(cfg, overrides) if overrides else cfg
    except (FileNotFoundError, ValueError) as e:
        return fail("train", e)
    if args.resume is not None and not args.resume.is_file():
        return fail("train", f"--resume checkpoint {args.resume} not found")
    try:
        from ..rpr.train import TrainerOptions, fit
    except ImportError as e:
        print(f"mapfree train needs the training extra (pip install 'mapfree[train]'): {e}", file=sys.stderr)
        return 1
    _quiet_lightning()
    lvb = args.limit_val_batches
    opts = TrainerOptions(
        accelerator=args.accelerator,
        devices=args.devices,
        num_nodes=args.num_nodes,
        strategy=args.strategy,
        precision=args.precision,
        max_epochs=args.max_epochs,
        max_steps=args.max_steps,
        sync_batchnorm=args.sync_batchnorm,
        progress=not args.no_progress,
        limit_val_batches=int(lvb) if lvb is not None and lvb > 1 else lvb,
    )
    out = args.out or Path("runs") / "rpr" / path.stem
    try:
        trainer, _ = fit(cfg, out, opts, resume=args.resume)
    except (FileNotFoundError, ValueError) as e:
        return fail("train", e)
    ck = trainer.checkpoint_callback
    if trainer.is_global_zero:
        best = getattr(ck, "best_model_path", "") or "none yet: no validation ran, use last.ckpt"
        print(f"checkpoints: {out / 'checkpoints'} (best: {best}); logs: {out / 'logs' / 'metrics.csv'}")
    return 0


def _quiet_lightning() -> None:
    """Lightning's start-up lines (available accelerators, tips, the model summary's preamble) at INFO go away;
    its warnings stay."""
    import logging
    import warnings

    for name in (
        "pytorch_lightning.utilities.rank_zero",
        "lightning.pytorch.utilities.rank_zero",
        "pytorch_lightning.accelerators.cuda",
        "lightning.pytorch.accelerators.cuda",
    ):
        logging.getLogger(name).setLevel(logging.WARNING)
    # Two warnings every run prints that ask nothing of the user: a deprecation inside Lightning itself, and
    # the frozen pretrained encoder being (deliberately) in eval mode.
    warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\)")
    warnings.filterwarnings("ignore", message=r"Found \d+ module\(s\) in eval mode")
