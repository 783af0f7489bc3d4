"""Training and validation pairs over the Map-free layout, and a Lightning data module.

Train: ``pairs_per_scene`` pairs per scene per epoch (scene-balanced), drawn from ``overlaps.npz`` strictly
inside the overlap bounds, resampled every epoch. Val: every (scored) query against its scene's reference.
Images are resized to 360×270 (in the frames' orientation) and the intrinsics follow via ``Intrinsics.resized``.

Throughput: with ``data.cache_dir`` every frame is decoded and resized once, then read back as raw
uint8 (no JPEG decode); un-augmented batches stay uint8 until the device (``RPRModule`` divides by 255 there,
bit-identical to the CPU conversion); ``TrainPairs`` + ``EpochSampler`` resample the pairs every epoch inside
one dataset, so loader workers persist across epochs and batches come pinned.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Sampler
from torch.utils.data import Dataset as TorchDataset

from ..data import Dataset, Frame, Scene
from ..geometry import Intrinsics
from .config import DataConfig

log = logging.getLogger(__name__)

__all__ = [
    "Pair",
    "pose_statistics",
    "sample_pairs",
    "val_pairs",
    "PairDataset",
    "RPRDataModule",
    "resolve_size",
    "load_pair_image",
    "resized_image",
    "to_input",
    "as_float_input",
    "EpochPairs",
    "TrainPairs",
    "EpochSampler",
]


@dataclass(frozen=True)
class Pair:
    """Image 0 (reference) and image 1 (query) of one scene; the target is image 1's pose relative to image 0."""

    scene: str  # scene folder path
    name0: str
    name1: str


def sample_pairs(
    scenes: list[Scene], per_scene: int, rng: np.random.Generator, min_overlap: float = 0.4, max_overlap: float = 0.8
) -> list[Pair]:
    """``per_scene`` pairs from each scene's overlaps with ``min < overlap < max`` (with replacement)."""
    pairs: list[Pair] = []
    for scene in scenes:
        ov = scene.overlaps
        if ov is None:
            log.warning("%s: no overlaps.npz, scene skipped for training", scene.path)
            continue
        rows = ov.sample(per_scene, rng, min_overlap, max_overlap)
        if len(rows) == 0:
            log.warning("%s: no pair with %g < overlap < %g, scene skipped", scene.path, min_overlap, max_overlap)
            continue
        for sa, fa, sb, fb in rows:
            pairs.append(Pair(str(scene.path), f"seq{sa}/frame_{fa:05d}.jpg", f"seq{sb}/frame_{fb:05d}.jpg"))
    return pairs


def pose_statistics(pairs: list[Pair]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chordal mean rotation (3,3), mean translation (3,) and its per-axis std (3,) of the pairs' targets."""
    if not pairs:
        raise ValueError("no pairs to take pose statistics from")
    scenes: dict[str, Scene] = {}
    Rs, ts = [], []
    for p in pairs:
        scene = scenes.setdefault(p.scene, Scene(Path(p.scene)))
        f0, f1 = scene.frame(p.name0), scene.frame(p.name1)
        if f0.pose is None or f1.pose is None:
            continue
        rel = f1.pose.relative_to(f0.pose)
        Rs.append(rel.R)
        ts.append(rel.t)
    if not Rs:
        raise ValueError("no pair with both poses to take statistics from")
    U, _, Vt = np.linalg.svd(np.mean(Rs, 0))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    t = np.asarray(ts)
    return R, t.mean(0), np.maximum(t.std(0), 1e-3)


def val_pairs(scenes: list[Scene], every_query: int = 5) -> list[Pair]:
    """Reference–query pairs of val scenes: the benchmark's scored queries (5) or all of them (1)."""
    pairs = []
    for scene in scenes:
        queries = scene.scored_queries() if every_query == 5 else scene.queries[:: max(every_query, 1)]
        pairs += [Pair(str(scene.path), scene.reference.name, q.name) for q in queries if q.pose is not None]
    return pairs


def resolve_size(frame_size: tuple[int, int], cfg: DataConfig) -> tuple[int, int]:
    """Network input (W, H): the configured size, or long×short side in the frames' orientation."""
    if cfg.image_size:
        return int(cfg.image_size[0]), int(cfg.image_size[1])
    w, h = frame_size
    return (cfg.long_side, cfg.short_side) if w >= h else (cfg.short_side, cfg.long_side)


#: Resized uint8 images kept by ``PairDataset(cache=True)``: small CPU runs revisit the same frames every epoch.
_IMAGE_CACHE: dict[tuple[str, tuple[int, int]], np.ndarray] = {}


def resized_image(
    frame: Frame, size: tuple[int, int], cache: bool = False, cache_dir: os.PathLike | str | None = None
) -> np.ndarray:
    """(H,W,3) uint8 RGB resized to ``size`` = (W,H): from memory (``cache``), from ``cache_dir`` (raw ``.npy``
    written on first use, refreshed when the image is newer), or decoded and resized now."""
    key = (str(frame.image_path), (size[0], size[1]))
    if cache and key in _IMAGE_CACHE:
        return _IMAGE_CACHE[key]
    stored = _cache_path(frame, size, cache_dir) if cache_dir else None
    img = None
    if stored is not None and stored.is_file() and stored.stat().st_mtime >= frame.image_path.stat().st_mtime:
        try:
            img = np.load(stored)
        except (OSError, ValueError) as e:  # a torn or foreign file: decode again and overwrite it
            log.warning("%s: unreadable cached image (%s), decoding %s again", stored, e, frame.image_path)
        if img is not None and img.shape != (size[1], size[0], 3):
            img = None
    if img is None:
        img = frame.image()
        h, w = img.shape[:2]
        if (w, h) != (frame.intrinsics.width, frame.intrinsics.height):
            log.debug(
                "%s: image is %dx%d but intrinsics say %dx%d",
                frame.image_path,
                w,
                h,
                frame.intrinsics.width,
                frame.intrinsics.height,
            )
        img = np.ascontiguousarray(cv2.resize(img, tuple(size)) if (w, h) != tuple(size) else img)
        if stored is not None:
            stored.parent.mkdir(parents=True, exist_ok=True)
            tmp = stored.with_suffix(f".{os.getpid()}.tmp")
            with open(tmp, "wb") as f:  # write then rename: concurrent workers never read half a file
                np.save(f, img)
            os.replace(tmp, stored)
    if cache:
        _IMAGE_CACHE[key] = img
    return img


def _cache_path(frame: Frame, size: tuple[int, int], cache_dir: os.PathLike | str) -> Path:
    """``cache_dir/WxH/<split>/<scene>/<seq>/<frame>.npy``: one file per frame and input size."""
    scene = frame.image_path.parents[len(Path(frame.name).parts) - 1]
    return (
        Path(cache_dir) / f"{size[0]}x{size[1]}" / scene.parent.name / scene.name / Path(frame.name).with_suffix(".npy")
    )


def load_pair_image(
    frame: Frame, size: tuple[int, int], cache: bool = False, cache_dir: os.PathLike | str | None = None
) -> tuple[np.ndarray, Intrinsics]:
    """(H,W,3) float32 RGB in [0,1] resized to ``size`` = (W,H), with the matching intrinsics."""
    return to_input(resized_image(frame, size, cache, cache_dir), size), frame.intrinsics.resized(*size)


def to_input(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H,W,3) uint8 RGB -> the network's input (H',W',3) float32 in [0,1] at ``size`` = (W',H'): the public
    release's preprocessing (OpenCV bilinear resize, /255, no mean/std normalisation)."""
    if (img.shape[1], img.shape[0]) != tuple(size):
        img = cv2.resize(img, tuple(size))
    return img.astype(np.float32) / 255.0


def as_float_input(img: torch.Tensor) -> torch.Tensor:
    """A batch from the loader as the network's input: uint8 images become float32 / 255 where they are (on
    the device after the copy), bit-identical to ``to_input``; float images pass unchanged."""
    return img.float().div_(255.0) if img.dtype == torch.uint8 else img


def _photometric(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Brightness, contrast, saturation and per-channel gain jitter; geometry untouched."""
    img = img * rng.uniform(0.7, 1.3) + rng.uniform(-0.1, 0.1)
    mean = img.mean()
    img = (img - mean) * rng.uniform(0.7, 1.3) + mean
    grey = img.mean(-1, keepdims=True)
    img = (img - grey) * rng.uniform(0.6, 1.4) + grey
    img = img * rng.uniform(0.9, 1.1, size=3).astype(np.float32)
    return np.clip(img, 0.0, 1.0).astype(np.float32)


class PairDataset(TorchDataset):
    """Map-style dataset of ``Pair`` -> dict of tensors (images, R, t, q, resized and original K).

    ``uint8``: images stay (3,H,W) uint8 (a quarter of the bytes to collate, pin and copy; the model's side
    divides by 255) unless ``augment`` jitters them in float. ``cache_dir``: see ``resized_image``.
    """

    def __init__(
        self,
        pairs: list[Pair],
        size: tuple[int, int],
        augment: bool = False,
        seed: int = 0,
        cache: bool = False,
        scenes: dict[str, Scene] | None = None,
        cache_dir: str | None = None,
        uint8: bool = False,
    ):
        self.pairs, self.size, self.augment, self.seed, self.cache = pairs, size, augment, seed, cache
        self.cache_dir, self.uint8 = cache_dir or None, uint8
        self._scenes: dict[str, Scene] = {} if scenes is None else scenes

    def __len__(self) -> int:
        return len(self.pairs)

    def scene(self, path: str) -> Scene:
        if path not in self._scenes:
            self._scenes[path] = Scene(Path(path))
        return self._scenes[path]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor | str]:
        return self.item(self.pairs[i], i, self.seed)

    def item(self, p: Pair, i: int, seed: int) -> dict[str, torch.Tensor | str]:
        """The tensors of pair ``p``; ``i`` and ``seed`` draw its augmentation."""
        scene = self.scene(p.scene)
        f0, f1 = scene.frame(p.name0), scene.frame(p.name1)
        if f0.pose is None or f1.pose is None:
            raise ValueError(f"{scene.path}/poses.txt: no pose for {p.name0 if f0.pose is None else p.name1}")
        im0, im1 = (resized_image(f, self.size, self.cache, self.cache_dir) for f in (f0, f1))
        k0, k1 = f0.intrinsics.resized(*self.size), f1.intrinsics.resized(*self.size)
        rel = f1.pose.relative_to(f0.pose)
        if self.augment or not self.uint8:
            im0, im1 = to_input(im0, self.size), to_input(im1, self.size)
        if self.augment:
            rng = np.random.default_rng([seed, i, torch.initial_seed() % (2**32)])
            im0, im1 = _photometric(im0, rng), _photometric(im1, rng)
            if rng.random() < 0.5:  # swap the pair: the target becomes the inverse pose
                im0, im1, k0, k1, f0, f1, rel = im1, im0, k1, k0, f1, f0, rel.inverse()
        q, t = rel.qt()
        return {
            "img0": torch.from_numpy(np.ascontiguousarray(im0.transpose(2, 0, 1))),
            "img1": torch.from_numpy(np.ascontiguousarray(im1.transpose(2, 0, 1))),
            "R": torch.from_numpy(rel.R).float(),
            "t": torch.from_numpy(t).float(),
            "q": torch.from_numpy(q).float(),
            "K0": torch.from_numpy(k0.K).float(),
            "K1": torch.from_numpy(k1.K).float(),
            # Original query intrinsics and size: VCRE is measured on the full-resolution image.
            "K1_orig": torch.from_numpy(f1.intrinsics.K).float(),
            # Which frames (after any swap): lets a frozen encoder's features be cached per image.
            "key0": f"{scene.path}/{f0.name}",
            "key1": f"{scene.path}/{f1.name}",
            "size1_orig": torch.tensor([f1.intrinsics.width, f1.intrinsics.height], dtype=torch.float32),
        }


@dataclass(frozen=True)
class EpochPairs:
    """The training pairs of an epoch, drawn in whichever process asks (loader workers too): the same
    ``sample_pairs`` call as ``RPRDataModule.train_pairs``, so every process agrees on epoch e's list."""

    scenes: tuple[str, ...]
    per_scene: int
    seed: int
    min_overlap: float
    max_overlap: float

    def __call__(self, epoch: int, cache: dict[str, Scene] | None = None) -> list[Pair]:
        cache = {} if cache is None else cache
        for p in self.scenes:
            if p not in cache:
                cache[p] = Scene(Path(p))
        scenes = [cache[p] for p in self.scenes]
        return sample_pairs(
            scenes, self.per_scene, np.random.default_rng([self.seed, epoch]), self.min_overlap, self.max_overlap
        )


class TrainPairs(PairDataset):
    """Training dataset indexed by ``(epoch, i)``: resamples its pairs when the epoch changes, so one dataset
    (and persistent loader workers) serves every epoch. Pair counts are the same every epoch."""

    def __init__(
        self,
        sampling: EpochPairs,
        size: tuple[int, int],
        augment: bool = False,
        seed: int = 0,
        cache: bool = False,
        scenes: dict[str, Scene] | None = None,
        cache_dir: str | None = None,
        uint8: bool = False,
    ):
        super().__init__([], size, augment, seed, cache, scenes, cache_dir, uint8)
        self.sampling = sampling
        self.epoch = 0
        self.pairs = sampling(0, self._scenes)

    def pairs_of(self, epoch: int) -> list[Pair]:
        if epoch != self.epoch:
            self.epoch, self.pairs = epoch, self.sampling(epoch, self._scenes)
        return self.pairs

    def __getitem__(self, index: int | tuple[int, int]) -> dict[str, torch.Tensor | str]:
        epoch, i = index if isinstance(index, tuple) else (self.epoch, index)
        return self.item(self.pairs_of(epoch)[i], i, self.seed * 100003 + epoch)


class EpochSampler(Sampler):
    """Shuffled ``(epoch, i)`` indices for ``TrainPairs``; the epoch is read when an epoch's iteration starts
    (``epoch_fn``, e.g. the trainer's current epoch), so it also holds under Lightning's distributed wrapper."""

    def __init__(self, n: int, epoch_fn: Callable[[], int], seed: int = 0):
        self.n, self.epoch_fn, self.seed = n, epoch_fn, seed

    def __len__(self) -> int:
        return self.n

    def __iter__(self) -> Iterator[tuple[int, int]]:
        epoch = int(self.epoch_fn())
        order = torch.randperm(self.n, generator=torch.Generator().manual_seed(self.seed * 100003 + epoch))
        return iter([(epoch, int(i)) for i in order])


class RPRDataModule(pl.LightningDataModule):
    """Lightning data module of RPR training: pairs resampled each epoch, persistent loader workers.

    One training dataset resamples its pairs each epoch (``TrainPairs``); loader workers persist across
    epochs; batches are pinned when a GPU is present.

    Args:
        cfg: The data section of the configuration.
    """

    def __init__(self, cfg: DataConfig):
        super().__init__()
        self.cfg = cfg
        self.train_scenes: list[Scene] = []
        self.val_scenes: list[Scene] = []
        self.size: tuple[int, int] | None = None
        self._scene_cache: dict[str, Scene] = {}  # parsed poses/intrinsics, shared by every epoch's dataset

    def setup(self, stage: str | None = None) -> None:
        if self.size is not None:
            return
        if not self.cfg.root:
            raise ValueError("data.root is not set: pass --data ROOT or set data.root in the config")
        ds = Dataset(self.cfg.root)
        self.train_scenes = ds.scenes("train") if "train" in ds.splits() else []
        self.val_scenes = ds.scenes(self.cfg.val_split) if self.cfg.val_split in ds.splits() else []
        first = (
            next(iter((self.train_scenes or self.val_scenes)[0].frames.values()), None)
            if (self.train_scenes or self.val_scenes)
            else None
        )
        if first is None:
            raise ValueError(f"{self.cfg.root}: no train or {self.cfg.val_split} scenes with frames")
        self.size = resolve_size((first.intrinsics.width, first.intrinsics.height), self.cfg)
        self._scene_cache.update({str(s.path): s for s in self.train_scenes})

    def _input_size(self) -> tuple[int, int]:
        """(W, H) of the network input, read from the dataset by ``setup``."""
        if self.size is None:
            raise RuntimeError("call setup() first: the input size is read from the dataset")
        return self.size

    def _epoch(self) -> int:
        trainer = getattr(self, "trainer", None)
        return int(trainer.current_epoch) if trainer is not None else 0

    def sampling(self) -> EpochPairs:
        c = self.cfg
        return EpochPairs(
            tuple(str(s.path) for s in self.train_scenes), c.pairs_per_scene, c.seed, c.min_overlap, c.max_overlap
        )

    def train_pairs(self, epoch: int | None = None) -> list[Pair]:
        return self.sampling()(self._epoch() if epoch is None else epoch, self._scene_cache)

    def _loader(self, ds: TorchDataset, batch_size: int, **kw) -> DataLoader:
        workers = self.cfg.num_workers
        return DataLoader(
            ds,
            batch_size=batch_size,
            num_workers=workers,
            persistent_workers=workers > 0,
            pin_memory=torch.cuda.is_available(),
            prefetch_factor=4 if workers > 0 else None,
            **kw,
        )

    def train_dataloader(self) -> DataLoader:
        ds = TrainPairs(
            self.sampling(),
            self._input_size(),
            self.cfg.augment,
            seed=self.cfg.seed,
            cache=self.cfg.cache_images,
            scenes=self._scene_cache,
            cache_dir=self.cfg.cache_dir,
            uint8=True,
        )
        if not ds.pairs:
            raise ValueError(
                f"{self.cfg.root}/train: no training pairs inside the overlap bounds "
                f"({self.cfg.min_overlap} < overlap < {self.cfg.max_overlap})"
            )
        return self._loader(
            ds,
            self.cfg.batch_size,
            sampler=EpochSampler(len(ds), self._epoch, self.cfg.seed),
            drop_last=len(ds) > self.cfg.batch_size,
        )

    def val_pairs(self) -> list[Pair]:
        pairs = val_pairs(self.val_scenes, self.cfg.val_every_query)
        return pairs[: self.cfg.max_val_pairs] if self.cfg.max_val_pairs > 0 else pairs

    def val_dataloader(self) -> DataLoader | list:
        pairs = self.val_pairs()
        if not pairs:
            return []
        ds = PairDataset(
            pairs,
            self._input_size(),
            augment=False,
            cache=self.cfg.cache_images,
            scenes=self._scene_cache,
            cache_dir=self.cfg.cache_dir,
            uint8=True,
        )
        return self._loader(ds, self.cfg.val_batch_size, shuffle=False)
