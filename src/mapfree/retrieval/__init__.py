"""Image-level retrieval: global descriptors (DenseVLAD), K-means choice of K references, nearest references.

    desc = mapfree.retrieval.create("densevlad").fit(mapping_images)
    G = desc.describe_many(mapping_images)
    keep = select_references(G, k=10)               # the 10 most representative mapping images
    idx, sim = retrieve(desc.describe(query), G[keep])

A sibling of ``matching`` (pixels in, descriptors out); it imports only ``matching``'s SIFT helpers.
"""

from __future__ import annotations

from collections.abc import Callable

from .densevlad import DenseVLAD, DenseVLADOptions, dense_rootsift
from .select import retrieve, select_references

__all__ = ["DenseVLAD", "DenseVLADOptions", "dense_rootsift", "retrieve", "select_references", "create", "names"]

_REGISTRY: dict[str, Callable[..., DenseVLAD]] = {"densevlad": DenseVLAD}


def names() -> list[str]:
    """Names of the global descriptors ``create`` knows."""
    return list(_REGISTRY)


def create(name: str = "densevlad", **options: object) -> DenseVLAD:
    """A global descriptor by name, not yet fitted.

    Args:
        name: Descriptor name (case-insensitive), one of ``names()``.
        **options: Its options' fields, overriding the defaults.

    Returns:
        The descriptor; call ``fit`` on the mapping images before ``describe``.

    Raises:
        KeyError: The name is unknown.
    """
    key = name.strip().lower()
    if key not in _REGISTRY:
        raise KeyError(f"unknown global descriptor {name!r}; available: {', '.join(_REGISTRY)}")
    return _REGISTRY[key](**options)
