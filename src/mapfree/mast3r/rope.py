"""2-D rotary position embedding of the CroCo/DUSt3R/MASt3R transformers (``pos_embed='RoPE100'``).

Each attention head's channels are split in two halves: the first half is rotated by the token's row index,
the second by its column index, with 1-D RoPE frequencies ``base ** (-2i / D)`` (``D`` = half a head).
"""

from __future__ import annotations

import torch

__all__ = ["RoPE2D", "patch_positions"]


def patch_positions(batch: int, rows: int, cols: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """(batch, rows*cols, 2) integer (row, col) of every patch, row-major."""
    r = torch.arange(rows, device=device)
    c = torch.arange(cols, device=device)
    grid = torch.stack(torch.meshgrid(r, c, indexing="ij"), dim=-1).reshape(1, rows * cols, 2)
    return grid.expand(batch, -1, 2).clone()


def _rotate_half(x: torch.Tensor) -> torch.Tensor:
    half = x.shape[-1] // 2
    return torch.cat((-x[..., half:], x[..., :half]), dim=-1)


class RoPE2D(torch.nn.Module):
    """Rotates queries/keys (B, heads, N, head_dim) by their patches' (row, col) positions (B, N, 2)."""

    def __init__(self, base: float = 100.0) -> None:
        super().__init__()
        self.base = float(base)
        self._tables: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    def _table(
        self, dim: int, length: int, device: torch.device, dtype: torch.dtype
    ) -> tuple[torch.Tensor, torch.Tensor]:
        key = (dim, length, device, dtype)
        if key not in self._tables:
            inv_freq = 1.0 / (self.base ** (torch.arange(0, dim, 2, device=device).float() / dim))
            angles = torch.arange(length, device=device, dtype=inv_freq.dtype)[:, None] * inv_freq[None, :]
            angles = torch.cat((angles, angles), dim=-1).to(dtype)
            self._tables[key] = (angles.cos(), angles.sin())
        return self._tables[key]

    def _rotate(self, x: torch.Tensor, pos: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
        c = cos[pos][:, None]  # (B, 1, N, D)
        s = sin[pos][:, None]
        return x * c + _rotate_half(x) * s

    def forward(self, tokens: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        dim = tokens.shape[-1] // 2
        cos, sin = self._table(dim, int(positions.max()) + 1, tokens.device, tokens.dtype)
        rows, cols = tokens.chunk(2, dim=-1)
        rows = self._rotate(rows, positions[:, :, 0], cos, sin)
        cols = self._rotate(cols, positions[:, :, 1], cos, sin)
        return torch.cat((rows, cols), dim=-1)
