"""The DPT head of DUSt3R/MASt3R: four decoder layers reassembled at 1/4..1/32 scale, fused coarse to fine,
upsampled to full resolution; ``num_channels`` output maps (x, y, z, confidence)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["DPTHead", "dpt_hooks"]

#: Channels of the four reassembled layers, and of the fused features (the public configuration).
LAYER_DIMS = (96, 192, 384, 768)
FEATURE_DIM = 256


def dpt_hooks(dec_depth: int) -> list[int]:
    """Which entries of [encoder output, decoder block 1..dec_depth] feed the head."""
    return [0, dec_depth * 2 // 4, dec_depth * 3 // 4, dec_depth]


def _up2(x: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)


class _ResidualConv(nn.Module):
    """x + conv(relu(conv(relu(x))))."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(dim, dim, 3, padding=1)
        self.conv2 = nn.Conv2d(dim, dim, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class _Fusion(nn.Module):
    """Adds the refined skip connection (if any), refines, upsamples x2 and projects (1x1)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.resConfUnit1 = _ResidualConv(dim)
        self.resConfUnit2 = _ResidualConv(dim)
        self.out_conv = nn.Conv2d(dim, dim, 1)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None) -> torch.Tensor:
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        return self.out_conv(_up2(self.resConfUnit2(x)))


class _Scratch(nn.Module):
    """Per-layer 3x3 projections to the feature width (registered twice, as ``layerK_rn`` and ``layer_rn.K-1``,
    which is how the published state dicts store them) and the four fusion blocks."""

    def __init__(self, dims: Sequence[int], feature_dim: int) -> None:
        super().__init__()
        for i, d in enumerate(dims, 1):
            setattr(self, f"layer{i}_rn", nn.Conv2d(d, feature_dim, 3, padding=1, bias=False))
        self.layer_rn = nn.ModuleList([getattr(self, f"layer{i}_rn") for i in range(1, len(dims) + 1)])
        self.refinenet1 = _Fusion(feature_dim)
        self.refinenet2 = _Fusion(feature_dim)
        self.refinenet3 = _Fusion(feature_dim)
        self.refinenet4 = _Fusion(feature_dim)


def _reassemble(dim_in: int, dim: int, level: int) -> nn.Sequential:
    """1x1 projection, then resampling to the level's scale: x4 and x2 transposed convs, identity, stride-2 conv."""
    proj = nn.Conv2d(dim_in, dim, 1)
    if level == 0:
        return nn.Sequential(proj, nn.ConvTranspose2d(dim, dim, 4, stride=4))
    if level == 1:
        return nn.Sequential(proj, nn.ConvTranspose2d(dim, dim, 2, stride=2))
    if level == 2:
        return nn.Sequential(proj)
    return nn.Sequential(proj, nn.Conv2d(dim, dim, 3, stride=2, padding=1))


class _DPT(nn.Module):
    """The adapter itself (``downstream_headN.dpt`` in a checkpoint)."""

    def __init__(self, dims_in: Sequence[int], hooks: Sequence[int], num_channels: int, patch_size: int) -> None:
        super().__init__()
        self.hooks = list(hooks)
        self.patch_size = patch_size
        self.scratch = _Scratch(LAYER_DIMS, FEATURE_DIM)
        self.act_postprocess = nn.ModuleList([_reassemble(d, LAYER_DIMS[i], i) for i, d in enumerate(dims_in)])
        half = FEATURE_DIM // 2
        self.head = nn.Sequential(
            nn.Conv2d(FEATURE_DIM, half, 3, padding=1),
            # x2 at patch 16; DUNE's patch-14 heads scale it by 14/16, so 8 * (H/14) rows come out H rows
            nn.Upsample(scale_factor=2 * patch_size / 16, mode="bilinear", align_corners=True),
            nn.Conv2d(half, half, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(half, num_channels, 1),
        )

    def forward(self, tokens: Sequence[torch.Tensor], hw: tuple[int, int]) -> torch.Tensor:
        rows, cols = hw[0] // self.patch_size, hw[1] // self.patch_size
        maps = []
        for i, hook in enumerate(self.hooks):
            t = tokens[hook]
            t = t.transpose(1, 2).reshape(t.shape[0], t.shape[2], rows, cols)
            maps.append(self.scratch.layer_rn[i](self.act_postprocess[i](t)))
        s = self.scratch
        x = s.refinenet4(maps[3])[:, :, : maps[2].shape[2], : maps[2].shape[3]]  # odd grids: crop the x2 upsample
        x = s.refinenet3(x, maps[2])
        x = s.refinenet2(x, maps[1])
        x = s.refinenet1(x, maps[0])
        return self.head(x)


class DPTHead(nn.Module):
    """Wraps ``_DPT`` under the attribute name the checkpoints use."""

    def __init__(self, dims_in: Sequence[int], hooks: Sequence[int], num_channels: int, patch_size: int) -> None:
        super().__init__()
        self.dpt = _DPT(dims_in, hooks, num_channels, patch_size)
