"""The MicKey network: DINOv2 features -> per-cell keypoint, depth, score and descriptor; two images' descriptors
-> the dual-softmax matching matrix with a learned dustbin; and the final scores MicKey's solver samples from.

Images are processed independently (a reference's output is reused for every query); only the matching matrix
depends on the pair. Keypoints are ``(offset + cell) * 14`` in the pixels of the network input (540x720 by
default), with pixel centres at integers as in the public code's intrinsics scaling.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .config import MickeyConfig
from .dinov2 import DinoV2, ViTShape
from .heads import DepthHead, DescriptorHead, OffsetHead, ScoreHead

__all__ = ["MickeyNet", "Keypoints"]


@dataclass
class Keypoints:
    """A batch of images through the network: one keypoint per cell of a rows x cols grid, row-major.

    Attributes:
        xy: (B, N, 2) keypoint x, y in network-input pixels.
        depth: (B, N) depth along the optical axis, metres.
        score: (B, N) keypoint scores.
        desc: (B, N, D) descriptors.
        grid: (rows, cols) of the cells, N = rows * cols.
    """

    xy: torch.Tensor  # (B, N, 2) x, y in network-input pixels
    depth: torch.Tensor  # (B, N) metres along the optical axis
    score: torch.Tensor  # (B, N)
    desc: torch.Tensor  # (B, N, D)
    grid: tuple[int, int]  # (rows, cols)

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def item(self, i: int) -> Keypoints:
        """One image of the batch, as a batch of one.

        Args:
            i: Index in the batch.

        Returns:
            Its keypoints.
        """
        return Keypoints(
            self.xy[i : i + 1], self.depth[i : i + 1], self.score[i : i + 1], self.desc[i : i + 1], self.grid
        )


class MickeyNet(nn.Module):
    """The MicKey network: metric keypoints from a frozen DINOv2, matched by a dual softmax.

    Module names: ``backbone`` (the DINOv2 file's keys), the four heads and ``dustbin_score`` (the published
    checkpoint's, without its ``compute_matches.extractor.`` / ``compute_matches.matcher.matching_mat.`` prefixes).

    Args:
        cfg: The configuration.
        vit: The DINOv2 backbone's shape (read from its weight file).
    """

    def __init__(self, cfg: MickeyConfig, vit: ViTShape) -> None:
        super().__init__()
        self.cfg, self.vit = cfg, vit
        self.backbone = DinoV2(vit)
        self.depth_head = DepthHead(vit.dim, cfg)
        self.det_offset = OffsetHead(vit.dim, cfg)
        self.dsc_head = DescriptorHead(vit.dim, cfg)
        self.det_head = ScoreHead(vit.dim, cfg)
        if cfg.dustbin:
            self.dustbin_score = nn.Parameter(torch.tensor(1.0))
        self.backbone_dtype = torch.float32

    def half_backbone(self, on: bool) -> MickeyNet:
        """Run DINOv2 in float16 (as the published config does on a GPU) or float32; the heads stay float32.

        Args:
            on: float16 when True.

        Returns:
            This network.
        """
        self.backbone_dtype = torch.float16 if on else torch.float32
        self.backbone.to(self.backbone_dtype)
        return self

    def extract(self, images: torch.Tensor) -> Keypoints:
        """Keypoints of images, each image on its own (a reference's output serves every query).

        Args:
            images: (B, 3, H, W) RGB in [0, 1]; cropped at the bottom and right to multiples of the patch (14).

        Returns:
            One keypoint per 14 x 14 cell of each image.
        """
        p = self.vit.patch
        b, _, h, w = images.shape
        rows, cols = h // p, w // p
        x = images[:, :, : rows * p, : cols * p]
        feats = self.backbone(x.to(self.backbone_dtype)).float()
        scores = self.det_head(feats)
        offsets = self.det_offset(feats)
        depths = self.depth_head(feats)
        descs = self.dsc_head(feats)
        gy, gx = torch.meshgrid(torch.arange(rows, device=x.device), torch.arange(cols, device=x.device), indexing="ij")
        cells = torch.stack((gx, gy)).to(offsets.dtype)  # (2, rows, cols): x = column, y = row
        xy = ((offsets + cells) * p).flatten(2).transpose(1, 2)
        return Keypoints(xy, depths.flatten(1), scores.flatten(1), descs.flatten(2).transpose(1, 2), (rows, cols))

    def matching_matrix(self, desc0: torch.Tensor, desc1: torch.Tensor) -> torch.Tensor:
        """Dual softmax of the descriptor similarities over the temperature, with the learned dustbin.

        Args:
            desc0: (B, N0, D) descriptors of image 0.
            desc1: (B, N1, D) descriptors of image 1.

        Returns:
            (B, N0, N1) matching probabilities (the dustbin row and column dropped).
        """
        s = desc0 @ desc1.transpose(1, 2) / self.cfg.temperature
        if not self.cfg.dustbin:
            return F.softmax(s, 1) * F.softmax(s, 2)
        b, m, n = s.shape
        bin_ = self.dustbin_score.to(s.dtype)
        full = torch.cat(
            [torch.cat([s, bin_.expand(b, m, 1)], -1), torch.cat([bin_.expand(b, 1, n), bin_.expand(b, 1, 1)], -1)], 1
        )
        return (F.softmax(full, 1) * F.softmax(full, 2))[:, :-1, :-1]

    def scores(self, k0: Keypoints, k1: Keypoints) -> tuple[torch.Tensor, torch.Tensor]:
        """Match two images' keypoints: the matching matrix and the final scores MicKey's solver samples from.

        Args:
            k0: Keypoints of image 0; a batch of one is matched against every image of ``k1`` (the reference
                against many queries).
            k1: Keypoints of image 1.

        Returns:
            The (B, N0, N1) matching matrix and the (B, N0, N1) final scores (matching matrix times
                ``score0 score1^T``).
        """
        d0, s0 = k0.desc, k0.score
        if len(k0) == 1 and len(k1) > 1:
            d0, s0 = d0.expand(len(k1), -1, -1), s0.expand(len(k1), -1)
        match = self.matching_matrix(d0, k1.desc)
        return match, match * (s0[:, :, None] * k1.score[:, None, :])
