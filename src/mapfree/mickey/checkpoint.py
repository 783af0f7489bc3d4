"""Finding and reading MicKey's files: the authors' checkpoint, Meta's DINOv2 backbone and the shipped config.

Layout (``$MAPFREE_WEIGHTS_DIR/mickey/``): ``mickey.ckpt`` or ``mickey_sc.ckpt`` and ``config.yaml`` from the
authors' ``mickey_weights.zip`` (its ``mickey_weights/`` folder may be kept), and ``dinov2_vitl14_pretrain.pth``
(also found in ``$MAPFREE_WEIGHTS_DIR`` itself or torch's hub cache, where the public code downloads it, and
downloaded there on first use when online). mapfree ships none of them: MicKey's weights are under Niantic's
non-commercial licence.

The checkpoint is a PyTorch Lightning file whose ``state_dict`` holds every key of the network except DINOv2's;
DINOv2 comes from its own file. Files are read with ``torch.load(weights_only=True)``: only tensors and plain
containers are built. Other objects a Lightning file may carry (its callbacks' and loops' state) are replaced
by inert placeholders, never constructed, and ignored. Keys load strictly.
"""

from __future__ import annotations

import os
import pickle
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import torch

from ..mast3r.checkpoint import load_error_gist
from ..matching.weights import WEIGHTS_ENV, MissingWeightsError, WeightFile, resolve_weights, weights_dir
from .config import MickeyConfig, config_from_yaml
from .dinov2 import ViTShape
from .model import MickeyNet

__all__ = ["MickeyFiles", "CHECKPOINTS", "WEIGHTS_ZIP_URL", "DINOV2_URL", "SUBDIR", "find_files", "files_available",
           "read_checkpoint", "read_dinov2", "network_from_state_dicts", "load_network", "published_key",
           "EXTRACTOR_PREFIX", "DUSTBIN_KEY", "DINOV2_FILE"]

SUBDIR = "mickey"
CHECKPOINTS = ("mickey", "mickey_sc")
WEIGHTS_ZIP_URL = "https://storage.googleapis.com/niantic-lon-static/research/mickey/assets/mickey_weights.zip"
DINOV2_URL = "https://dl.fbaipublicfiles.com/dinov2/dinov2_vitl14/dinov2_vitl14_pretrain.pth"
DINOV2_FILE = "dinov2_vitl14_pretrain.pth"
CONFIG_NAMES = ("config.yaml", "config.yml")
EXTRACTOR_PREFIX = "compute_matches.extractor."
DUSTBIN_KEY = "compute_matches.matcher.matching_mat.dustbin_score"
_CKPT_DINOV2 = EXTRACTOR_PREFIX + "dinov2_vitl14."  # absent from the published files; ignored when present
_LICENCE = "Niantic non-commercial licence: mapfree does not ship it"


@dataclass(frozen=True)
class MickeyFiles:
    checkpoint: Path
    dinov2: Path
    config: Path | None


def _folders() -> list[Path]:
    root = weights_dir()
    return [] if root is None else [root / SUBDIR, root / SUBDIR / "mickey_weights"]


def _where() -> str:
    root = weights_dir()
    now = f"now {root / SUBDIR}" if root is not None else f"${WEIGHTS_ENV} is not set"
    return f"${WEIGHTS_ENV}/{SUBDIR}/ ({now})"


def _explicit(path: str | os.PathLike, name: str, what: str) -> Path:
    p = Path(path).expanduser()
    if p.is_dir():
        p = p / name
    if not p.is_file():
        raise MissingWeightsError(f"MicKey: {what} {p} not found")
    return p


def _find_checkpoint(name: str, explicit: str | os.PathLike | None) -> Path:
    if name not in CHECKPOINTS:
        raise ValueError(f"MicKey: unknown checkpoint {name!r}; choose {' or '.join(CHECKPOINTS)}")
    if explicit is not None:
        return _explicit(explicit, f"{name}.ckpt", "checkpoint")
    for d in _folders():
        if (d / f"{name}.ckpt").is_file():
            return d / f"{name}.ckpt"
    raise MissingWeightsError(
        f"MicKey: weights file '{name}.ckpt' not found. Place '{name}.ckpt' (and the config.yaml beside it) in "
        f"{_where()}. It is published in mickey_weights.zip at {WEIGHTS_ZIP_URL} ({_LICENCE}).")


def _find_dinov2(explicit: str | os.PathLike | None, download: bool) -> Path:
    if explicit is not None:
        return _explicit(explicit, DINOV2_FILE, "DINOv2 weights")
    for d in _folders():
        if (d / DINOV2_FILE).is_file():
            return d / DINOV2_FILE
    wf = WeightFile(DINOV2_FILE, "MicKey's DINOv2 ViT-L/14 backbone", (DINOV2_URL,))
    try:
        return resolve_weights(wf, download=download)
    except MissingWeightsError:
        raise MissingWeightsError(
            f"MicKey: weights file '{DINOV2_FILE}' not found (offline or downloads off). Place '{DINOV2_FILE}' "
            f"in {_where()}. It is published at {DINOV2_URL} (Meta's DINOv2, Apache 2.0).") from None


def find_files(checkpoint: str = "mickey", weights: str | os.PathLike | None = None,
               dinov2: str | os.PathLike | None = None, config: str | os.PathLike | None = None,
               download: bool = True) -> MickeyFiles:
    """The checkpoint (``checkpoint`` = ``mickey`` | ``mickey_sc``, or the file ``weights``), the DINOv2 file and
    the config YAML (the one beside the checkpoint when there is one; else the published defaults are used).
    A missing file is a ``MissingWeightsError`` naming it, where to put it and where it is published."""
    ckpt = _find_checkpoint(checkpoint, weights)
    dino = _find_dinov2(dinov2, download)
    if config is not None:
        cfg: Path | None = _explicit(config, CONFIG_NAMES[0], "config")
    else:
        cfg = next((ckpt.parent / n for n in CONFIG_NAMES if (ckpt.parent / n).is_file()), None)
    return MickeyFiles(ckpt, dino, cfg)


def files_available(checkpoint: str = "mickey") -> bool:
    """Whether the checkpoint and DINOv2 are on this machine (no download)."""
    try:
        find_files(checkpoint, download=False)
    except MissingWeightsError:
        return False
    return True


class _Inert:
    """Stands for any non-tensor object a checkpoint pickles (never constructed from the file's data)."""

    def __new__(cls, *args: Any, **kwargs: Any) -> "_Inert":
        return object.__new__(cls)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        pass


_UNSUPPORTED = re.compile(r"Unsupported global: GLOBAL (\S+) was not")


def _load_tensors(path: Path, what: str, expected: str) -> Any:
    """``torch.load(weights_only=True)``, any other global it meets standing in as an inert placeholder."""
    inert: list[str] = []
    for _ in range(64):
        try:
            with torch.serialization.safe_globals([(_Inert, name) for name in inert]):
                return torch.load(path, map_location="cpu", weights_only=True)
        except pickle.UnpicklingError as e:
            m = _UNSUPPORTED.search(str(e))
            if m is None:
                err: Exception = e
                break
            name = m.group(1)
            inert.append(name if "." in name else f"builtins.{name}")
        except Exception as e:  # noqa: BLE001 - any unreadable file is the same user error
            err = e
            break
    else:  # pragma: no cover - 64 distinct foreign classes
        raise ValueError(f"{path}: not a readable {what} (too many non-tensor objects); expected {expected}")
    raise ValueError(f"{path}: not a readable {what} ({load_error_gist(err)}); expected {expected}") from None


def read_checkpoint(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The heads' state dict of a MicKey checkpoint (published key names; any DINOv2 keys dropped)."""
    path = Path(path)
    expected = f"mickey.ckpt or mickey_sc.ckpt from {WEIGHTS_ZIP_URL}"
    ckpt = _load_tensors(path, "MicKey checkpoint", expected)
    sd = ckpt.get("state_dict") if isinstance(ckpt, dict) and "state_dict" in ckpt else ckpt
    if not isinstance(sd, Mapping) or not any(str(k).startswith(EXTRACTOR_PREFIX) for k in sd):
        raise ValueError(f"{path}: not a MicKey checkpoint (no 'state_dict' with {EXTRACTOR_PREFIX}* keys); "
                         f"expected {expected}")
    return {k: v for k, v in sd.items() if not k.startswith(_CKPT_DINOV2) and isinstance(v, torch.Tensor)}


def read_dinov2(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The DINOv2 file's state dict."""
    path = Path(path)
    sd = _load_tensors(path, "DINOv2 weight file", f"{DINOV2_FILE} from {DINOV2_URL}")
    if not isinstance(sd, Mapping) or "pos_embed" not in sd:
        raise ValueError(f"{path}: not a DINOv2 weight file (no 'pos_embed'); expected {DINOV2_FILE} from "
                         f"{DINOV2_URL}")
    return dict(sd)


def published_key(key: str) -> str:
    """Our network's parameter name -> the published file's (the backbone's: the DINOv2 file's own key)."""
    if key.startswith("backbone."):
        return key[len("backbone."):]
    return DUSTBIN_KEY if key == "dustbin_score" else EXTRACTOR_PREFIX + key


def network_from_state_dicts(cfg: MickeyConfig, heads: Mapping[str, torch.Tensor],
                             dinov2: Mapping[str, torch.Tensor], source: str = "checkpoint",
                             dinov2_source: str = "DINOv2 weights") -> MickeyNet:
    """Build the network (DINOv2's size from its state dict) and load both state dicts strictly."""
    vit = ViTShape.from_state_dict(dinov2, dinov2_source)
    if cfg.channel_dim is not None and cfg.channel_dim != vit.dim:
        raise ValueError(f"{dinov2_source}: a DINOv2 of width {vit.dim}, but the MicKey config says CHANNEL_DIM "
                         f"{cfg.channel_dim}")
    with torch.device("meta"):
        net = MickeyNet(cfg, vit)
    ours = net.state_dict()
    sd: dict[str, torch.Tensor] = {}
    for key in ours:
        pub = published_key(key)
        src = dinov2 if key.startswith("backbone.") else heads
        if pub in src:
            sd[key] = src[pub]
    head_keys = {published_key(k) for k in ours if not k.startswith("backbone.")}
    dino_keys = {published_key(k) for k in ours if k.startswith("backbone.")}
    for what, have, want in ((source, set(heads), head_keys), (dinov2_source, set(dinov2), dino_keys)):
        missing, unexpected = sorted(want - have), sorted(have - want)
        if missing or unexpected:
            raise ValueError(f"{what}: state dict does not fit MicKey ({len(missing)} missing, e.g. {missing[:2]}; "
                             f"{len(unexpected)} unexpected, e.g. {unexpected[:2]})")
    try:
        net.load_state_dict(sd, strict=True, assign=True)
    except RuntimeError as e:
        why = str(e).strip().splitlines()[-1].strip()
        raise ValueError(f"{source}: state dict does not fit MicKey ({why})") from None
    return net.float().eval()


def load_network(files: MickeyFiles, device: str | torch.device = "cpu", fp16: bool | None = False) -> MickeyNet:
    """The files -> the network in eval mode on ``device``; DINOv2 in float16 when ``fp16``, or (None) where
    the config says so and ``device`` is a GPU (CPU half kernels are slow)."""
    cfg = config_from_yaml(files.config) if files.config is not None else MickeyConfig()
    net = network_from_state_dicts(cfg, read_checkpoint(files.checkpoint), read_dinov2(files.dinov2),
                                   str(files.checkpoint), str(files.dinov2))
    half = cfg.float16 and torch.device(device).type == "cuda" if fp16 is None else bool(fp16)
    return net.to(device).half_backbone(half)
