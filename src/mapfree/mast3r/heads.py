"""Prediction heads and their output activations.

``PointHead`` (DUSt3R, ``head_type='dpt'``): a DPT map of (x, y, z, conf). ``PointDescHead`` (MASt3R,
``head_type='catmlp+dpt'``): the same DPT map plus a per-patch MLP on [encoder, last decoder] tokens that
predicts ``desc_dim`` descriptor channels (and a descriptor confidence) for each of the patch's pixels.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from .blocks import Mlp
from .config import Mode, ModelConfig
from .dpt import DPTHead, dpt_hooks

__all__ = ["PointHead", "PointDescHead", "points_from_raw", "confidence_from_raw", "make_head"]


def points_from_raw(xyz: torch.Tensor, mode: Mode) -> torch.Tensor:
    """3-D points from raw (…, 3): the direction is kept, the distance d becomes expm1(d) (``exp``) or d²
    (``square``)."""
    kind, vmin, vmax = mode
    if kind == "linear":
        return xyz if (vmin, vmax) == (-float("inf"), float("inf")) else xyz.clip(min=vmin, max=vmax)
    d = xyz.norm(dim=-1, keepdim=True)
    unit = xyz / d.clip(min=1e-8)
    if kind == "exp":
        return unit * torch.expm1(d)
    if kind == "square":
        return unit * d.square()
    raise ValueError(f"unsupported depth mode {kind!r}")


def confidence_from_raw(x: torch.Tensor, mode: Mode) -> torch.Tensor:
    """Confidence >= vmin: ``vmin + exp(x)`` (capped at ``vmax - vmin``) or a scaled sigmoid."""
    kind, vmin, vmax = mode
    if kind == "exp":
        return vmin + x.exp().clip(max=vmax - vmin)
    if kind == "sigmoid":
        return (vmax - vmin) * torch.sigmoid(x) + vmin
    raise ValueError(f"unsupported confidence mode {kind!r}")


def _dims(cfg: ModelConfig) -> list[int]:
    return [cfg.enc_embed_dim, cfg.dec_embed_dim, cfg.dec_embed_dim, cfg.dec_embed_dim]


class PointHead(DPTHead):
    """DUSt3R's head: ``pts3d`` (H, W, 3) and ``conf`` (H, W)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__(_dims(cfg), dpt_hooks(cfg.dec_depth), 4, cfg.patch_size)
        self.cfg = cfg

    def forward(self, tokens: Sequence[torch.Tensor], hw: tuple[int, int]) -> dict[str, torch.Tensor]:
        fmap = self.dpt(tokens, hw).permute(0, 2, 3, 1)
        return {
            "pts3d": points_from_raw(fmap[..., :3], self.cfg.depth_mode),
            "conf": confidence_from_raw(fmap[..., 3], self.cfg.conf_mode),
        }


class PointDescHead(DPTHead):
    """MASt3R's head: ``pts3d``, ``conf``, unit ``desc`` (H, W, desc_dim) and ``desc_conf`` (H, W)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__(_dims(cfg), dpt_hooks(cfg.dec_depth), 4, cfg.patch_size)
        self.cfg = cfg
        width = cfg.enc_embed_dim + cfg.dec_embed_dim
        per_pixel = cfg.desc_dim + int(cfg.two_confs)
        self.head_local_features = Mlp(width, int(4.0 * width), per_pixel * cfg.patch_size**2)

    def forward(self, tokens: Sequence[torch.Tensor], hw: tuple[int, int]) -> dict[str, torch.Tensor]:
        p = self.cfg.patch_size
        dense = self.dpt(tokens, hw)
        cat = torch.cat([tokens[0], tokens[-1]], dim=-1)
        b = cat.shape[0]
        local = self.head_local_features(cat).transpose(-1, -2).reshape(b, -1, hw[0] // p, hw[1] // p)
        fmap = torch.cat([dense, F.pixel_shuffle(local, p)], dim=1).permute(0, 2, 3, 1)
        cfg = self.cfg
        out = {
            "pts3d": points_from_raw(fmap[..., :3], cfg.depth_mode),
            "conf": confidence_from_raw(fmap[..., 3], cfg.conf_mode),
        }
        desc = fmap[..., 4 : 4 + cfg.desc_dim]
        out["desc"] = desc / desc.norm(dim=-1, keepdim=True)
        if cfg.two_confs:
            out["desc_conf"] = confidence_from_raw(fmap[..., 4 + cfg.desc_dim], cfg.desc_conf_mode or cfg.conf_mode)
        else:
            out["desc_conf"] = out["conf"].clone()
        return out


def make_head(cfg: ModelConfig) -> nn.Module:
    return PointDescHead(cfg) if cfg.has_descriptors else PointHead(cfg)
