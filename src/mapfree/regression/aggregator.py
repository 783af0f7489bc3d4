"""Aggregation of the two feature maps into one volume for the pose head (SPEC §4, public Map-free release).

``warp``: every position of image 0 gets a softmax over all positions of image 1 (the correlation volume of raw
dot products); it warps image-1 features onto image 0 and, as soft-argmax, image 1's pixel grid (2 position
channels, row then column in [-1, 1]), plus the peak probability (1 max-score channel): 32 + 32 + 2 + 1 = 67
channels for 32-d features. ``qkv``: the same on learned 1×1 query/key/value projections with residuals.
``concat``: the no-warping ablation, both feature maps side by side.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["CorrelationAggregator", "ConcatAggregator", "build_aggregator", "AGGREGATORS"]

AGGREGATORS = ("warp", "qkv", "concat")


def _grid(h: int, w: int, like: torch.Tensor) -> torch.Tensor:
    """(2, h*w): row coordinate, then column coordinate, each linearly in [-1, 1]."""
    u = torch.linspace(-1, 1, h, device=like.device, dtype=like.dtype)
    v = torch.linspace(-1, 1, w, device=like.device, dtype=like.dtype)
    return torch.stack(torch.meshgrid(u, v, indexing="ij"), 0).reshape(2, h * w)


class CorrelationAggregator(nn.Module):
    """Correlation-volume warping (``qkv=False``) or its query/key/value variant (``qkv=True``)."""

    def __init__(self, dim: int = 32, position: bool = True, max_score: bool = True, qkv: bool = False,
                 temperature: float = 0.0, own_position: bool = False):
        super().__init__()
        self.dim, self.position, self.max_score, self.qkv = dim, position, max_score, qkv
        # temperature > 0: cosine similarity / temperature (beyond the paper: sharp matches from the first step);
        # 0: the public code's raw dot product.
        self.temperature = float(temperature)
        self.own_position = own_position and position  # image 0's own grid too (public POSITION_ENCODER_IM1)
        if qkv:
            self.Q_mlp = nn.Conv2d(dim, dim, 1, bias=False)
            self.K_mlp = nn.Conv2d(dim, dim, 1, bias=False)
            self.V_mlp = nn.Conv2d(dim, dim, 1, bias=False)

    @property
    def out_channels(self) -> int:
        return 2 * self.dim + 2 * self.position + 2 * self.own_position + self.max_score

    def forward(self, f0: torch.Tensor, f1: torch.Tensor) -> torch.Tensor:
        if f0.shape != f1.shape:
            raise ValueError(f"feature maps must have one shape, got {tuple(f0.shape)} and {tuple(f1.shape)}")
        B, C, H, W = f0.shape
        if self.qkv:  # residual projections: queries from image 0, keys from image 1, values from both
            q, k = self.Q_mlp(f0) + f0, self.K_mlp(f1) + f1
            v0, v1 = self.V_mlp(f0) + f0, self.V_mlp(f1) + f1
        else:
            q, k, v0, v1 = f0, f1, f0, f1
        q, k = q.reshape(B, C, H * W), k.reshape(B, C, H * W)
        if self.temperature > 0:
            logits = F.normalize(q, dim=1).transpose(1, 2) @ F.normalize(k, dim=1) / self.temperature
        else:
            logits = q.transpose(1, 2) @ k
        attn = torch.softmax(logits, dim=2)  # (B, N0, N1): for each image-0 position, a distribution over image 1
        attn_t = attn.transpose(1, 2)
        chans = [v0.reshape(B, C, H * W), v1.reshape(B, C, H * W) @ attn_t]
        if self.position:
            grid = _grid(H, W, attn)
            chans.append(grid.expand(B, -1, -1) @ attn_t)
            if self.own_position:
                chans.append(grid.expand(B, -1, -1))
        if self.max_score:
            chans.append(attn.amax(2).unsqueeze(1))
        return torch.cat(chans, 1).reshape(B, -1, H, W)


class ConcatAggregator(nn.Module):
    """No warping (ablation): the two feature maps concatenated along channels."""

    def __init__(self, dim: int = 32):
        super().__init__()
        self.dim = dim

    @property
    def out_channels(self) -> int:
        return 2 * self.dim

    def forward(self, f0: torch.Tensor, f1: torch.Tensor) -> torch.Tensor:
        return torch.cat([f0, f1], 1)


def build_aggregator(kind: str, dim: int, position: bool = True, max_score: bool = True, temperature: float = 0.0,
                     own_position: bool = False) -> nn.Module:
    if kind == "concat":
        return ConcatAggregator(dim)
    if kind in ("warp", "qkv"):
        return CorrelationAggregator(dim, position, max_score, kind == "qkv", temperature, own_position)
    raise ValueError(f"unknown aggregator {kind!r} (known: {', '.join(AGGREGATORS)})")
