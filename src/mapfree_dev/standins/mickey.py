"""Deterministic stand-in weights for MicKey in the published files' layout (tests, ``bench/``, the GPU probe).

Every tensor is filled by the rule of ``mapfree_dev.standins.mast3r.fill_value`` under its published name (DINOv2's
as ``"dinov2." + key``), except the constants the checkpoint stores (the score head's ``eps``, ``offset_par1/2``
and ``ones_kernel`` keep their values) and integer buffers (``num_batches_tracked``: 0, as built). The public code
run on the same rule gives the arrays of ``shared/fixtures/mickey``.
"""

from __future__ import annotations

from pathlib import Path

import torch

from mapfree.mickey.checkpoint import DINOV2_FILE, SUBDIR, published_key
from mapfree.mickey.config import MickeyConfig
from mapfree.mickey.dinov2 import ViTShape
from mapfree.mickey.model import MickeyNet

from .mast3r import fill_value

__all__ = ["VIT_SIZES", "published_layout", "synthetic_state_dicts", "write_standin"]

#: DINOv2 sizes: the published ViT-L/14 (518-pixel pretraining grid) and the tests' tiny one.
VIT_SIZES = {
    "full": ViTShape(dim=1024, depth=24, patch=14, grid=37, mlp_hidden=4096),
    "tiny": ViTShape(dim=384, depth=2, patch=14, grid=37, mlp_hidden=1536),
}
_CONSTANTS = {"eps": 1e-16, "offset_par1": 0.5, "offset_par2": 2.0}


def _value(pub: str, ours: torch.Tensor, dinov2: bool) -> torch.Tensor:
    leaf = pub.rsplit(".", 1)[-1]
    if not ours.dtype.is_floating_point:
        return torch.zeros(ours.shape, dtype=ours.dtype)
    if leaf in _CONSTANTS:
        return torch.tensor(_CONSTANTS[leaf], dtype=torch.float32)
    if leaf == "ones_kernel":
        return torch.ones(ours.shape)
    return torch.from_numpy(fill_value(f"dinov2.{pub}" if dinov2 else pub, tuple(ours.shape)))


def published_layout(vit: ViTShape, cfg: MickeyConfig | None = None) -> dict[str, torch.Tensor]:
    """Published key -> a meta tensor of its dtype and shape (checkpoint keys and DINOv2 keys alike)."""
    with torch.device("meta"):
        return {published_key(k): v for k, v in MickeyNet(cfg or MickeyConfig(), vit).state_dict().items()}


StateDict = dict[str, torch.Tensor]


def synthetic_state_dicts(
    vit: ViTShape, cfg: MickeyConfig | None = None, dtype: torch.dtype = torch.float32
) -> tuple[StateDict, StateDict]:
    """(checkpoint state dict, DINOv2 state dict), published key names, filled by the rule."""
    heads: dict[str, torch.Tensor] = {}
    dino: dict[str, torch.Tensor] = {}
    for pub, t in published_layout(vit, cfg).items():
        is_dino = not pub.startswith("compute_matches.")
        v = _value(pub, t, is_dino)
        keep = not v.dtype.is_floating_point or pub.rsplit(".", 1)[-1] in _CONSTANTS  # eps would be 0 in float16
        (dino if is_dino else heads)[pub] = v if keep else v.to(dtype)
    return heads, dino


def write_standin(
    folder: str | Path, size: str = "full", dtype: torch.dtype = torch.float32, checkpoint: str = "mickey"
) -> Path:
    """``folder/mickey/{checkpoint}.ckpt`` (a Lightning-style ``{"state_dict": ...}``) and ``folder/mickey/
    dinov2_vitl14_pretrain.pth`` with fill-rule weights of ``size`` (``full`` | ``tiny``): a ``$MAPFREE_WEIGHTS_DIR``
    for runs without the real files (``dtype`` float16 halves them; the loader computes in float32)."""
    out = Path(folder) / SUBDIR
    out.mkdir(parents=True, exist_ok=True)
    heads, dino = synthetic_state_dicts(VIT_SIZES[size], dtype=dtype)
    torch.save({"state_dict": heads, "epoch": 0, "global_step": 0}, out / f"{checkpoint}.ckpt")
    torch.save(dino, out / DINOV2_FILE)
    return Path(folder)
