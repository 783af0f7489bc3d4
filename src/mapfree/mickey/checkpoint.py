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
    """The files of one MicKey network, found by ``find_files``.

    Attributes:
        checkpoint: The authors' checkpoint (``mickey.ckpt`` or ``mickey_sc.ckpt``).
        dinov2: The DINOv2 ViT-L/14 weight file.
        config: The config YAML, or None for the published defaults.
    """

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
    """Find a MicKey network's files by the weights rule.

    Args:
        checkpoint: ``mickey`` or ``mickey_sc``.
        weights: A checkpoint file (or a folder holding it) the user gave: then only there.
        dinov2: A DINOv2 file (or a folder holding it) the user gave.
        config: A config YAML the user gave; default the one beside the checkpoint, if any.
        download: Download DINOv2 into torch's hub cache when it is missing and the machine is online.

    Returns:
        The files.

    Raises:
        ValueError: ``checkpoint`` is unknown.
        MissingWeightsError: A file is missing (naming it, where it was looked for and where it is published).
        BrokenWeightsError: A file is cut short (an interrupted download).
    """
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
    """Whether a MicKey network's checkpoint and DINOv2 are on this machine, whole (nothing downloaded).

    Args:
        checkpoint: ``mickey`` or ``mickey_sc``.

    Returns:
        True when ``find_files`` finds both.
    """
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
    if why:  # cut short, a web page, text: said so, not torch's zip-reader internals
        raise BrokenWeightsError(
            f"MicKey: {path} is refused: {why} (an interrupted download? fetch it again); expected {expected}"
        )
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
    """Read the heads' weights from a MicKey checkpoint (tensors only, never code).

    Args:
        path: The Lightning checkpoint.

    Returns:
        The state dict with the published key names; any DINOv2 keys dropped.

    Raises:
        MissingWeightsError: The file does not exist.
        BrokenWeightsError: It is cut short or not a MicKey checkpoint.
    """
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
    """Read the DINOv2 backbone's weights.

    Args:
        path: Meta's ``dinov2_vitl14_pretrain.pth``.

    Returns:
        The state dict.

    Raises:
        MissingWeightsError: The file does not exist.
        BrokenWeightsError: It is cut short or not a DINOv2 file.
    """
    path = Path(path)
    sd = _load_tensors(path, "DINOv2 weight file", f"{DINOV2_FILE} from {DINOV2_URL}")
    if not isinstance(sd, Mapping) or "pos_embed" not in sd:
        raise BrokenWeightsError(
            f"{path}: not a DINOv2 weight file (no 'pos_embed'); expected {DINOV2_FILE} from {DINOV2_URL}"
        )
    return dict(sd)


def published_key(key: str) -> str:
    """The published files' name of one of our network's parameters.

    Args:
        key: Parameter name in ``MickeyNet``.

    Returns:
        The key in the checkpoint, or for the backbone the DINOv2 file's own key.
    """
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
    """Build the network (DINOv2's size read from its state dict) and load both state dicts strictly.

    Args:
        cfg: The MicKey configuration.
        heads: The checkpoint's state dict (``read_checkpoint``).
        dinov2: The DINOv2 state dict (``read_dinov2``).
        source: The checkpoint file, named in errors.
        dinov2_source: The DINOv2 file, named in errors.

    Returns:
        The network in eval mode, float32, on the CPU.

    Raises:
        ValueError: A state dict does not fit (missing or unexpected keys, a width the config contradicts).
    """
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
    """Load a MicKey network from its files.

    Args:
        files: The files (``find_files``).
        device: Where the network is put.
        fp16: DINOv2 in float16; None: where the config says so and ``device`` is a GPU (CPU half kernels are
            slow).

    Returns:
        The network in eval mode on ``device``.
    """
    cfg = config_from_yaml(files.config) if files.config is not None else MickeyConfig()
    net = network_from_state_dicts(
        cfg, read_checkpoint(files.checkpoint), read_dinov2(files.dinov2), str(files.checkpoint), str(files.dinov2)
    )
    half = cfg.float16 and torch.device(device).type == "cuda" if fp16 is None else bool(fp16)
    return net.to(device).half_backbone(half)
