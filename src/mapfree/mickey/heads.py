"""MicKey's four heads on the DINOv2 feature map: score, keypoint offset, depth and descriptor.

Each head is four residual blocks (3x3 convolutions with batch norm, a 1x1 shortcut where the width changes) with
LoFTR's linear-attention self-attention (three layers, eight heads, 128 channels, a sine position encoding added
first) between the third and the fourth block, then its own output:

- score: a 1x1 convolution, minus the map's mean, ``exp(. / 100)``, a 3-cell border set to zero, divided by the
  sum (a softmax over the map); a sigmoid instead when the config says so;
- offset: a 1x1 convolution to (x, y), sigmoid: where in its 14-pixel cell the keypoint lies;
- depth: a 1x1 convolution (``max_depth * sigmoid`` when the config says so): metric depth of the keypoint;
- descriptor: the fourth block without its last ReLU, L2-normalised.

The attention layers and the position encoding are kornia's LoFTR modules: MicKey's are LoFTR's.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.feature.loftr.loftr_module.transformer import LoFTREncoderLayer
from kornia.feature.loftr.utils.position_encoding import PositionEncodingSine
from torch import nn

from .config import ATTENTION_DIM, MickeyConfig

__all__ = [
    "ResBlock",
    "SelfAttentionStack",
    "ScoreHead",
    "OffsetHead",
    "DepthHead",
    "DescriptorHead",
    "SCORE_BORDER",
    "SCORE_TEMPERATURE",
]

#: Cells at each side of the score map that never hold a keypoint.
SCORE_BORDER = 3
#: Temperature of the score softmax.
SCORE_TEMPERATURE = 100.0


class ResBlock(nn.Module):
    """conv3x3-BN-ReLU-conv3x3-BN plus the (1x1-projected) input, then ReLU unless told otherwise."""

    def __init__(self, cin: int, cout: int, bn: bool = True) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout) if bn else nn.Identity()
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout) if bn else nn.Identity()
        self.shortcut = nn.Sequential(nn.Conv2d(cin, cout, 1, bias=False)) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, relu: bool = True) -> torch.Tensor:
        out = self.bn2(self.conv2(F.relu(self.bn1(self.conv1(x)))))
        out = out + self.shortcut(x)
        return F.relu(out) if relu else out


class SelfAttentionStack(nn.Module):
    """Three LoFTR linear self-attention layers over the map's cells, after the sine position encoding."""

    def __init__(self, dim: int = ATTENTION_DIM, layers: int = 3, heads: int = 8, pos_encoding: bool = True) -> None:
        super().__init__()
        self.layers = nn.ModuleList([LoFTREncoderLayer(dim, heads, "linear") for _ in range(layers)])
        self.dim, self.pos_encoding = dim, pos_encoding
        # Encodings per (rows, cols, device, dtype): computed on first use, so that a network built on the meta
        # device (to load a checkpoint without a second copy) needs no buffer materialised.
        self._encodings: dict[tuple, torch.Tensor] = {}

    def encoding(self, h: int, w: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
        """(1, dim, h, w): LoFTR's sine encoding (its fixed form), the same values as its 256x256 table's corner."""
        key = (h, w, device, dtype)
        if key not in self._encodings:
            pe = PositionEncodingSine(self.dim, max_shape=(h, w), temp_bug_fix=True).pe
            self._encodings[key] = pe.to(device=device, dtype=dtype)
        return self._encodings[key]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        if self.pos_encoding:
            x = x + self.encoding(h, w, x.device, x.dtype)
        t = x.flatten(2).transpose(1, 2)
        for layer in self.layers:
            t = layer(t, t)
        return t.transpose(1, 2).reshape(b, c, h, w)


class _Trunk(nn.Module):
    """resblock1..3, the attention layers, resblock4: what every head shares (not its weights)."""

    def __init__(self, cin: int, dims: tuple[int, ...], bn: bool, pos_encoding: bool) -> None:
        super().__init__()
        self.resblock1 = ResBlock(cin, dims[0], bn)
        self.resblock2 = ResBlock(dims[0], dims[1], bn)
        self.resblock3 = ResBlock(dims[1], dims[2], bn)
        self.resblock4 = ResBlock(dims[2], dims[3], bn)
        self.att_layer = SelfAttentionStack(pos_encoding=pos_encoding)

    def trunk(self, x: torch.Tensor, last_relu: bool = True) -> torch.Tensor:
        x = self.resblock3(self.resblock2(self.resblock1(x)))
        return self.resblock4(self.att_layer(x), relu=last_relu)


def _out(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 1, bias=False)


class ScoreHead(_Trunk):
    """Keypoint score per cell, summing to 1 over the map (softmax mode). The constants the checkpoint stores
    (``eps``, ``offset_par1/2``, ``ones_kernel``) are kept as frozen parameters so that it loads strictly."""

    def __init__(self, cin: int, cfg: MickeyConfig) -> None:
        super().__init__(cin, cfg.kp_blocks, cfg.batch_norm, cfg.kp_pos_encoding)
        self.score = _out(cfg.kp_blocks[3], 1)
        self.softmax = cfg.score_softmax
        self.eps = nn.Parameter(torch.tensor(1e-16), requires_grad=False)
        self.offset_par1 = nn.Parameter(torch.tensor(0.5), requires_grad=False)
        self.offset_par2 = nn.Parameter(torch.tensor(2.0), requires_grad=False)
        self.ones_kernel = nn.Parameter(torch.ones(1, 1, 3, 3), requires_grad=False)

    @staticmethod
    def _inner(x: torch.Tensor) -> torch.Tensor:
        """``x`` with the ``SCORE_BORDER`` cells at each side set to zero."""
        mask = torch.zeros_like(x)
        b = SCORE_BORDER
        mask[:, :, b : x.shape[2] - b, b : x.shape[3] - b] = 1
        return x * mask

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = self.score(self.trunk(x))
        if not self.softmax:
            return self._inner(torch.sigmoid(s))
        s = s - (s.flatten(1).mean(-1).view(-1, 1, 1, 1) + self.eps)
        e = self._inner(torch.exp(s / SCORE_TEMPERATURE))
        return e / (e.sum(dim=(2, 3), keepdim=True) + self.eps)


class OffsetHead(_Trunk):
    """(x, y) of the keypoint inside its cell, in [0, 1]."""

    def __init__(self, cin: int, cfg: MickeyConfig) -> None:
        super().__init__(cin, cfg.kp_blocks, cfg.batch_norm, cfg.kp_pos_encoding)
        self.xy_offset = _out(cfg.kp_blocks[3], 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.xy_offset(self.trunk(x)))


class DepthHead(_Trunk):
    """Metric depth (camera z, metres) of each cell's keypoint."""

    def __init__(self, cin: int, cfg: MickeyConfig) -> None:
        super().__init__(cin, cfg.kp_blocks, cfg.batch_norm, cfg.kp_pos_encoding)
        self.depth = _out(cfg.kp_blocks[3], 1)
        self.sigmoid_max = cfg.max_depth if cfg.depth_sigmoid else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        d = self.depth(self.trunk(x))
        return d if self.sigmoid_max is None else self.sigmoid_max * torch.sigmoid(d)


class DescriptorHead(_Trunk):
    """Descriptor per cell (unit length unless the config says otherwise)."""

    def __init__(self, cin: int, cfg: MickeyConfig) -> None:
        super().__init__(cin, (*cfg.kp_blocks[:3], cfg.dsc_dim), cfg.batch_norm, cfg.dsc_pos_encoding)
        self.normalize = cfg.dsc_normalize

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        d = self.trunk(x, last_relu=False)
        return d / d.pow(2).sum(dim=1, keepdim=True).add(1e-10).sqrt() if self.normalize else d
