"""DUNE-MASt3R (NAVER LABS Europe, CVPR 2025): MASt3R's ViT-B decoders and heads at patch 14 on a DUNE encoder.

DUNE is a DINOv2-style ViT/14 (a class token, 4 register tokens, LayerScale, a learned position embedding
resized to the input's patch grid) distilled from DINOv2, MASt3R and Multi-HMR. The public class
(``AsymmetricMASt3RWithDUNEBackbone``) re-normalises the [-1, 1] images to ImageNet statistics, runs the DUNE
blocks, drops the class and register tokens (DUNE's own final norm is not applied), normalises with its own
LayerNorm (eps 1e-5) and hands the tokens to MASt3R's decoders and heads, built at patch 14 (the DPT's last
upsampling scaled by 14/16). Portrait images go through as they are (``landscape_only=False``).

``DuneMast3rModel`` has the two stages of ``AsymmetricModel`` (``encode``, ``predict``), so the pair engine,
its caches, the matcher and the depth source are the MASt3R ones. Parameter names are the public state dict's
(``imagenet_mean``, ``dune_backbone.*``, ``norm.*``, ``mast3r.*``), so the published files load strictly.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import nn

from .config import ModelConfig
from .dino import DinoBlock, DinoPatchEmbed, resize_position_embedding
from .model import AsymmetricModel, Encoded
from .rope import patch_positions

__all__ = ["DuneShape", "DuneEncoder", "DuneMast3rModel", "IMAGENET_MEAN", "IMAGENET_STD"]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class DuneShape:
    """The architecture of a DUNE encoder, as its state dict shows it (heads come from its arguments).

    Attributes:
        dim: Token width.
        depth: Blocks (all in one chunk, as the public class iterates ``blocks[0]``).
        heads: Attention heads.
        patch: Patch side, pixels.
        grid: Side of the stored position-embedding grid (image_size / patch: 32 for 448 at 14).
        registers: Register tokens.
        mlp_hidden: Hidden width of the MLPs.
    """

    dim: int
    depth: int
    heads: int
    patch: int
    grid: int
    registers: int
    mlp_hidden: int

    @classmethod
    def from_state_dict(cls, sd: Mapping[str, torch.Tensor], heads: int, source: str) -> DuneShape:
        """The shape of an encoder state dict (keys without a prefix: ``pos_embed``, ``blocks.0.I.*``, …).

        Args:
            sd: The encoder's tensors.
            heads: Its attention heads (not visible in the tensors).
            source: The file, named in errors.

        Returns:
            The shape.

        Raises:
            ValueError: Not a DUNE encoder, more or fewer than one block chunk, a grid that is not square, or a
                width that the heads do not divide (the message names the file and what is off).
        """
        try:
            proj, pos = sd["patch_embed.proj.weight"], sd["pos_embed"]
            hidden = int(sd["blocks.0.0.mlp.fc1.weight"].shape[0])
        except KeyError as e:
            raise ValueError(f"{source}: not a DUNE encoder state dict (no {e.args[0]!r})") from None
        dim, patch = int(proj.shape[0]), int(proj.shape[-1])
        chunks = {m.group(1) for k in sd if (m := re.match(r"blocks\.(\d+)\.", k))}
        if chunks != {"0"}:
            raise ValueError(
                f"{source}: encoder blocks in chunks {sorted(chunks)}; the DUNE-MASt3R class runs one chunk "
                f"(blocks.0.*)"
            )
        blocks = {int(m.group(1)) for k in sd if (m := re.match(r"blocks\.0\.(\d+)\.", k))}
        depth = len(blocks)
        if blocks != set(range(depth)):
            raise ValueError(f"{source}: encoder block indices {sorted(blocks)[:5]}... are not 0..{depth - 1}")
        grid = math.isqrt(int(pos.shape[1]) - 1)
        if grid * grid != int(pos.shape[1]) - 1:
            raise ValueError(f"{source}: position embedding {tuple(pos.shape)} is not a square grid + class token")
        if heads <= 0 or dim % heads:
            raise ValueError(f"{source}: {heads} attention heads do not divide the encoder width {dim}")
        reg = sd.get("register_tokens")
        return cls(dim, depth, heads, patch, grid, int(reg.shape[1]) if reg is not None else 0, hidden)


class DuneEncoder(nn.Module):
    """DUNE's ViT (``dune_backbone.*`` in a DUNE-MASt3R file; ``encoder.*`` in a DUNE encoder file).

    Args:
        shape: The architecture.
    """

    def __init__(self, shape: DuneShape) -> None:
        super().__init__()
        self.shape = shape
        self.cls_token = nn.Parameter(torch.zeros(1, 1, shape.dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, shape.grid**2 + 1, shape.dim))
        if shape.registers:
            self.register_tokens = nn.Parameter(torch.zeros(1, shape.registers, shape.dim))
        self.mask_token = nn.Parameter(torch.zeros(1, shape.dim))  # training only; kept for the keys
        self.patch_embed = DinoPatchEmbed(shape.patch, shape.dim)
        chunk = nn.ModuleList([DinoBlock(shape.dim, shape.heads, shape.mlp_hidden) for _ in range(shape.depth)])
        self.blocks = nn.ModuleList([chunk])  # one block chunk: the keys are blocks.0.I.*
        self.norm = nn.LayerNorm(shape.dim, eps=1e-6)  # DUNE's own final norm: stored, never applied here

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Patch tokens after the last block, class and register tokens dropped, not normalised.

        Args:
            x: (B, 3, H, W) ImageNet-normalised RGB, H and W multiples of the patch.

        Returns:
            (B, (H/p)·(W/p), dim), row-major over the patch grid.
        """
        b, _, h, w = x.shape
        p = self.shape.patch
        if h % p or w % p:
            raise ValueError(f"image size {w}x{h} is not a multiple of the patch size {p}")
        t = self.patch_embed(x)
        t = torch.cat((self.cls_token.expand(b, -1, -1).to(t.dtype), t), dim=1)
        t = t + resize_position_embedding(self.pos_embed, h // p, w // p, t.dtype)
        if self.shape.registers:
            t = torch.cat((t[:, :1], self.register_tokens.expand(b, -1, -1).to(t.dtype), t[:, 1:]), dim=1)
        chunk = self.blocks[0]
        assert isinstance(chunk, nn.ModuleList)
        for blk in chunk:
            t = blk(t)
        return t[:, 1 + self.shape.registers :]


class DuneMast3rModel(nn.Module):
    """DUNE encoder + LayerNorm + MASt3R decoders and heads at patch 14 (``AsymmetricMASt3RWithDUNEBackbone``).

    Args:
        cfg: The MASt3R part's architecture (the file's ``mast3r_model_str`` at patch 14).
        shape: The DUNE encoder's architecture.
    """

    #: The public recipe's loader (``load_images(..., square_ok=True)``) keeps a square image square.
    square_ok = True

    def __init__(self, cfg: ModelConfig, shape: DuneShape) -> None:
        super().__init__()
        if cfg.enc_embed_dim != shape.dim:
            raise ValueError(f"DUNE encoder width {shape.dim} does not fit a decoder built for {cfg.enc_embed_dim}")
        if cfg.patch_size != shape.patch:
            raise ValueError(f"DUNE encoder patch {shape.patch} differs from the heads' patch {cfg.patch_size}")
        self.imagenet_mean: torch.Tensor
        self.imagenet_std: torch.Tensor
        self.register_buffer("imagenet_mean", torch.tensor(IMAGENET_MEAN).reshape(1, 3, 1, 1))
        self.register_buffer("imagenet_std", torch.tensor(IMAGENET_STD).reshape(1, 3, 1, 1))
        self.dune_backbone = DuneEncoder(shape)
        self.norm = nn.LayerNorm(shape.dim)  # the class's own, eps 1e-5 (replaces DUNE's final norm)
        self.mast3r = AsymmetricModel(cfg)

    @property
    def cfg(self) -> ModelConfig:
        """The MASt3R part's architecture (descriptor head, patch 14)."""
        return self.mast3r.cfg

    def features(self, img: torch.Tensor) -> torch.Tensor:
        """DUNE's patch tokens before ``norm`` (the public ``_encode_image_pairs`` output).

        Args:
            img: (B, 3, H, W) RGB in [-1, 1], H and W multiples of 14.

        Returns:
            (B, (H/14)·(W/14), E).
        """
        x = (img * 0.5 + 0.5 - self.imagenet_mean) / self.imagenet_std
        return self.dune_backbone(x)

    def encode(self, img: torch.Tensor) -> Encoded:
        """The encoder stage (see ``AsymmetricModel.encode``): DUNE, then the LayerNorm.

        Args:
            img: (B, 3, H, W) RGB in [-1, 1], H and W multiples of 14.

        Returns:
            The tokens, their (row, col) patch positions and the input size.
        """
        b, _, h, w = img.shape
        p = self.dune_backbone.shape.patch
        tokens = self.norm(self.features(img))
        return Encoded(tokens, patch_positions(b, h // p, w // p, img.device), (int(h), int(w)))

    def predict(self, e1: Encoded, e2: Encoded) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """MASt3R's decoders and heads on a pair of encoded views (see ``AsymmetricModel.predict``)."""
        return self.mast3r.predict(e1, e2)

    def forward(
        self, img1: torch.Tensor, img2: torch.Tensor
    ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """``predict`` of two batches of images (see ``encode`` for their form)."""
        return self.predict(self.encode(img1), self.encode(img2))
