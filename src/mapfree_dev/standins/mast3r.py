"""Deterministic stand-in weights for any architecture: each tensor filled from a seed of its own name.

No published weights are needed to exercise the whole path (tests, ``bench/``, the GPU probe): the rule gives
the same numbers everywhere, so another implementation run on the same rule can be compared array by array.
"""

from __future__ import annotations

import argparse
import json
import math
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from mapfree.mast3r.config import ModelConfig, parse_constructor
from mapfree.mast3r.model import AsymmetricModel

__all__ = [
    "fill_value",
    "synthetic_state_dict",
    "iter_synthetic_state_dict",
    "save_pth",
    "save_hub",
    "write_published_standin",
]


def fill_value(key: str, shape: tuple[int, ...]) -> np.ndarray:
    """The tensor ``key`` of ``shape``: uniform [-1, 1) from seed crc32(key), scaled by the kind of tensor."""
    rng = np.random.default_rng(zlib.crc32(key.encode()))
    numel = int(np.prod(shape)) if shape else 1
    u = rng.random(numel) * 2 - 1
    leaf = key.rsplit(".", 1)[-1]
    if leaf == "running_var":
        v = 1 + 0.25 * np.abs(u)
    elif leaf in ("running_mean", "bias"):
        v = 0.05 * u
    elif len(shape) >= 2:
        v = u * math.sqrt(3 / int(np.prod(shape[1:])))
    else:
        v = 1 + 0.1 * u
    return v.reshape(shape).astype(np.float32)


def _layout(cfg: ModelConfig) -> dict[str, tuple[int, ...]]:
    with torch.device("meta"):
        net = AsymmetricModel(cfg)
    return {k: tuple(v.shape) for k, v in net.state_dict().items()}


def iter_synthetic_state_dict(cfg: ModelConfig) -> Iterator[tuple[str, torch.Tensor]]:
    """(key, tensor) in state-dict order, one at a time (a ViT-L model is built without two copies in memory)."""
    for key, shape in _layout(cfg).items():
        yield key, torch.from_numpy(fill_value(key, shape))


def synthetic_state_dict(cfg: ModelConfig) -> dict[str, torch.Tensor]:
    return dict(iter_synthetic_state_dict(cfg))


def save_pth(path: str | Path, expr: str, state_dict: dict[str, torch.Tensor]) -> Path:
    """Write ``state_dict`` in the authors' ``.pth`` form: ``{"model": …, "args": Namespace(model=expr)}``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"model": state_dict, "args": argparse.Namespace(model=expr)}, path)
    return path


def save_hub(folder: str | Path, expr: str, state_dict: dict[str, torch.Tensor]) -> Path:
    """Write ``state_dict`` in the hub's form: ``config.json`` (the constructor's keyword arguments) and
    ``model.safetensors``."""
    from safetensors.torch import save_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    _, kwargs = parse_constructor(expr)
    (folder / "config.json").write_text(json.dumps(kwargs, indent=1))
    save_file({k: v.contiguous() for k, v in state_dict.items()}, str(folder / "model.safetensors"))
    return folder


def write_published_standin(folder: str | Path, kind: str, dtype: torch.dtype = torch.float32) -> Path:
    """``<published stem>.pth`` in ``folder``: the published architecture of ``kind`` with fill-rule weights
    (``dtype`` float16 halves the file; the loader computes in float32). For benchmarks without the real file."""
    from mapfree.mast3r.checkpoint import PUBLISHED
    from mapfree.mast3r.config import config_from_kwargs

    pub = PUBLISHED[kind]
    cfg = config_from_kwargs(*parse_constructor(pub.expr))
    sd = {k: v.to(dtype) for k, v in iter_synthetic_state_dict(cfg)}
    return save_pth(Path(folder) / f"{pub.stem}.pth", pub.expr, sd)
