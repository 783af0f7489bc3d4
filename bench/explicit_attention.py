"""A pytest plugin (``-p explicit_attention``, with bench/ on the path) that computes attention the way the public
DUSt3R / MASt3R / DINOv2 / RPR code does, ``softmax(q kᵀ · scale) v`` in explicit steps, instead of PyTorch's fused
``scaled_dot_product_attention``: ``kernel_spread.py`` uses it to measure the public forward's own float32 spread."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def _explicit(q, k, v, attn_mask=None, dropout_p=0.0, is_causal=False, scale=None, enable_gqa=False):
    assert not is_causal and dropout_p == 0.0
    a = (q @ k.transpose(-2, -1)) * (q.shape[-1] ** -0.5 if scale is None else scale)
    if attn_mask is not None:
        a = a.masked_fill(~attn_mask, float("-inf")) if attn_mask.dtype == torch.bool else a + attn_mask
    return a.softmax(dim=-1) @ v


def pytest_configure(config) -> None:
    F.scaled_dot_product_attention = _explicit
