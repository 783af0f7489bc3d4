"""``mapfree export``'s library side: a matcher of the MASt3R family, loaded as the engine loads it, written as
its two ONNX graphs (``onnxgraph``) for the network input of one photo size."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from .engine import PUBLISHED_SIZE, shared_engine
from .onnxgraph import ExportResult, export_graphs
from .preprocess import PATCH, crop_box, resized_size
from .published import DUNE_KINDS

__all__ = ["EXPORTABLE", "DEFAULT_PHOTO_SIZE", "input_shape", "export_matcher"]

#: Matchers whose network ``export_matcher`` writes: the engine's family (each loaded by ``shared_engine``).
EXPORTABLE = ("mast3r", "dust3r", *DUNE_KINDS)
#: (width, height) of a Map-free photo: the shape the graphs take by default.
DEFAULT_PHOTO_SIZE = (540, 720)


def input_shape(
    photo_size: tuple[int, int], long_side: int, patch: int = PATCH, square_ok: bool = False
) -> tuple[int, int]:
    """(H, W) network input of a photo of ``photo_size`` (width, height) prepared at ``long_side`` (resize, then
    centre crop to multiples of the network's patch, as ``preprocess.prepare_image``)."""
    left, top, right, bottom = crop_box(*resized_size(*photo_size, long_side), square_ok, patch)
    return bottom - top, right - left


def export_matcher(
    kind: str,
    path: os.PathLike | str,
    long_side: int | None = None,
    photo_size: tuple[int, int] = DEFAULT_PHOTO_SIZE,
    weights: str | os.PathLike | None = None,
    external_data: bool | None = None,
    progress: Callable[[str], None] | None = None,
) -> ExportResult:
    """Export the network of matcher ``kind`` (its published weights by the weights rule, or ``weights``).

    Args:
        kind: One of ``EXPORTABLE``.
        path: The encoder graph to write, ``NAME.onnx`` (the decoder goes beside it as ``NAME.decoder.onnx``).
        long_side: Network input long side, pixels (the matcher's ``long_side``); None: the published size (512,
            DUNE-MASt3R 518).
        photo_size: (width, height) of the photos the graphs will see (any photo of that aspect ratio).
        weights: A checkpoint file or folder; default: the published file in the weights folders.
        external_data: Weights as ONNX external data beside each graph: None decides by size (past 2 GiB).
        progress: Called with a line before each step.

    Returns:
        The files written.

    Raises:
        KeyError: ``kind`` is not exportable.
        MissingWeightsError: No checkpoint.
    """
    if kind not in EXPORTABLE:
        raise KeyError(f"matcher {kind!r} cannot be exported (exportable: {', '.join(EXPORTABLE)})")
    size = PUBLISHED_SIZE[kind] if long_side is None else int(long_side)
    say = progress or (lambda _msg: None)
    say(f"loading {kind}")
    net = shared_engine(kind, None if weights is None else Path(weights), "cpu", size).model
    hw = input_shape(photo_size, size, net.cfg.patch_size, net.square_ok)
    if min(hw) < net.cfg.patch_size:
        raise ValueError(
            f"photos of {photo_size[0]}x{photo_size[1]} at long side {size}: a network input under a patch"
        )
    return export_graphs(net, kind, hw, Path(path), long_side=size, external_data=external_data, progress=say)
