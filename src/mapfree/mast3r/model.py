"""The asymmetric two-view network of DUSt3R (``AsymmetricCroCo3DStereo``) and MASt3R (``AsymmetricMASt3R``).

A shared ViT encoder with 2-D RoPE embeds each image; two decoders (one per view) alternate self-attention and
cross-attention to the other view; each view's head reads the encoder output and decoder layers. View 1's
points come in its own camera frame, view 2's in view 1's frame (``pts3d_in_other_view``).

Encoding is separate from decoding so that a reference image is encoded once and reused for every query.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
from torch import nn

from .blocks import DecoderBlock, EncoderBlock, layer_norm
from .config import ModelConfig
from .heads import make_head
from .rope import RoPE2D, patch_positions

__all__ = ["AsymmetricModel", "Encoded", "PairNetwork"]


@dataclass
class Encoded:
    """Images after the encoder (one per batch row), kept to pair each with any other image.

    Attributes:
        tokens: (B, N, enc_dim) encoder tokens, one per patch (16 x 16; DUNE-MASt3R's 14 x 14).
        positions: (B, N, 2) (row, col) grid position of each patch.
        hw: (H, W) of the network input, pixels.
    """

    tokens: torch.Tensor
    positions: torch.Tensor
    hw: tuple[int, int]


class PairNetwork(Protocol):
    """A network of the MASt3R family in two stages: what the pair engine runs (``AsymmetricModel`` for MASt3R
    and DUSt3R, ``DuneMast3rModel`` for DUNE-MASt3R)."""

    #: Whether the public loader of this network keeps square images square (else it crops them to 4:3).
    square_ok: bool

    @property
    def cfg(self) -> ModelConfig:
        """The decoder and heads' architecture (``patch_size``, ``has_descriptors``)."""
        ...

    def encode(self, img: torch.Tensor) -> Encoded:
        """(B, 3, H, W) RGB in [-1, 1] -> the encoder's tokens."""
        ...

    def predict(self, e1: Encoded, e2: Encoded) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Decoders and heads on two encoded views."""
        ...


class _PatchEmbed(nn.Module):
    """Non-overlapping patch_size x patch_size convolution -> tokens, with their (row, col) grid positions."""

    def __init__(self, patch_size: int, dim: int) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(3, dim, patch_size, stride=patch_size)

    def forward(self, img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, _, h, w = img.shape
        p = self.patch_size
        if h % p or w % p:
            raise ValueError(f"image size {w}x{h} is not a multiple of the patch size {p}")
        x = self.proj(img)
        pos = patch_positions(b, x.shape[2], x.shape[3], x.device)
        return x.flatten(2).transpose(1, 2), pos


class AsymmetricModel(nn.Module):
    """The asymmetric two-view network of DUSt3R and MASt3R (a ViT encoder, two cross-attending decoders, heads).

    Parameter names follow the published checkpoints, so their state dicts load strictly.

    Args:
        cfg: The architecture, read from a checkpoint.
    """

    #: The public ``load_images(..., size=512)`` crops a square image to 4:3.
    square_ok = False

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        rope = RoPE2D(cfg.rope_base)
        self.patch_embed = _PatchEmbed(cfg.patch_size, cfg.enc_embed_dim)
        self.enc_blocks = nn.ModuleList(
            [EncoderBlock(cfg.enc_embed_dim, cfg.enc_num_heads, cfg.mlp_ratio, rope) for _ in range(cfg.enc_depth)]
        )
        self.enc_norm = layer_norm(cfg.enc_embed_dim)
        self.mask_token = nn.Parameter(torch.zeros(1, 1, cfg.dec_embed_dim))  # pretraining only; kept for the keys
        self.decoder_embed = nn.Linear(cfg.enc_embed_dim, cfg.dec_embed_dim)

        def decoder() -> nn.ModuleList:
            return nn.ModuleList(
                [
                    DecoderBlock(cfg.dec_embed_dim, cfg.dec_num_heads, cfg.mlp_ratio, rope, cfg.norm_im2_in_dec)
                    for _ in range(cfg.dec_depth)
                ]
            )

        self.dec_blocks = decoder()
        self.dec_norm = layer_norm(cfg.dec_embed_dim)
        self.dec_blocks2 = decoder()
        self.downstream_head1 = make_head(cfg)
        self.downstream_head2 = make_head(cfg)

    # ------------------------------------------------------------------ stages

    def encode(self, img: torch.Tensor) -> Encoded:
        """Run the encoder on images (once per image, whatever it is paired with).

        Args:
            img: (B, 3, H, W) RGB in [-1, 1], H and W multiples of 16.

        Returns:
            The encoder tokens.
        """
        x, pos = self.patch_embed(img)
        for blk in self.enc_blocks:
            x = blk(x, pos)
        return Encoded(self.enc_norm(x), pos, (int(img.shape[2]), int(img.shape[3])))

    def decode(self, e1: Encoded, e2: Encoded) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Run the two decoders, each view attending to the other.

        Args:
            e1: View 1 (B images).
            e2: View 2 (B images).

        Returns:
            Each view's token list: encoder output, decoder block 1, …, last block (normalised).
        """
        f1, f2 = self.decoder_embed(e1.tokens), self.decoder_embed(e2.tokens)
        out1, out2 = [e1.tokens], [e2.tokens]
        for blk1, blk2 in zip(self.dec_blocks, self.dec_blocks2):
            f1, f2 = blk1(f1, f2, e1.positions, e2.positions), blk2(f2, f1, e2.positions, e1.positions)
            out1.append(f1)
            out2.append(f2)
        out1[-1], out2[-1] = self.dec_norm(out1[-1]), self.dec_norm(out2[-1])
        return out1, out2

    def predict(self, e1: Encoded, e2: Encoded) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Decoders and heads on a pair of encoded views.

        Args:
            e1: View 1 (B images), the frame of both point maps.
            e2: View 2 (B images).

        Returns:
            Each view's outputs, (B, H, W, C) maps: view 1's ``pts3d`` and ``conf``; view 2's
                ``pts3d_in_other_view`` (in view 1's frame) and ``conf``; MASt3R adds ``desc`` and ``desc_conf``.
        """
        t1, t2 = self.decode(e1, e2)
        res1 = self.downstream_head1([t.float() for t in t1], e1.hw)
        res2 = self.downstream_head2([t.float() for t in t2], e2.hw)
        res2["pts3d_in_other_view"] = res2.pop("pts3d")
        return res1, res2

    def forward(
        self, img1: torch.Tensor, img2: torch.Tensor
    ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """``predict`` of two batches of images (see ``encode`` for their form)."""
        return self.predict(self.encode(img1), self.encode(img2))
