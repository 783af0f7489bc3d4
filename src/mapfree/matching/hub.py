"""Matchers published as transformers models on the Hugging Face hub (SuperGlue, EfficientLoFTR): where their
folders come from, how they are loaded, and the grey input their image processors would make.

A model folder (``config.json`` + ``model.safetensors``) is found, in order, at the ``weights=`` option,
``$MAPFREE_WEIGHTS_DIR/<name>`` (``<name>`` = the last part of the hub id), or the Hugging Face cache; online,
``from_pretrained`` downloads it into that cache. Offline with none of these: one ``MissingWeightsError``
naming the hub id and where to place the folder, before any work."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from .utils import matching_size
from .weights import OFFLINE_ENV, WEIGHTS_ENV, MissingWeightsError, in_hf_cache, reachable, weights_dir

__all__ = ["HubModel", "find_hub_model", "load_hub_model", "transformers_classes", "grey_pixels", "GREY_WEIGHTS"]

#: The transformers image processors' grey conversion (NTSC weights on the [0,1] RGB values).
GREY_WEIGHTS = (0.2989, 0.5870, 0.1140)


@dataclass(frozen=True)
class HubModel:
    """A transformers model on the hub: its id, what it is (for messages) and its weights' licence."""

    repo_id: str
    what: str
    licence: str = ""

    @property
    def folder(self) -> str:
        """The folder name looked for under ``$MAPFREE_WEIGHTS_DIR``."""
        return self.repo_id.rsplit("/", 1)[-1]

    @property
    def url(self) -> str:
        return f"https://huggingface.co/{self.repo_id}"


def _is_model_dir(p: Path) -> bool:
    return (p / "config.json").is_file()


def find_hub_model(hm: HubModel, explicit: str | os.PathLike | None = None) -> str | None:
    """A local source for ``hm``: a folder path, or the hub id when the Hugging Face cache holds it; else None."""
    if explicit is not None:
        p = Path(explicit).expanduser()
        return str(p) if _is_model_dir(p) else None
    root = weights_dir()
    if root is not None:
        for cand in (root / hm.folder, root / hm.repo_id):
            if _is_model_dir(cand):
                return str(cand)
    return hm.repo_id if in_hf_cache(hm.repo_id) else None


def _missing(hm: HubModel, explicit: str | os.PathLike | None, why: str) -> MissingWeightsError:
    root = weights_dir()
    if explicit is not None:
        where = f"the folder given as weights= ({explicit})"
    else:
        where = f"${WEIGHTS_ENV}/{hm.folder}" + (f" ({root / hm.folder})" if root is not None else "")
        where += ", or into the Hugging Face cache"
    return MissingWeightsError(
        f"{hm.what}: model '{hm.repo_id}' not found ({why}). Place its folder (config.json, model.safetensors; "
        f"`huggingface-cli download {hm.repo_id} --local-dir DIR` on a machine with internet) as {where}. "
        f"It is published at {hm.url}" + (f" ({hm.licence})." if hm.licence else ".")
    )


def transformers_classes(*names: str) -> tuple[Any, ...]:
    """Classes of the installed transformers; an older release without them is an ImportError saying so."""
    import transformers

    missing = [n for n in names if not hasattr(transformers, n)]
    if missing:
        raise ImportError(f"transformers {transformers.__version__} has no {', '.join(missing)}: "
                          f"pip install -U transformers")
    return tuple(getattr(transformers, n) for n in names)


class _OptionError(ValueError):
    """A matcher option the model's config refuses (reported as such, not as a bad model folder)."""


def load_hub_model(
    model_cls: Any, config_cls: Any, hm: HubModel, explicit: str | os.PathLike | None = None,
    configure: Callable[[Any], None] | None = None,
) -> Any:
    """``model_cls.from_pretrained`` of ``hm`` from its local source (or a download when online), its config
    first edited by ``configure`` (the paper's settings). Raises ``MissingWeightsError`` before any work."""
    src = find_hub_model(hm, explicit)
    if src is None:
        if explicit is not None:
            raise _missing(hm, explicit, f"{explicit} holds no config.json")
        if not reachable(hm.url):
            flag = next((v for v in (OFFLINE_ENV, "HF_HUB_OFFLINE") if os.environ.get(v)), None)
            why = f"${flag} is set" if flag else "offline: huggingface.co unreachable"
            raise _missing(hm, None, why)
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
        net, info = model_cls.from_pretrained(src, config=config, local_files_only=local_only,
                                              output_loading_info=True)
        # transformers fills missing weights with random ones and only warns: refuse such a folder instead
        bad = [*info.get("missing_keys", ()), *info.get("mismatched_keys", ())]
        if bad:
            raise ValueError(f"{len(bad)} weights missing or of the wrong shape, e.g. {bad[0]}")
        return net.eval()
    except _OptionError:
        raise
    except (OSError, ValueError, TypeError, RuntimeError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if isinstance(e, RuntimeError):  # transformers' refusal of mismatched sizes says only that
            first = "weights of the wrong shape for its config.json"
        if Path(src).is_dir():
            raise ValueError(f"{src}: not a {hm.what} model folder ({first})") from None
        raise _missing(hm, None, first) from None


def grey_pixels(
    image: np.ndarray, max_size: int | None, multiple: int, device: torch.device
) -> tuple[torch.Tensor, tuple[float, float]]:
    """(1,1,H,W) float32 grey input and the resize scale ``(sx, sy)``, made the way the models' transformers image
    processors make it: PIL bilinear resize of the uint8 RGB image, rescale to [0,1], NTSC grey."""
    h, w = image.shape[:2]
    nw, nh = matching_size(w, h, max_size, multiple)
    if (nw, nh) != (w, h):
        from PIL import Image

        image = np.asarray(Image.fromarray(image).resize((nw, nh), Image.Resampling.BILINEAR))
    x = (image.astype(np.float64) * (1 / 255)).astype(np.float32)
    grey = x[..., 0] * GREY_WEIGHTS[0] + x[..., 1] * GREY_WEIGHTS[1] + x[..., 2] * GREY_WEIGHTS[2]
    return torch.from_numpy(grey)[None, None].to(device), (nw / w, nh / h)
