"""LoFTR (Sun et al., CVPR 2021) through kornia, default configuration, indoor or outdoor weights.

Dense: ``extract`` runs the CNN backbone once per image (so a reference is encoded once per scene) and
``match`` runs the coarse-to-fine transformer on the pair."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from kornia.feature import LoFTR
from kornia.feature.loftr import loftr as _kloftr

from ..geometry import to_original
from ..options import Options, option
from ..runtime import resolve_device, steady_kernels
from ..weights import find_local, load_checkpoint, resolve_weights
from .base import Features, Matcher, Matches
from .published import LOFTR_WEIGHTS
from .utils import (
    autocast,
    checked_or_blank,
    image_tensor,
    inside,
    resize_for_matching,
)

__all__ = ["LoFTROptions", "LoFTRMatcher", "LOFTR_WEIGHTS", "loftr_weights_available"]


@dataclass
class LoFTROptions(Options):
    """The paper ran LoFTR's default configuration on the 540x720 images (``max_size`` 720 keeps them native)."""

    weights_kind: str = option("outdoor", choices=("outdoor", "indoor", "indoor_new"))
    weights: str | None = None  # a checkpoint file, or a folder holding loftr_<kind>.ckpt
    max_size: int | None = option(720, min=32)
    min_confidence: float = option(0.0, min=0, max=1)  # extra filter on top of LoFTR's own coarse threshold (0.2)
    mixed_precision: bool = False  # CUDA autocast; off until validated on a GPU (kornia supports half models)
    device: str | None = option(None, device=True)


def loftr_weights_available(kind: str = "outdoor", weights: str | None = None) -> bool:
    """Whether LoFTR can be built here without a download.

    Args:
        kind: ``outdoor``, ``indoor`` or ``indoor_new``.
        weights: A model folder given in place of the default one, or None.

    Returns:
        True when the weights are found locally (a weights folder, the Hugging Face cache).
    """
    return find_local(LOFTR_WEIGHTS[kind], weights) is not None


class LoFTRMatcher(Matcher):
    """``loftr-outdoor`` / ``loftr-indoor`` (``loftr`` = outdoor): kornia's LoFTR, a dense matcher (``extract``
    prepares the image, ``match`` runs the network on the pair).

    Args:
        options: ``LoFTROptions``.
        **overrides: Single options over ``options``.
    """

    def __init__(self, options: LoFTROptions | None = None, **overrides: object) -> None:
        self.options = o = LoFTROptions.build(overrides, owner="matcher 'loftr'", base=options)
        if o.weights_kind not in LOFTR_WEIGHTS:
            raise ValueError(f"unknown LoFTR weights {o.weights_kind!r}; choose from {sorted(LOFTR_WEIGHTS)}")
        self.name = f"loftr-{o.weights_kind.replace('_', '-')}"
        self.device: torch.device = resolve_device(o.device)
        path = resolve_weights(LOFTR_WEIGHTS[o.weights_kind], o.weights)
        net = LoFTR(pretrained=None, config=self._config(o.weights_kind))
        sd = load_checkpoint(path, "state_dict")
        try:
            net.load_state_dict(sd)
        except RuntimeError as e:
            raise ValueError(f"{path}: not a LoFTR checkpoint ({str(e).splitlines()[0]})") from None
        self.net = net.eval().to(self.device)

    @classmethod
    def runs_offline(cls, weights_kind: str = "outdoor", **args: object) -> bool:
        return loftr_weights_available(weights_kind)

    @staticmethod
    def _config(kind: str) -> dict[str, Any]:
        import copy

        cfg: dict[str, Any] = copy.deepcopy(_kloftr.default_cfg)
        if kind == "indoor_new":
            cfg["coarse"]["temp_bug_fix"] = True
        return cfg

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> Features:
        image, blank = checked_or_blank(image)
        if blank is not None:
            return blank
        size = (image.shape[1], image.shape[0])
        small, scale = resize_for_matching(image, self.options.max_size, multiple=8)
        x = image_tensor(small, self.device, gray=True)
        with autocast(self.device, self.options.mixed_precision), steady_kernels():
            feats = self.net.extract_features(x)
        # Dense: the candidate keypoints are the coarse cells at (8 col, 8 row) in LoFTR's frame, where pixel
        # centres sit at +0.5; ours (and kornia's) put them at integers, hence the -0.5 here and in ``match``.
        h, w = feats["coarse"].shape[-2:]
        grid = np.stack(np.meshgrid(np.arange(w) * 8.0, np.arange(h) * 8.0), -1).reshape(-1, 2) - 0.5
        return Features(to_original(grid, scale), size, {"features": feats, "scale": scale})

    @torch.inference_mode()
    def match(self, f0: Features, f1: Features) -> Matches:
        if len(f0) == 0 or len(f1) == 0:
            return Matches.empty()
        with autocast(self.device, self.options.mixed_precision), steady_kernels():
            out = self.net({"features0": f0.data["features"], "features1": f1.data["features"]})
        k0 = to_original(out["keypoints0"].float().cpu().numpy() - 0.5, f0.data["scale"])
        k1 = to_original(out["keypoints1"].float().cpu().numpy() - 0.5, f1.data["scale"])
        m = Matches(k0, k1, out["confidence"].float().cpu().numpy())
        keep = inside(m.kpts0, f0.image_size) & inside(m.kpts1, f1.image_size)
        keep &= m.scores >= self.options.min_confidence
        return m.subset(keep)
