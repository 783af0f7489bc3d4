"""Finding and reading MicKey's files: the authors' checkpoint, Meta's DINOv2 backbone and the shipped config.

The files follow the one weights rule (``mapfree.weights``, the models ``MICKEY_CHECKPOINTS`` and
``MICKEY_DINOV2`` of ``mickey.published``): a path given for a file (the matcher's ``weights``, ``dinov2``,
``config`` options), else ``mickey/`` (or the authors' ``mickey/mickey_weights/``) in ``$MAPFREE_WEIGHTS_DIR``,
then in the default folder ``~/.cache/mapfree/weights``. There: ``mickey.ckpt`` or ``mickey_sc.ckpt`` and
``config.yaml`` from the authors' ``mickey_weights.zip``, and ``dinov2_vitl14_pretrain.pth`` (also found in the
weights folder itself and in torch's hub cache, where the public code downloads it, and downloaded there on
first use when online). mapfree ships none of them: MicKey's weights are under Niantic's non-commercial licence.

The checkpoint is a PyTorch Lightning file whose ``state_dict`` holds every key of the network except DINOv2's;
DINOv2 comes from its own file. Files are read with ``torch.load(weights_only=True)``: only tensors and plain
containers are built. Other objects a Lightning file may carry (its callbacks' and loops' state) are replaced
by inert placeholders, never constructed, and ignored. Keys load strictly. A file that is missing is a
``MissingWeightsError``, one cut short or unreadable a ``BrokenWeightsError``, each naming it, as for every model.
"""

from __future__ import annotations

import os
import pickle
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ..mast3r.checkpoint import load_error_gist
from ..weights import BrokenWeightsError, MissingWeightsError, file_problem, resolve_weights
from .config import MickeyConfig, config_from_yaml
from .dinov2 import ViTShape
from .model import MickeyNet
from .published import MICKEY_CHECKPOINTS, MICKEY_DINOV2, MICKEY_ZIP_URL

__all__ = [
    "MickeyFiles",
    "CHECKPOINTS",
    "WEIGHTS_ZIP_URL",
    "DINOV2_URL",
    "SUBDIR",
    "find_files",
    "files_available",
    "read_checkpoint",
    "read_dinov2",
    "network_from_state_dicts",
    "load_network",
    "published_key",
    "EXTRACTOR_PREFIX",
    "DUSTBIN_KEY",
    "DINOV2_FILE",
]

SUBDIR = MICKEY_DINOV2.folder
CHECKPOINTS = tuple(MICKEY_CHECKPOINTS)
WEIGHTS_ZIP_URL = MICKEY_ZIP_URL
DINOV2_URL = MICKEY_DINOV2.urls[0]
DINOV2_FILE = MICKEY_DINOV2.filename
CONFIG_NAMES = ("config.yaml", "config.yml")
EXTRACTOR_PREFIX = "compute_matches.extractor."
DUSTBIN_KEY = "compute_matches.matcher.matching_mat.dustbin_score"
_CKPT_DINOV2 = EXTRACTOR_PREFIX + "dinov2_vitl14."  # absent from the published files; ignored when present


@dataclass(frozen=True)
class MickeyFiles:
    checkpoint: Path
    dinov2: Path
    config: Path | None


def _config(path: str | os.PathLike) -> Path:
    p = Path(path).expanduser()
    if p.is_dir():
        p = p / CONFIG_NAMES[0]
    if not p.is_file():
        raise MissingWeightsError(f"MicKey: config {p} not found (the config.yaml of {WEIGHTS_ZIP_URL})")
    return p


def find_files(
    checkpoint: str = "mickey",
    weights: str | os.PathLike | None = None,
    dinov2: str | os.PathLike | None = None,
    config: str | os.PathLike | None = None,
    download: bool = True,
) -> MickeyFiles:
    """The checkpoint (``checkpoint`` = ``mickey`` | ``mickey_sc``, or the file ``weights``), the DINOv2 file and
    the config YAML (the one beside the checkpoint when there is one; else the published defaults are used), by
    the weights rule. A missing file is a ``MissingWeightsError`` naming it, where it was looked for and where it is
    published; a file cut short (an interrupted download) a ``BrokenWeightsError`` naming it."""
    if checkpoint not in MICKEY_CHECKPOINTS:
        raise ValueError(f"MicKey: unknown checkpoint {checkpoint!r}; choose {' or '.join(CHECKPOINTS)}")
    ckpt = resolve_weights(MICKEY_CHECKPOINTS[checkpoint], weights)  # never downloaded: the zip is the user's
    dino = resolve_weights(MICKEY_DINOV2, dinov2, download=download)
    if config is not None:
        cfg: Path | None = _config(config)
    else:
        cfg = next((ckpt.parent / n for n in CONFIG_NAMES if (ckpt.parent / n).is_file()), None)
    return MickeyFiles(ckpt, dino, cfg)


def files_available(checkpoint: str = "mickey") -> bool:
    """Whether the checkpoint and DINOv2 are on this machine, whole (no download)."""
    try:
        find_files(checkpoint, download=False)
    except (MissingWeightsError, BrokenWeightsError):
        return False
    return True


class _Inert:
    """Stands for any non-tensor object a checkpoint pickles (never constructed from the file's data)."""

    def __new__(cls, *args: Any, **kwargs: Any) -> _Inert:
        return object.__new__(cls)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        pass


_UNSUPPORTED = re.compile(r"Unsupported global: GLOBAL (\S+) was not")


def _load_tensors(path: Path, what: str, expected: str) -> Any:
    """``torch.load(weights_only=True)``, any other global it meets standing in as an inert placeholder. A file
    cut short or unreadable is a ``BrokenWeightsError`` naming it."""
    why = file_problem(path)
    if why:  # cut short: said so, not torch's zip-reader internals
        raise BrokenWeightsError(f"MicKey: {path} is refused: {why} (an interrupted download? fetch it again)")
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
        raise BrokenWeightsError(f"{path}: not a readable {what} (too many non-tensor objects); expected {expected}")
    raise BrokenWeightsError(f"{path}: not a readable {what} ({load_error_gist(err)}); expected {expected}") from None


def read_checkpoint(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The heads' state dict of a MicKey checkpoint (published key names; any DINOv2 keys dropped)."""
    path = Path(path)
    expected = f"mickey.ckpt or mickey_sc.ckpt from {WEIGHTS_ZIP_URL}"
    ckpt = _load_tensors(path, "MicKey checkpoint", expected)
    sd = ckpt.get("state_dict") if isinstance(ckpt, dict) and "state_dict" in ckpt else ckpt
    if not isinstance(sd, Mapping) or not any(str(k).startswith(EXTRACTOR_PREFIX) for k in sd):
        raise BrokenWeightsError(
            f"{path}: not a MicKey checkpoint (no 'state_dict' with {EXTRACTOR_PREFIX}* keys); expected {expected}"
        )
    return {k: v for k, v in sd.items() if not k.startswith(_CKPT_DINOV2) and isinstance(v, torch.Tensor)}


def read_dinov2(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The DINOv2 file's state dict."""
    path = Path(path)
    sd = _load_tensors(path, "DINOv2 weight file", f"{DINOV2_FILE} from {DINOV2_URL}")
    if not isinstance(sd, Mapping) or "pos_embed" not in sd:
        raise BrokenWeightsError(
            f"{path}: not a DINOv2 weight file (no 'pos_embed'); expected {DINOV2_FILE} from {DINOV2_URL}"
        )
    return dict(sd)


def published_key(key: str) -> str:
    """Our network's parameter name -> the published file's (the backbone's: the DINOv2 file's own key)."""
    if key.startswith("backbone."):
        return key[len("backbone.") :]
    return DUSTBIN_KEY if key == "dustbin_score" else EXTRACTOR_PREFIX + key


def network_from_state_dicts(
    cfg: MickeyConfig,
    heads: Mapping[str, torch.Tensor],
    dinov2: Mapping[str, torch.Tensor],
    source: str = "checkpoint",
    dinov2_source: str = "DINOv2 weights",
) -> MickeyNet:
    """Build the network (DINOv2's size from its state dict) and load both state dicts strictly."""
    vit = ViTShape.from_state_dict(dinov2, dinov2_source)
    if cfg.channel_dim is not None and cfg.channel_dim != vit.dim:
        raise ValueError(
            f"{dinov2_source}: a DINOv2 of width {vit.dim}, but the MicKey config says CHANNEL_DIM {cfg.channel_dim}"
        )
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
            raise ValueError(
                f"{what}: state dict does not fit MicKey ({len(missing)} missing, e.g. {missing[:2]}; "
                f"{len(unexpected)} unexpected, e.g. {unexpected[:2]})"
            )
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
    net = network_from_state_dicts(
        cfg, read_checkpoint(files.checkpoint), read_dinov2(files.dinov2), str(files.checkpoint), str(files.dinov2)
    )
    half = cfg.float16 and torch.device(device).type == "cuda" if fp16 is None else bool(fp16)
    return net.to(device).half_backbone(half)
