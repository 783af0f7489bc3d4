"""Monocular metric depth networks through transformers (Depth Anything V2 Metric, ZoeDepth, DPT-DINOv2,
Depth Pro), batched, on the GPU when present, resized to the image, and cached on disk."""

from __future__ import annotations

import inspect
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data import Frame
from ..options import Options, option
from ..runtime import resolve_device, steady_kernels
from ..weights import BrokenWeightsError, HubModel, MissingWeightsError, check_folder, offline_why, reachable
from .base import NetworkDepthSource
from .cache import DepthCache
from .hub import HUB_MODELS

__all__ = ["HUB_MODELS", "HFDepthOptions", "HFDepth", "MissingModelError", "resolve_model"]


class MissingModelError(MissingWeightsError):
    """The model is in no weights folder, not in the Hugging Face cache, and the hub is unreachable."""


def resolve_model(model: str) -> str:
    """The model to load for a name a user typed.

    Args:
        model: A short name (``dav2-indoor``), a local folder or a hub id.

    Returns:
        The hub id, or the folder's absolute path.

    Raises:
        MissingModelError: A path (``./``, ``/``, ``~``) that is no folder.
    """
    if model in HUB_MODELS:
        return HUB_MODELS[model]
    p = Path(model).expanduser()
    if p.is_dir():
        return str(p.resolve())
    if model.startswith((".", "/", "~")):
        raise MissingModelError(f"depth model folder {model} does not exist")
    return model


@dataclass
class HFDepthOptions(Options):
    """Options of a transformers depth network.

    Attributes:
        batch_size: Images per network pass.
        device: ``cpu``, ``cuda``, ``cuda:1``; None: CUDA when available.
        half: float16 weights on CUDA.
        cache_dir: Where predicted maps are cached on disk (None: no cache).
        cache_dtype: ``float16`` or ``float32`` cached maps.
        use_intrinsics: Depth Pro: take the focal length from the frame instead of estimating it.
    """

    batch_size: int = option(4, min=1)
    device: str | None = option(None, device=True)  # None: cuda when available
    half: bool = True  # float16 weights on CUDA
    cache_dir: str | None = None  # None: no disk cache
    cache_dtype: str = option("float16", choices=("float16", "float32"))  # 1 mm at 2 m, 1 cm at 20 m: half the disk
    use_intrinsics: bool = True  # Depth Pro: take the focal length from the frame instead of estimating it


_HUB_URL = "https://huggingface.co"


class HFDepth(NetworkDepthSource):
    """A transformers depth-estimation model as a ``NetworkDepthSource``; loaded on the first cache miss.

    Args:
        model: A short name (``dav2-indoor``, ``depth-pro``), a hub id or a local model folder.
        options: ``HFDepthOptions``.
        **overrides: Single options over ``options`` (``device="cpu"``, ``cache_dir=…``).
    """

    def __init__(self, model: str, options: HFDepthOptions | None = None, **overrides: object) -> None:
        self.options = o = HFDepthOptions.build(overrides, owner=f"depth network {model!r}", base=options)
        self.model_id = resolve_model(model)
        self.name = model if model in HUB_MODELS else f"hf:{model}"
        # a hub id is looked for by the weights rule ($MAPFREE_WEIGHTS_DIR/<name>, the default folder, the cache)
        self.hub = None if Path(self.model_id).is_dir() else HubModel(self.model_id, f"depth network {model}")
        self.device = resolve_device(o.device)  # None/"auto": cuda when available
        self.cache = DepthCache(o.cache_dir, self.model_id, o.cache_dtype) if o.cache_dir else None
        self._model: Any = None  # a transformers depth model and its processor, once loaded
        self._processor: Any = None
        self.predictions = 0  # images run through the network (cache misses)

    # ------------------------------------------------------------------ loading
    def _source(self) -> str | None:
        """A local folder (or the cached hub id) to load from, by the weights rule; None: only a download would do."""
        if self.hub is None:
            check_folder(self.model_id, f"depth network hf:{self.model_id}")
            return self.model_id
        hit = self.hub.locate()
        if hit is None:
            return None
        if hit.where == "the Hugging Face cache":  # its own downloads are atomic and complete themselves online
            return self.model_id
        check_folder(hit.path, self.hub.what)  # cut short or incomplete: named, before transformers reads it
        return str(hit.path)

    def check_available(self) -> None:
        """Raise ``MissingModelError`` now if the model could not be loaded (in no weights folder, not cached, hub
        unreachable), without loading it: a run refuses before any work instead of failing every frame."""
        if self._model is not None or self._source() is not None or reachable(_HUB_URL):
            return
        raise self._missing()

    def _missing(self) -> MissingModelError:
        assert self.hub is not None
        return MissingModelError(str(self.hub.missing(offline_why(_HUB_URL))))

    def load(self) -> None:
        """Load model + processor now (otherwise on first use); ``MissingModelError`` when unavailable."""
        if self._model is not None:
            return
        from transformers import AutoImageProcessor, AutoModelForDepthEstimation
        from transformers.utils import logging as hf_logging

        hf_logging.set_verbosity_error()
        dtype = torch.float16 if self.options.half and self.device.type == "cuda" else torch.float32
        src = self._source()
        local = src is not None and Path(src).is_dir()

        def load(source: str, local_only: bool) -> tuple[Any, Any]:
            proc = AutoImageProcessor.from_pretrained(source, local_files_only=local_only)
            net = AutoModelForDepthEstimation.from_pretrained(source, local_files_only=local_only, dtype=dtype)
            return proc, net

        try:
            if src is None:
                raise OSError("not on this machine")
            proc, net = load(src, True)
        except Exception as e:  # noqa: BLE001 - transformers, safetensors and torch each raise their own kinds
            if local:
                first = (str(e).strip().splitlines() or [type(e).__name__])[0]
                raise BrokenWeightsError(f"{src}: not a transformers depth model folder ({first})") from None
            if not reachable(_HUB_URL):
                raise self._missing() from None
            proc, net = load(self.model_id, False)
        self._processor, self._model = proc, net.to(self.device).eval()

    # ------------------------------------------------------------------ prediction
    @torch.inference_mode()
    def predict(self, images: Sequence[np.ndarray], focals: Sequence[float | None] | None = None) -> list[np.ndarray]:
        """Metric depth of same-size images, in batches on the network's device.

        Args:
            images: (H, W, 3) uint8 RGB images, all of one size.
            focals: Each image's fx in pixels (Depth Pro turns its inverse depth into metres with it), or None.

        Returns:
            One (H, W) float32 map in metres per image (NaN, inf and negatives as 0).

        Raises:
            MissingModelError: The model is neither on this machine nor downloadable.
        """
        self.load()
        if not images:
            return []
        h, w = images[0].shape[:2]
        proc, net = self._processor, self._model
        inputs = proc(images=list(images), return_tensors="pt")
        pix = inputs["pixel_values"].to(self.device, dtype=next(net.parameters()).dtype)
        with steady_kernels():  # no per-shape cuDNN attention graphs or conv autotuning on a never-seen size
            out = net(pixel_values=pix)
        sizes = [(h, w)] * len(images)
        post = proc.post_process_depth_estimation
        params = inspect.signature(post).parameters
        if net.config.model_type == "depth_pro" and self.options.use_intrinsics and focals and all(focals):
            # Depth Pro turns its canonical inverse depth into metres with the focal length: give it the true one.
            fov = [2 * math.degrees(math.atan(0.5 * w / f)) for f in focals if f]
            out.field_of_view = torch.tensor(fov, device=out.predicted_depth.device)
        if "source_sizes" in params:  # ZoeDepth removes its padding given the input size
            res = post(out, source_sizes=sizes, target_sizes=sizes)
        else:
            res = post(out, target_sizes=sizes)
        self.predictions += len(images)
        deps = []
        for r in res:
            d = r["predicted_depth"].float().cpu().numpy().reshape(h, w)
            deps.append(np.clip(np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None).astype(np.float32))
        return deps

    def _extra(self, frame: Frame) -> str:
        return f"fx={frame.intrinsics.fx:.4f}" if self.options.use_intrinsics else ""

    def depth(self, frame: Frame) -> np.ndarray | None:
        """The depth of one frame (``depth_many`` of one).

        Args:
            frame: A dataset frame.

        Returns:
            (H, W) float32 metres.
        """
        return self.depth_many([frame])[0]

    def depth_many(self, frames: Sequence[Frame]) -> list[np.ndarray | None]:
        """Depth for many frames: cached ones from disk, the rest predicted in batches of same-size images.

        Args:
            frames: Dataset frames.

        Returns:
            One (H, W) float32 map in metres per frame (a newly predicted one is cached, and returned as the cache
            will give it back).
        """
        out: list[np.ndarray | None] = [None] * len(frames)
        todo: list[int] = []
        for i, f in enumerate(frames):
            if self.cache is not None and Path(f.image_path).is_file():  # a missing image fails in f.image()
                out[i] = self.cache.get(self.cache.path(f.image_path, self._extra(f)))
            if out[i] is None:
                todo.append(i)
        images = {i: frames[i].image() for i in todo}
        by_size: dict[tuple[int, ...], list[int]] = {}
        for i in todo:
            by_size.setdefault(images[i].shape, []).append(i)
        for idx in by_size.values():
            for s in range(0, len(idx), self.options.batch_size):
                chunk = idx[s : s + self.options.batch_size]
                deps = self.predict([images[i] for i in chunk], [frames[i].intrinsics.fx for i in chunk])
                for i, d in zip(chunk, deps):
                    if self.cache is not None:
                        d = self.cache.round_trip(d)
                        self.cache.put(self.cache.path(frames[i].image_path, self._extra(frames[i])), d)
                    out[i] = d
        return out
