"""Depth sources by spec: ``files:SUFFIX``, ``none``, a short model name (``dav2-indoor``, ``dpt-kitti``,
``zoedepth``, ``depth-pro``, ...), ``hf:HUB_ID_OR_LOCAL_DIR``, or a two-view network (``mast3r``, ``dust3r``)
whose depth comes with the pair. Each answers ``depth(frame)`` (or ``pair_depth``) in metres."""

from __future__ import annotations

from .base import DepthSource
from .files import FileDepth, NoDepth

__all__ = ["DepthSource", "FileDepth", "NoDepth", "create", "names", "HUB_MODELS", "PAIR_MODELS"]

from .hub import HUB_MODELS  # noqa: E402  (torch and transformers load only with a network source)

#: Two-view networks whose pointmaps give both images' depth after matching (``depth/mast3r.py``).
PAIR_MODELS = ("mast3r", "dust3r")


def names() -> list[str]:
    """Spec forms and short model names a user can type."""
    return ["none", "files:SUFFIX", "hf:HUB_ID_OR_DIR", *HUB_MODELS, *PAIR_MODELS]


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
    if s in PAIR_MODELS:
        from .mast3r import Mast3rDepth

        return Mast3rDepth(s, **options)  # type: ignore[arg-type]
    if s in HUB_MODELS:
        from .hf import HFDepth

        return HFDepth(s, **options)
    raise KeyError(f"unknown depth spec {spec!r}; use one of: {', '.join(names())}")
