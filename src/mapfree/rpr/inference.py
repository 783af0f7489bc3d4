"""A trained RPR checkpoint as a relocalization method: one pair, a cached reference, or a batch.

Ignores depth and intrinsics (the network regresses the metric pose from pixels). Preprocessing is the public
release's: both images resized (bilinear) to the config's input size — 270×360 (W×H) for the published models,
whatever the photo's orientation — as RGB in [0, 1]. The pose is the network's R, t (``X_query = R X_ref + t``);
the confidence is the predicted-uncertainty score (0 for models without that head, as the published ones).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable
from typing import Any

import numpy as np
import torch

from ..data import read_image
from ..estimate import Estimate, Signals
from ..geometry import Pose
from ..localizer import Localizer
from .config import RPRConfig, load_config, resolve_config
from .data import as_float_input, resolve_size, to_input
from .metrics import confidence_from_log_sigma
from .module import RPRModule
from .official import is_public, load_weights, official_config_for, read_checkpoint

__all__ = ["RPRMethod", "load_method", "image_of"]


def image_of(x: Any) -> np.ndarray:
    """(H,W,3) uint8 RGB from an array, a path, a ``Frame`` (``.image()``), a ``View`` (``.image``) or a tuple."""
    if isinstance(x, tuple):
        x = x[0]
    if isinstance(x, (str, os.PathLike)):
        return read_image(x)
    img = getattr(x, "image", x)
    img = img() if callable(img) else img
    img = np.asarray(img)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an RGB image (H,W,3), got shape {img.shape}")
    return img


def _default_device() -> torch.device:
    if torch.cuda.is_available():
        return torch.device("cuda")
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        return torch.device("mps")
    return torch.device("cpu")


class RPRMethod(Localizer[Any]):
    """A trained RPR network as a relocalization method: a ``Localizer`` without a reusable anchor.

    ``relocalize(ref, query)`` for one pair; ``set_reference`` then ``localize`` or ``localize_many`` reuse the
    reference (``prepare`` keeps the reference itself, which ``localize(query, anchor)`` sets again);
    ``predict(batch)`` runs a batch of tensors on the model's device.

    Args:
        module: The trained network.
        device: Where to run; None picks cuda, then mps, then cpu.
    """

    def __init__(self, module: RPRModule, device: str | torch.device | None = None):
        self.device = torch.device(device) if device is not None else _default_device()
        self.module = module.to(self.device).eval()
        self.cfg: RPRConfig = module.cfg
        self._ref: tuple[np.ndarray, torch.Tensor] | None = None

    @property
    def name(self) -> str:
        return f"rpr {self.cfg.name}"

    def _tensor(self, img: np.ndarray, size: tuple[int, int]) -> torch.Tensor:
        """The public preprocessing: bilinear resize to ``size`` (W, H), RGB float in [0, 1], no normalisation."""
        return torch.from_numpy(to_input(img, size).transpose(2, 0, 1).copy()).unsqueeze(0).to(self.device)

    def input_size(self, img: np.ndarray) -> tuple[int, int]:
        """(width, height) of the network input for an image of this shape (the config's, by orientation).

        Args:
            img: (H, W, 3) image.

        Returns:
            The input size, pixels.
        """
        return resolve_size((img.shape[1], img.shape[0]), self.cfg.data)

    @torch.inference_mode()
    def predict(self, batch: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
        """Run the network on a batch of image pairs.

        Args:
            batch: ``img0`` (reference) and ``img1`` (query), (B, 3, H, W) float in [0, 1] or uint8.

        Returns:
            ``R`` (B, 3, 3) and ``t`` (B, 3, metres) of each query relative to its reference, ``confidence``
                (B,), and ``log_sigma`` (B, 2) when the network has the uncertainty head.
        """
        out = self.module.net(
            as_float_input(batch["img0"].to(self.device)), as_float_input(batch["img1"].to(self.device))
        )
        res = {"R": out.R.float().cpu().numpy().astype(np.float64), "t": out.t.float().cpu().numpy().astype(np.float64)}
        if out.log_sigma is not None:
            res["log_sigma"] = out.log_sigma.float().cpu().numpy()
            res["confidence"] = confidence_from_log_sigma(res["log_sigma"])
        else:
            res["confidence"] = np.zeros(len(res["t"]))
        return res

    def relocalize_images(self, img_ref: np.ndarray, img_query: np.ndarray) -> Estimate:
        """Metric pose of the query camera relative to the reference camera, from the two images alone.

        Args:
            img_ref: The reference: (H, W, 3) uint8 RGB, a path, or a frame.
            img_query: The query, likewise.

        Returns:
            The estimate (``extras`` holds the predicted error scales when the network has the uncertainty head).
        """
        t0 = time.perf_counter()
        img_ref, img_query = image_of(img_ref), image_of(img_query)
        size = self.input_size(img_ref)
        res = self.predict({"img0": self._tensor(img_ref, size), "img1": self._tensor(img_query, size)})
        return self._estimate(res, 0, time.perf_counter() - t0)

    def _estimate(self, res: dict[str, np.ndarray], i: int, seconds: float) -> Estimate:
        extras: dict[str, str | float] = {"method": self.name}
        if "log_sigma" in res:
            extras["sigma_rot_deg"] = float(np.degrees(np.exp(res["log_sigma"][i, 0])))
            extras["sigma_trans_m"] = float(np.exp(res["log_sigma"][i, 1]))
        conf = float(res["confidence"][i])
        signals = Signals(learned_confidence=conf)
        return Estimate(Pose(res["R"][i], res["t"][i]), conf, 0, "", {"regression": seconds}, extras, signals)

    # The Localizer interface (mapfree.localizer): set_reference / localize / relocalize / localize_many.
    def set_reference(self, reference: Any) -> Any:
        """Keep a reference's network input for ``localize`` and ``localize_many``.

        Args:
            reference: (H, W, 3) uint8 RGB, a path, or a frame.

        Returns:
            The kept image and input tensor.
        """
        img = image_of(reference)
        self._ref = (img, self._tensor(img, self.input_size(img)))
        return self._ref

    def localize(self, query: Any, anchor: Any = None) -> Estimate:
        """``relocalize`` against the reference of ``set_reference`` (or ``anchor``, which becomes the reference).

        Args:
            query: (H, W, 3) uint8 RGB, a path, or a frame.
            anchor: A reference to set first, or None for the current one.

        Returns:
            The estimate.

        Raises:
            RuntimeError: No reference was set.
        """
        if anchor is not None:
            self.set_reference(anchor)
        if self._ref is None:
            raise RuntimeError("call set_reference(reference) before localize(query)")
        t0 = time.perf_counter()
        img_ref, ref_t = self._ref
        q = self._tensor(image_of(query), (ref_t.shape[-1], ref_t.shape[-2]))
        res = self.predict({"img0": ref_t, "img1": q})
        return self._estimate(res, 0, time.perf_counter() - t0)

    def relocalize(self, reference: Any, query: Any) -> Estimate:
        """Same as ``relocalize_images``."""
        return self.relocalize_images(reference, query)

    def localize_many(
        self, queries: Iterable[Any], anchor: Any = None, *, prefetch: int = 1, batch_size: int = 16
    ) -> list[Estimate]:
        """``localize`` of many queries against the current reference (or ``anchor``), in batches (GPU-friendly).

        Args:
            queries: (H, W, 3) uint8 RGB images, paths or frames.
            anchor: A reference to set first, or None for the current one.
            prefetch: Not used (the interface's read-ahead).
            batch_size: Queries per network pass.

        Returns:
            One estimate per query, in order.

        Raises:
            RuntimeError: No reference was set.
        """
        queries = list(queries)
        if anchor is not None:
            self.set_reference(anchor)
        if self._ref is None:
            raise RuntimeError("call set_reference(reference) before localize_many(queries)")
        _, ref_t = self._ref
        size = (ref_t.shape[-1], ref_t.shape[-2])
        out: list[Estimate] = []
        for s in range(0, len(queries), batch_size):
            t0 = time.perf_counter()
            q = torch.cat([self._tensor(image_of(x), size) for x in queries[s : s + batch_size]])
            res = self.predict({"img0": ref_t.expand(len(q), -1, -1, -1), "img1": q})
            dt = (time.perf_counter() - t0) / len(q)
            out += [self._estimate(res, i, dt) for i in range(len(q))]
        return out


def load_method(
    checkpoint: os.PathLike | str, device: str | torch.device | None = None, config: str | None = None
) -> RPRMethod:
    """Load a trained checkpoint as a relocalization method.

    Ours (written by ``mapfree train``) carry their config; a public Map-free checkpoint is built from
    ``configs/rpr/<config>.yaml`` and loaded by key.

    Args:
        checkpoint: The ``.ckpt`` file.
        device: Where to run; None picks cuda, then mps, then cpu.
        config: The published configuration of a public checkpoint (e.g. ``3d3d``); default the file's stem.

    Returns:
        The method.
    """
    ckpt = read_checkpoint(checkpoint)
    if is_public(ckpt):
        module = RPRModule(load_config(resolve_config(official_config_for(checkpoint, config))))
    else:
        module = RPRModule(ckpt["hyper_parameters"]["config"])
    load_weights(module, ckpt, str(checkpoint))
    return RPRMethod(module, device)
