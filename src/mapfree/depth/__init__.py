"""Depth sources by spec: ``files:SUFFIX``, ``none``, a short model name (``dav2-indoor``, ``dpt-kitti``,
``zoedepth``, ``depth-pro``, ...) or ``hf:HUB_ID_OR_LOCAL_DIR``. Each answers ``depth(frame)`` in metres."""

from __future__ import annotations

from .base import DepthSource
from .files import FileDepth, NoDepth

__all__ = ["DepthSource", "FileDepth", "NoDepth", "create", "names", "HUB_MODELS"]

from .hub import HUB_MODELS  # noqa: E402  (torch and transformers load only with a network source)


def names() -> list[str]:
    """Spec forms and short model names a user can type."""
    return ["none", "files:SUFFIX", "hf:HUB_ID_OR_DIR", *HUB_MODELS]


def create(spec: str, **options: object) -> DepthSource:
    """Build a depth source from its spec; ``options`` go to network sources (``cache_dir=``, ``device=``,
    ``batch_size=``)."""
    s = spec.strip()
    if s.lower() == "none":
        return NoDepth()
    if s.startswith("files:"):
        return FileDepth(s[len("files:") :])
    if s.startswith("hf:"):
        from .hf import HFDepth

        return HFDepth(s[len("hf:") :], **options)
    if s in HUB_MODELS:
        from .hf import HFDepth

        return HFDepth(s, **options)
    raise KeyError(f"unknown depth spec {spec!r}; use one of: {', '.join(names())}")
