"""Aggregation of the two feature maps into one volume for the pose head (the paper's, as in the public
Map-free release).

``warp``: every position of image 0 gets a softmax over all positions of image 1 (the correlation volume of raw
dot products); it warps image-1 features onto image 0 and, as soft-argmax, image 1's pixel grid (2 position
channels, row then column in [-1, 1]), plus the peak probability (1 max-score channel): 32 + 32 + 2 + 1 = 67
channels for 32-d features. ``qkv``: the same on learned 1×1 query/key/value projections with residuals.
``concat``: the no-warping ablation, both feature maps side by side.

The warping is ``softmax(scale · q kᵀ) · values``, the shape of attention, so ``soft_warp`` computes it with
``scaled_dot_product_attention`` (flash / memory-efficient kernels on a GPU) without materialising the
(H·W)² correlation volume; the peak probability comes from one extra "sink" key (see ``soft_warp``).
``CorrelationAggregator(fused=False)`` keeps the direct computation as the reference.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel

from .config import AGGREGATORS

__all__ = ["CorrelationAggregator", "ConcatAggregator", "build_aggregator", "soft_warp", "AGGREGATORS"]


def _grid(h: int, w: int, like: torch.Tensor) -> torch.Tensor:
    """(2, h*w): row coordinate, then column coordinate, each linearly in [-1, 1]."""
    u = torch.linspace(-1, 1, h, device=like.device, dtype=like.dtype)
    v = torch.linspace(-1, 1, w, device=like.device, dtype=like.dtype)
    return torch.stack(torch.meshgrid(u, v, indexing="ij"), 0).reshape(2, h * w)


#: Attention kernels for the warping: never cuDNN attention, which builds a graph per new shape.
_SDPA_BACKENDS = [SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.MATH]
#: Logit elements per chunk of the argmax pass (64 Mi: 256 MiB in float32), whatever the batch and image size.
_ARGMAX_CHUNK = 1 << 26


def _pad8(x: torch.Tensor) -> torch.Tensor:
    """Zero-pad the last dimension to a multiple of 8 (flash / memory-efficient attention head sizes)."""
    return F.pad(x, (0, -x.shape[-1] % 8))


@torch.no_grad()
def _argmax_rows(q: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """(B, N0) index of the largest ``q_i · k_j`` over j, in row chunks so no (N0, N1) volume is kept."""
    B, N0, _ = q.shape
    rows = max(1, _ARGMAX_CHUNK // max(B * k.shape[1], 1))
    kt = k.transpose(1, 2)
    with torch.autocast(device_type=q.device.type, enabled=False):
        return torch.cat([(q[:, i : i + rows] @ kt).argmax(2) for i in range(0, N0, rows)], 1)


def soft_warp(
    q: torch.Tensor, k: torch.Tensor, values: torch.Tensor, scale: float = 1.0, max_score: bool = True
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``softmax(scale · q kᵀ) @ values`` (B, N0, D) and each row's peak probability (B, N0), or None.

    q (B, N0, C), k (B, N1, C), values (B, N1, D). Fused attention returns only normalised outputs, so the peak
    probability s_i = exp(m_i - lse_i) (m_i the row's largest logit) is recovered from one extra key whose logit
    is m_i (an extra query channel holding m_i, the key's matching channel 1) and whose value is a one-hot
    channel: that channel's output is o_i = s_i / (1 + s_i) ∈ [1/(N1+1), 1/2], so s_i = o_i / (1 - o_i) and the
    warped values are the other channels / (1 - o_i), both well conditioned. m_i is taken at the row's argmax
    (a chunked no-grad pass) as q_i · k_argmax, so the gradient of s_i through m_i and lse_i is exact.
    """
    B, N0, C = q.shape
    D = values.shape[-1]
    dev = q.device.type
    dt = torch.get_autocast_dtype(dev) if torch.is_autocast_enabled(dev) else q.dtype  # what attention runs in
    if not max_score:
        with sdpa_kernel(_SDPA_BACKENDS):
            out = F.scaled_dot_product_attention(
                _pad8(q.to(dt))[:, None], _pad8(k.to(dt))[:, None], _pad8(values.to(dt))[:, None], scale=scale
            )
        return out[:, 0, :, :D], None
    q32, k32 = q.float(), k.float()
    idx = _argmax_rows(q32, k32)
    m = (q32 * k32.gather(1, idx.unsqueeze(2).expand(-1, -1, C))).sum(2)  # (B, N0): largest logit / scale
    c = m.detach().to(dt)  # the sink's logit / scale, as attention will see it
    one = torch.ones((B, 1, 1), dtype=dt, device=q.device)
    q1 = torch.cat([q.to(dt), c.unsqueeze(2)], 2)
    k1 = torch.cat([F.pad(k.to(dt), (0, 1)), F.pad(one, (C, 0))], 1)  # (B, N1 + 1, C + 1): the sink key last
    v1 = torch.cat([F.pad(values.to(dt), (0, 1)), F.pad(one, (D, 0))], 1)
    with sdpa_kernel(_SDPA_BACKENDS):
        out = F.scaled_dot_product_attention(_pad8(q1)[:, None], _pad8(k1)[:, None], _pad8(v1)[:, None], scale=scale)[
            :, 0
        ].float()
    rest = 1.0 - out[..., D]
    # exp(scale (m - c)): 1 up to c's rounding, and the gradient of s_i through m_i.
    peak = torch.exp(scale * (m - c.float())) * out[..., D] / rest
    return (out[..., :D] / rest.unsqueeze(2)).to(dt), peak.to(dt)


class CorrelationAggregator(nn.Module):
    """Correlation-volume warping (``qkv=False``) or its query/key/value variant (``qkv=True``)."""

    def __init__(
        self,
        dim: int = 32,
        position: bool = True,
        max_score: bool = True,
        qkv: bool = False,
        temperature: float = 0.0,
        own_position: bool = False,
        fused: bool = True,
    ):
        super().__init__()
        self.fused = fused  # soft_warp (attention kernels); False: the explicit correlation volume (reference)
        self.dim, self.position, self.max_score, self.qkv = dim, position, max_score, qkv
        # temperature > 0: cosine similarity / temperature (beyond the paper: sharp matches from the first step);
        # 0: the public code's raw dot product.
        self.temperature = float(temperature)
        self.own_position = own_position and position  # image 0's own grid too (public POSITION_ENCODER_IM1)
        if qkv:
            self.Q_mlp = nn.Conv2d(dim, dim, 1, bias=False)
            self.K_mlp = nn.Conv2d(dim, dim, 1, bias=False)
            self.V_mlp = nn.Conv2d(dim, dim, 1, bias=False)

    @property
    def out_channels(self) -> int:
        return 2 * self.dim + 2 * self.position + 2 * self.own_position + self.max_score

    def forward(self, f0: torch.Tensor, f1: torch.Tensor) -> torch.Tensor:
        if f0.shape != f1.shape:
            raise ValueError(f"feature maps must have one shape, got {tuple(f0.shape)} and {tuple(f1.shape)}")
        B, C, H, W = f0.shape
        if self.qkv:  # residual projections: queries from image 0, keys from image 1, values from both
            q, k = self.Q_mlp(f0) + f0, self.K_mlp(f1) + f1
            v0, v1 = self.V_mlp(f0) + f0, self.V_mlp(f1) + f1
        else:
            q, k, v0, v1 = f0, f1, f0, f1
        if self.fused:
            out = self._fused(q, k, v0, v1)
            nhwc = f0.is_contiguous(memory_format=torch.channels_last) and not f0.is_contiguous()
            return out if nhwc else out.contiguous()
        q, k = q.reshape(B, C, H * W), k.reshape(B, C, H * W)
        if self.temperature > 0:
            logits = F.normalize(q, dim=1).transpose(1, 2) @ F.normalize(k, dim=1) / self.temperature
        else:
            logits = q.transpose(1, 2) @ k
        attn = torch.softmax(logits, dim=2)  # (B, N0, N1): for each image-0 position, a distribution over image 1
        attn_t = attn.transpose(1, 2)
        chans = [v0.reshape(B, C, H * W), v1.reshape(B, C, H * W) @ attn_t]
        if self.position:
            grid = _grid(H, W, attn)
            chans.append(grid.expand(B, -1, -1) @ attn_t)
            if self.own_position:
                chans.append(grid.expand(B, -1, -1))
        if self.max_score:
            chans.append(attn.amax(2).unsqueeze(1))
        return torch.cat(chans, 1).reshape(B, -1, H, W)

    def _fused(self, q: torch.Tensor, k: torch.Tensor, v0: torch.Tensor, v1: torch.Tensor) -> torch.Tensor:
        """The same channels as the reference path through ``soft_warp``, kept in (B, H·W, channels) order."""
        B, C, H, W = q.shape
        rows = lambda x: x.permute(0, 2, 3, 1).reshape(B, H * W, -1)  # noqa: E731
        q, k, v0, v1 = rows(q), rows(k), rows(v0), rows(v1)
        scale = 1.0
        if self.temperature > 0:
            q, k, scale = F.normalize(q, dim=2), F.normalize(k, dim=2), 1.0 / self.temperature
        values = v1
        if self.position:
            grid = _grid(H, W, v1).t().to(v1.dtype)
            values = torch.cat([v1, grid.expand(B, -1, -1)], 2)
        warped, peak = soft_warp(q, k, values, scale, self.max_score)
        chans = [v0, warped]
        if self.own_position:
            chans.append(grid.expand(B, -1, -1))
        if peak is not None:
            chans.append(peak.unsqueeze(2))
        out = torch.cat([x.to(warped.dtype) for x in chans], 2).reshape(B, H, W, -1).permute(0, 3, 1, 2)
        return out  # channels-last strides (the head's convolutions read it as it is)


class ConcatAggregator(nn.Module):
    """No warping (ablation): the two feature maps concatenated along channels."""

    def __init__(self, dim: int = 32):
        super().__init__()
        self.dim = dim

    @property
    def out_channels(self) -> int:
        return 2 * self.dim

    def forward(self, f0: torch.Tensor, f1: torch.Tensor) -> torch.Tensor:
        return torch.cat([f0, f1], 1)


def build_aggregator(
    kind: str,
    dim: int,
    position: bool = True,
    max_score: bool = True,
    temperature: float = 0.0,
    own_position: bool = False,
) -> CorrelationAggregator | ConcatAggregator:
    if kind == "concat":
        return ConcatAggregator(dim)
    if kind in ("warp", "qkv"):
        return CorrelationAggregator(dim, position, max_score, kind == "qkv", temperature, own_position)
    raise ValueError(f"unknown aggregator {kind!r} (known: {', '.join(AGGREGATORS)})")
