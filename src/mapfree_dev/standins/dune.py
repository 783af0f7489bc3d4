"""Fill-rule stand-ins of DUNE-MASt3R files in the published layouts (tests, ``bench/``): the decoder file
``{"dune_backbone_name", "mast3r_model_str", "model"}`` with or without the encoder's ``dune_backbone.*`` tensors,
and the encoder file ``{"args": Namespace(image_size, enc_args), "model": {"encoder.K": …}}``.

Every tensor is ``fill_value`` of its key in the whole model (``dune_backbone.…``, ``norm.…``, ``mast3r.…``),
the ImageNet statistics the constructor's constants: the rule the public-code fixture was built with.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch

from mapfree.mast3r.config import ModelConfig, config_from_kwargs, parse_constructor
from mapfree.mast3r.dune import IMAGENET_MEAN, IMAGENET_STD, DuneMast3rModel, DuneShape
from mapfree.mast3r.dune_checkpoint import ARCH_HEADS
from mapfree.mast3r.published import DUNE_DECODERS, DUNE_ENCODERS, DUNE_KINDS

from .mast3r import fill_value

__all__ = [
    "PUBLISHED_STR",
    "architecture",
    "iter_filled_state_dict",
    "filled_state_dict",
    "save_decoder",
    "save_encoder",
    "write_published_standin",
    "write_tiny_standin",
]

BACKBONE = "dune_backbone."
#: ``mast3r_model_str`` of the published decoders as the public-code fixture derives them (ViT-B decoder).
PUBLISHED_STR = (
    "AsymmetricMASt3R(pos_embed='RoPE100', patch_embed_cls='PatchEmbedDust3R', img_size=(518, 518), "
    "head_type='catmlp+dpt', output_mode='pts3d+desc24', depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), "
    "enc_embed_dim={E}, enc_depth=12, enc_num_heads={H}, dec_embed_dim=768, dec_depth=12, dec_num_heads=12, "
    "two_confs=True, desc_conf_mode=('exp', 0, inf))"
)
_PUBLISHED_ARCH = {"dune-mast3r": ("vit_base", 768, 12), "dune-mast3r-small": ("vit_small", 384, 6)}


def architecture(model_str: str, image_size: int, enc_args: Mapping[str, Any]) -> tuple[ModelConfig, DuneShape]:
    """The decoder's configuration (patch 14) and the encoder's shape from a decoder string and encoder args.

    Args:
        model_str: ``mast3r_model_str``.
        image_size: The encoder's training size (pixels; its position grid is image_size / 14).
        enc_args: ``arch`` (``vit_small``, ``vit_base``), or ``embed_dim``/``depth``/``num_heads``/``mlp_ratio``.

    Returns:
        (config, shape).
    """
    cls, kwargs = parse_constructor(model_str)
    cfg = config_from_kwargs(cls, {**kwargs, "patch_size": 14})
    arch = enc_args.get("arch")
    if arch in ARCH_HEADS:
        dim, depth = {"vit_small": (384, 12), "vit_base": (768, 12), "vit_large": (1024, 24)}[arch]
        heads = ARCH_HEADS[arch]
    else:
        dim, depth, heads = int(enc_args["embed_dim"]), int(enc_args["depth"]), int(enc_args["num_heads"])
    mlp = int(dim * float(enc_args.get("mlp_ratio", 4)))
    return cfg, DuneShape(dim, depth, heads, 14, image_size // 14, 4, mlp)


def iter_filled_state_dict(cfg: ModelConfig, shape: DuneShape) -> Iterator[tuple[str, torch.Tensor]]:
    """(key, tensor) of the whole model in state-dict order, one at a time."""
    with torch.device("meta"):
        net = DuneMast3rModel(cfg, shape)
    for key, t in net.state_dict().items():
        if key == "imagenet_mean":
            yield key, torch.tensor(IMAGENET_MEAN).reshape(1, 3, 1, 1)
        elif key == "imagenet_std":
            yield key, torch.tensor(IMAGENET_STD).reshape(1, 3, 1, 1)
        else:
            yield key, torch.from_numpy(fill_value(key, tuple(t.shape)))


def filled_state_dict(cfg: ModelConfig, shape: DuneShape) -> dict[str, torch.Tensor]:
    return dict(iter_filled_state_dict(cfg, shape))


def save_decoder(
    path: str | Path, backbone_name: str, model_str: str, sd: Mapping[str, torch.Tensor], with_encoder: bool = True
) -> Path:
    """A decoder file in the published layout (the ImageNet buffers left out, as the published files do).

    Args:
        path: Where to write.
        backbone_name: ``dune_backbone_name``.
        model_str: ``mast3r_model_str``.
        sd: The whole model's state dict.
        with_encoder: Keep the ``dune_backbone.*`` tensors (else the encoder file is needed).

    Returns:
        ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = {
        k: v for k, v in sd.items() if not k.startswith("imagenet_") and (with_encoder or not k.startswith(BACKBONE))
    }
    torch.save({"dune_backbone_name": backbone_name, "mast3r_model_str": model_str, "model": model}, path)
    return path


def save_encoder(
    path: str | Path, image_size: int, enc_args: Mapping[str, Any], sd: Mapping[str, torch.Tensor]
) -> Path:
    """An encoder file in the published layout: the ``dune_backbone.*`` tensors of ``sd`` as ``encoder.*``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    enc = {"encoder." + k[len(BACKBONE) :]: v for k, v in sd.items() if k.startswith(BACKBONE)}
    torch.save({"args": argparse.Namespace(image_size=image_size, enc_args=dict(enc_args)), "model": enc}, path)
    return path


def write_published_standin(folder: str | Path, kind: str, dtype: torch.dtype = torch.float32) -> tuple[Path, Path]:
    """The published decoder and encoder files of ``kind`` (``dune-mast3r``, ``dune-mast3r-small``) in
    ``folder``, at the published sizes, with fill-rule weights (for benchmarks without the real files).

    Returns:
        (decoder file, encoder file).
    """
    arch, dim, heads = _PUBLISHED_ARCH[kind]
    model_str = PUBLISHED_STR.format(E=dim, H=heads)
    enc_args = {"arch": arch}
    cfg, shape = architecture(model_str, 448, enc_args)
    sd = {k: v.to(dtype) for k, v in iter_filled_state_dict(cfg, shape)}
    name = DUNE_KINDS[kind]
    folder = Path(folder)
    dec = save_decoder(folder / DUNE_DECODERS[kind].filename, name, model_str, sd, with_encoder=False)
    enc = save_encoder(folder / DUNE_ENCODERS[name].filename, 448, enc_args, sd)
    return dec, enc


#: A tiny DUNE-MASt3R (the public-code fixture's ``dune-small-tiny``): for tests of the whole path.
TINY_STR = (
    "AsymmetricMASt3R(pos_embed='RoPE100', patch_embed_cls='PatchEmbedDust3R', img_size=(518, 518), "
    "head_type='catmlp+dpt', output_mode='pts3d+desc24', depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), "
    "enc_embed_dim=48, enc_depth=2, enc_num_heads=3, dec_embed_dim=32, dec_depth=10, dec_num_heads=2, "
    "two_confs=True, desc_conf_mode=('exp', 0, inf))"
)
TINY_ENC_ARGS = {"arch": "DinoVisionTransformer", "embed_dim": 48, "depth": 2, "num_heads": 3, "mlp_ratio": 4}


def write_tiny_standin(folder: str | Path, kind: str) -> tuple[Path, Path]:
    """The files of ``kind`` under their published names in ``folder``, holding the tiny fill-rule model (the
    decoder without the encoder, so the encoder file is found by name as a user's download is).

    Returns:
        (decoder file, encoder file).
    """
    cfg, shape = architecture(TINY_STR, 56, TINY_ENC_ARGS)
    sd = filled_state_dict(cfg, shape)
    name = DUNE_KINDS[kind]
    folder = Path(folder)
    dec = save_decoder(folder / DUNE_DECODERS[kind].filename, name, TINY_STR, sd, with_encoder=False)
    enc = save_encoder(folder / DUNE_ENCODERS[name].filename, 56, TINY_ENC_ARGS, sd)
    return dec, enc
