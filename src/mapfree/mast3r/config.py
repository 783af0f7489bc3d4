"""Model configuration read from a checkpoint, never by ``eval``.

The published ``.pth`` files carry the constructor call as a string (``AsymmetricMASt3R(pos_embed='RoPE100',
…)``) and the hub copies a ``config.json`` of the same keyword arguments. We parse the call with ``ast``,
accept only literal arguments, and refuse any argument we do not implement by name.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

__all__ = ["ModelConfig", "Mode", "UnsupportedCheckpointError", "parse_constructor", "config_from_kwargs", "CLASSES"]

Mode = tuple[str, float, float]
INF = math.inf

#: Public class names -> whether the model has the local-feature (descriptor) head.
CLASSES = {"AsymmetricMASt3R": True, "AsymmetricCroCo3DStereo": False}


class UnsupportedCheckpointError(ValueError):
    """A checkpoint whose architecture this port does not implement; the message names the argument."""


@dataclass(frozen=True)
class ModelConfig:
    """The architecture of a checkpoint: CroCo defaults, DUSt3R's head options, MASt3R's descriptor options.

    Field names are the public constructor's keyword arguments.

    Attributes:
        has_descriptors: MASt3R's descriptor head (``AsymmetricMASt3R``).
        img_size: Image size the network was built for, pixels.
        patch_size: ViT patch side, pixels.
        enc_embed_dim: Encoder width.
        enc_depth: Encoder blocks.
        enc_num_heads: Encoder attention heads.
        dec_embed_dim: Decoder width.
        dec_depth: Decoder blocks per view.
        dec_num_heads: Decoder attention heads.
        mlp_ratio: MLP hidden width over the block width.
        norm_im2_in_dec: Normalise the other view's tokens in cross-attention.
        pos_embed: ``RoPE<base>`` (only RoPE is implemented).
        head_type: ``dpt`` (DUSt3R) or ``catmlp+dpt`` (MASt3R).
        output_mode: ``pts3d``, or ``pts3d+descD`` with D-dimensional descriptors.
        depth_mode: (mode, min, max) of the depth activation.
        conf_mode: (mode, min, max) of the confidence activation.
        desc_mode: Descriptor activation (``norm``: unit length).
        two_confs: A separate descriptor confidence.
        desc_conf_mode: (mode, min, max) of the descriptor confidence, or None.
    """

    has_descriptors: bool = False
    img_size: tuple[int, int] = (224, 224)
    patch_size: int = 16
    enc_embed_dim: int = 768
    enc_depth: int = 12
    enc_num_heads: int = 12
    dec_embed_dim: int = 512
    dec_depth: int = 8
    dec_num_heads: int = 16
    mlp_ratio: float = 4.0
    norm_im2_in_dec: bool = True
    pos_embed: str = "RoPE100"
    head_type: str = "linear"  # the public default; only the DPT heads are implemented
    output_mode: str = "pts3d"
    depth_mode: Mode = ("exp", -INF, INF)
    conf_mode: Mode = ("exp", 1.0, INF)
    desc_mode: str = "norm"
    two_confs: bool = False
    desc_conf_mode: Mode | None = None

    @property
    def rope_base(self) -> float:
        """Frequency base of the rotary position embedding."""
        return float(self.pos_embed[len("RoPE") :])

    @property
    def desc_dim(self) -> int:
        """Descriptor width; 0 without the descriptor head."""
        return int(self.output_mode[len("pts3d+desc") :]) if self.has_descriptors else 0

    @property
    def class_name(self) -> str:
        """The public class name of the architecture."""
        return "AsymmetricMASt3R" if self.has_descriptors else "AsymmetricCroCo3DStereo"


#: Arguments the public code takes that do not change inference (training options; the landscape wrapper,
#: which the public inference loader turns off as we do; the patch-embed class, whose two choices are the same
#: computation once ``landscape_only`` is off).
_IGNORED = {"freeze", "mask_ratio", "landscape_only"}
_MODE_ARGS = {"depth_mode", "conf_mode", "desc_conf_mode"}


def _literal(node: ast.AST, where: str) -> Any:
    """A literal value: numbers, strings, booleans, None, tuples/lists, ``inf`` and unary minus."""
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, (ast.Tuple, ast.List)):
        return tuple(_literal(e, where) for e in node.elts)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        v = _literal(node.operand, where)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return -v if isinstance(node.op, ast.USub) else v
    if isinstance(node, ast.Name) and node.id == "inf":
        return INF
    raise UnsupportedCheckpointError(f"{where}: argument value {ast.unparse(node)!r} is not a literal")


def parse_constructor(expr: str) -> tuple[str, dict[str, Any]]:
    """Parse the constructor call a ``.pth`` stores, with ``ast`` and without evaluating anything.

    Args:
        expr: E.g. ``"AsymmetricMASt3R(pos_embed='RoPE100', …)"``; literal arguments only.

    Returns:
        The class name and the keyword arguments.

    Raises:
        UnsupportedCheckpointError: Not a call of a class name, positional or ``**`` arguments, a non-literal.
    """
    try:
        tree = ast.parse(expr.strip(), mode="eval")
    except SyntaxError as e:
        raise UnsupportedCheckpointError(f"model expression is not a Python call: {e.msg}") from None
    call = tree.body
    if not isinstance(call, ast.Call) or not isinstance(call.func, ast.Name):
        raise UnsupportedCheckpointError(f"model expression is not a call of a class name: {expr[:80]!r}")
    if call.args:
        raise UnsupportedCheckpointError(f"{call.func.id}: positional arguments are not supported")
    kwargs = {}
    for kw in call.keywords:
        if kw.arg is None:
            raise UnsupportedCheckpointError(f"{call.func.id}: **kwargs are not supported")
        kwargs[kw.arg] = _literal(kw.value, f"{call.func.id}({kw.arg}=…)")
    return call.func.id, kwargs


def _mode(name: str, v: Any) -> Mode | None:
    if v is None and name == "desc_conf_mode":
        return None
    if not (isinstance(v, (tuple, list)) and len(v) == 3 and isinstance(v[0], str)):
        raise UnsupportedCheckpointError(f"argument {name}={v!r}: expected (mode, min, max)")
    return (v[0], float(v[1]), float(v[2]))


def config_from_kwargs(class_name: str, kwargs: Mapping[str, Any]) -> ModelConfig:
    """Validate constructor arguments into a ``ModelConfig``.

    Args:
        class_name: ``AsymmetricMASt3R`` or ``AsymmetricCroCo3DStereo``.
        kwargs: The constructor's keyword arguments (a ``.pth``'s call or a hub ``config.json``).

    Returns:
        The configuration.

    Raises:
        UnsupportedCheckpointError: An unknown class, or an argument this port does not implement (named).
    """
    if class_name not in CLASSES:
        raise UnsupportedCheckpointError(f"unsupported model class {class_name!r} (supported: {', '.join(CLASSES)})")
    has_desc = CLASSES[class_name]
    known = {f.name for f in fields(ModelConfig)} - {"has_descriptors"}
    if not has_desc:
        known -= {"desc_mode", "two_confs", "desc_conf_mode"}
    values: dict[str, Any] = {"has_descriptors": has_desc}
    for name, v in kwargs.items():
        if name in _IGNORED:
            continue
        if name == "patch_embed_cls":
            if v not in ("PatchEmbedDust3R", "ManyAR_PatchEmbed"):
                raise UnsupportedCheckpointError(f"unsupported argument patch_embed_cls={v!r}")
            continue
        if name not in known:
            raise UnsupportedCheckpointError(f"{class_name}: unsupported argument {name}={v!r}")
        if name in _MODE_ARGS:
            v = _mode(name, v)
        elif name == "img_size":
            v = (int(v), int(v)) if isinstance(v, int) else tuple(int(x) for x in v)
        values[name] = v
    cfg = ModelConfig(**values)
    _check(cfg)
    return cfg


def _check(cfg: ModelConfig) -> None:
    if not cfg.pos_embed.startswith("RoPE"):
        raise UnsupportedCheckpointError(f"unsupported argument pos_embed={cfg.pos_embed!r} (only RoPE<base>)")
    try:
        _ = cfg.rope_base  # a property that parses pos_embed
    except ValueError:
        raise UnsupportedCheckpointError(f"unsupported argument pos_embed={cfg.pos_embed!r}") from None
    want = "catmlp+dpt" if cfg.has_descriptors else "dpt"
    if cfg.head_type != want:
        raise UnsupportedCheckpointError(f"unsupported argument head_type={cfg.head_type!r} (this class: {want!r})")
    if cfg.has_descriptors:
        if not cfg.output_mode.startswith("pts3d+desc") or not cfg.output_mode[10:].isdigit():
            raise UnsupportedCheckpointError(f"unsupported argument output_mode={cfg.output_mode!r}")
        if cfg.desc_mode != "norm":
            raise UnsupportedCheckpointError(f"unsupported argument desc_mode={cfg.desc_mode!r}")
    elif cfg.output_mode != "pts3d":
        raise UnsupportedCheckpointError(f"unsupported argument output_mode={cfg.output_mode!r}")
    if cfg.dec_depth <= 9:
        raise UnsupportedCheckpointError(f"unsupported argument dec_depth={cfg.dec_depth} (the DPT head needs > 9)")
    for name in ("depth_mode", "conf_mode", "desc_conf_mode"):
        mode = getattr(cfg, name)
        if mode is None:
            continue
        allowed = ("linear", "exp", "square") if name == "depth_mode" else ("exp", "sigmoid")
        if mode[0] not in allowed:
            raise UnsupportedCheckpointError(f"unsupported argument {name}={mode!r}")
    if cfg.depth_mode[1:] != (-INF, INF):
        raise UnsupportedCheckpointError(f"unsupported argument depth_mode={cfg.depth_mode!r} (bounds must be ±inf)")
