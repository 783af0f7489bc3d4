"""``mast3r``, ``dust3r`` and ``dune-mast3r`` matchers: dense two-view networks whose pair forward pass gives
the matches (``dune-mast3r``: MASt3R's decoders on a DUNE ViT-B/14 encoder; ``dune-mast3r-small``: ViT-S/14).

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

from ..geometry import focal_from_pointmap
from ..mast3r.engine import BACKENDS, EncodedImage, PairEngine, PairOutput, shared_engine
from ..mast3r.preprocess import Prepared
from ..mast3r.published import DUNE_KINDS
from ..mast3r.reciprocal import reciprocal_matches
from ..options import Options, option
from .base import BatchedMatcher, Features, FocalEstimator, Matches
from .utils import checked_or_blank

if TYPE_CHECKING:
    import torch

__all__ = ["Mast3rOptions", "Mast3rMatcher", "KINDS", "focal_at_original"]

#: The networks of the family: MASt3R, DUSt3R and DUNE-MASt3R with either encoder.
KINDS = ("mast3r", "dust3r", *DUNE_KINDS)


@dataclass
class Mast3rOptions(Options):
    """Options of ``mast3r`` / ``dust3r`` / ``dune-mast3r`` / ``dune-mast3r-small``.

    Attributes:
        kind: ``mast3r`` (descriptors), ``dust3r`` (pointmaps), ``dune-mast3r`` (descriptors, DUNE ViT-B
            encoder) or ``dune-mast3r-small`` (DUNE ViT-S encoder).
        weights: A ``.pth`` or hub folder (DUNE: the decoder file); default: the published file in the weights
            folders.
        subsample: Grid step (network pixels) of the starting points, as the public visloc code.
        border_px: Matches this close to the network image's border are dropped.
        min_score: Keep matches whose confidence (>= 1 with the published models) is at least this.
        long_side: Network input size; None: the published size (MASt3R/DUSt3R 512, DUNE-MASt3R 518).
        device: ``cpu``, ``cuda``; None: CUDA when available.
        backend: ``torch`` (our PyTorch port) or ``onnxruntime`` (the graphs written by ``mapfree export``).
        onnx: With ``onnxruntime``: the encoder graph ``NAME.onnx``; default ``KIND.onnx`` in the weights folders.
    """

    kind: str = option("mast3r", choices=KINDS)  # mast3r | dune-mast3r[-small] (descriptors) | dust3r (pointmaps)
    weights: str | None = None  # a .pth or hub folder; default: the published file in the weights folders
    subsample: int = option(8, min=1)  # grid step (network pixels) of the starting points, as the public visloc
    border_px: int = option(3, min=0)  # matches this close to the network image's border are dropped
    min_score: float = option(0.0, min=0)  # keep matches whose confidence (>= 1 with the published modes) is >= this
    long_side: int | None = option(None, min=14)  # network input size; None: published (512; DUNE-MASt3R 518)
    device: str | None = option(None, device=True)
    backend: str = option("torch", choices=BACKENDS)  # torch | onnxruntime (graphs of `mapfree export`)
    onnx: str | None = None  # with onnxruntime: the encoder graph NAME.onnx; default KIND.onnx in the weights folders


def focal_at_original(pts: np.ndarray, prepared: Prepared) -> float | None:
    """The focal length of an original image from its pointmap at the network's input.

    The focal that best explains the pointmap (``geometry.focal_from_pointmap``), kept within 0.5-3.5 times that
    of a 60° field of view as DUSt3R's global alignment keeps it, then brought from the network's pixels to the
    original's (the input is the original resized, then centre-cropped: the centre stays the centre).

    Args:
        pts: (h, w, 3) points of the image in its own camera frame, at the network's input size.
        prepared: How the image was resized and cropped for the network.

    Returns:
        Pixels of the original image; None without a usable pointmap.
    """
    f = focal_from_pointmap(pts)
    if not np.isfinite(f) or f <= 0:
        return None
    base = max(pts.shape[:2]) / (2 * np.tan(np.deg2rad(60) / 2))
    f = float(np.clip(f, 0.5 * base, 3.5 * base))
    return f / float(np.mean(prepared.scale()))


class Mast3rMatcher(BatchedMatcher, FocalEstimator):
    """Dense matcher on MASt3R descriptors or DUSt3R pointmaps; keypoints in original-image pixels. Its network
    (``engine``) also serves the ``mast3r`` / ``dust3r`` depth source: one forward pass per pair.

    ``extract_many`` runs the encoder once per input size; ``match_many`` runs ``batch_size`` pairs per pass through
    the decoders and heads (default 8 on a GPU, 1 elsewhere), each pair getting the matches it gets alone.

    Args:
        options: ``Mast3rOptions``.
        **overrides: Single options over ``options``.
    """

    def __init__(self, options: Mast3rOptions | None = None, **overrides: object) -> None:
        self.options = o = Mast3rOptions.build(
            overrides, owner=f"matcher {overrides.get('kind', 'mast3r')!r}", base=options
        )
        if o.kind not in KINDS:
            raise ValueError(f"unknown kind {o.kind!r}; choose one of {', '.join(KINDS)}")
        self.name = o.kind
        self.engine: PairEngine = shared_engine(o.kind, o.weights, o.device, o.long_side, o.backend, o.onnx)
        self.device: torch.device = self.engine.device

    @classmethod
    def runs_offline(cls, kind: str = "mast3r", **args: object) -> bool:
        if kind in DUNE_KINDS:
            from ..mast3r.dune_checkpoint import dune_checkpoint_available

            return dune_checkpoint_available(kind)
        from ..mast3r.checkpoint import checkpoint_available

        return checkpoint_available(kind)

    def extract_many(self, images: Sequence[np.ndarray]) -> list[Features]:
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

    def estimate_focal(self, image: np.ndarray, other: np.ndarray | None = None) -> float | None:
        """The focal length of ``image`` from its own pointmap in the pass (``image``, ``other``); see
        ``FocalEstimator.estimate_focal``.

        Args:
            image: (H, W, 3) uint8 RGB, upright.
            other: The pair's other photo; None: ``image`` with itself.

        Returns:
            Pixels of ``image`` at its size, or None for a blank photo.
        """
        pair = [image, image if other is None else other]
        if any(checked_or_blank(im)[1] is not None for im in pair):
            return None
        e0, e1 = self.engine.encode_many(pair)
        return focal_at_original(self.engine.pair(e0, e1).pts1, e0.prepared)

    def match_many(self, f0: Features, f1s: Sequence[Features], batch_size: int | None = None) -> list[Matches]:
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
        if self.options.kind != "dust3r":
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
