"""The DINOv2 ViT/14 pieces shared by MicKey's frozen backbone (``mickey.dinov2``) and DUNE's encoder
(``mast3r.dune``): pre-norm blocks with LayerScale, the patch embedding, and the resize of the learned
position embedding to the input's patch grid as the public DINOv2 code does it.

The resize is bicubic with the scale factors ``(rows + 0.1) / g`` and ``(cols + 0.1) / g`` (``g`` the side of
the stored grid) rather than the output size, so the sampling positions are those of the public code
(source = (dst + 0.5) / s - 0.5, PyTorch's bicubic A = -0.75, borders clamped).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .blocks import Mlp, SelfAttention, layer_norm

__all__ = ["LayerScale", "DinoBlock", "DinoPatchEmbed", "resize_position_embedding"]


class LayerScale(nn.Module):
    """Per-channel gain of a residual branch."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class DinoBlock(nn.Module):
    """x + ls1(attn(norm1 x)); x + ls2(mlp(norm2 x)) (LayerNorm eps 1e-6, exact GELU, qkv bias).

    Args:
        dim: Token width.
        heads: Attention heads.
        mlp_hidden: Hidden width of the MLP.
    """

    def __init__(self, dim: int, heads: int, mlp_hidden: int) -> None:
        super().__init__()
        self.norm1 = layer_norm(dim)
        self.attn = SelfAttention(dim, heads, rope=None)
        self.ls1 = LayerScale(dim)
        self.norm2 = layer_norm(dim)
        self.mlp = Mlp(dim, mlp_hidden)
        self.ls2 = LayerScale(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x), None))
        return x + self.ls2(self.mlp(self.norm2(x)))


class DinoPatchEmbed(nn.Module):
    """Non-overlapping ``patch`` x ``patch`` convolution -> (B, rows*cols, dim) tokens, row-major."""

    def __init__(self, patch: int, dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, dim, patch, stride=patch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


def resize_position_embedding(pos_embed: torch.Tensor, rows: int, cols: int, dtype: torch.dtype) -> torch.Tensor:
    """The stored position embedding for a ``rows`` x ``cols`` patch grid (the public DINOv2 rule).

    Args:
        pos_embed: (1, 1 + g*g, dim): the class token's entry, then a g x g grid, row-major.
        rows: Patch rows of the input.
        cols: Patch columns of the input.
        dtype: Dtype of the result.

    Returns:
        (1, 1 + rows*cols, dim): as stored when the grid is g x g, else the class entry unchanged and the grid
            resized bicubically (computed in float32).
    """
    rows, cols = int(rows), int(cols)  # python numbers even while tracing (an ONNX graph has a fixed input size)
    g = math.isqrt(int(pos_embed.shape[1]) - 1)
    if rows == g and cols == g:
        return pos_embed.to(dtype)
    pos = pos_embed.float()
    patches = pos[:, 1:].reshape(1, g, g, -1).permute(0, 3, 1, 2)
    side = math.sqrt(g * g)  # as the public code computes it (a float)
    out = F.interpolate(patches, scale_factor=((rows + 0.1) / side, (cols + 0.1) / side), mode="bicubic")
    if tuple(out.shape[-2:]) != (rows, cols):  # pragma: no cover - the +0.1 guards against exactly this
        raise RuntimeError(f"position embedding resized to {tuple(out.shape[-2:])}, not {(rows, cols)}")
    out = out.permute(0, 2, 3, 1).reshape(1, rows * cols, -1)
    return torch.cat((pos[:, :1], out), dim=1).to(dtype)
