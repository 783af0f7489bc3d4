"""Transformer blocks of the CroCo encoder and decoders: pre-norm self-attention (and cross-attention to the
other image's tokens in the decoder) with 2-D RoPE on queries and keys, and a GELU MLP."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .rope import RoPE2D

__all__ = ["Mlp", "SelfAttention", "CrossAttention", "EncoderBlock", "DecoderBlock", "layer_norm"]


def layer_norm(dim: int) -> nn.LayerNorm:
    """The LayerNorm of these models (eps 1e-6)."""
    return nn.LayerNorm(dim, eps=1e-6)


class Mlp(nn.Module):
    """fc1 -> exact GELU -> fc2."""

    def __init__(self, dim: int, hidden: int, out: int | None = None) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, out or dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


def _attend(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, scale: float) -> torch.Tensor:
    """softmax(q k^T * scale) v over (B, heads, N, head_dim), then heads merged back to (B, N, C).

    Through ``scaled_dot_product_attention``: on a GPU a fused kernel that never writes the N x N weights (the
    public code materialises them); the same function to float rounding."""
    out = F.scaled_dot_product_attention(q, k, v, scale=scale)
    return out.transpose(1, 2).reshape(out.shape[0], out.shape[2], -1)


class SelfAttention(nn.Module):
    """Multi-head self-attention with a fused qkv projection."""

    def __init__(self, dim: int, heads: int, rope: RoPE2D | None) -> None:
        super().__init__()
        self.heads = heads
        self.scale = (dim // heads) ** -0.5
        self.qkv = nn.Linear(dim, dim * 3)
        self.proj = nn.Linear(dim, dim)
        self.rope = rope

    def forward(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.heads, c // self.heads).transpose(1, 3)
        q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]
        if self.rope is not None:
            q, k = self.rope(q, pos), self.rope(k, pos)
        return self.proj(_attend(q, k, v, self.scale))


class CrossAttention(nn.Module):
    """Multi-head attention of one image's tokens (queries) to the other image's tokens (keys, values)."""

    def __init__(self, dim: int, heads: int, rope: RoPE2D | None) -> None:
        super().__init__()
        self.heads = heads
        self.scale = (dim // heads) ** -0.5
        self.projq = nn.Linear(dim, dim)
        self.projk = nn.Linear(dim, dim)
        self.projv = nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)
        self.rope = rope

    def _split(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        return x.reshape(b, n, self.heads, c // self.heads).permute(0, 2, 1, 3)

    def forward(self, x: torch.Tensor, mem: torch.Tensor, xpos: torch.Tensor, mpos: torch.Tensor) -> torch.Tensor:
        q, k, v = self._split(self.projq(x)), self._split(self.projk(mem)), self._split(self.projv(mem))
        if self.rope is not None:
            q, k = self.rope(q, xpos), self.rope(k, mpos)
        return self.proj(_attend(q, k, v, self.scale))


class EncoderBlock(nn.Module):
    """x + attn(norm1 x); x + mlp(norm2 x)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float, rope: RoPE2D | None) -> None:
        super().__init__()
        self.norm1 = layer_norm(dim)
        self.attn = SelfAttention(dim, heads, rope)
        self.norm2 = layer_norm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), pos)
        return x + self.mlp(self.norm2(x))


class DecoderBlock(nn.Module):
    """Self-attention, then cross-attention to the other image's (normalised) tokens, then the MLP."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float, rope: RoPE2D | None, norm_mem: bool = True) -> None:
        super().__init__()
        self.norm1 = layer_norm(dim)
        self.attn = SelfAttention(dim, heads, rope)
        self.cross_attn = CrossAttention(dim, heads, rope)
        self.norm2 = layer_norm(dim)
        self.norm3 = layer_norm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.norm_y = layer_norm(dim) if norm_mem else nn.Identity()

    def forward(self, x: torch.Tensor, other: torch.Tensor, xpos: torch.Tensor, opos: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), xpos)
        mem = self.norm_y(other)
        x = x + self.cross_attn(self.norm2(x), mem, xpos, opos)
        return x + self.mlp(self.norm3(x))
