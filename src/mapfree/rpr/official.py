"""The published Map-free RPR checkpoints: names, where the weights are found, and loading them into our modules.

The release (``mapfree_rpr_weights.zip``) holds one Lightning checkpoint per configuration of the public
``config/regression/mapfree/``; ours are ``configs/rpr/<name>.yaml`` with the same network. Its ``state_dict``
keys are the public ``RegressionModel``'s: ``encoder.*``, ``aggregator.*``, ``head.*`` (our ``RPRNet``'s names)
and, for the learned loss weighting, ``s_r`` / ``s_t`` (our ``PoseLoss``'s ``s_rot`` / ``s_trans``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..weights import MissingWeightsError, WeightFile, file_problem, find_in_dirs, missing_message

if TYPE_CHECKING:
    import torch

__all__ = [
    "OFFICIAL_CONFIGS",
    "WEIGHTS_URL",
    "RPR_WEIGHTS",
    "find_weights",
    "is_public",
    "read_checkpoint",
    "load_weights",
    "official_config_for",
]

#: The 12 single-frame configurations of the public release (its file names, our config names).
OFFICIAL_CONFIGS = (
    "3d3d",
    "3d3d_lowoverlap",
    "3d3d_no_posencoder",
    "3d3d_no_warping",
    "3d3d_weighted_loss",
    "rot6d_trans",
    "rotbin_trans",
    "rotbin_transdirectionbin_scale",
    "rotbin_transdirectionbin_scale_lowoverlap",
    "rotbin_transdirectionbin_scale_qkv",
    "rotquat_trans",
    "rotquat_transdirection_scale",
)
WEIGHTS_URL = "https://storage.googleapis.com/niantic-lon-static/research/map-free-reloc/assets/mapfree_rpr_weights.zip"
_LOSS_KEYS = {"s_r": "criterion.s_rot", "s_t": "criterion.s_trans"}


_LICENCE = "Niantic's non-commercial licence"
#: The published checkpoints as ``mapfree.weights`` files: found by the one rule, ``<name>.ckpt`` (or as unzipped,
#: ``mapfree/<name>.ckpt``) in ``$MAPFREE_WEIGHTS_DIR`` or the default folder.
RPR_WEIGHTS = {
    name: WeightFile(
        f"{name}.ckpt",
        f"rpr-{name}",
        (WEIGHTS_URL,),
        aliases=(f"mapfree/{name}.ckpt", f"weights/mapfree/{name}.ckpt"),
        licence=_LICENCE,
        archive=True,
    )
    for name in OFFICIAL_CONFIGS
}


def find_weights(name: str) -> Path:
    """``<name>.ckpt`` by the weights rule (also as unzipped: ``mapfree/<name>.ckpt``); a clear error if absent."""
    wf = RPR_WEIGHTS.get(name) or WeightFile(f"{name}.ckpt", f"rpr-{name}", (WEIGHTS_URL,), archive=True)
    hit = find_in_dirs(wf.filename, *wf.aliases)
    if hit is None:
        raise MissingWeightsError(
            missing_message(wf.what, wf.item(), wf.filename, f"{wf.how()}, or pass --checkpoint FILE")
        )
    return hit[0]


def read_checkpoint(path: os.PathLike | str) -> dict[str, Any]:
    """A checkpoint file as a dict holding ``state_dict``; a clear error naming the file otherwise."""
    import torch  # here, not at import: ``mapfree.rpr`` registers its methods without loading torch

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"RPR checkpoint {path} not found")
    if (why := file_problem(path)) is not None:  # a web page or text is named so, not unpickled
        raise ValueError(f"{path} is refused: {why} (an interrupted download? fetch it again)")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)  # Lightning checkpoints pickle extras
    except Exception as e:  # noqa: BLE001 - any unreadable file is the same user error
        raise ValueError(f"{path}: not a readable PyTorch checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict):
        raise ValueError(f"{path}: not a Lightning checkpoint (no 'state_dict')")
    return ckpt


def is_public(ckpt: dict[str, Any]) -> bool:
    """True for a public Map-free checkpoint (no config of ours, the public key layout)."""
    ours = isinstance(ckpt.get("hyper_parameters"), dict) and "config" in ckpt["hyper_parameters"]
    return not ours and "encoder.firstconv.weight" in ckpt["state_dict"]


def official_config_for(path: os.PathLike | str, name: str | None = None) -> str:
    """The configuration of a public checkpoint: ``name`` if given, else the file's stem (``3d3d.ckpt``)."""
    name = name or Path(path).stem
    if name not in OFFICIAL_CONFIGS:
        raise ValueError(
            f"{path}: a public Map-free checkpoint; say which configuration it is with "
            f"--method rpr-<config>, <config> one of {', '.join(OFFICIAL_CONFIGS)}"
        )
    return name


def load_weights(module: torch.nn.Module, ckpt: dict[str, Any], source: str = "checkpoint") -> None:
    """Load a public or our own checkpoint's weights into an ``RPRModule``.

    Every key of the checkpoint must exist in the module with its shape, and every module key must come from the
    checkpoint except an uncertainty head the checkpoint lacks (added for fine-tuning a confidence).
    """
    sd = ckpt["state_dict"]
    if is_public(ckpt):
        sd = {_LOSS_KEYS.get(k, f"net.{k}"): v for k, v in sd.items()}
    own = module.state_dict()
    unexpected = sorted(k for k in sd if k not in own)
    missing = sorted(k for k in own if k not in sd and not k.startswith("net.uncertainty."))
    shapes = sorted(
        f"{k} {tuple(sd[k].shape)} vs {tuple(own[k].shape)}"
        for k in sd
        if k in own and tuple(sd[k].shape) != tuple(own[k].shape)
    )
    if unexpected or missing or shapes:
        parts = [
            f"unexpected: {', '.join(unexpected[:5])}" if unexpected else "",
            f"missing: {', '.join(missing[:5])}" if missing else "",
            f"shape: {', '.join(shapes[:5])}" if shapes else "",
        ]
        raise ValueError(f"{source}: does not match the configured network ({'; '.join(p for p in parts if p)})")
    module.load_state_dict(sd, strict=False)
