"""Relative pose regression (RPR): the paper's networks, parameterisations, losses, training and inference.

Importing this package is cheap (torch and Lightning load on first use) and registers the method kind
``regression``, the method ``rpr`` (any checkpoint: ``--checkpoint CKPT`` or ``$MAPFREE_RPR_CHECKPOINT``) and
``rpr-<config>`` for the 12 published configurations (``rpr-3d3d`` …: ``--checkpoint``, else ``<config>.ckpt``
found by the weights rule of ``mapfree.weights``).
"""

from __future__ import annotations

import importlib
import os
from typing import Any

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


def build_from_method(method: Any) -> Any:
    """``Method(kind="regression", options={"checkpoint": …, "config": …, "device": …})`` -> a loaded ``RPRMethod``."""
    opts = dict(getattr(method, "options", {}) or {})
    config = opts.get("config")
    ckpt = opts.get("checkpoint")
    if not ckpt and config:
        from .official import find_weights

        ckpt = find_weights(config)
    ckpt = ckpt or os.environ.get("MAPFREE_RPR_CHECKPOINT")
    if not ckpt:
        raise ValueError(
            f"method {getattr(method, 'name', 'rpr')!r} needs a checkpoint: pass --checkpoint CKPT "
            "(options.checkpoint in a method YAML, or $MAPFREE_RPR_CHECKPOINT)"
        )
    from .inference import load_method

    return load_method(ckpt, opts.get("device"), config=config)


def _register() -> None:
    from .. import methods
    from .official import OFFICIAL_CONFIGS

    methods.register_kind("regression", build_from_method)
    registry = getattr(methods, "_REGISTRY", {})
    if "rpr" not in registry:
        methods.register(
            methods.Method(
                name="rpr",
                kind="regression",
                matcher="",
                solver="",
                depth="none",
                description="relative pose regression network (mapfree train); needs --checkpoint CKPT",
            )
        )
    for config in OFFICIAL_CONFIGS:
        if f"rpr-{config}" not in registry:
            methods.register(
                methods.Method(
                    name=f"rpr-{config}",
                    kind="regression",
                    matcher="",
                    solver="",
                    depth="none",
                    options={"config": config},
                    description=f"published Map-free RPR model {config} (configs/rpr/{config}.yaml); "
                    f"--checkpoint CKPT or {config}.ckpt in a weights folder (`mapfree weights`)",
                )
            )


try:
    _register()
except ImportError:  # the registry is optional for training-only installs
    pass
