"""What the pair engine needs of a network, whatever runs it: the two stages of the MASt3R family.

``AsymmetricModel`` (PyTorch) and ``OnnxPairNetwork`` (two exported graphs run by onnxruntime) both satisfy
``PairNetwork``; ``engine.PairEngine`` holds either, so the reference's encoding is cached per anchor the same way
on both backends.
"""

from __future__ import annotations

from typing import Protocol

import torch

from .model import Encoded

__all__ = ["BACKENDS", "PairNetwork"]

#: The ways the family's networks can be run: our PyTorch port, or exported graphs in onnxruntime.
BACKENDS = ("torch", "onnxruntime")


class PairNetwork(Protocol):
    """A two-view network split in its two stages (encoder; decoders and heads)."""

    @property
    def has_descriptors(self) -> bool:
        """Whether ``predict`` returns MASt3R's ``desc`` and ``desc_conf``."""
        ...

    def encode(self, img: torch.Tensor) -> Encoded:
        """Encoder tokens of (B, 3, H, W) images in [-1, 1] (see ``AsymmetricModel.encode``)."""
        ...

    def predict(self, e1: Encoded, e2: Encoded) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Each view's (B, H, W, C) output maps for a batch of encoded pairs (see ``AsymmetricModel.predict``)."""
        ...
