"""What the learned networks run on: the device a ``device`` option names, and explicit GPU kernel choices so
that a never-seen input costs no set-up. ``matching``, ``depth``, ``mast3r`` and ``mickey`` all take them from here.

PyTorch's scaled-dot-product attention may pick the cuDNN backend, which builds (and caches) a cuDNN graph per
new sequence length; LightGlue's adaptive pruning makes a new length at almost every layer of every pair, so on
an H100 a never-seen pair cost 0.5-1.3 s of graph building against ~6 ms of GPU work. ``steady_kernels`` allows
only FlashAttention and memory-efficient attention (the math kernel as the last resort for inputs neither
supports) and turns cuDNN's per-shape convolution autotuning off. On the CPU it changes nothing that matters.

torch is imported by the functions that use it, not here: importing this module loads nothing heavy.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any, ParamSpec, TypeVar

if TYPE_CHECKING:
    import torch

__all__ = ["resolve_device", "STEADY_BACKENDS", "steady_kernels", "with_steady_kernels"]  # noqa: F822 (lazy)

P = ParamSpec("P")
R = TypeVar("R")


def resolve_device(device: str | torch.device | None = None) -> torch.device:
    """The torch device a ``device`` option names.

    Args:
        device: A device name or object; None and ``auto`` mean cuda when available, else cpu.

    Returns:
        The device.
    """
    import torch

    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def _steady_backends() -> tuple:
    from torch.nn.attention import SDPBackend

    return (SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.MATH)


def __getattr__(name: str) -> Any:
    #: ``STEADY_BACKENDS``: attention backends allowed on every learned path (no cuDNN attention: per-shape graph
    #: building). Computed on first use so that importing this module does not load torch.
    if name == "STEADY_BACKENDS":
        return _steady_backends()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@contextlib.contextmanager
def steady_kernels() -> Iterator[None]:
    """Run learned networks without per-shape kernel set-up: attention limited to ``STEADY_BACKENDS``, cuDNN
    autotuning (``cudnn.benchmark``) off, both restored on exit.

    Yields:
        Nothing; the settings hold inside the ``with`` block.
    """
    import torch
    from torch.nn.attention import sdpa_kernel

    bench = torch.backends.cudnn.benchmark
    torch.backends.cudnn.benchmark = False
    try:
        with sdpa_kernel(list(_steady_backends())):
            yield
    finally:
        torch.backends.cudnn.benchmark = bench


def with_steady_kernels(fn: Callable[P, R]) -> Callable[P, R]:
    """Decorator form of ``steady_kernels`` for a network's forward entry points.

    Args:
        fn: The function to run inside ``steady_kernels``.

    Returns:
        The wrapped function, same signature.
    """

    @functools.wraps(fn)
    def wrapped(*args: P.args, **kwargs: P.kwargs) -> R:
        with steady_kernels():
            return fn(*args, **kwargs)

    return wrapped
