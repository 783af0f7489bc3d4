"""MicKey's network configuration: the published defaults, or the config YAML shipped with the weights.

The authors' ``mickey_weights.zip`` holds a yacs config next to each checkpoint. We read only the keys that shape
the network at inference (``MICKEY``, ``FEATURE_MATCHER``, ``DATASET.WIDTH/HEIGHT``) and refuse, by name, a value
this port does not implement; training keys are ignored. The solver's ``PROCRUSTES`` section has the same values
as the solver's defaults (``mapfree.solvers.mickey``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from ..yamlio import read_yaml

__all__ = ["MickeyConfig", "config_from_yaml", "config_from_mapping", "ATTENTION_DIM"]

#: Width of the heads' linear-attention layers (fixed in the public code): the third block's output.
ATTENTION_DIM = 128


@dataclass(frozen=True)
class MickeyConfig:
    """Inference settings of MicKey; the defaults are the published ``curriculum_learning`` configuration's.

    Attributes:
        float16: DINOv2 in half precision (the published config; on a GPU).
        kp_blocks: Channels of the res-blocks of every head (the descriptor's last is ``dsc_dim``).
        batch_norm: Batch normalisation in the heads.
        score_softmax: Score map by a softmax over the map (else a sigmoid).
        depth_sigmoid: Depth as ``max_depth * sigmoid(.)`` (else the raw output).
        max_depth: Depth bound of the sigmoid, metres.
        kp_pos_encoding: Position encoding in the keypoint heads.
        dsc_dim: Descriptor width.
        dsc_normalize: Unit-length descriptors.
        dsc_pos_encoding: Position encoding in the descriptor head.
        temperature: Temperature of the dual softmax.
        dustbin: A learned dustbin row and column in the matching matrix.
        width: Network input width before the crop to multiples of the patch, pixels.
        height: Network input height, pixels.
        channel_dim: DINOv2 width as the YAML states it (checked against the weight file), or None.
        down_factor: Patch side of the backbone, pixels.
    """

    float16: bool = True  # DINOv2 in half precision (the published config; on a GPU)
    kp_blocks: tuple[int, ...] = (512, 256, 128, 64)  # the res-blocks of every head (the descriptor's last: dsc_dim)
    batch_norm: bool = True
    score_softmax: bool = True  # score map: softmax over the map (else a sigmoid)
    depth_sigmoid: bool = False  # depth = max_depth * sigmoid(.) (else the raw output)
    max_depth: float = 60.0
    kp_pos_encoding: bool = True
    dsc_dim: int = 128
    dsc_normalize: bool = True
    dsc_pos_encoding: bool = True
    temperature: float = 0.1  # dual softmax
    dustbin: bool = True
    width: int = 540  # network input (W x H) before the crop to multiples of the patch
    height: int = 720
    channel_dim: int | None = None  # DINOv2 width as the YAML states it (checked against the weight file)
    down_factor: int = 14


def _get(tree: Mapping[str, Any], path: str, default: Any) -> Any:
    node: Any = tree
    for part in path.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return default
        node = node[part]
    return node


def config_from_mapping(tree: Mapping[str, Any], where: str = "config") -> MickeyConfig:
    """A configuration from a parsed config tree (the authors' yacs keys).

    Args:
        tree: The parsed YAML.
        where: The file it came from, named in errors.

    Returns:
        The configuration; absent keys keep the defaults.

    Raises:
        ValueError: A value mapfree's MicKey does not support (naming the key).
    """
    d = MickeyConfig()

    def need(ok: bool, key: str, value: Any, what: str) -> None:
        if not ok:
            raise ValueError(f"{where}: {key}={value!r} is not supported by mapfree's MicKey ({what})")

    model = _get(tree, "MODEL", "MicKey")
    need(model == "MicKey", "MODEL", model, "only MicKey")
    ftype = _get(tree, "FEATURE_MATCHER.TYPE", "DualSoftmax")
    need(ftype == "DualSoftmax", "FEATURE_MATCHER.TYPE", ftype, "the published matcher is DualSoftmax")
    use_tf = _get(tree, "FEATURE_MATCHER.USE_TRANSFORMER", False)
    need(not use_tf, "FEATURE_MATCHER.USE_TRANSFORMER", use_tf, "no matching transformer in the published model")
    blocks = tuple(int(v) for v in _get(tree, "MICKEY.KP_HEADS.BLOCKS_DIM", d.kp_blocks))
    need(
        len(blocks) == 4 and blocks[2] == ATTENTION_DIM,
        "MICKEY.KP_HEADS.BLOCKS_DIM",
        list(blocks),
        f"four blocks, the third {ATTENTION_DIM} wide (the attention layers' width)",
    )
    down = int(_get(tree, "MICKEY.DINOV2.DOWN_FACTOR", 14))
    need(down == 14, "MICKEY.DINOV2.DOWN_FACTOR", down, "DINOv2 ViT/14")
    channel = _get(tree, "MICKEY.DINOV2.CHANNEL_DIM", None)
    cfg = replace(
        d,
        float16=bool(_get(tree, "MICKEY.DINOV2.FLOAT16", d.float16)),
        kp_blocks=blocks,
        batch_norm=bool(_get(tree, "MICKEY.KP_HEADS.BN", d.batch_norm)),
        score_softmax=bool(_get(tree, "MICKEY.KP_HEADS.USE_SOFTMAX", d.score_softmax)),
        depth_sigmoid=bool(_get(tree, "MICKEY.KP_HEADS.USE_DEPTHSIGMOID", d.depth_sigmoid)),
        max_depth=float(_get(tree, "MICKEY.KP_HEADS.MAX_DEPTH", d.max_depth)),
        kp_pos_encoding=bool(_get(tree, "MICKEY.KP_HEADS.POS_ENCODING", d.kp_pos_encoding)),
        dsc_dim=int(_get(tree, "MICKEY.DSC_HEAD.LAST_DIM", d.dsc_dim)),
        dsc_normalize=bool(_get(tree, "MICKEY.DSC_HEAD.NORM_DSC", d.dsc_normalize)),
        dsc_pos_encoding=bool(_get(tree, "MICKEY.DSC_HEAD.POS_ENCODING", d.dsc_pos_encoding)),
        temperature=float(_get(tree, "FEATURE_MATCHER.DUAL_SOFTMAX.TEMPERATURE", d.temperature)),
        dustbin=bool(_get(tree, "FEATURE_MATCHER.DUAL_SOFTMAX.USE_DUSTBIN", d.dustbin)),
        width=int(_get(tree, "DATASET.WIDTH", d.width)),
        height=int(_get(tree, "DATASET.HEIGHT", d.height)),
        channel_dim=None if channel is None else int(channel),
        down_factor=down,
    )
    need(cfg.temperature > 0, "FEATURE_MATCHER.DUAL_SOFTMAX.TEMPERATURE", cfg.temperature, "must be positive")
    need(
        cfg.width >= 14 * 8 and cfg.height >= 14 * 8,
        "DATASET.WIDTH/HEIGHT",
        (cfg.width, cfg.height),
        "at least 8 patches a side (the score map's 3-cell border)",
    )
    return cfg


def config_from_yaml(path: str | os.PathLike) -> MickeyConfig:
    """Read the authors' config file (yacs YAML).

    Args:
        path: The ``config.yaml``.

    Returns:
        The configuration.

    Raises:
        ValueError: Unreadable, invalid, or a value not supported (naming the file).
    """
    path = Path(path)
    try:
        tree = read_yaml(path)
    except OSError as e:
        raise ValueError(f"{path}: cannot read the MicKey config ({e.strerror or e})") from None
    if not isinstance(tree, Mapping):
        raise ValueError(f"{path}: not a MicKey config (expected a mapping with MICKEY and FEATURE_MATCHER)")
    return config_from_mapping(tree, str(path))
