"""``mickey`` matcher: MicKey's metric keypoints (one per 14-pixel cell of the 540x720 input) and their matching.

``extract`` runs the network on one image (a reference once per scene or anchor); ``match`` scores every pair of
keypoints (dual softmax with the learned dustbin, times both keypoint scores: MicKey's final scores) and returns
the mutual best pairs with a positive score, in original pixels, scored by their final score. The matches also
carry every keypoint with its metric depth and the full score matrix (``CandidateMatches``): the ``mickey``
solver draws from it, and the ``mickey`` depth source reads the keypoints' depths.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..mickey.engine import MickeyEngine, MickeyImage, MickeyNetworkOptions, engine_for
from ..options import option
from .base import BatchedMatcher, CandidateMatches, Features, MatchCandidates, Matches
from .utils import checked_or_blank

__all__ = ["MickeyOptions", "MickeyMatcher", "mutual_best"]


@dataclass
class MickeyOptions(MickeyNetworkOptions):
    """The network's options (checkpoint, weights, dinov2, config, fp16, device) and the matching's."""

    min_score: float = option(0.0, min=0, max=1)  # keep mutual matches whose final score (a probability) exceeds it
    batch_size: int = option(8, min=1)  # images (extract_many) or pairs (match_many) per network pass


def mutual_best(scores: torch.Tensor, min_score: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pairs that are each other's best in a score matrix.

    Args:
        scores: (N0, N1) scores.
        min_score: Pairs of a score not above it are dropped.

    Returns:
        (M,) rows, (M,) columns and (M,) scores, best first.
    """
    best0, j = scores.max(dim=1)
    i_of_j = scores.max(dim=0).indices
    i = torch.arange(scores.shape[0], device=scores.device)
    keep = (i_of_j[j] == i) & (best0 > min_score)
    i, j, s = i[keep], j[keep], best0[keep]
    order = torch.argsort(s, descending=True)
    return i[order], j[order], s[order]


class MickeyMatcher(BatchedMatcher):
    """MicKey keypoints and matches; keypoints in original pixels. Its network also serves the ``mickey`` depth
    source and the matches carry the scored candidates the ``mickey`` solver draws from.

    ``extract_many`` runs ``batch_size`` images per network pass and ``match_many`` scores the pairs in batches of
    ``batch_size``; each pair gets the matches it gets alone.

    Args:
        options: ``MickeyOptions``.
        **overrides: Single options over ``options``.
    """

    name = "mickey"

    def __init__(self, options: MickeyOptions | None = None, **overrides: object) -> None:
        self.options = o = MickeyOptions.build(overrides, owner="matcher 'mickey'", base=options)
        self.engine: MickeyEngine = engine_for(o)
        self.device: torch.device = self.engine.device

    @classmethod
    def runs_offline(cls, **args: object) -> bool:
        from ..mickey.checkpoint import files_available

        return files_available()

    @staticmethod
    def _features(out: MickeyImage) -> Features:
        return Features(out.xy_original().cpu().numpy(), out.original_size, {"mickey": out})

    def extract_many(self, images: Sequence[np.ndarray]) -> list[Features]:
        checked = [checked_or_blank(im) for im in images]
        todo = [img for img, blank in checked if blank is None]
        outs = iter(self.engine.extract(todo, self.options.batch_size)) if todo else iter(())
        return [blank if blank is not None else self._features(next(outs)) for _, blank in checked]

    def match_many(self, f0: Features, f1s: Sequence[Features], batch_size: int | None = None) -> list[Matches]:
        ref = f0.data.get("mickey")
        todo = [i for i, f in enumerate(f1s) if f.data.get("mickey") is not None]
        out: list[Matches] = [Matches.empty() for _ in f1s]
        if ref is None or not todo:
            return out
        step = batch_size or self.options.batch_size
        finals = self.engine.scores(ref, [f1s[i].data["mickey"] for i in todo], step)
        for i, final in zip(todo, finals):
            out[i] = self._matches(ref, f1s[i].data["mickey"], final)
        return out

    def _matches(self, ref: MickeyImage, query: MickeyImage, final: torch.Tensor) -> CandidateMatches:
        i, j, s = mutual_best(final, self.options.min_score)
        xy0, xy1 = ref.xy_original(), query.xy_original()
        cand = MatchCandidates(xy0, xy1, ref.keypoints.depth[0], query.keypoints.depth[0], final)
        return CandidateMatches(xy0[i].cpu().numpy(), xy1[j].cpu().numpy(), s.double().cpu().numpy(), cand)
