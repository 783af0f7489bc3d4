"""LightGlue over a batch of pairs with one reference: padded to length buckets with masks, adaptive depth and
width decided per pair, so a pair's matches do not depend on which other pairs share its batch.

kornia's ``LightGlue.forward`` runs a batch one pair at a time as soon as point pruning is on (pairs keep
different numbers of points), and stops early only when every pair of a batch is confident. Here the same
network modules run on padded tensors: a pruned point leaves the attention masks (and the batch is compacted to
the longest survivor, rounded up to a bucket), a pair that is confident leaves the batch with its assignment of
that layer. One host synchronisation per layer decides both; a batch's matches come to the host in one copy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from kornia.feature.lightglue import filter_matches, normalize_keypoints

from ..runtime import steady_kernels
from .base import Features

__all__ = ["GlueInput", "glue_input", "run_glue", "bucket_length", "BUCKET"]

#: Sequence lengths are padded up to a multiple of this (fewer distinct shapes, batches of mixed counts).
BUCKET = 256
#: A kornia ``LightGlue`` network: its layers are nn.Module attributes, which type checkers see as untyped.
GlueNet = Any


@dataclass
class GlueInput:
    """One image's side of a pair: keypoints (N,2) in the pixels of the image the network saw, descriptors
    (N,D), and that image's (width, height)."""

    keypoints: torch.Tensor
    descriptors: torch.Tensor
    size: tuple[int, int]


def glue_input(f: Features) -> GlueInput:
    """The LightGlue side of a matcher's feature set.

    Args:
        f: Features whose ``data`` holds keypoints, descriptors and the resized image's size.

    Returns:
        The side (no keypoints for an image without features).
    """
    if "keypoints" not in f.data:  # an image without features
        return GlueInput(torch.zeros((0, 2)), torch.zeros((0, 1)), f.image_size)
    return GlueInput(f.data["keypoints"], f.data["descriptors"], f.data["resized"])


def bucket_length(n: int, bucket: int = BUCKET) -> int:
    """A sequence length rounded up to a multiple of ``bucket`` (at least one bucket).

    Args:
        n: Keypoints.
        bucket: The multiple.

    Returns:
        The padded length.
    """
    return max(bucket, -(-n // bucket) * bucket)


def _pad(sides: list[GlueInput], length: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Normalised keypoints (B,L,2), descriptors (B,L,D) and the validity mask (B,L), zero-padded to ``length``."""
    b, d = len(sides), sides[0].descriptors.shape[-1]
    kp = torch.zeros((b, length, 2), device=device)
    desc = torch.zeros((b, length, d), device=device, dtype=sides[0].descriptors.dtype)
    mask = torch.zeros((b, length), device=device, dtype=torch.bool)
    sizes = torch.tensor([s.size for s in sides], device=device, dtype=torch.float32)
    for i, s in enumerate(sides):
        n = len(s.keypoints)
        kp[i, :n] = s.keypoints.float()
        desc[i, :n] = s.descriptors
        mask[i, :n] = True
    return normalize_keypoints(kp, sizes), desc, mask


class _Side:
    """The running state of one image side of the active pairs: descriptors, encodings, mask, original index."""

    def __init__(self, desc: torch.Tensor, enc: torch.Tensor, mask: torch.Tensor) -> None:
        self.desc, self.enc, self.mask = desc, enc, mask
        self.index = torch.arange(mask.shape[1], device=mask.device).expand_as(mask)

    def take(self, rows: torch.Tensor) -> _Side:
        out = _Side.__new__(_Side)
        out.desc, out.enc, out.mask, out.index = self.desc[rows], self.enc[:, rows], self.mask[rows], self.index[rows]
        return out

    def compact(self, length: int) -> None:
        """Valid tokens first (in their order), then cut to ``length``."""
        order = torch.sort((~self.mask).to(torch.uint8), dim=1, stable=True).indices[:, :length]
        self.desc = self.desc.gather(1, order[..., None].expand(-1, -1, self.desc.shape[-1]))
        enc_idx = order[None, :, None, :, None].expand(self.enc.shape[0], -1, 1, -1, self.enc.shape[-1])
        self.enc = self.enc.gather(3, enc_idx)
        self.mask = self.mask.gather(1, order)
        self.index = self.index.gather(1, order)

    @property
    def attn_mask(self) -> torch.Tensor:
        return self.mask[:, None, :, None]  # (B,1,L,1): broadcasts over heads in kornia's masked layer


def _assign(net: GlueNet, layer: int, s0: _Side, s1: _Side, threshold: float):
    """Dual-softmax assignment of ``layer`` restricted to valid tokens; returns (m0, scores0) per row of side 0,
    with m0 in original indices of side 1 (-1: unmatched)."""
    la = net.log_assignment[layer]
    md0, md1 = la.final_proj(s0.desc), la.final_proj(s1.desc)
    d = md0.shape[-1]
    sim = (md0 / d**0.25) @ (md1 / d**0.25).transpose(-1, -2)
    valid = s0.mask[:, :, None] & s1.mask[:, None, :]
    sim = sim.float().masked_fill(~valid, float("-inf"))
    z0, z1 = la.matchability(s0.desc).float(), la.matchability(s1.desc).float()
    scores = F.log_softmax(sim, 2) + F.log_softmax(sim, 1) + F.logsigmoid(z0) + F.logsigmoid(z1).transpose(1, 2)
    scores = scores.masked_fill(~valid, float("-inf"))  # rows/columns of padding: never a match
    m0, _, ms0, _ = filter_matches(F.pad(scores, (0, 1, 0, 1), value=float("-inf")), threshold)
    m0 = torch.where(m0 >= 0, s1.index.gather(1, m0.clamp(min=0)), -1)
    return s0.index, m0, ms0


def run_glue(
    net: GlueNet, ref: GlueInput, queries: list[GlueInput], *, mixed_precision: bool = False, bucket: int = BUCKET
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Match one reference against many queries with a LightGlue network, the pairs in one padded batch.

    Uses the net's ``depth_confidence``, ``width_confidence`` and ``filter_threshold`` like kornia; early stopping
    and pruning are decided per pair, so each pair gets the matches it gets alone.

    Args:
        net: A kornia ``LightGlue``.
        ref: The reference's side.
        queries: The queries' sides.
        mixed_precision: float16 autocast on CUDA.
        bucket: Sequence lengths are padded to multiples of it.

    Returns:
        Per query: (K, 2) int64 indices into the reference's and the query's keypoints, and (K,) scores.
    """
    out: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros((0, 2), np.int64), np.zeros(0))] * len(queries)
    live = [i for i, q in enumerate(queries) if len(q.keypoints) and len(ref.keypoints)]
    if not live:
        return out
    device = ref.descriptors.device
    conf = net.conf
    amp = mixed_precision and device.type == "cuda"
    with torch.inference_mode(), steady_kernels(), torch.autocast(device.type, dtype=torch.float16, enabled=amp):
        k0, d0, m0 = _pad([ref], bucket_length(len(ref.keypoints), bucket), device)
        k1, d1, m1 = _pad(
            [queries[i] for i in live], bucket_length(max(len(queries[i].keypoints) for i in live), bucket), device
        )
        b = len(live)
        pe = net.posenc.Wr.weight.dtype
        enc0 = net.posenc(k0.to(pe)).expand(-1, b, -1, -1, -1)
        s0 = _Side(net.input_proj(d0.half() if amp else d0).expand(b, -1, -1), enc0, m0.expand(b, -1))
        s1 = _Side(net.input_proj(d1.half() if amp else d1), net.posenc(k1.to(pe)), m1)
        counts = torch.tensor([len(ref.keypoints) + len(queries[i].keypoints) for i in live], device=device)
        rows = torch.tensor(live, device=device)
        prune_from = net.pruning_min_kpts(device)
        done: list[tuple] = []
        for layer in range(conf.n_layers):
            s0.desc, s1.desc = net.transformers[layer].masked_forward(
                s0.desc, s1.desc, s0.enc, s1.enc, s0.attn_mask, s1.attn_mask
            )
            if layer == conf.n_layers - 1:
                break
            stop = torch.zeros(len(rows), dtype=torch.bool, device=device)
            tok0 = tok1 = None
            if conf.depth_confidence > 0:
                tok0, tok1 = net.token_confidence[layer](s0.desc, s1.desc)
                th = net.confidence_thresholds[layer]
                unsure = ((tok0 < th) & s0.mask).sum(-1) + ((tok1 < th) & s1.mask).sum(-1)
                stop = (1.0 - unsure / counts) > conf.depth_confidence
            if conf.width_confidence > 0:
                for side, tok in ((s0, tok0), (s1, tok1)):
                    _prune(net, layer, side, tok, stop, prune_from)
            # The one host synchronisation of the layer: who stops, and how long the survivors are.
            stats = torch.stack([stop.long(), s0.mask.sum(-1), s1.mask.sum(-1)]).cpu()
            stopped = stats[0].bool()
            if stopped.any():
                sel = stopped.nonzero().flatten().to(device)
                done.append((rows[sel], *_assign(net, layer, s0.take(sel), s1.take(sel), conf.filter_threshold)))
                keep_rows = (~stopped).nonzero().flatten().to(device)
                if len(keep_rows) == 0:
                    rows = rows[:0]
                    break
                s0, s1, rows, counts = s0.take(keep_rows), s1.take(keep_rows), rows[keep_rows], counts[keep_rows]
                stats = stats[:, ~stopped]
            if conf.width_confidence > 0:
                for side, n in ((s0, int(stats[1].max())), (s1, int(stats[2].max()))):
                    length = min(side.mask.shape[1], bucket_length(n, bucket))
                    if length < side.mask.shape[1]:
                        side.compact(length)
        if len(rows):
            done.append((rows, *_assign(net, layer, s0, s1, conf.filter_threshold)))
        for group in done:  # one copy per group of pairs that stopped together
            _to_host(group, out)
    return out


def _prune(
    net: GlueNet, layer: int, side: _Side, tok: torch.Tensor | None, stop: torch.Tensor, prune_from: int
) -> None:
    """Width confidence: drop the points of ``side`` that will not match from its mask (kornia's point pruning)."""
    keep = net.log_assignment[layer].get_matchability(side.desc) > 1 - net.conf.width_confidence
    if tok is not None:
        keep |= tok <= net.confidence_thresholds[layer]
    busy = side.mask.sum(-1, keepdim=True) > prune_from  # kornia prunes while above this count
    # A pair that stops now is assigned on its points before this layer's pruning.
    side.mask = side.mask & (keep | ~busy | stop[:, None])


def _to_host(group: tuple[torch.Tensor, ...], out: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """Put a group of pairs' assignments into ``out``: (K, 2) index pairs and (K,) scores per pair, one copy."""
    rows, idx, match, score = group
    rws, idx0, m, sc = rows.cpu().numpy(), idx.cpu().numpy(), match.cpu().numpy(), score.float().cpu().numpy()
    for j, r in enumerate(rws):
        ok = m[j] >= 0
        out[r] = (np.stack([idx0[j][ok], m[j][ok]], -1).astype(np.int64), sc[j][ok].astype(np.float64))
