"""Matchers published as transformers models on the Hugging Face hub (SuperGlue, EfficientLoFTR): where their
folders come from, how they are loaded, and the grey input their image processors would make.

A model folder (``config.json`` + ``model.safetensors``) is found by the one rule of ``mapfree.weights``: the
``weights=`` option, ``$MAPFREE_WEIGHTS_DIR/<name>``, the default folder ``~/.cache/mapfree/weights/<name>``
(``<name>`` = the last part of the hub id), the Hugging Face cache; online, ``from_pretrained`` downloads it into
that cache. Offline with none of these: one ``MissingWeightsError`` naming the hub id and where to place the
folder, before any work; a folder that is there but incomplete or cut short: a ``BrokenWeightsError`` naming it."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..weights import BrokenWeightsError, HubModel, check_folder, offline_why, reachable
from .utils import matching_size

__all__ = ["HubModel", "find_hub_model", "load_hub_model", "transformers_classes", "grey_pixels", "GREY_WEIGHTS"]

#: The transformers image processors' grey conversion (NTSC weights on the [0,1] RGB values).
GREY_WEIGHTS = (0.2989, 0.5870, 0.1140)


def find_hub_model(hm: HubModel, explicit: str | os.PathLike | None = None) -> str | None:
    """A local source for a hub model, by the weights rule.

    Args:
        hm: The model.
        explicit: A folder given in place of the default one.

    Returns:
        The folder (possibly incomplete: loading says what is wrong), the hub id when the Hugging Face cache holds
        it, else None.
    """
    hit = hm.locate(explicit)
    if hit is None:
        return None
    return hm.repo_id if hit.where == "the Hugging Face cache" else str(hit.path)


def transformers_classes(*names: str) -> tuple[Any, ...]:
    """Classes of the installed transformers.

    Args:
        *names: Class names (``SuperGlueForKeypointMatching``).

    Returns:
        The classes, in order.

    Raises:
        ImportError: An older transformers without them, saying so.
    """
    import transformers

    missing = [n for n in names if not hasattr(transformers, n)]
    if missing:
        raise ImportError(
            f"transformers {transformers.__version__} has no {', '.join(missing)}: pip install -U transformers"
        )
    return tuple(getattr(transformers, n) for n in names)


class _OptionError(ValueError):
    """A matcher option the model's config refuses (reported as such, not as a bad model folder)."""


def load_hub_model(
    model_cls: Any,
    config_cls: Any,
    hm: HubModel,
    explicit: str | os.PathLike | None = None,
    configure: Callable[[Any], None] | None = None,
) -> Any:
    """A transformers model from its local source (or a download when online).

    Args:
        model_cls: The model class.
        config_cls: Its config class.
        hm: The model's hub entry.
        explicit: A folder given in place of the default one.
        configure: Edits the config first (the paper's settings).

    Returns:
        The model, in eval mode.

    Raises:
        MissingWeightsError: Neither local nor downloadable (before any work).
        BrokenWeightsError: A folder that is there but incomplete or cut short (an interrupted download).
    """
    hit = hm.locate(explicit)
    if hit is None:
        if explicit is not None:
            raise hm.missing(explicit=explicit)
        if not reachable(hm.url):
            raise hm.missing(offline_why(hm.url))
    elif hit.where != "the Hugging Face cache":  # its own downloads are atomic and complete themselves online
        check_folder(hit.path, hm.what)  # config.json, a whole weights file: before transformers reads it
    src = find_hub_model(hm, explicit) if hit is not None else None
    from transformers.utils import logging as hf_logging

    hf_logging.set_verbosity_error()
    hf_logging.disable_progress_bar()
    local_only = src is not None
    src = src or hm.repo_id
    try:
        config = config_cls.from_pretrained(src, local_files_only=local_only)
        if config.model_type != config_cls.model_type:
            raise ValueError(f"its config.json is a '{config.model_type}' model, not '{config_cls.model_type}'")
        if configure is not None:
            try:
                configure(config)
            except (TypeError, ValueError) as e:
                raise _OptionError(f"{hm.what}: an option has a value of the wrong type ({e})") from None
        net, info = model_cls.from_pretrained(src, config=config, local_files_only=local_only, output_loading_info=True)
        # transformers fills missing weights with random ones and only warns: refuse such a folder instead
        bad = [*info.get("missing_keys", ()), *info.get("mismatched_keys", ())]
        if bad:
            raise ValueError(f"{len(bad)} weights missing or of the wrong shape, e.g. {bad[0]}")
        return net.eval()
    except _OptionError:
        raise
    except Exception as e:  # noqa: BLE001 - safetensors, torch and transformers each raise their own kinds
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if isinstance(e, RuntimeError) and "size" in first:  # transformers' refusal of mismatched sizes says only that
            first = "weights of the wrong shape for its config.json"
        if Path(src).is_dir():
            raise BrokenWeightsError(
                f"{hm.what}: model folder {src} is refused: not a {hm.what} model folder ({first})"
            ) from None
        raise hm.missing(first) from None


def grey_pixels(
    image: np.ndarray, max_size: int | None, multiple: int, device: torch.device
) -> tuple[torch.Tensor, tuple[float, float]]:
    """The grey network input, made the way the models' transformers image processors make it.

    PIL bilinear resize of the uint8 RGB image, rescale to [0, 1], NTSC grey.

    Args:
        image: (H, W, 3) uint8 RGB.
        max_size: Long-side cap (None: none).
        multiple: Both sides become multiples of it.
        device: Where the tensor goes.

    Returns:
        (1, 1, h, w) float32 in [0, 1] and the resize scale ``(sx, sy)`` = new size / old size.
    """
    h, w = image.shape[:2]
    nw, nh = matching_size(w, h, max_size, multiple)
    if (nw, nh) != (w, h):
        from PIL import Image

        image = np.asarray(Image.fromarray(image).resize((nw, nh), Image.Resampling.BILINEAR))
    x = (image.astype(np.float64) * (1 / 255)).astype(np.float32)
    grey = x[..., 0] * GREY_WEIGHTS[0] + x[..., 1] * GREY_WEIGHTS[1] + x[..., 2] * GREY_WEIGHTS[2]
    return torch.from_numpy(grey)[None, None].to(device), (nw / w, nh / h)
