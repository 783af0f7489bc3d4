"""SuperPoint + SuperGlue (Sarlin et al., CVPR 2020), the paper's headline matcher, through transformers'
``SuperGlueForKeypointMatching`` with the published indoor or outdoor weights.

``extract`` runs SuperPoint once per image (a reference is described once per scene); ``match`` runs the
SuperGlue graph network and Sinkhorn on the pair. Defaults are the paper's: 1024 keypoints, keypoint threshold
0.005, NMS radius 4, 20 Sinkhorn iterations, match threshold 0.2, images matched at their native 540x720."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..geometry import to_original
from ..options import Options, option
from ..runtime import resolve_device, steady_kernels
from .base import Features, Matcher, Matches
from .hub import find_hub_model, grey_pixels, load_hub_model, transformers_classes
from .published import SUPERGLUE_MODELS
from .utils import autocast, checked_or_blank

__all__ = ["SuperGlueOptions", "SuperGlueMatcher", "SUPERGLUE_MODELS", "superglue_available"]


@dataclass
class SuperGlueOptions(Options):
    """Options of ``superglue`` / ``superglue-indoor`` (the published models' values).

    Attributes:
        weights_kind: ``outdoor`` or ``indoor``.
        weights: A model folder (config.json + model.safetensors) instead of the hub's.
        max_keypoints: SuperPoint keypoints per image.
        keypoint_threshold: SuperPoint's detection threshold.
        nms_radius: SuperPoint's non-maximum suppression radius, pixels.
        sinkhorn_iterations: Optimal-transport iterations.
        match_threshold: Matches of a lower score are dropped.
        max_size: Long side the images are matched at (None: as they are).
        mixed_precision: CUDA autocast.
        device: ``cpu``, ``cuda``; None: CUDA when available.
    """

    weights_kind: str = option("outdoor", choices=("outdoor", "indoor"))
    weights: str | None = None  # a model folder (config.json + model.safetensors) instead of the hub's
    max_keypoints: int = option(1024, min=1)
    keypoint_threshold: float = option(0.005, min=0, max=1)
    nms_radius: int = option(4, min=0)
    sinkhorn_iterations: int = option(20, min=1)
    match_threshold: float = option(0.2, min=0, max=1)
    max_size: int | None = option(720, min=16)  # long side; the dataset's 540x720 images are matched as they are
    mixed_precision: bool = False  # CUDA autocast; off until validated on a GPU
    device: str | None = option(None, device=True)


def superglue_available(kind: str = "outdoor", weights: str | None = None) -> bool:
    """Whether SuperPoint + SuperGlue can be built here without a download.

    Args:
        kind: ``outdoor`` or ``indoor``.
        weights: A model folder given in place of the default one, or None.

    Returns:
        True when the weights are found locally (a weights folder, the Hugging Face cache).
    """
    return find_hub_model(SUPERGLUE_MODELS[kind], weights) is not None


def _normalised_into(kpts: torch.Tensor, size: tuple[int, int], target: tuple[int, int]) -> torch.Tensor:
    """Keypoints of an image of ``size`` (w, h) moved so that SuperGlue's normalisation with ``target``'s size
    gives what normalising with their own size gives (centre, and 0.7 x the long side, per image)."""
    if size == target:
        return kpts
    c, s = kpts.new_tensor(size) / 2, max(size) * 0.7
    ct, st = kpts.new_tensor(target) / 2, max(target) * 0.7
    return (kpts - c) * (st / s) + ct


class SuperGlueMatcher(Matcher):
    """``superglue`` (outdoor weights) / ``superglue-indoor``: SuperPoint + SuperGlue through transformers.

    Args:
        options: ``SuperGlueOptions``.
        **overrides: Single options over ``options``.
    """

    def __init__(self, options: SuperGlueOptions | None = None, **overrides: object) -> None:
        SuperGlueConfig, SuperGlueForKeypointMatching = transformers_classes(
            "SuperGlueConfig", "SuperGlueForKeypointMatching"
        )

        self.options = o = SuperGlueOptions.build(overrides, owner="matcher 'superglue'", base=options)
        if o.weights_kind not in SUPERGLUE_MODELS:
            raise ValueError(f"unknown SuperGlue weights {o.weights_kind!r}; choose from {sorted(SUPERGLUE_MODELS)}")
        self.name = "superglue" if o.weights_kind == "outdoor" else f"superglue-{o.weights_kind}"
        self.device: torch.device = resolve_device(o.device)

        def configure(cfg: Any) -> None:
            # the configs are strict dataclasses: an int where a float belongs (e.g. from YAML "0") is refused
            cfg.sinkhorn_iterations = int(o.sinkhorn_iterations)
            cfg.matching_threshold = float(o.match_threshold)
            sp = cfg.keypoint_detector_config
            sp.max_keypoints, sp.nms_radius = int(o.max_keypoints), int(o.nms_radius)
            sp.keypoint_threshold = float(o.keypoint_threshold)

        net = load_hub_model(
            SuperGlueForKeypointMatching, SuperGlueConfig, SUPERGLUE_MODELS[o.weights_kind], o.weights, configure
        )
        self.net = net.to(self.device)

    @classmethod
    def runs_offline(cls, weights_kind: str = "outdoor", **args: object) -> bool:
        return superglue_available(weights_kind)

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> Features:
        image, blank = checked_or_blank(image)
        if blank is not None:
            return blank
        x, scale = grey_pixels(image, self.options.max_size, 1, self.device)
        h, w = x.shape[-2:]
        with autocast(self.device, self.options.mixed_precision), steady_kernels():
            det = self.net.keypoint_detector(x)
        n = int(det.mask[0].sum())
        # SuperPoint reports keypoints relative to the input size; times (w, h) they are its integer pixels.
        kp = det.keypoints[0, :n].float() * det.keypoints.new_tensor([w, h]).float()
        data = {
            "keypoints": kp,
            "scores": det.scores[0, :n].float(),
            "descriptors": det.descriptors[0, :n].float(),
            "resized": (w, h),
        }
        return Features(to_original(kp.cpu().numpy(), scale), (image.shape[1], image.shape[0]), data)

    @torch.inference_mode()
    def match(self, f0: Features, f1: Features) -> Matches:
        if len(f0) == 0 or len(f1) == 0:
            return Matches.empty()
        d0, d1 = f0.data, f1.data
        n0, n1 = len(f0), len(f1)
        n = max(n0, n1)
        w, h = d0["resized"]
        kp = torch.zeros((1, 2, n, 2), device=self.device)
        desc = torch.zeros((1, 2, n, d0["descriptors"].shape[1]), device=self.device)
        scores = torch.zeros((1, 2, n), device=self.device)
        mask = torch.zeros((1, 2, n), dtype=torch.int, device=self.device)
        kp[0, 0, :n0] = d0["keypoints"]
        kp[0, 1, :n1] = _normalised_into(d1["keypoints"], d1["resized"], d0["resized"])
        for i, (d, k) in enumerate(((d0, n0), (d1, n1))):
            desc[0, i, :k], scores[0, i, :k], mask[0, i, :k] = d["descriptors"], d["scores"], 1
        with autocast(self.device, self.options.mixed_precision), steady_kernels():
            matches, match_scores, _, _ = self.net._match_image_pair(kp, desc, scores, h, w, mask=mask)
        m0 = matches[0, 0, :n0].cpu().numpy()
        s0 = match_scores[0, 0, :n0].float().cpu().numpy()
        ok = (m0 > -1) & (m0 < n1)
        return Matches(f0.kpts[ok], f1.kpts[m0[ok]], s0[ok])
