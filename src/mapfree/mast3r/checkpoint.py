"""Reading published MASt3R/DUSt3R checkpoints into ``AsymmetricModel`` with strict key matching.

Two forms: the authors' ``.pth`` (``{"model": state_dict, "args": Namespace(model="AsymmetricMASt3R(…)")}``)
and the hub's folder (``config.json`` of constructor arguments + ``model.safetensors``, or ``pytorch_model.bin``
in older pushes). A checkpoint without the second decoder gets a copy of the first, as the public loader does.
Weights are never shipped with mapfree (CC BY-NC-SA 4.0): the user downloads them and we find them by name in
the weights folders (``$MAPFREE_WEIGHTS_DIR``, then ``~/.cache/mapfree/weights``: ``mapfree.weights``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import torch

from ..weights import BrokenWeightsError, MissingWeightsError, check_folder, file_problem
from .config import ModelConfig, UnsupportedCheckpointError, config_from_kwargs, parse_constructor
from .model import AsymmetricModel
from .published import MAST3R_WEIGHTS

M = TypeVar("M", bound=torch.nn.Module)

__all__ = [
    "Published",
    "read_pth",
    "load_strict",
    "PUBLISHED",
    "find_checkpoint",
    "checkpoint_available",
    "load_model",
    "read_checkpoint",
    "model_from_state_dict",
    "load_error_gist",
]


@dataclass(frozen=True)
class Published:
    """A published checkpoint and its architecture.

    Attributes:
        stem: File stem looked for (``STEM.pth`` or the hub folder ``STEM/``).
        hub_id: Hugging Face hub id.
        url: Direct download of the ``.pth``.
        expr: The constructor call stored in the ``.pth`` (the architecture).
    """

    stem: str
    hub_id: str
    url: str
    expr: str  # the constructor call stored in the .pth (the architecture)


_EXPR = {
    "mast3r": (
        "AsymmetricMASt3R(pos_embed='RoPE100', patch_embed_cls='PatchEmbedDust3R', img_size=(512, 512), "
        "head_type='catmlp+dpt', output_mode='pts3d+desc24', depth_mode=('exp', -inf, inf), conf_mode=('exp', "
        "1, inf), enc_embed_dim=1024, enc_depth=24, enc_num_heads=16, dec_embed_dim=768, dec_depth=12, "
        "dec_num_heads=12, two_confs=True, desc_conf_mode=('exp', 0, inf), landscape_only=False)"
    ),
    "dust3r": (
        "AsymmetricCroCo3DStereo(pos_embed='RoPE100', patch_embed_cls='PatchEmbedDust3R', img_size=(512, 512), "
        "head_type='dpt', output_mode='pts3d', depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), "
        "enc_embed_dim=1024, enc_depth=24, enc_num_heads=16, dec_embed_dim=768, dec_depth=12, "
        "dec_num_heads=12, landscape_only=False)"
    ),
}
PUBLISHED = {kind: Published(w.stem, w.hub_id, w.url, _EXPR[kind]) for kind, w in MAST3R_WEIGHTS.items()}
_HUB_WEIGHTS = ("model.safetensors", "pytorch_model.bin")


def _is_hub_folder(p: Path) -> bool:
    return (p / "config.json").is_file() and any((p / w).is_file() for w in _HUB_WEIGHTS)


def find_checkpoint(kind: str, explicit: str | os.PathLike | None = None) -> Path:
    """Find the published checkpoint of a network by the weights rule (``mapfree.weights``).

    Args:
        kind: ``mast3r`` or ``dust3r``.
        explicit: A ``.pth`` file or hub folder the user gave: then only there. Else ``STEM.pth`` or the hub
            folder ``STEM/`` is looked for in ``$MAPFREE_WEIGHTS_DIR`` and the default folder.

    Returns:
        The file or folder.

    Raises:
        MissingWeightsError: Not found (saying which file to put where, and where it is published).
    """
    w = MAST3R_WEIGHTS[kind]
    hit = w.locate(explicit)
    if hit is None or (hit.path.is_dir() and not _is_hub_folder(hit.path)):
        raise w.missing(explicit=explicit)
    return hit.path


def checkpoint_available(kind: str) -> bool:
    """Whether the published checkpoint of a network is in a weights folder.

    Args:
        kind: ``mast3r`` or ``dust3r``.

    Returns:
        True when ``find_checkpoint`` finds it.
    """
    try:
        find_checkpoint(kind)
    except MissingWeightsError:
        return False
    return True


def load_error_gist(e: Exception) -> str:
    """The gist of a ``torch.load`` failure, for a one-line error (its weights-only errors bury it in advice).

    Args:
        e: The exception ``torch.load`` raised.

    Returns:
        ``TYPE: gist``, at most about 200 characters.
    """
    m = re.search(r"WeightsUnpickler error:\s*(.+?)(?:\n\s*\n|$)", str(e), re.S)
    gist = m.group(1) if m else (str(e).strip().splitlines() or [""])[0]
    return f"{type(e).__name__}: {' '.join(gist.split())[:200]}"


def read_pth(path: Path, what: str = "MASt3R/DUSt3R") -> Any:
    """``torch.load`` of a checkpoint file, weights only (tensors, containers, ``argparse.Namespace``).

    Args:
        path: The file.
        what: The kind of checkpoint expected, named in errors.

    Returns:
        What the file holds.

    Raises:
        BrokenWeightsError: The file is cut short (an interrupted download).
        ValueError: Not a readable checkpoint (or one that needs more than weights-only loading).
    """
    why = file_problem(path)
    if why:  # cut short: said so, not torch's zip-reader internals
        raise BrokenWeightsError(f"{path} is refused: {why} (an interrupted download? fetch it again)")
    try:
        with torch.serialization.safe_globals([argparse.Namespace]):
            return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable file is the same user error
        raise ValueError(
            f"{path}: not a readable {what} checkpoint ({load_error_gist(e)}); expected the "
            f"authors' .pth file" + (" or a hub folder (config.json + model.safetensors)" if "MASt3R/" in what else "")
        ) from None


def _load_pth(path: Path) -> tuple[Mapping[str, torch.Tensor], str]:
    ckpt = read_pth(path)
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("model"), dict) or "args" not in ckpt:
        hint = " (a DUNE-MASt3R file: use dune-mast3r)" if isinstance(ckpt, dict) and "mast3r_model_str" in ckpt else ""
        raise ValueError(f"{path}: not a MASt3R/DUSt3R checkpoint (expected the keys 'model' and 'args'){hint}")
    args = ckpt["args"]
    expr = getattr(args, "model", None) if not isinstance(args, dict) else args.get("model")
    if not isinstance(expr, str):
        raise ValueError(f"{path}: its 'args' has no model constructor string")
    return ckpt["model"], expr


def _load_hub(folder: Path) -> tuple[Mapping[str, torch.Tensor], dict[str, Any]]:
    check_folder(folder, "MASt3R/DUSt3R")  # a weights file cut short: named, before safetensors reads it
    try:
        kwargs = json.loads((folder / "config.json").read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{folder / 'config.json'}: not readable JSON ({e})") from None
    if (folder / "model.safetensors").is_file():
        from safetensors.torch import load_file

        return load_file(str(folder / "model.safetensors")), kwargs
    sd = torch.load(folder / "pytorch_model.bin", map_location="cpu", weights_only=True)
    return sd, kwargs


def _hub_class(kwargs: Mapping[str, Any]) -> str:
    """The hub's config.json does not name the class; MASt3R's is the one with a descriptor head."""
    return "AsymmetricMASt3R" if str(kwargs.get("head_type", "")).startswith("catmlp") else "AsymmetricCroCo3DStereo"


def read_checkpoint(path: str | os.PathLike) -> tuple[ModelConfig, Mapping[str, torch.Tensor]]:
    """Read a checkpoint's architecture and weights without building the network.

    Args:
        path: The authors' ``.pth`` file or a hub folder (``config.json`` + ``model.safetensors``).

    Returns:
        The configuration and the state dict.

    Raises:
        UnsupportedCheckpointError: An architecture argument this port does not implement (named).
        BrokenWeightsError: A file is cut short.
        ValueError: Not a MASt3R/DUSt3R checkpoint.
    """
    p = Path(path)
    try:
        if p.is_dir():
            sd, kwargs = _load_hub(p)
            return config_from_kwargs(_hub_class(kwargs), kwargs), sd
        sd, expr = _load_pth(p)
        return config_from_kwargs(*parse_constructor(expr)), sd
    except UnsupportedCheckpointError as e:
        raise UnsupportedCheckpointError(f"{p}: {e}") from None


def model_from_state_dict(
    cfg: ModelConfig, sd: Mapping[str, torch.Tensor], source: str = "checkpoint"
) -> AsymmetricModel:
    """Build the network and load a state dict strictly (``dec_blocks2`` copied from ``dec_blocks`` when absent).

    Args:
        cfg: The architecture.
        sd: The weights.
        source: The file they came from, named in errors.

    Returns:
        The network in eval mode, float32, on the CPU.

    Raises:
        ValueError: The state dict does not fit the architecture (missing or unexpected keys, shapes).
    """
    sd = dict(sd)
    if not any(k.startswith("dec_blocks2.") for k in sd):
        first = [(k, v) for k, v in sd.items() if k.startswith("dec_blocks.")]
        sd.update({"dec_blocks2." + k[len("dec_blocks.") :]: v for k, v in first})
    with torch.device("meta"):
        net = AsymmetricModel(cfg)
    return load_strict(net, sd, source, cfg.class_name)


def load_strict(net: M, sd: Mapping[str, torch.Tensor], source: str, what: str) -> M:
    """Load a state dict into a network built on the meta device, every key matched (the tensors are taken
    as they are, not copied).

    Args:
        net: The network, built under ``torch.device("meta")``.
        sd: The weights.
        source: The file they came from, named in errors.
        what: The architecture, named in errors.

    Returns:
        The network in eval mode, float32, on the CPU.

    Raises:
        ValueError: Missing or unexpected keys, or shapes that differ (one line, with examples).
    """
    missing = sorted(set(net.state_dict()) - set(sd))
    unexpected = sorted(set(sd) - set(net.state_dict()))
    if missing or unexpected:
        raise ValueError(
            f"{source}: state dict does not fit {what}: "
            f"{len(missing)} missing (e.g. {missing[:3]}), "
            f"{len(unexpected)} unexpected (e.g. {unexpected[:3]})"
        )
    try:
        net.load_state_dict(sd, strict=True, assign=True)
    except RuntimeError as e:
        why = str(e).splitlines()[-1].strip()
        raise ValueError(f"{source}: state dict does not fit {what} ({why})") from None
    return net.float().eval()


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu") -> AsymmetricModel:
    """Load a checkpoint into the network (``read_checkpoint`` then ``model_from_state_dict``).

    Args:
        path: The authors' ``.pth`` file or a hub folder.
        device: Where the network is put.

    Returns:
        The network in eval mode on ``device``.
    """
    cfg, sd = read_checkpoint(path)
    return model_from_state_dict(cfg, sd, str(path)).to(device)
