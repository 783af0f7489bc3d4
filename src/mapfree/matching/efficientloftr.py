"""EfficientLoFTR (Wang et al., CVPR 2024), semi-dense matching, through transformers'
``EfficientLoFTRForKeypointMatching`` with the published weights.

The network is pair-conditioned from its first transformer layer, so ``extract`` only prepares the grey input
and ``match`` runs the model's networks (backbone + coarse transformer, fine feature fusion). The matching steps
after them hold no weights and are done here as the published EfficientLoFTR code does them: transformers 5.24's
forward lists the two images' matched cells in different orders (image 0's in the order of image 1's and vice
versa), which pairs the wrong cells whenever matches do not keep raster order, and its first fine stage gathers
along the wrong axis, so every match gets the window's first offset instead of its best pixel."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ..geometry import to_original
from ..options import Options, option
from ..runtime import resolve_device, steady_kernels
from .base import Features, Matcher, Matches
from .hub import find_hub_model, grey_pixels, load_hub_model, transformers_classes
from .published import EFFICIENTLOFTR_MODEL
from .utils import autocast, checked_or_blank, inside

__all__ = [
    "EfficientLoFTROptions",
    "EfficientLoFTRMatcher",
    "EFFICIENTLOFTR_MODEL",
    "efficientloftr_available",
    "mutual_pairs",
    "refine",
]

#: The backbone's coarse map is 1/8 of the input and its aggregated attention pools by 4: sides multiples of 32.
MULTIPLE = 32


@dataclass
class EfficientLoFTROptions(Options):
    """Options of ``efficientloftr``.

    Attributes:
        weights: A model folder (config.json + model.safetensors) instead of the hub's.
        max_size: Long side the images are matched at, a multiple of 32.
        match_threshold: Coarse matching threshold; None: the model's (0.2 published).
        mixed_precision: CUDA autocast.
        device: ``cpu``, ``cuda``; None: CUDA when available.
    """

    weights: str | None = None  # a model folder (config.json + model.safetensors) instead of the hub's
    max_size: int | None = option(720, min=32)  # long side, as the other matchers match the dataset's 540x720 images
    match_threshold: float | None = option(None, min=0, max=1)  # coarse threshold; None: the model's (0.2 published)
    mixed_precision: bool = False  # CUDA autocast; off until validated on a GPU
    device: str | None = option(None, device=True)


def efficientloftr_available(weights: str | None = None) -> bool:
    """Whether EfficientLoFTR can be built here without a download.

    Args:
        weights: A model folder given in place of the default one, or None.

    Returns:
        True when the weights are found locally (a weights folder, the Hugging Face cache).
    """
    return find_hub_model(EFFICIENTLOFTR_MODEL, weights) is not None


def mutual_pairs(
    conf: torch.Tensor, shape0: tuple[int, int], shape1: tuple[int, int], threshold: float, border: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mutual best cells of a coarse confidence matrix.

    Args:
        conf: (N0, N1) confidences between the cells of image 0 and image 1.
        shape0: (rows, cols) of image 0's coarse grid.
        shape1: (rows, cols) of image 1's.
        threshold: Pairs of a lower confidence are dropped.
        border: Cells this close to either grid's edge are excluded.

    Returns:
        (M,) cells of image 0, (M,) their partners in image 1 and (M,) their confidences (ties: the first column).
    """
    keep = conf > threshold
    if border > 0:

        def inner(shape: tuple[int, int]) -> torch.Tensor:
            m = torch.zeros(shape, dtype=torch.bool, device=conf.device)
            m[border:-border, border:-border] = True
            return m.flatten()

        keep &= inner(shape0)[:, None] & inner(shape1)[None, :]
    keep &= conf == conf.max(dim=1, keepdim=True).values
    keep &= conf == conf.max(dim=0, keepdim=True).values
    # Ties (a flat image region) can leave several columns in a row: keep the first, as the published code does.
    has, j = keep.max(dim=1)
    i = has.nonzero().flatten()
    j = j[i]
    return i, j, conf[i, j]


def refine(
    fine0: torch.Tensor,
    fine1: torch.Tensor,
    kp0: torch.Tensor,
    kp1: torch.Tensor,
    slice_dim: int,
    temperature: float,
    step: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """EfficientLoFTR's two fine stages for M coarse matches.

    Stage 1 moves both points to the best pixel pair of their windows (dual softmax on all but the last
    ``slice_dim`` channels); stage 2 moves image 1's point by the expectation over the 3x3 neighbourhood scored
    with the last ``slice_dim`` channels.

    Args:
        fine0: (M, W*W, C) image 0's window around each match.
        fine1: (M, (W+2)^2, C) image 1's, one pixel wider.
        kp0: (M, 2) coarse points in image 0, pixels.
        kp1: (M, 2) coarse points in image 1, pixels.
        slice_dim: Channels of the second stage.
        temperature: Softmax temperature of the second stage.
        step: Fine pixels per input pixel (1 at full resolution).

    Returns:
        The refined (M, 2) points of image 0 and of image 1, pixels.
    """
    m, ww, c = fine0.shape
    w = int(round(ww**0.5))
    a0, b0 = fine0[..., :-slice_dim], fine0[..., -slice_dim:]
    a1, b1 = fine1[..., :-slice_dim], fine1[..., -slice_dim:]
    sim = (a0 / c**0.5) @ (a1 / c**0.5).transpose(1, 2)  # (M, WW, (W+2)^2)
    conf = (sim.softmax(1) * sim.softmax(2)).reshape(m, ww, w + 2, w + 2)[..., 1:-1, 1:-1].reshape(m, ww * ww)
    best = conf.argmax(1)
    left, r = best // ww, best % ww
    # Window pixel m sits at m - W/2 + 0.5 from the coarse point (8 x cell): the frame the published models were
    # trained in (their fine-level ground truth is built on the same grid), so the output is in image pixels.
    offsets = torch.arange(w, device=fine0.device, dtype=kp0.dtype) - w // 2 + 0.5
    kp0 = kp0 + torch.stack([offsets[left % w], offsets[left // w]], -1) * step
    kp1 = kp1 + torch.stack([offsets[r % w], offsets[r // w]], -1) * step
    # Stage 2: image 0's best pixel against the 3x3 block of image 1's window at (row r//w, col r%w) - 1 + d.
    sim2 = (b0 @ (b1 / slice_dim**0.5).transpose(1, 2)).reshape(m, ww, w + 2, w + 2)
    d = torch.arange(-1, 2, device=fine0.device)
    rows = (r // w)[:, None, None] + d[None, :, None]
    cols = (r % w)[:, None, None] + d[None, None, :]
    idx = torch.arange(m, device=fine0.device)[:, None, None]
    heat = (sim2[idx, left[:, None, None], rows, cols].reshape(m, 9) / temperature).softmax(1).reshape(m, 3, 3)
    grid = d.to(heat.dtype)  # normalised coordinates -1, 0, 1 of the 3x3 block
    shift = torch.stack([(heat.sum(1) * grid).sum(1), (heat.sum(2) * grid).sum(1)], -1)
    return kp0, kp1 + shift * step


class EfficientLoFTRMatcher(Matcher):
    """``efficientloftr``: EfficientLoFTR through transformers, a dense matcher (``extract`` prepares the image,
    ``match`` runs the network on the pair).

    Args:
        options: ``EfficientLoFTROptions``.
        **overrides: Single options over ``options``.
    """

    name = "efficientloftr"

    def __init__(self, options: EfficientLoFTROptions | None = None, **overrides: object) -> None:
        EfficientLoFTRConfig, EfficientLoFTRForKeypointMatching = transformers_classes(
            "EfficientLoFTRConfig", "EfficientLoFTRForKeypointMatching"
        )

        self.options = o = EfficientLoFTROptions.build(overrides, owner="matcher 'efficientloftr'", base=options)
        self.device: torch.device = resolve_device(o.device)

        def configure(cfg: Any) -> None:
            if o.match_threshold is not None:
                cfg.coarse_matching_threshold = float(o.match_threshold)  # a strict dataclass field

        self.net = load_hub_model(
            EfficientLoFTRForKeypointMatching, EfficientLoFTRConfig, EFFICIENTLOFTR_MODEL, o.weights, configure
        ).to(self.device)

    @classmethod
    def runs_offline(cls, **args: object) -> bool:
        return efficientloftr_available()

    def extract(self, image: np.ndarray) -> Features:
        image, blank = checked_or_blank(image)
        if blank is not None:
            return blank
        size = (image.shape[1], image.shape[0])
        x, scale = grey_pixels(image, self.options.max_size, MULTIPLE, self.device)
        h, w = x.shape[-2:]
        # Candidate points: the coarse cells (8-pixel steps) in original pixels; matches refine them per pair.
        grid = np.stack(np.meshgrid(np.arange(w // 8) * 8.0, np.arange(h // 8) * 8.0), -1).reshape(-1, 2)
        return Features(to_original(grid, scale), size, {"pixels": x, "scale": scale})

    @torch.inference_mode()
    def match(self, f0: Features, f1: Features) -> Matches:
        if len(f0) == 0 or len(f1) == 0:
            return Matches.empty()
        x0, x1 = f0.data["pixels"], f1.data["pixels"]
        scale1 = f1.data["scale"]
        if x1.shape != x0.shape:  # the model takes a pair of one size: bring the query to the reference's
            h1, w1 = x1.shape[-2:]
            x1 = F.interpolate(x1, size=x0.shape[-2:], mode="bilinear", align_corners=False)
            scale1 = (scale1[0] * x0.shape[-1] / w1, scale1[1] * x0.shape[-2] / h1)
        net, cfg = self.net, self.net.config
        with autocast(self.device, self.options.mixed_precision), steady_kernels():
            feats = net.efficientloftr(torch.stack([x0, x1], 1)).feature_maps
            coarse = feats[0]  # (1, 2, C, h, w)
            c, hc, wc = coarse.shape[-3:]
            flat = coarse[0].flatten(2).transpose(1, 2).float() / c**0.5  # (2, h*w, C)
            sim = flat[0] @ flat[1].t() / cfg.coarse_matching_temperature
            conf = sim if cfg.coarse_matching_skip_softmax else sim.softmax(0) * sim.softmax(1)
            i, j, score = mutual_pairs(
                conf, (hc, wc), (hc, wc), cfg.coarse_matching_threshold, cfg.coarse_matching_border_removal
            )
            if len(i) == 0:
                return Matches.empty()
            step = x0.shape[-2] / hc  # input pixels per coarse cell (8)
            kp0 = torch.stack([i % wc, i // wc], -1).float() * step
            kp1 = torch.stack([j % wc, j // wc], -1).float() * step
            fine0, fine1 = net.refinement_layer(coarse / cfg.hidden_size**0.5, feats[1:])
            fine_step = x0.shape[-2] / int(hc * step)
            kp0, kp1 = refine(
                fine0[0, i].float(),
                fine1[0, j].float(),
                kp0,
                kp1,
                cfg.fine_matching_slice_dim,
                cfg.fine_matching_regress_temperature,
                fine_step,
            )
        m = Matches(
            to_original(kp0.cpu().numpy(), f0.data["scale"]),
            to_original(kp1.cpu().numpy(), scale1),
            score.float().cpu().numpy(),
        )
        return m.subset(inside(m.kpts0, f0.image_size) & inside(m.kpts1, f1.image_size))
