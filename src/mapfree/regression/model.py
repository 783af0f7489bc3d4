"""The RPR network: Siamese ResUNet -> warping aggregator -> residual head + pooling -> MLP -> pose."""

from __future__ import annotations

import torch
import torch.nn as nn

from .aggregator import WarpAggregator
from .config import ModelConfig
from .encoder import PreActBlock, ResUNet, XFeatEncoder
from .params import Parameterisation, PoseOutput, build_parameterisation

__all__ = ["RPRNet"]


class RPRNet(nn.Module):
    """Two RGB images (B,3,H,W) in [0,1] -> metric pose of image 1 relative to image 0 (and error scales)."""

    def __init__(self, cfg: ModelConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or ModelConfig()
        self.param: Parameterisation = build_parameterisation(cfg)
        if cfg.encoder == "xfeat":
            self.encoder = XFeatEncoder()
            dim = XFeatEncoder.out_dim
        else:
            self.encoder = ResUNet(tuple(cfg.encoder_channels), cfg.encoder_blocks, cfg.feature_dim)
            dim = cfg.feature_dim
        self.aggregator = WarpAggregator(dim, cfg.warping, cfg.position, cfg.max_score,
                                         cfg.temperature, cfg.own_position)
        chans = [self.aggregator.out_channels, *cfg.head_channels]
        self.head = nn.Sequential(
            *[PreActBlock(chans[i], chans[i + 1], stride=2) for i in range(len(cfg.head_channels))],
            nn.BatchNorm2d(chans[-1]), nn.ReLU(inplace=True), nn.AdaptiveAvgPool2d(1), nn.Flatten(),
        )
        dims = [chans[-1], *cfg.mlp]
        layers: list[nn.Module] = []
        for i in range(len(cfg.mlp)):
            layers += [nn.Linear(dims[i], dims[i + 1]), nn.ReLU(inplace=True)]
        self.mlp = nn.Sequential(*layers)
        self.n_sigma = 2 if cfg.uncertainty else 0
        self.out = nn.Linear(dims[-1], self.param.dim + self.n_sigma)
        # Centre the outputs on the prior pose (identity rotation, forward direction).
        with torch.no_grad():
            self.out.bias.zero_()
            self.out.bias[: self.param.dim] = torch.tensor(self.param.prior())

    @property
    def frozen_encoder(self) -> bool:
        """True when no encoder weight trains (XFeat): its features of an image never change."""
        return not any(p.requires_grad for p in self.encoder.parameters())

    def forward(self, img0: torch.Tensor, img1: torch.Tensor) -> PoseOutput:
        B = img0.shape[0]
        feats = self.encoder(torch.cat([img0, img1], 0))  # shared weights: one pass over both images
        return self.from_features(feats[:B], feats[B:])

    def from_features(self, f0: torch.Tensor, f1: torch.Tensor) -> PoseOutput:
        """The pose from the two encoder feature maps (everything after the Siamese encoder)."""
        x = self.out(self.mlp(self.head(self.aggregator(f0, f1))))
        # Decoding (Gram–Schmidt, SVD, bins) runs in float32 even under mixed precision.
        with torch.autocast(device_type=x.device.type, enabled=False):
            x = x.float()
            out = self.param.decode(x[:, : self.param.dim])
            if self.n_sigma:
                out.log_sigma = x[:, self.param.dim:]
        return out
