"""DINOv2 ViT/14 (Oquab et al., 2023), the frozen backbone of MicKey, as its public ``forward_features`` runs it.

Patch embedding, a class token, the position embedding of the 518-pixel pretraining grid resized to the input's
grid, pre-norm blocks with LayerScale, and the final LayerNorm; MicKey reads the normalised patch tokens. The
resize is the one of the DINOv2 code MicKey ships: bicubic, with the scale factors ``(rows + 0.1) / g`` and
``(cols + 0.1) / g`` (``g`` = the pretraining grid side) rather than the output size, so the sampling positions
are those of the public code.

The architecture is read from the weight file: width, depth, patch size, heads of 64 channels (ViT-S/B/L/g all
use 64), so the published ViT-L/14 and any smaller ViT built the same way (the tests' tiny one) both load.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import nn

from ..mast3r.blocks import layer_norm
from ..mast3r.dino import DinoBlock, DinoPatchEmbed, resize_position_embedding

__all__ = ["ViTShape", "DinoV2", "HEAD_DIM"]

#: Channels per attention head of every DINOv2 ViT.
HEAD_DIM = 64


@dataclass(frozen=True)
class ViTShape:
    """The architecture of a DINOv2 ViT, as its state dict shows it."""

    dim: int
    depth: int
    patch: int
    grid: int  # side of the pretraining grid (37 for 518 px at patch 14)
    mlp_hidden: int

    @property
    def heads(self) -> int:
        return self.dim // HEAD_DIM

    @classmethod
    def from_state_dict(cls, sd: Mapping[str, torch.Tensor], source: str = "DINOv2 weights") -> ViTShape:
        """Width, depth, patch and grid of ``sd`` (the DINOv2 file's keys); ``ValueError`` naming what is off."""
        try:
            proj, pos = sd["patch_embed.proj.weight"], sd["pos_embed"]
            hidden = int(sd["blocks.0.mlp.fc1.weight"].shape[0])
        except KeyError as e:
            raise ValueError(f"{source}: not a DINOv2 ViT state dict (no {e.args[0]!r})") from None
        dim, patch = int(proj.shape[0]), int(proj.shape[-1])
        blocks = {int(m.group(1)) for k in sd if (m := re.match(r"blocks\.(\d+)\.", k))}
        depth = len(blocks)
        if blocks != set(range(depth)):
            raise ValueError(
                f"{source}: block indices {sorted(blocks)[:5]}... are not 0..{depth - 1} (a chunked "
                f"checkpoint? MicKey's backbone has unchunked blocks)"
            )
        grid = math.isqrt(int(pos.shape[1]) - 1)
        if grid * grid != int(pos.shape[1]) - 1 or dim % HEAD_DIM:
            raise ValueError(
                f"{source}: position embedding {tuple(pos.shape)} / width {dim} do not fit a square "
                f"grid of {HEAD_DIM}-channel heads"
            )
        return cls(dim, depth, patch, grid, hidden)


class DinoV2(nn.Module):
    """Parameter names are the DINOv2 file's, so it loads strictly."""

    def __init__(self, shape: ViTShape) -> None:
        super().__init__()
        self.shape = shape
        self.cls_token = nn.Parameter(torch.zeros(1, 1, shape.dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, shape.grid**2 + 1, shape.dim))
        self.mask_token = nn.Parameter(torch.zeros(1, shape.dim))  # pretraining only; kept for the keys
        self.patch_embed = DinoPatchEmbed(shape.patch, shape.dim)
        self.blocks = nn.ModuleList([DinoBlock(shape.dim, shape.heads, shape.mlp_hidden) for _ in range(shape.depth)])
        self.norm = layer_norm(shape.dim)

    def position_embedding(self, rows: int, cols: int, dtype: torch.dtype) -> torch.Tensor:
        """(1, 1 + rows*cols, dim): the class token's entry and the patch grid resized to rows x cols."""
        return resize_position_embedding(self.pos_embed, rows, cols, dtype)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W), H and W multiples of the patch -> normalised patch tokens (B, dim, H/p, W/p)."""
        b, _, h, w = x.shape
        p = self.shape.patch
        rows, cols = h // p, w // p
        t = self.patch_embed(x)
        t = torch.cat((self.cls_token.expand(b, -1, -1).to(t.dtype), t), dim=1)
        t = t + self.position_embedding(rows, cols, t.dtype)
        for blk in self.blocks:
            t = blk(t)
        t = self.norm(t)[:, 1:]
        return t.transpose(1, 2).reshape(b, -1, rows, cols)
