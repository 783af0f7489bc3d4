"""One loaded MicKey network, shared by the ``mickey`` matcher and depth source (and every method built with the
same files, device and precision): images go through it in batches, pairs are scored from their outputs.

An image's output (``MickeyImage``) is all that matching it ever needs: whoever holds a reference's ``Features``
(``Relocalizer.set_reference``, ``mapfree run``'s scene reference, the service's prepared anchors) matches every
query against it without running the network on the reference again.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..options import Options, option
from ..runtime import resolve_device
from .checkpoint import CHECKPOINTS, MickeyFiles, find_files, load_network
from .model import Keypoints, MickeyNet
from .preprocess import Prepared, prepare_array

__all__ = ["MickeyImage", "MickeyEngine", "MickeyNetworkOptions", "shared_engine", "engine_for"]


@dataclass
class MickeyNetworkOptions(Options):
    """Which MicKey network to run and how: the options the ``mickey`` matcher and depth source share.

    Attributes:
        checkpoint: The published file, found by the weights rule.
        weights: A checkpoint file elsewhere (or a folder holding ``CHECKPOINT.ckpt``).
        dinov2: The DINOv2 ViT-L/14 file elsewhere (or a folder holding it).
        config: The config YAML elsewhere (default: the one beside the checkpoint, if any).
        fp16: DINOv2 in float16; None: as the config says (published: yes) on a GPU, no on the CPU.
        device: Where to run; None: cuda when available.
    """

    checkpoint: str = option("mickey", choices=CHECKPOINTS)  # the published file, found by the weights rule
    weights: str | None = None  # a checkpoint file elsewhere (or a folder holding <checkpoint>.ckpt)
    dinov2: str | None = None  # the DINOv2 ViT-L/14 file elsewhere (or a folder holding it)
    config: str | None = None  # the config YAML elsewhere (default: the one beside the checkpoint, if any)
    fp16: bool | None = None  # DINOv2 in float16: None = as the config says (published: yes) on a GPU, no on CPU
    device: str | None = option(None, device=True)  # None: cuda when available


@dataclass
class MickeyImage:
    """One image after the network: all that matching it against any other image needs.

    Attributes:
        keypoints: Its keypoints, a batch of one on the engine's device.
        original_size: (width, height) of the original image, pixels.
        scale: (sx, sy) network input size / original size.
        engine_id: ``id()`` of the engine that made it.
    """

    keypoints: Keypoints
    original_size: tuple[int, int]  # (width, height)
    scale: tuple[float, float]  # network input / original
    engine_id: int

    def xy_original(self) -> torch.Tensor:
        """(N, 2) keypoints in original-image pixels, float64 on the engine's device."""
        s = torch.tensor(self.scale, dtype=torch.float64, device=self.keypoints.xy.device)
        return (self.keypoints.xy[0].double() + 0.5) / s - 0.5


class MickeyEngine:
    """A loaded MicKey network on a device: ``extract`` runs it on images, ``scores`` matches their outputs.

    Thread-safe for inference (the relocalizer prepares the next query in a thread). Get one with
    ``shared_engine`` or ``engine_for``.

    Args:
        net: The network, on ``device``.
        device: Where it runs.
        files: The files it was loaded from.
    """

    name = "mickey"

    def __init__(self, net: MickeyNet, device: torch.device, files: MickeyFiles | None = None) -> None:
        self.net, self.device, self.files = net, device, files
        self._lock = threading.Lock()
        self.images = 0  # images run through the network (tests and benchmarks read it)
        self.pairs = 0

    @property
    def input_size(self) -> tuple[int, int]:
        """(width, height) of the network input, pixels."""
        return self.net.cfg.width, self.net.cfg.height

    def extract(self, images: Sequence[np.ndarray], batch_size: int = 8) -> list[MickeyImage]:
        """Run the network on images, in batches.

        Args:
            images: (H, W, 3) uint8 RGB images.
            batch_size: Images per network pass.

        Returns:
            One output per image, in order.
        """
        out: list[MickeyImage] = []
        step = max(1, int(batch_size))
        for i in range(0, len(images), step):
            preps: list[Prepared] = [prepare_array(im, self.input_size) for im in images[i : i + step]]
            x = torch.stack([p.tensor for p in preps]).to(self.device)
            with torch.inference_mode():
                k = self.net.extract(x)
            out += [MickeyImage(k.item(j), p.original_size, p.scale(), id(self)) for j, p in enumerate(preps)]
        with self._lock:
            self.images += len(images)
        return out

    def scores(self, ref: MickeyImage, others: Sequence[MickeyImage], batch_size: int = 8) -> list[torch.Tensor]:
        """Match one image's keypoints against each of others' (the reference against queries).

        Args:
            ref: The output of one image.
            others: The outputs of the other images (one network input size).
            batch_size: Pairs per pass.

        Returns:
            Per other image, (N_ref, N_other) final scores: matching matrix times both keypoint scores.
        """
        out: list[torch.Tensor] = []
        step = max(1, int(batch_size))
        for i in range(0, len(others), step):
            chunk = others[i : i + step]
            k1 = Keypoints(
                torch.cat([o.keypoints.xy for o in chunk]),
                torch.cat([o.keypoints.depth for o in chunk]),
                torch.cat([o.keypoints.score for o in chunk]),
                torch.cat([o.keypoints.desc for o in chunk]),
                chunk[0].keypoints.grid,
            )
            with torch.inference_mode():
                _, final = self.net.scores(ref.keypoints, k1)
            out += list(final)
        with self._lock:
            self.pairs += len(others)
        return out


_ENGINES: dict[tuple, MickeyEngine] = {}
_ENGINES_LOCK = threading.Lock()


def shared_engine(
    checkpoint: str = "mickey",
    weights: str | None = None,
    dinov2: str | None = None,
    config: str | None = None,
    device: str | torch.device | None = None,
    fp16: bool | None = None,
) -> MickeyEngine:
    """The one engine per (files, device, precision): a method's matcher and depth source share it.

    Files are found first, so a missing one fails before any image is read.

    Args:
        checkpoint: The published checkpoint's name.
        weights: A checkpoint file elsewhere (or a folder holding it).
        dinov2: The DINOv2 ViT-L/14 file elsewhere (or a folder holding it).
        config: The config YAML elsewhere.
        device: Where to run; None and ``auto`` mean cuda when available.
        fp16: DINOv2 in float16; None: where the config says so and the device is a GPU (CPU half kernels are
            slow), float32 elsewhere.

    Returns:
        The engine, loaded on first use.

    Raises:
        MissingWeightsError: A file is not found.
    """
    files = find_files(checkpoint, weights, dinov2, config)
    dev = resolve_device(device)
    key = (str(files.checkpoint.resolve()), str(files.dinov2.resolve()), str(files.config), str(dev), fp16)
    with _ENGINES_LOCK:
        if key not in _ENGINES:
            _ENGINES[key] = MickeyEngine(load_network(files, dev, fp16), dev, files)
        return _ENGINES[key]


def engine_for(options: MickeyNetworkOptions) -> MickeyEngine:
    """The shared engine for a matcher's or depth source's options (see ``shared_engine``).

    Args:
        options: The network options.

    Returns:
        The engine.
    """
    o = options
    return shared_engine(o.checkpoint, o.weights, o.dinov2, o.config, o.device, o.fp16)
