"""Relative pose regression (RPR): the paper's networks, parameterisations, losses, training and inference.

Importing this package is cheap (torch and Lightning load on first use). ``build_from_method`` builds the methods
of kind ``regression`` (``mapfree.methods`` names them: ``rpr``, any checkpoint with ``--checkpoint CKPT`` or
``$MAPFREE_RPR_CHECKPOINT``, and ``rpr-<config>`` for the 12 published configurations, ``<config>.ckpt`` found
by the weights rule of ``mapfree.weights``).
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from .inference import RPRMethod

__all__ = [
    "load_method",
    "RPRMethod",
    "RPRNet",
    "RPRModule",
    "RPRDataModule",
    "RPRConfig",
    "load_config",
    "Parameterisation",
    "PoseOutput",
    "PoseLoss",
    "procrustes",
    "build_from_method",
]

_LAZY = {
    "load_method": "inference",
    "RPRMethod": "inference",
    "RPRNet": "model",
    "RPRModule": "module",
    "RPRDataModule": "data",
    "RPRConfig": "config",
    "load_config": "config",
    "Parameterisation": "params",
    "PoseOutput": "params",
    "PoseLoss": "losses",
    "procrustes": "procrustes",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class RegressionSpec(Protocol):
    """What ``build_from_method`` reads of a ``mapfree.methods.Method`` of kind ``regression``."""

    name: str
    options: Mapping[str, Any]


def build_from_method(method: RegressionSpec) -> RPRMethod:
    """A regression method's network, loaded.

    Args:
        method: ``Method(kind="regression", options={"checkpoint": …, "config": …, "device": …})``.

    Returns:
        The loaded ``RPRMethod``.

    Raises:
        ValueError: No checkpoint given, found or set in ``$MAPFREE_RPR_CHECKPOINT``.
    """
    opts = dict(method.options or {})
    config = opts.get("config")
    ckpt = opts.get("checkpoint")
    if not ckpt and config:
        from .official import find_weights

        ckpt = find_weights(config)
    ckpt = ckpt or os.environ.get("MAPFREE_RPR_CHECKPOINT")
    if not ckpt:
        raise ValueError(
            f"method {method.name!r} needs a checkpoint: pass --checkpoint CKPT "
            "(options.checkpoint in a method YAML, or $MAPFREE_RPR_CHECKPOINT)"
        )
    from .inference import load_method

    return load_method(ckpt, opts.get("device"), config=config)
