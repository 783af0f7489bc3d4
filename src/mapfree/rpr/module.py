"""Lightning module: the RPR network, its loss, Adam, and validation metrics (VCRE precision and AUC)."""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np
import pytorch_lightning as pl
import torch

from .config import RPRConfig
from .data import as_float_input
from .losses import PoseLoss
from .metrics import confidence_from_log_sigma, pose_errors, summarize, vcre_px
from .model import RPRNet
from .params import PoseOutput

__all__ = ["RPRModule", "warmup_cosine"]


class RPRModule(pl.LightningModule):
    """Lightning module that trains ``RPRNet``; the full ``RPRConfig`` is saved in the checkpoint's hyper-parameters.

    Args:
        config: The configuration, or its nested dicts (validated here); the defaults when None.
    """

    def __init__(self, config: dict[str, Any] | RPRConfig | None = None):
        super().__init__()
        cfg = config if isinstance(config, RPRConfig) else RPRConfig.from_dict(config or {}).validate()
        self.save_hyperparameters({"config": cfg.to_dict()})
        self.cfg = cfg
        self.net = RPRNet(cfg.model, cfg.data.image_size)
        self.criterion = PoseLoss(cfg.loss)
        self._val: list[dict[str, np.ndarray]] = []
        self._features: dict[str, torch.Tensor] = {}  # train.cache_features: image key -> frozen features
        self._frozen = self._freeze(cfg.train.freeze)

    def _freeze(self, what: str) -> list[torch.nn.Module]:
        """Stop gradients into the frozen parts; they also stay in eval mode (fixed BatchNorm statistics)."""
        if what == "encoder":
            parts = [self.net.encoder]
        elif what == "pose":  # everything but the uncertainty head, the learned loss weights included
            parts = [m for n, m in self.net.named_children() if n != "uncertainty"] + [self.criterion]
        else:
            return []
        for m in parts:
            m.requires_grad_(False)
            m.eval()
        return parts

    def train(self, mode: bool = True) -> RPRModule:
        super().train(mode)
        for m in self._frozen:
            m.eval()
        return self

    def forward(self, img0: torch.Tensor, img1: torch.Tensor) -> PoseOutput:
        return self.net(img0, img1)

    def on_fit_start(self) -> None:
        self.train(self.training)  # Lightning sets modes per submodule: put the frozen parts back in eval
        if self.cfg.train.channels_last:
            # Module.to(memory_format=...) is documented and works; torch's overloads leave the keyword out
            self.net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]

    def _step(self, batch: dict[str, Any]) -> tuple[PoseOutput, dict[str, torch.Tensor]]:
        img0, img1 = as_float_input(batch["img0"]), as_float_input(batch["img1"])
        if self.cfg.train.channels_last:
            img0 = img0.contiguous(memory_format=torch.channels_last)
            img1 = img1.contiguous(memory_format=torch.channels_last)
        if self.cfg.train.cache_features and "key0" in batch:
            out = self.net.from_features(self._cached(batch["key0"], img0), self._cached(batch["key1"], img1))
        else:
            out = self.net(img0, img1)
        return out, self.criterion(out, batch["R"], batch["t"], batch.get("q"))

    def _cached(self, keys: list[str], images: torch.Tensor) -> torch.Tensor:
        """Frozen-encoder features of ``images`` (B,3,H,W), computed once per distinct key and kept in float16."""
        todo: dict[str, int] = {}
        for i, k in enumerate(keys):
            if k not in self._features:
                todo.setdefault(k, i)
        if todo:
            with torch.no_grad():
                feats = self.net.encoder(images[list(todo.values())])
            for k, f in zip(todo, feats):
                self._features[k] = f.to(torch.float16)
        return torch.stack([self._features[k] for k in keys]).float()

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        _, terms = self._step(batch)
        bs = batch["img0"].shape[0]
        self.log("train/loss", terms["loss"], prog_bar=True, batch_size=bs, sync_dist=False)
        for k in ("loss_rot", "loss_trans", "loss_vp", "loss_nll"):
            if k in terms:
                self.log(f"train/{k}", terms[k], batch_size=bs)
        if self.cfg.loss.weighting == "learned":
            self.log("train/s_rot", self.criterion.s_rot.detach()[0], batch_size=bs)
            self.log("train/s_trans", self.criterion.s_trans.detach()[0], batch_size=bs)
        return terms["loss"]

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        out, terms = self._step(batch)
        bs = batch["img0"].shape[0]
        self.log("val/loss", terms["loss"], prog_bar=True, batch_size=bs, sync_dist=True)
        self.log("val/loss_pose", terms["loss_pose"], batch_size=bs, sync_dist=True)
        R, t = out.R.detach().float().cpu().numpy(), out.t.detach().float().cpu().numpy()
        Rg, tg = batch["R"].cpu().numpy(), batch["t"].cpu().numpy()
        te, re = pose_errors(R, t, Rg, tg)
        ls = out.log_sigma.detach().float().cpu().numpy() if out.log_sigma is not None else None
        conf = confidence_from_log_sigma(ls) if ls is not None else np.zeros(bs)
        vc = vcre_px(R, t, Rg, tg, batch["K1_orig"].cpu().numpy(), batch["size1_orig"].cpu().numpy())
        self._val.append({"trans_err": te, "rot_err": re, "vcre": vc, "confidence": conf})

    def on_validation_epoch_start(self) -> None:
        self._val = []

    def on_validation_epoch_end(self) -> None:
        if not self._val:
            return
        cols = {k: np.concatenate([v[k] for v in self._val]) for k in self._val[0]}
        distributed = self.trainer is not None and self.trainer.world_size > 1
        if distributed:  # every rank holds a shard of the pairs: score them all, identically on every rank
            local = {k: torch.as_tensor(v, device=self.device) for k, v in cols.items()}
            gathered = cast(dict[str, torch.Tensor], self.all_gather(local))  # a dict in, a dict out
            cols = {k: v.reshape(-1).cpu().numpy() for k, v in gathered.items()}
        for k, v in summarize(cols["trans_err"], cols["rot_err"], cols["vcre"], cols["confidence"]).items():
            self.log(f"val/{k}", float(v), prog_bar=k in ("vcre_prec", "vcre_auc"), sync_dist=distributed)
        self._val = []

    def configure_optimizers(self):
        tc = self.cfg.train
        params = [p for p in self.parameters() if p.requires_grad]
        # On a GPU, one fused kernel for the whole update instead of several per parameter tensor.
        # None is torch's default (its own choice, never fused on the CPU).
        fused: bool | None = True if params and params[0].is_cuda else None
        opt = (
            torch.optim.AdamW(params, lr=tc.lr, weight_decay=tc.weight_decay, eps=tc.adam_eps, fused=fused)
            if tc.weight_decay
            else torch.optim.Adam(params, lr=tc.lr, eps=tc.adam_eps, fused=fused)
        )
        if tc.scheduler == "none":
            return opt
        total = max(int(self.trainer.estimated_stepping_batches), 1) if self.trainer is not None else 1
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda step: warmup_cosine(step, total, tc.warmup_steps))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}


def warmup_cosine(step: int, total: int, warmup: int) -> float:
    """Learning-rate factor: linear warmup over ``warmup`` steps, then cosine decay to 0 at ``total``."""
    if warmup > 0 and step < warmup:
        return (step + 1) / warmup
    progress = min(max(step - warmup, 0) / max(total - warmup, 1), 1.0)
    return 0.5 * (1.0 + math.cos(math.pi * progress))
