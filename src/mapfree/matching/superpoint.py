"""SuperPoint (DeTone et al., 2018) keypoints and descriptors; kornia 0.9 has LightGlue weights for it but no
extractor. Layer names follow the released ``superpoint_v1.pth`` so that file loads as is."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["SuperPoint"]


def _conv(cin: int, cout: int, k: int = 3) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, kernel_size=k, stride=1, padding=k // 2)


class SuperPoint(nn.Module):
    """SuperPoint: grey image (B, 1, H, W) in [0, 1], H and W multiples of 8 -> per image keypoints (x, y), scores and
    descriptors.

    Args:
        max_keypoints: Keypoints per image (the best scores; <= 0: all).
        detection_threshold: Keypoints of a lower score are dropped.
        nms_radius: Non-maximum suppression radius, pixels.
        remove_borders: Pixels at each border without keypoints.
        descriptor_dim: Descriptor size.
    """

    def __init__(
        self,
        max_keypoints: int = 2048,
        detection_threshold: float = 0.0005,
        nms_radius: int = 4,
        remove_borders: int = 4,
        descriptor_dim: int = 256,
    ) -> None:
        super().__init__()
        self.max_keypoints = max_keypoints
        self.detection_threshold = detection_threshold
        self.nms_radius = nms_radius
        self.remove_borders = remove_borders
        self.conv1a, self.conv1b = _conv(1, 64), _conv(64, 64)
        self.conv2a, self.conv2b = _conv(64, 64), _conv(64, 64)
        self.conv3a, self.conv3b = _conv(64, 128), _conv(128, 128)
        self.conv4a, self.conv4b = _conv(128, 128), _conv(128, 128)
        self.convPa, self.convPb = _conv(128, 256), _conv(256, 65, 1)  # 64 cells of an 8x8 block + "no point"
        self.convDa, self.convDb = _conv(128, 256), _conv(256, descriptor_dim, 1)

    def encode(self, image: torch.Tensor) -> torch.Tensor:
        """The shared encoder.

        Args:
            image: (B, 1, H, W) grey in [0, 1].

        Returns:
            (B, 128, H/8, W/8) features.
        """
        x = image
        blocks = [(self.conv1a, self.conv1b), (self.conv2a, self.conv2b), (self.conv3a, self.conv3b)]
        for i, (a, b) in enumerate([*blocks, (self.conv4a, self.conv4b)]):
            x = F.relu(b(F.relu(a(x))))
            if i < 3:
                x = F.max_pool2d(x, 2, 2)
        return x

    def score_map(self, x: torch.Tensor) -> torch.Tensor:
        """Keypoint probability at full resolution.

        Args:
            x: (B, 128, H/8, W/8) encoder features.

        Returns:
            (B, H, W) probabilities.
        """
        logits = self.convPb(F.relu(self.convPa(x)))
        prob = logits.softmax(1)[:, :-1]
        return F.pixel_shuffle(prob, 8)[:, 0]

    def _nms(self, scores: torch.Tensor) -> torch.Tensor:
        r = self.nms_radius
        peak = F.max_pool2d(scores[:, None], 2 * r + 1, stride=1, padding=r)[:, 0]
        return torch.where(scores == peak, scores, torch.zeros_like(scores))

    def forward(self, image: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        """Keypoints, scores and descriptors of a batch.

        Args:
            image: (B, 1, H, W) grey or (B, 3, H, W) RGB in [0, 1].

        Returns:
            Per image: ``keypoints`` (N, 2) x, y pixels, ``scores`` (N,), ``descriptors`` (N, D) unit vectors.
        """
        if image.shape[1] == 3:
            image = (image * image.new_tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)).sum(1, keepdim=True)
        x = self.encode(image)
        scores = self._nms(self.score_map(x))
        b = self.remove_borders
        if b > 0:
            scores[:, :b], scores[:, -b:], scores[:, :, :b], scores[:, :, -b:] = 0, 0, 0, 0
        dense = F.normalize(self.convDb(F.relu(self.convDa(x))), dim=1)
        h, w = image.shape[-2:]
        out = []
        for i in range(len(image)):
            yx = torch.nonzero(scores[i] > self.detection_threshold)
            s = scores[i][yx[:, 0], yx[:, 1]]
            if self.max_keypoints > 0 and len(s) > self.max_keypoints:
                s, top = s.topk(self.max_keypoints)
                yx = yx[top]
            kpts = yx.flip(1).float()
            # the released models sample the 1/8 map with this normalisation (not exactly the cell centres)
            grid = (kpts - 3.5) / kpts.new_tensor([w - 4.5, h - 4.5]) * 2 - 1
            d = F.grid_sample(dense[i : i + 1], grid[None, None], mode="bilinear", align_corners=True)[0, :, 0].t()
            out.append({"keypoints": kpts, "scores": s, "descriptors": F.normalize(d, dim=1)})
        return out
