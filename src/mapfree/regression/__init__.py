"""Relative pose regression (RPR): the paper's networks, parameterisations, losses, training and inference.

Importing this package is cheap (torch and Lightning load on first use) and registers the method kind
``regression`` and the method ``rpr`` with ``mapfree.methods``; ``rpr`` needs ``options.checkpoint``
(``mapfree run … --method rpr --checkpoint CKPT``) or ``$MAPFREE_RPR_CHECKPOINT``.
"""

from __future__ import annotations

import importlib
import os
from typing import Any

__all__ = [
    "load_method", "RPRMethod", "RPRNet", "RPRModule", "RPRDataModule", "RPRConfig", "load_config",
    "Parameterisation", "PoseOutput", "PoseLoss", "procrustes", "build_from_method",
]

_LAZY = {
    "load_method": "inference", "RPRMethod": "inference", "RPRNet": "model", "RPRModule": "module",
    "RPRDataModule": "data", "RPRConfig": "config", "load_config": "config", "Parameterisation": "params",
    "PoseOutput": "params", "PoseLoss": "losses", "procrustes": "procrustes",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def build_from_method(method: Any) -> Any:
    """``Method(kind="regression", options={"checkpoint": …, "device": …})`` -> a loaded ``RPRMethod``."""
    opts = dict(getattr(method, "options", {}) or {})
    ckpt = opts.get("checkpoint") or os.environ.get("MAPFREE_RPR_CHECKPOINT")
    if not ckpt:
        raise ValueError(f"method {getattr(method, 'name', 'rpr')!r} needs a checkpoint: pass --checkpoint CKPT "
                         "(options.checkpoint in a method YAML, or $MAPFREE_RPR_CHECKPOINT)")
    from .inference import load_method

    return load_method(ckpt, opts.get("device"))


def _register() -> None:
    from .. import methods

    methods.register_kind("regression", build_from_method)
    if "rpr" not in getattr(methods, "_REGISTRY", {}):
        methods.register(methods.Method(
            name="rpr", kind="regression", matcher="", solver="", depth="none",
            description="relative pose regression network (mapfree train); needs --checkpoint CKPT",
        ))


try:
    _register()
except ImportError:  # the registry is optional for training-only installs
    pass
