"""Reading the published DUNE-MASt3R files into ``DuneMast3rModel``, keys matched strictly.

A decoder file (``dunemast3r_cvpr25_vit{base,small}.pth``) is ``{"dune_backbone_name": str, "mast3r_model_str":
str, "model": state_dict}``; the string is MASt3R's constructor call, parsed (never evaluated) and built at patch
14, as the public class does. The encoder comes from the same file when it holds ``dune_backbone.*`` keys, else
from the DUNE encoder file the name stands for (``dune_vitbase14_448_paper.pth``, ``dune_vitsmall14_448.pth``),
looked for in the weights folders: ``{"args": Namespace(image_size, enc_args), "model": {"encoder.K": …}}``, of
which the keys holding ``encoder.`` are kept, that prefix dropped, as the public hub loader does; its attention
heads come from ``enc_args`` (``num_heads``, or ``arch``: ``vit_small`` 6, ``vit_base`` 12). An encoder inside the
decoder file takes its heads from the string's ``enc_num_heads``. The ImageNet statistics, which the published
files lack, are the constructor's constants.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from ..weights import MissingWeightsError
from .checkpoint import load_strict, read_pth
from .config import ModelConfig, UnsupportedCheckpointError, config_from_kwargs, parse_constructor
from .dune import IMAGENET_MEAN, IMAGENET_STD, DuneMast3rModel, DuneShape
from .published import DUNE_DECODERS, DUNE_ENCODERS, DUNE_KINDS

__all__ = ["find_dune_checkpoint", "dune_checkpoint_available", "read_dune_checkpoint", "load_dune_model"]

#: Attention heads of DUNE's named architectures (naver/dune's ``vit_*``; the tensors do not show them).
ARCH_HEADS = {"vit_small": 6, "vit_base": 12, "vit_large": 16}
_ENCODER_PREFIX = "encoder."
_BACKBONE = "dune_backbone."
PATCH = 14


def find_dune_checkpoint(kind: str, explicit: str | os.PathLike | None = None) -> Path:
    """The decoder file of ``dune-mast3r`` / ``dune-mast3r-small`` by the weights rule.

    Args:
        kind: The matcher name.
        explicit: A file the user gave: then only there.

    Returns:
        The file.

    Raises:
        MissingWeightsError: Not found (which file, where to put it, where it is published).
    """
    wf = DUNE_DECODERS[kind]
    hit = wf.locate(explicit)
    if hit is None:
        raise wf.missing(explicit=explicit)
    return hit.path


def dune_checkpoint_available(kind: str) -> bool:
    """Whether the decoder file of ``kind`` and the encoder file it names (by the published name) are found.

    Args:
        kind: ``dune-mast3r`` or ``dune-mast3r-small``.

    Returns:
        True when both are in a weights folder.
    """
    return DUNE_DECODERS[kind].locate() is not None and DUNE_ENCODERS[DUNE_KINDS[kind]].locate() is not None


def _heads(args: Any, source: Path) -> int:
    """Attention heads from an encoder file's ``args.enc_args`` (``num_heads``, or the named architecture)."""
    enc_args = getattr(args, "enc_args", None) if not isinstance(args, dict) else args.get("enc_args")
    if not isinstance(enc_args, dict):
        raise ValueError(f"{source}: its 'args' has no 'enc_args' (not a DUNE encoder file)")
    if isinstance(enc_args.get("num_heads"), int):
        return int(enc_args["num_heads"])
    arch = enc_args.get("arch")
    if arch not in ARCH_HEADS:
        raise UnsupportedCheckpointError(
            f"{source}: unsupported DUNE encoder arch={arch!r} (supported: {', '.join(ARCH_HEADS)})"
        )
    return ARCH_HEADS[arch]


def read_dune_encoder(path: Path) -> tuple[dict[str, torch.Tensor], int]:
    """A DUNE encoder file's tensors (``encoder.`` dropped) and its attention heads.

    Args:
        path: ``dune_vit…pth``.

    Returns:
        The encoder's state dict and heads.

    Raises:
        BrokenWeightsError: The file is cut short.
        ValueError: Not a DUNE encoder file.
    """
    ckpt = read_pth(path, "DUNE encoder")
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("model"), dict) or "args" not in ckpt:
        raise ValueError(f"{path}: not a DUNE encoder file (expected the keys 'args' and 'model')")
    sd = {
        k[k.index(_ENCODER_PREFIX) + len(_ENCODER_PREFIX) :]: v
        for k, v in ckpt["model"].items()
        if _ENCODER_PREFIX in k
    }
    if not sd:
        raise ValueError(f"{path}: not a DUNE encoder file (no 'encoder.*' tensors)")
    return sd, _heads(ckpt["args"], path)


def _decoder_config(expr: str, source: Path) -> ModelConfig:
    try:
        cls, kwargs = parse_constructor(expr)
        if cls != "AsymmetricMASt3R":
            raise UnsupportedCheckpointError(f"mast3r_model_str builds {cls!r}, not AsymmetricMASt3R")
        cfg = config_from_kwargs(cls, {**kwargs, "patch_size": PATCH})  # appended by the public class
    except UnsupportedCheckpointError as e:
        raise UnsupportedCheckpointError(f"{source}: {e}") from None
    if any(s % PATCH for s in cfg.img_size):
        raise UnsupportedCheckpointError(f"{source}: img_size={cfg.img_size} is not a multiple of the patch {PATCH}")
    return cfg


def read_dune_checkpoint(
    path: str | os.PathLike, encoder: str | os.PathLike | None = None
) -> tuple[ModelConfig, DuneShape, dict[str, torch.Tensor]]:
    """Read a DUNE-MASt3R decoder file and its encoder, without building the network.

    Args:
        path: The decoder file.
        encoder: The encoder file (or a folder holding it); default: the file the decoder names, in the weights
            folders. Not read when the decoder file holds the encoder.

    Returns:
        The MASt3R part's configuration (patch 14), the encoder's shape and the whole state dict
            (``imagenet_*``, ``dune_backbone.*``, ``norm.*``, ``mast3r.*``).

    Raises:
        MissingWeightsError: The encoder file is not found (named, with where it is published).
        BrokenWeightsError: A file is cut short.
        UnsupportedCheckpointError: An architecture this port does not implement (named).
        ValueError: Not a DUNE-MASt3R file; an unknown encoder name; an encoder of another width.
    """
    p = Path(path)
    ckpt = read_pth(p, "DUNE-MASt3R")
    keys = (("dune_backbone_name", str), ("mast3r_model_str", str), ("model", dict))
    if not isinstance(ckpt, dict) or not all(isinstance(ckpt.get(k), t) for k, t in keys):
        raise ValueError(
            f"{p}: not a DUNE-MASt3R decoder file (expected the keys 'dune_backbone_name', 'mast3r_model_str', 'model')"
        )
    cfg = _decoder_config(ckpt["mast3r_model_str"], p)
    name: str = ckpt["dune_backbone_name"]
    sd: dict[str, torch.Tensor] = dict(ckpt["model"])
    if any(k.startswith(_BACKBONE) for k in sd):
        enc = {k[len(_BACKBONE) :]: v for k, v in sd.items() if k.startswith(_BACKBONE)}
        shape = DuneShape.from_state_dict(enc, cfg.enc_num_heads, f"{p} (its {_BACKBONE}* tensors)")
    else:
        enc, shape = _published_encoder(name, p, cfg, encoder)
        sd.update({_BACKBONE + k: v for k, v in enc.items()})
    sd.setdefault("imagenet_mean", torch.tensor(IMAGENET_MEAN).reshape(1, 3, 1, 1))
    sd.setdefault("imagenet_std", torch.tensor(IMAGENET_STD).reshape(1, 3, 1, 1))
    return cfg, shape, sd


def _published_encoder(
    name: str, decoder: Path, cfg: ModelConfig, explicit: str | os.PathLike | None
) -> tuple[dict[str, torch.Tensor], DuneShape]:
    wf = DUNE_ENCODERS.get(name)
    if explicit is not None:  # the user's file, whatever the decoder calls it
        path = Path(explicit).expanduser()
        if path.is_dir() and wf is not None:
            path = path / wf.filename
        if not path.is_file():
            raise MissingWeightsError(f"DUNE encoder for {decoder.name}: {explicit} not found")
    elif wf is None:
        raise ValueError(
            f"{decoder}: holds no encoder and names an unknown DUNE encoder dune_backbone_name={name!r} "
            f"(known: {', '.join(DUNE_ENCODERS)})"
        )
    else:
        hit = wf.locate()
        if hit is None:
            raise wf.missing(why=f"{decoder.name} holds no encoder and names {name}")
        path = hit.path
    enc, heads = read_dune_encoder(path)
    shape = DuneShape.from_state_dict(enc, heads, str(path))
    if shape.dim != cfg.enc_embed_dim:
        needs = f" (that decoder needs {wf.filename}, published at {wf.urls[0]})" if wf is not None else ""
        raise ValueError(
            f"{path}: a DUNE encoder of width {shape.dim} does not fit {decoder}, built for width "
            f"{cfg.enc_embed_dim}{needs}"
        )
    return enc, shape


def load_dune_model(
    path: str | os.PathLike, device: str | torch.device = "cpu", encoder: str | os.PathLike | None = None
) -> DuneMast3rModel:
    """Load a DUNE-MASt3R decoder file and its encoder into the network (strict keys).

    Args:
        path: The decoder file.
        device: Where the network is put.
        encoder: The encoder file; default: found by the name the decoder gives (see ``read_dune_checkpoint``).

    Returns:
        The network in eval mode on ``device``.
    """
    cfg, shape, sd = read_dune_checkpoint(path, encoder)
    with torch.device("meta"):
        net = DuneMast3rModel(cfg, shape)
    return load_strict(net, sd, str(path), "DUNE-MASt3R").to(device)
