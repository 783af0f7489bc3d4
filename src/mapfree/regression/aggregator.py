"""Correlation-volume aggregation of the two feature maps into one (SPEC §4).

Each position of image 0 gets a softmax over all positions of image 1 (soft matching); the attention warps
image-1 features and the image-1 pixel grid (2 soft-argmax position channels) onto image 0, plus the
peak attention (1 max-score channel). With 32-d features that is 32 + 32 + 2 + 1 = 67 channels.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["WarpAggregator"]


class WarpAggregator(nn.Module):
    def __init__(self, dim: int = 32, warping: bool = True, position: bool = True, max_score: bool = True,
                 temperature: float = 0.0, own_position: bool = False):
        super().__init__()
        self.dim, self.warping = dim, warping
        self.position, self.max_score = position and warping, max_score and warping
        # temperature > 0: cosine similarity / temperature (sharp matches from the first step, as in LoFTR);
        # 0: the paper's dot product / sqrt(C), nearly uniform attention until the features have learnt to match.
        self.temperature = float(temperature)
        self.own_position = own_position and self.position  # image-0 grid too: the head sees flow = pos1 - pos0

    @property
    def out_channels(self) -> int:
        return 2 * self.dim + 2 * self.position + self.max_score + 2 * self.own_position

    def forward(self, f0: torch.Tensor, f1: torch.Tensor) -> torch.Tensor:
        if not self.warping:  # ablation: plain channel concatenation
            if f1.shape[-2:] != f0.shape[-2:]:
                f1 = F.interpolate(f1, size=f0.shape[-2:], mode="bilinear", align_corners=False)
            return torch.cat([f0, f1], 1)
        B, C, H, W = f0.shape
        h1, w1 = f1.shape[-2:]
        a = f0.flatten(2).transpose(1, 2)  # (B, N0, C)
        b = f1.flatten(2)  # (B, C, N1)
        if self.temperature > 0:
            logits = (F.normalize(a, dim=-1) @ F.normalize(b, dim=1)) / self.temperature
        else:
            logits = (a @ b) / math.sqrt(C)
        attn = torch.softmax(logits, dim=-1)  # (B, N0, N1): softmax over all image-1 positions
        chans = [f0, (attn @ b.transpose(1, 2)).transpose(1, 2).reshape(B, C, H, W)]
        if self.position:
            ys = torch.linspace(-1, 1, h1, device=f1.device, dtype=attn.dtype)
            xs = torch.linspace(-1, 1, w1, device=f1.device, dtype=attn.dtype)
            grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)  # (N1, 2) as (x, y)
            chans.append((attn @ grid).transpose(1, 2).reshape(B, 2, H, W))
        if self.own_position:
            ys0 = torch.linspace(-1, 1, H, device=f0.device, dtype=attn.dtype)
            xs0 = torch.linspace(-1, 1, W, device=f0.device, dtype=attn.dtype)
            grid0 = torch.stack(torch.meshgrid(xs0, ys0, indexing="xy"), 0)  # (2, H, W) as (x, y)
            chans.append(grid0.unsqueeze(0).expand(B, -1, -1, -1).to(f0.dtype))
        if self.max_score:
            chans.append(attn.amax(-1).reshape(B, 1, H, W))
        return torch.cat(chans, 1)
