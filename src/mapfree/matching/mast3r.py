"""``mast3r`` and ``dust3r`` matchers: dense two-view networks whose pair forward pass gives the matches.

``extract`` preprocesses and encodes one image (so a reference is encoded once per scene); ``match`` runs the
decoders on the pair and takes reciprocal nearest neighbours from a grid every ``subsample`` pixels: of the
local descriptors (MASt3R) or of the two pointmaps in view 1's frame (DUSt3R). Scores are the lower of the two
pixels' confidences. The same forward pass serves the ``mast3r``/``dust3r`` depth source (``depth/mast3r.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..mast3r.engine import BACKENDS, EncodedImage, PairEngine, PairOutput, shared_engine
from ..mast3r.reciprocal import reciprocal_matches
from ..options import Options, option
from .base import Features, Matcher, Matches
from .utils import checked_or_blank

if TYPE_CHECKING:
    import torch

__all__ = ["Mast3rOptions", "Mast3rMatcher"]


@dataclass
class Mast3rOptions(Options):
    """Options of ``mast3r`` / ``dust3r``.

    Attributes:
        kind: ``mast3r`` (descriptors) or ``dust3r`` (pointmaps).
        weights: A ``.pth`` or hub folder; default: the published file in the weights folders.
        subsample: Grid step (network pixels) of the starting points, as the public visloc code.
        border_px: Matches this close to the network image's border are dropped.
        min_score: Keep matches whose confidence (>= 1 with the published models) is at least this.
        long_side: Network input size (the published models': 512).
        device: ``cpu``, ``cuda``; None: CUDA when available.
        backend: ``torch`` (our PyTorch port) or ``onnxruntime`` (the graphs written by ``mapfree export``).
        onnx: With ``onnxruntime``: the encoder graph ``NAME.onnx``; default ``KIND.onnx`` in the weights folders.
    """

    kind: str = option("mast3r", choices=("mast3r", "dust3r"))  # mast3r (descriptors) | dust3r (pointmaps)
    weights: str | None = None  # a .pth or hub folder; default: the published file in the weights folders
    subsample: int = option(8, min=1)  # grid step (network pixels) of the starting points, as the public visloc
    border_px: int = option(3, min=0)  # matches this close to the network image's border are dropped
    min_score: float = option(0.0, min=0)  # keep matches whose confidence (>= 1 with the published modes) is >= this
    long_side: int = option(512, min=16)  # network input size (the published models': 512)
    device: str | None = option(None, device=True)
    backend: str = option("torch", choices=BACKENDS)  # torch | onnxruntime (graphs of `mapfree export`)
    onnx: str | None = None  # with onnxruntime: the encoder graph NAME.onnx; default KIND.onnx in the weights folders


class Mast3rMatcher(Matcher):
    """Dense matcher on MASt3R descriptors or DUSt3R pointmaps; keypoints in original-image pixels. Its network
    (``engine``) also serves the ``mast3r`` / ``dust3r`` depth source: one forward pass per pair.

    Args:
        options: ``Mast3rOptions``.
        **overrides: Single options over ``options``.
    """

    def __init__(self, options: Mast3rOptions | None = None, **overrides: object) -> None:
        self.options = o = Mast3rOptions.build(
            overrides, owner=f"matcher {overrides.get('kind', 'mast3r')!r}", base=options
        )
        if o.kind not in ("mast3r", "dust3r"):
            raise ValueError(f"unknown kind {o.kind!r}; choose mast3r or dust3r")
        self.name = o.kind
        self.engine: PairEngine = shared_engine(o.kind, o.weights, o.device, o.long_side, o.backend, o.onnx)
        self.device: torch.device = self.engine.device

    def extract(self, image: np.ndarray) -> Features:
        """Features of one image; see ``Matcher.extract``.

        Args:
            image: (H, W, 3) uint8 RGB.

        Returns:
            Keypoints in the image's own pixels and what ``match`` needs.
        """
        return self.extract_many([image])[0]

    def extract_many(self, images: Sequence[np.ndarray]) -> list[Features]:
        """Features of several images, in order: one encoder pass per input size.

        Args:
            images: (H, W, 3) uint8 RGB images.

        Returns:
            One ``Features`` per image (a textureless image: none).
        """
        checked = [checked_or_blank(im) for im in images]
        good = [i for i, (_, blank) in enumerate(checked) if blank is None]
        # the caller's arrays, not the checked copies: the depth source finds an encoding by the array's identity
        encoded = dict(zip(good, self.engine.encode_many([images[i] for i in good])))
        out = []
        for i, (img, blank) in enumerate(checked):
            if blank is not None:
                out.append(blank)
                continue
            h, w = img.shape[:2]
            out.append(Features(np.zeros((0, 2)), (w, h), {"encoded": encoded[i]}))
        return out

    def match(self, f0: Features, f1: Features) -> Matches:
        """Correspondences of a pair; see ``Matcher.match``.

        Args:
            f0: Features of image 0 (the reference).
            f1: Features of image 1 (the query).

        Returns:
            ``kpts0[i]`` matching ``kpts1[i]``, original pixels, with their scores.
        """
        return self.match_many(f0, [f1], batch_size=1)[0]

    def match_many(self, f0: Features, f1s: Sequence[Features], batch_size: int | None = None) -> list[Matches]:
        """``match(f0, f1)`` for each of ``f1s``: ``batch_size`` pairs per pass through the decoders and heads (default 8 on a GPU, 1 elsewhere); each pair gets the matches it gets alone.

        Args:
            f0: Features of the reference image.
            f1s: Features of the query images.
            batch_size: Pairs per network pass (None: the matcher's default).

        Returns:
            One ``Matches`` per query.
        """
        e0 = f0.data.get("encoded")
        out: list[Matches] = [Matches.empty() for _ in f1s]
        if not isinstance(e0, EncodedImage):
            return out
        todo = [(i, e) for i, f in enumerate(f1s) if isinstance(e := f.data.get("encoded"), EncodedImage)]
        step = max(1, batch_size or (8 if self.device.type == "cuda" else 1))
        for start in range(0, len(todo), step):
            chunk = todo[start : start + step]
            pairs = self.engine.pair_many(e0, [e for _, e in chunk], descriptors=True, on_device=True)
            for (i, e), pair in zip(chunk, pairs):
                out[i] = self._matches(e0, e, pair)
        return out

    def _matches(self, e0: EncodedImage, e1: EncodedImage, out: PairOutput) -> Matches:
        if self.options.kind == "mast3r":
            if out.desc1 is None or out.desc2 is None or out.desc_conf1 is None or out.desc_conf2 is None:
                raise ValueError("the MASt3R pass gave no descriptors (a DUSt3R checkpoint?)")
            # Unit descriptors: nearest by L2 = largest dot product, found by blocks of matrix products (the
            # public GPU path); a KD-tree in 24-D is ~20x slower on a 512x384 map and finds the same pixels.
            xy0, xy1 = reciprocal_matches(out.desc1, out.desc2, self.options.subsample, self.engine.device, "dot")
            c0, c1 = out.desc_conf1, out.desc_conf2
        else:  # 3-D points in view 1's frame: KD-trees on the CPU, as the public code
            xy0, xy1 = reciprocal_matches(out.pts1, out.pts2, self.options.subsample, self.engine.device)
            c0, c1 = out.conf1, out.conf2
        keep = _away_from_border(xy0, c0.shape, self.options.border_px) & _away_from_border(
            xy1, c1.shape, self.options.border_px
        )
        xy0, xy1 = xy0[keep], xy1[keep]
        scores = np.minimum(c0[xy0[:, 1], xy0[:, 0]], c1[xy1[:, 1], xy1[:, 0]]).astype(np.float64)
        m = Matches(e0.prepared.to_original(xy0), e1.prepared.to_original(xy1), scores)
        return m.subset(m.scores >= self.options.min_score) if self.options.min_score > 0 else m


def _away_from_border(xy: np.ndarray, hw: tuple[int, ...], border: int) -> np.ndarray:
    h, w = hw[:2]
    return (xy[:, 0] >= border) & (xy[:, 0] < w - border) & (xy[:, 1] >= border) & (xy[:, 1] < h - border)
