"""Explicit GPU kernel choices for the learned networks, so that a never-seen input costs no set-up.

PyTorch's scaled-dot-product attention may pick the cuDNN backend, which builds (and caches) a cuDNN graph per
new sequence length; LightGlue's adaptive pruning makes a new length at almost every layer of every pair, so on
an H100 a never-seen pair cost 0.5-1.3 s of graph building against ~6 ms of GPU work. ``steady_kernels`` allows
only FlashAttention and memory-efficient attention (the math kernel as the last resort for inputs neither
supports) and turns cuDNN's per-shape convolution autotuning off. On the CPU it changes nothing that matters.
"""

from __future__ import annotations

import contextlib
import functools
from typing import Callable, Iterator, TypeVar

import torch
from torch.nn.attention import SDPBackend, sdpa_kernel

__all__ = ["STEADY_BACKENDS", "steady_kernels", "with_steady_kernels"]

#: Attention backends allowed on every learned path: no cuDNN attention (per-shape graph building).
STEADY_BACKENDS = (SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.MATH)

F = TypeVar("F", bound=Callable)


@contextlib.contextmanager
def steady_kernels() -> Iterator[None]:
    """Attention restricted to ``STEADY_BACKENDS`` and no cuDNN autotuning (``cudnn.benchmark``) inside."""
    bench = torch.backends.cudnn.benchmark
    torch.backends.cudnn.benchmark = False
    try:
        with sdpa_kernel(list(STEADY_BACKENDS)):
            yield
    finally:
        torch.backends.cudnn.benchmark = bench


def with_steady_kernels(fn: F) -> F:
    """Decorator form of ``steady_kernels`` for a network's forward entry points."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with steady_kernels():
            return fn(*args, **kwargs)

    return wrapped  # type: ignore[return-value]
