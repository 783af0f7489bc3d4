"""The RPR network of the public Map-free release: Siamese encoder -> aggregator -> pose head (residual blocks,
pooling or flattening, MLP, decoding), plus our optional uncertainty head for the submission confidence."""

from __future__ import annotations

import torch
import torch.nn as nn

from .aggregator import build_aggregator
from .config import ModelConfig
from .encoder import PreActBlock, ResUNet, XFeatEncoder, conv_out
from .params import Parameterisation, PoseOutput, build_parameterisation

__all__ = ["RPRNet", "PoseHead"]


def _mlp(dims: list[int]) -> nn.Linear | nn.Sequential:
    """Linear layers with ReLU between them; a single ``Linear`` when there is no hidden layer (public layout)."""
    if len(dims) == 2:
        return nn.Linear(dims[0], dims[1])
    layers: list[nn.Module] = []
    for i in range(len(dims) - 1):
        layers.append(nn.Linear(dims[i], dims[i + 1]))
        if i < len(dims) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class PoseHead(nn.Module):
    """Stride-2 pre-activation residual blocks, global average pooling (or flattening of a fixed-size map),
    an MLP to the parameterisation's output vector, and its decoding (public ``DeepResBlock`` heads)."""

    def __init__(
        self,
        cin: int,
        channels: tuple[int, ...],
        mlp: tuple[int, ...],
        param: Parameterisation,
        avg_pool: bool = True,
        grid: tuple[int, int] | None = None,
    ):
        super().__init__()
        chans = [cin, *channels]
        for i in range(len(channels)):
            setattr(self, f"resblock{i + 1}", PreActBlock(chans[i], chans[i + 1], stride=2))
        self.n_blocks, self.avg_pool, self.param = len(channels), avg_pool, param
        if avg_pool:
            self.feature_dim = chans[-1]
        else:
            if grid is None:
                raise ValueError("a head without average pooling needs the input size (data.image_size)")
            h, w = grid
            for _ in channels:
                h, w = conv_out(h), conv_out(w)
            self.feature_dim = chans[-1] * h * w
        self.mlp = _mlp([self.feature_dim, *mlp, param.dim])
        last = self.mlp if isinstance(self.mlp, nn.Linear) else self.mlp[-1]
        assert isinstance(last, nn.Linear)  # _mlp ends with one
        with torch.no_grad():  # start at the prior pose (identity rotation, forward direction) when trained anew
            last.bias.copy_(torch.tensor(param.prior()))

    def features(self, volume: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) aggregated volume -> (B, feature_dim)."""
        x = volume
        for i in range(self.n_blocks):
            x = getattr(self, f"resblock{i + 1}")(x)
        if self.avg_pool:
            x = x.mean(dim=2, keepdim=True).mean(dim=3, keepdim=True)
        return x.flatten(1)

    def decode(self, feats: torch.Tensor) -> PoseOutput:
        x = self.mlp(feats)
        # Decoding (Gram–Schmidt, SVD, bins) runs in float32 even under mixed precision.
        with torch.autocast(device_type=x.device.type, enabled=False):
            return self.param.decode(x.float())


class RPRNet(nn.Module):
    """The regression network: two RGB images -> metric pose of image 1 relative to image 0 (and error scales).

    Parameter names match the public checkpoints (``encoder.*``, ``aggregator.*``, ``head.*``); the uncertainty
    head (``uncertainty.*``, beyond the paper) reads the head's pooled features.

    Args:
        cfg: The model section of the configuration; the defaults when None.
        input_size: (W, H) of the input, pixels; needed only by heads without average pooling (their MLP sees
            the flattened map).
    """

    def __init__(self, cfg: ModelConfig | None = None, input_size: tuple[int, int] | None = None):
        super().__init__()
        self.cfg = cfg = cfg or ModelConfig()
        self.param: Parameterisation = build_parameterisation(cfg)
        if cfg.encoder == "xfeat":
            self.encoder: nn.Module = XFeatEncoder()
            dim = XFeatEncoder.out_dim
        else:
            self.encoder = ResUNet(tuple(cfg.encoder_channels), cfg.encoder_blocks, cfg.feature_dim)
            dim = cfg.feature_dim
        self.aggregator = build_aggregator(
            cfg.aggregator, dim, cfg.position, cfg.max_score, cfg.temperature, cfg.own_position
        )
        grid = None if input_size is None else self.encoder.output_size(int(input_size[1]), int(input_size[0]))
        self.head = PoseHead(
            self.aggregator.out_channels, tuple(cfg.head_channels), tuple(cfg.mlp), self.param, cfg.avg_pool, grid
        )
        if cfg.uncertainty:
            self.uncertainty = nn.Sequential(nn.Linear(self.head.feature_dim, 64), nn.ReLU(), nn.Linear(64, 2))

    @property
    def frozen_encoder(self) -> bool:
        """True when no encoder weight trains (XFeat, or ``train.freeze``): its features of an image never change."""
        return not any(p.requires_grad for p in self.encoder.parameters())

    def forward(self, img0: torch.Tensor, img1: torch.Tensor) -> PoseOutput:
        """Pose of image 1 relative to image 0 (``X_1 = R X_0 + t``).

        Args:
            img0: (B, 3, H, W) RGB in [0, 1], the reference.
            img1: (B, 3, H, W) RGB in [0, 1], the query.

        Returns:
            R (B, 3, 3), t (B, 3) in metres, and ``log_sigma`` with the uncertainty head.
        """
        # Shared weights, one call per image set (as the public code: BatchNorm batch statistics per image set).
        return self.from_features(self.encoder(img0), self.encoder(img1))

    def from_features(self, f0: torch.Tensor, f1: torch.Tensor) -> PoseOutput:
        """The pose from the two encoder feature maps (everything after the Siamese encoder).

        Args:
            f0: (B, C, h, w) encoder features of the reference.
            f1: (B, C, h, w) encoder features of the query.

        Returns:
            The decoded pose (see ``forward``).
        """
        feats = self.head.features(self.aggregator(f0, f1))
        out = self.head.decode(feats)
        if self.cfg.uncertainty:
            with torch.autocast(device_type=feats.device.type, enabled=False):
                out.log_sigma = self.uncertainty(feats.float())
        return out
