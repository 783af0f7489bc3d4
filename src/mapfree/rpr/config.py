"""Options of an RPR experiment as dataclasses (defaults = the paper's values), loaded from YAML."""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import yaml

from ..yamlio import read_yaml_with_base

__all__ = [
    "ModelConfig",
    "LossConfig",
    "DataConfig",
    "TrainConfig",
    "RPRConfig",
    "load_config",
    "apply_overrides",
    "config_dir",
    "resolve_config",
]

ROTATIONS = ("quat", "6d", "euler_bins", "3d3d")
AGGREGATORS = ("warp", "qkv", "concat")
FREEZE = ("none", "encoder", "pose")
TRANSLATIONS = ("t", "s_tdir", "s_tbins")


@dataclass
class ModelConfig:
    """Network shape and output parameterisation (the public release's defaults)."""

    rotation: str = "6d"  # quat | 6d | euler_bins | 3d3d (joint: predicted points + Procrustes)
    translation: str = "t"  # t | s_tdir | s_tbins (ignored for 3d3d)
    encoder: str = (
        "resunet"  # resunet (the paper's, trained) | xfeat (frozen pretrained XFeat, 64-d at 1/8; beyond the paper)
    )
    encoder_channels: tuple[int, ...] = (64, 128, 256)  # ResUNet stage widths (bottleneck outputs are 4x these)
    encoder_blocks: int = 3  # pre-activation bottlenecks per stage
    feature_dim: int = 32  # encoder output channels at 1/4 resolution
    aggregator: str = "warp"  # warp (correlation-volume warping) | qkv (learned query/key/value) | concat (no warping)
    position: bool = True  # soft-argmax position channels (paper ablation switch)
    max_score: bool = True
    temperature: float = 0.0  # > 0: correlation = cosine / temperature (beyond the paper); 0: raw dot product
    own_position: bool = False  # also image 0's pixel grid (2 channels; the public POSITION_ENCODER_IM1)
    head_channels: tuple[int, ...] = (64, 128, 256, 512)  # stride-2 residual blocks of the pose head
    avg_pool: bool = True  # global average pooling; False: flatten the fixed-size map (needs data.image_size)
    mlp: tuple[int, ...] = (256, 128)  # hidden layers of the MLP; () = one linear layer (the binned heads)
    n_points: int = 6  # 3d3d: 3 (matched to a fixed basis) or 6+ predicted points, half per image
    basis: bool = True  # 3d3d: add the unit basis e_x, e_y, e_z to the points (n_points 3 or 6)
    uncertainty: bool = True  # beyond the paper: predicted log-scales of rotation/translation error
    # Target normalisation (beyond the paper; set by ``data.normalize_targets``): the network predicts
    # t = t_mean + t_std * output and starts at the mean training rotation, so its outputs stay O(1).
    t_mean: tuple[float, ...] = (0.0, 0.0, 0.0)
    t_std: tuple[float, ...] = (1.0, 1.0, 1.0)
    R_mean: tuple[float, ...] | None = None  # 9 values, row-major; None: identity prior


@dataclass
class LossConfig:
    """Pose loss: L_R + lam L_t, or learned homoscedastic weighting; plus the uncertainty NLL."""

    rotation: str = "geodesic"  # geodesic | frobenius | l1 | quat_l1 | ce (bins)
    translation: str = "l1"  # l1 | l2 | angle | scale_dir | ce (spherical bins + scale L1)
    weighting: str = "fixed"  # fixed | learned
    lam: float = 1.0
    init_s_rot: float = 0.0
    init_s_trans: float = 0.0
    uncertainty_weight: float = 1.0
    virtual_points: float = 0.0  # > 0: add this weight times the virtual-point loss (the VCRE in 3D; beyond the paper)


@dataclass
class DataConfig:
    """Pairs from the Map-free layout: scene-balanced, inside overlap bounds, resized to 360×270."""

    root: str = ""
    pairs_per_scene: int = 700
    min_overlap: float = 0.4
    max_overlap: float = 0.8
    image_size: tuple[int, int] | None = None  # (W, H) for every image (public: 270×360, landscape photos squashed);
    # None: long_side × short_side in the orientation of the frames
    long_side: int = 360
    short_side: int = 270
    augment: bool = True
    batch_size: int = 10
    val_batch_size: int = 10
    num_workers: int = 0
    val_split: str = "val"
    val_every_query: int = 5  # 5: the benchmark's scored queries; 1: all queries
    max_val_pairs: int = 0  # 0 = all
    seed: int = 0
    cache_images: bool = False  # keep resized uint8 images in memory (small datasets, num_workers 0)
    # Decode and resize every frame once into this folder (raw uint8 .npy, 285 kB a frame at 360×270), later
    # epochs read it back without JPEG decoding; "" = decode every time.
    cache_dir: str = ""
    normalize_targets: bool = False  # fit: store the training pairs' mean/std pose in model.{t_mean,t_std,R_mean}


@dataclass
class TrainConfig:
    lr: float = 1e-4
    max_epochs: int = 50
    max_steps: int = -1
    gradient_clip_val: float = 1.0
    adam_eps: float = 1e-8  # the public release trains with 1e-6
    # none | encoder (the Siamese encoder's weights and BatchNorm statistics stay fixed) | pose (only the
    # uncertainty head trains: a confidence on top of a loaded model whose poses stay exactly as they were)
    freeze: str = "none"
    init: str = ""  # checkpoint to start from: ours, or a public Map-free one (strict key match)
    scheduler: str = "none"  # none (paper: constant lr) | cosine (linear warmup, then cosine decay to 0)
    warmup_steps: int = 0
    weight_decay: float = 0.0
    precision: str = "32-true"
    channels_last: bool = False  # NHWC tensors: faster convolutions on CPUs and tensor cores (bench_train.py)
    # Frozen encoder only (xfeat or train.freeze): keep each image's features (float16, ~100 kB at 256×192) and run the encoder once
    # per image instead of once per pair: 3.5× the training pairs/s on CPU (bench_train.py). Needs
    # data.augment: false. Memory grows with the distinct images seen: 2 GB for 20k frames, too much for the
    # full Map-free train split (~0.5M frames).
    cache_features: bool = False
    monitor: str = "val/loss"
    monitor_mode: str = "min"
    log_every_n_steps: int = 10
    check_val_every_n_epoch: int = 1
    seed: int = 0


@dataclass
class RPRConfig:
    """Everything that defines a relative pose regression run: network, loss, data and training (a YAML file).

    Attributes:
        name: A label for tables and logs, e.g. ``R(6D)+t``.
        model: The network: encoder, aggregator, head and pose parameterisation.
        loss: The losses and their weighting.
        data: The dataset, pair sampling and input size.
        train: Optimiser, schedule, precision, freezing.
    """

    name: str = "R(6D)+t"
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_dict(self) -> dict[str, Any]:
        """The configuration as nested dicts (what a checkpoint and a YAML file store)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "<dict>") -> RPRConfig:
        """A configuration from nested dicts; values are coerced to the fields' types.

        Args:
            d: The sections and their keys; absent ones keep the defaults.
            source: Where they came from, named in errors.

        Returns:
            The configuration, not yet validated.

        Raises:
            ValueError: An unknown key, or a value of the wrong type (naming ``source`` and the key).
        """
        return _build(cls, d or {}, source)

    def validate(self) -> RPRConfig:
        """Check that the settings fit together (a parameterisation and its loss, freezing and caching, …).

        Returns:
            This configuration.

        Raises:
            ValueError: The first inconsistency, naming the keys.
        """
        m, loss = self.model, self.loss
        if m.rotation not in ROTATIONS:
            raise ValueError(f"model.rotation must be one of {ROTATIONS}, got {m.rotation!r}")
        if m.translation not in TRANSLATIONS:
            raise ValueError(f"model.translation must be one of {TRANSLATIONS}, got {m.translation!r}")
        if (m.rotation == "euler_bins") != (loss.rotation == "ce"):
            raise ValueError("rotation bins need loss.rotation: ce (and ce needs model.rotation: euler_bins)")
        if m.rotation != "3d3d" and (m.translation == "s_tbins") != (loss.translation == "ce"):
            raise ValueError("translation bins need loss.translation: ce (and ce needs model.translation: s_tbins)")
        if loss.rotation == "quat_l1" and m.rotation != "quat":
            raise ValueError("loss.rotation quat_l1 needs model.rotation: quat")
        if m.rotation == "3d3d" and (loss.rotation in ("ce", "quat_l1") or loss.translation == "ce"):
            raise ValueError("3d3d is supervised through its decoded pose: use a matrix rotation loss")
        if m.encoder not in ("resunet", "xfeat"):
            raise ValueError(f"model.encoder must be resunet or xfeat, got {m.encoder!r}")
        if len(m.t_mean) != 3 or len(m.t_std) != 3 or min(m.t_std) <= 0:
            raise ValueError(
                f"model.t_mean needs 3 values and model.t_std 3 positive values, got {m.t_mean}, {m.t_std}"
            )
        if m.R_mean is not None and len(m.R_mean) != 9:
            raise ValueError(f"model.R_mean needs 9 values (row-major 3×3), got {len(m.R_mean)}")
        if self.train.scheduler not in ("none", "cosine"):
            raise ValueError(f"train.scheduler must be none or cosine, got {self.train.scheduler!r}")
        if self.train.cache_features and ((m.encoder != "xfeat" and self.train.freeze == "none") or self.data.augment):
            raise ValueError(
                "train.cache_features needs a frozen encoder (model.encoder: xfeat or train.freeze) and "
                "data.augment: false (augmented pixels would change the features)"
            )
        if self.train.freeze not in FREEZE:
            raise ValueError(f"train.freeze must be one of {FREEZE}, got {self.train.freeze!r}")
        if self.train.freeze == "pose" and not m.uncertainty:
            raise ValueError("train.freeze: pose trains only the uncertainty head: set model.uncertainty: true")
        if m.aggregator not in AGGREGATORS:
            raise ValueError(f"model.aggregator must be one of {AGGREGATORS}, got {m.aggregator!r}")
        if not m.avg_pool and not self.data.image_size:
            raise ValueError("model.avg_pool: false flattens a fixed-size map: set data.image_size [W, H]")
        if loss.virtual_points < 0:
            raise ValueError(f"loss.virtual_points must be >= 0, got {loss.virtual_points}")
        if loss.weighting not in ("fixed", "learned"):
            raise ValueError(f"loss.weighting must be fixed or learned, got {loss.weighting!r}")
        return self


def _build(cls: type, d: dict[str, Any], source: str) -> Any:
    if not isinstance(d, dict):
        raise ValueError(f"{source}: expected a mapping for {cls.__name__}, got {type(d).__name__}")
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(d) - set(known))
    if unknown:
        raise ValueError(
            f"{source}: unknown key(s) {', '.join(unknown)} in {cls.__name__} (allowed: {', '.join(known)})"
        )
    kwargs = {}
    defaults = cls()
    for k, v in d.items():
        sub = getattr(defaults, k)
        if is_dataclass(sub):
            kwargs[k] = _build(type(sub), v or {}, f"{source}:{k}")
        else:
            kwargs[k] = _coerce(v, sub, f"{source}:{k}")
    return cls(**kwargs)


def _coerce(value: Any, default: Any, where: str) -> Any:
    """A YAML value in the type of the field's default (YAML 1.1 reads ``1e-4`` as a string)."""
    if isinstance(value, list):
        return tuple(value)
    try:
        if isinstance(default, bool) or value is None:
            if isinstance(default, bool) and not isinstance(value, bool):
                raise ValueError
            return value
        if isinstance(default, float) and isinstance(value, (int, float, str)):
            return float(value)
        if isinstance(default, int) and isinstance(value, (int, str)) and not isinstance(value, bool):
            return int(value)
    except ValueError:
        raise ValueError(f"{where}: expected {type(default).__name__}, got {value!r}") from None
    return value


def load_config(path: os.PathLike | str) -> RPRConfig:
    """Read a training or model configuration from a YAML file, validated.

    A top-level ``base: OTHER.yaml`` makes the file extend OTHER (relative to the file, else a name in
    ``configs/rpr``): OTHER's keys, then this file's deep-merged over them (``yamlio.read_yaml_with_base``).

    Args:
        path: The YAML file.

    Returns:
        The configuration.

    Raises:
        FileNotFoundError: The file does not exist.
        ValueError: Invalid YAML, an unknown key, a bad value or an inconsistency (naming the file).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config {path} not found")
    data = read_yaml_with_base(path, search=(config_dir(),))
    try:
        return RPRConfig.from_dict(data, str(path)).validate()
    except ValueError as e:
        msg = str(e)
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None


def apply_overrides(cfg: RPRConfig, overrides: list[str]) -> RPRConfig:
    """``["data.batch_size=4", "model.aggregator=concat"]`` -> a new config (values parsed as YAML)."""
    d = cfg.to_dict()
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"override {item!r} is not KEY=VALUE")
        node = d
        *parents, leaf = key.split(".")
        for p in parents:
            if p not in node or not isinstance(node[p], dict):
                raise ValueError(f"override {item!r}: no section {p!r}")
            node = node[p]
        if leaf not in node:
            raise ValueError(f"override {item!r}: unknown key {leaf!r}")
        node[leaf] = yaml.safe_load(value)
    return RPRConfig.from_dict(d, "overrides").validate()


def config_dir() -> Path:
    """``configs/rpr`` (one YAML per paper variant): the repository's, else the copy an installed wheel carries."""
    here = Path(__file__).resolve()
    checkout, packaged = here.parents[3] / "configs" / "rpr", here.parents[1] / "configs" / "rpr"
    return checkout if checkout.is_dir() or not packaged.is_dir() else packaged


def resolve_config(name_or_path: str | os.PathLike) -> Path:
    """A config path, or a name in ``configs/rpr`` (``R6D_t`` or ``R6D_t.yaml``)."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    for cand in (config_dir() / p.name, config_dir() / f"{p.name}.yaml"):
        if cand.is_file():
            return cand
    known = ", ".join(sorted(q.stem for q in config_dir().glob("*.yaml"))) if config_dir().is_dir() else "none"
    raise FileNotFoundError(f"config {name_or_path} not found (configs/rpr has: {known})")
