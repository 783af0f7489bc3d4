"""Matchers' weights follow the one rule of ``mapfree.weights`` (this module keeps the names matchers import)."""

from __future__ import annotations

from ..weights import (
    OFFLINE_ENV,
    WEIGHTS_ENV,
    BrokenWeightsError,
    MissingWeightsError,
    WeightFile,
    find_local,
    in_hf_cache,
    load_checkpoint,
    package_file,
    reachable,
    resolve_weights,
    shipped_weights,
    weights_dir,
)

__all__ = [
    "MissingWeightsError",
    "BrokenWeightsError",
    "WeightFile",
    "WEIGHTS_ENV",
    "OFFLINE_ENV",
    "find_local",
    "resolve_weights",
    "package_file",
    "shipped_weights",
    "load_checkpoint",
    "reachable",
    "in_hf_cache",
    "weights_dir",
]
