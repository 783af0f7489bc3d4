"""Depth sources by spec: ``files:SUFFIX``, ``none``, a short model name (``dav2-indoor``, ``dpt-kitti``,
``zoedepth``, ``depth-pro``, ...), ``hf:HUB_ID_OR_LOCAL_DIR``, or a network whose depth comes with the pair's
matches (``mast3r``, ``dust3r``: pointmaps; ``mickey``: its keypoints' depths). Each answers ``depth(frame)`` (or
``pair_depth``) in metres."""

from __future__ import annotations

from typing import Any

from .base import DepthSource, FileDepthSource, NetworkDepthSource, PairDepthSource
from .files import FileDepth, NoDepth

__all__ = [
    "DepthSource",
    "FileDepthSource",
    "NetworkDepthSource",
    "PairDepthSource",
    "FileDepth",
    "NoDepth",
    "create",
    "names",
    "HUB_MODELS",
    "PAIR_MODELS",
]

from .hub import HUB_MODELS  # noqa: E402  (torch and transformers load only with a network source)

#: Networks whose depth of both images comes with the pair's matching: two-view pointmaps (``depth/mast3r.py``:
#: MASt3R, DUSt3R, DUNE-MASt3R with its ViT-B or ViT-S encoder)
#: and MicKey's metric keypoints (``depth/mickey.py``).
PAIR_MODELS = ("mast3r", "dust3r", "dune-mast3r", "dune-mast3r-small", "mickey")


def names() -> list[str]:
    """Spec forms and short model names a user can type.

    Returns:
        ``none``, ``files:SUFFIX``, ``hf:HUB_ID_OR_DIR``, the hub networks' and the pair networks' names.
    """
    return ["none", "files:SUFFIX", "hf:HUB_ID_OR_DIR", *HUB_MODELS, *PAIR_MODELS]


def create(spec: str, **options: Any) -> DepthSource:
    """Build a depth source from its spec.

    Args:
        spec: ``none``, ``files:SUFFIX``, ``hf:HUB_ID_OR_DIR``, a hub network's short name (``dav2-indoor``) or a
            pair network's (``mast3r``, ``dust3r``, ``mickey``).
        **options: Options of a network source (``cache_dir=``, ``device=``, ``batch_size=``; ``engine=`` to share a
            matcher's network).

    Returns:
        The source: a ``FileDepthSource``, a ``NetworkDepthSource``, a ``PairDepthSource`` or ``NoDepth``.

    Raises:
        KeyError: An unknown spec.
    """
    s = spec.strip()
    if s.lower() == "none":
        return NoDepth()
    if s.startswith("files:"):
        return FileDepth(s[len("files:") :])
    if s.startswith("hf:"):
        from .hf import HFDepth

        return HFDepth(s[len("hf:") :], **options)
    if s == "mickey":
        from .mickey import MickeyDepth

        return MickeyDepth(**options)
    if s in PAIR_MODELS:
        from .mast3r import Mast3rDepth

        return Mast3rDepth(s, **options)
    if s in HUB_MODELS:
        from .hf import HFDepth

        return HFDepth(s, **options)
    raise KeyError(f"unknown depth spec {spec!r}; use one of: {', '.join(names())}")
