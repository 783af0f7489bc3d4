"""Build a Lightning ``Trainer`` for an ``RPRConfig`` and fit: logs, checkpoints (best, last), resume, DDP."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytorch_lightning as pl
import yaml
from pytorch_lightning.callbacks import LearningRateMonitor, ModelCheckpoint
from pytorch_lightning.loggers import CSVLogger

from .config import RPRConfig, config_dir, resolve_config
from .data import RPRDataModule, pose_statistics
from .module import RPRModule
from .official import load_weights, read_checkpoint
from .report import plot_curves

log = logging.getLogger(__name__)

__all__ = ["TrainerOptions", "build_trainer", "fit", "with_target_statistics", "config_dir", "resolve_config"]


@dataclass
class TrainerOptions:
    """Hardware and run-length options from the command line (None: the config's value)."""

    accelerator: str = "auto"
    devices: Any = "auto"
    num_nodes: int = 1
    strategy: str = "auto"
    precision: str | None = None
    max_epochs: int | None = None
    max_steps: int | None = None
    sync_batchnorm: bool = False
    progress: bool = True
    limit_train_batches: float | int | None = None
    limit_val_batches: float | int | None = None
    num_sanity_val_steps: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def _loggers(out: Path) -> list:
    loggers: list = [CSVLogger(save_dir=str(out), name="logs", version="")]
    try:
        from pytorch_lightning.loggers import TensorBoardLogger

        loggers.append(TensorBoardLogger(save_dir=str(out), name="tensorboard", version="", default_hp_metric=False))
    except (ImportError, ModuleNotFoundError):  # tensorboard is optional: CSV always works
        log.info("tensorboard not installed: CSV log only")
    return loggers


def build_trainer(
    cfg: RPRConfig, out: os.PathLike | str, opts: TrainerOptions | None = None, has_val: bool = True
) -> pl.Trainer:
    opts = opts or TrainerOptions()
    out = Path(out)
    monitor = cfg.train.monitor if has_val else "train/loss"
    mode = cfg.train.monitor_mode if has_val else "min"
    # Two callbacks: Lightning's ``save_last`` only refreshes last.ckpt when a new best is written.
    best = ModelCheckpoint(
        dirpath=str(out / "checkpoints"),
        filename="best",
        monitor=monitor,
        mode=mode,
        save_top_k=1,
        auto_insert_metric_name=False,
        enable_version_counter=False,
    )
    last = ModelCheckpoint(
        dirpath=str(out / "checkpoints"), filename="last", monitor=None, save_top_k=1, enable_version_counter=False
    )
    kwargs: dict[str, Any] = dict(
        accelerator=opts.accelerator,
        devices=opts.devices,
        num_nodes=opts.num_nodes,
        strategy=opts.strategy,
        precision=opts.precision or cfg.train.precision,
        max_epochs=opts.max_epochs if opts.max_epochs is not None else cfg.train.max_epochs,
        max_steps=opts.max_steps if opts.max_steps is not None else cfg.train.max_steps,
        gradient_clip_val=cfg.train.gradient_clip_val or None,
        log_every_n_steps=cfg.train.log_every_n_steps,
        check_val_every_n_epoch=cfg.train.check_val_every_n_epoch,
        # Fresh scene-balanced pairs every epoch come from the dataset itself (data.TrainPairs): the loaders
        # are built once and their workers persist.
        sync_batchnorm=opts.sync_batchnorm,
        # One input size for every batch (data.image_size): cuDNN picks its convolution kernels once and keeps them.
        benchmark=bool(cfg.data.image_size),
        enable_progress_bar=opts.progress,
        default_root_dir=str(out),
        logger=_loggers(out),
        callbacks=[best, last, LearningRateMonitor(logging_interval="epoch")],
    )
    for k in ("limit_train_batches", "limit_val_batches", "num_sanity_val_steps"):
        if getattr(opts, k) is not None:
            kwargs[k] = getattr(opts, k)
    kwargs.update(opts.extra)
    return pl.Trainer(**kwargs)


def fit(
    cfg: RPRConfig, out: os.PathLike | str, opts: TrainerOptions | None = None, resume: os.PathLike | str | None = None
) -> tuple[pl.Trainer, RPRModule]:
    """Train ``cfg`` into ``out`` (checkpoints/, logs/metrics.csv, tensorboard/, config.yaml, curves.png)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if resume is not None and not Path(resume).is_file():
        raise FileNotFoundError(f"checkpoint to resume from {resume} not found")
    pl.seed_everything(cfg.train.seed, workers=True, verbose=False)
    dm = RPRDataModule(cfg.data)
    dm.setup("fit")
    if cfg.data.normalize_targets and resume is None and not cfg.train.init:  # a loaded model keeps its decoding
        cfg = with_target_statistics(cfg, dm)
    has_val = bool(dm.val_pairs())
    (out / "config.yaml").write_text(yaml.safe_dump(_plain(cfg.to_dict()), sort_keys=False))
    module = RPRModule(cfg)
    if cfg.train.init and resume is None:  # fine-tuning: start from a public or our own checkpoint
        load_weights(module, read_checkpoint(cfg.train.init), cfg.train.init)
    trainer = build_trainer(cfg, out, opts, has_val=has_val)
    trainer.fit(module, datamodule=dm, ckpt_path=str(resume) if resume else None)
    # The final weights, also when max_steps stopped mid-epoch (every rank calls; rank 0 writes).
    trainer.save_checkpoint(str(out / "checkpoints" / "last.ckpt"))
    csv_path = out / "logs" / "metrics.csv"
    if trainer.is_global_zero and csv_path.is_file():
        try:
            plot_curves(csv_path, out / "curves.png", cfg.name)
        except Exception as e:  # a plot must never lose a finished training run
            log.warning("could not plot %s: %s", csv_path, e)
    return trainer, module


def with_target_statistics(cfg: RPRConfig, dm: RPRDataModule, epochs: int = 3) -> RPRConfig:
    """``cfg`` with ``model.{t_mean,t_std,R_mean}`` from the training pairs of the first ``epochs`` samplings."""
    pairs = [p for e in range(epochs) for p in dm.train_pairs(e)]
    if not pairs:
        return cfg
    R, t, s = pose_statistics(pairs)
    if cfg.data.augment:  # swapped pairs have the inverse pose: centre on no motion, widen the scale
        R, t, s = np.eye(3), np.zeros(3), np.sqrt(s**2 + t**2)
    log.info("target statistics over %d pairs: t mean %s std %s", len(pairs), np.round(t, 3), np.round(s, 3))
    model = replace(
        cfg.model,
        t_mean=tuple(float(v) for v in t),
        t_std=tuple(float(v) for v in s),
        R_mean=tuple(float(v) for v in R.reshape(-1)),
    )
    return replace(cfg, model=model).validate()


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x
