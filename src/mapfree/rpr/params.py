"""Output parameterisations: the pose head's output vector -> (R, t), plus what each loss needs.

Layouts and decodings are those of the public Map-free release, so its checkpoints give its poses:
rotation first — R(q) 4 (normalised, w x y z), R(6D) 6 (Gram–Schmidt), R(α,β,γ) 900 bin logits
(x 360, y 180, z 360; argmax → whole degrees − (180, 90, 180), extrinsic "xyz") — then translation:
t 3; s·t̂ as [s, t̂ 3] (|s| times the normalised direction); s·t̂(φ,θ) as [φ 360, θ 180, s] (|s| times the
direction of the argmax whole-degree angles). Or jointly [3D-3D]: ``n_points`` predicted 3D points (3: matched to
the fixed basis e_x, e_y, e_z; 6 or more: half per image, the basis added for 6), solved by Procrustes.
The pose is of image 1 (query) relative to image 0 (reference): ``X_1 = R X_0 + t``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ..geometry import rotmat_to_quat
from .procrustes import procrustes
from .rotations import (
    EULER_BINS,
    SPHERICAL_BINS,
    euler_bin_angles,
    matrix_from_euler,
    quat_to_matrix,
    rot6d_to_matrix,
    spherical_to_direction,
)

__all__ = ["PoseOutput", "Parameterisation", "build_parameterisation"]


@dataclass
class PoseOutput:
    """A decoded pose with the intermediate tensors the losses read (logits, scale, points).

    Attributes:
        R: (B, 3, 3) rotation of the query relative to the reference.
        t: (B, 3) translation, metres.
        raw: What the decoding went through (``quat``, ``euler_logits``, ``scale``, ``direction``,
            ``points0``/``points1``, …), by name.
        log_sigma: (B, 2) log-scale of the rotation (radians) and translation (metres) error, from the
            uncertainty head; None without it.
    """

    R: torch.Tensor
    t: torch.Tensor
    raw: dict[str, Any] = field(default_factory=dict)  # tensors, and lists of per-group bin logits
    log_sigma: torch.Tensor | None = None  # (B,2): log-scale of rotation (rad) and translation (m) error


class _Part:
    dim: int = 0

    def prior(self) -> list[float]:
        """Bias of the last layer: the output that decodes to a sensible prior (identity, forward)."""
        return [0.0] * self.dim

    def decode(self, x: torch.Tensor, raw: dict) -> torch.Tensor:
        """This part's slice of the network output -> a rotation matrix or a translation; extras go into ``raw``."""
        raise NotImplementedError


class _Quat(_Part):
    dim = 4

    def prior(self) -> list[float]:
        return [1.0, 0.0, 0.0, 0.0]

    def decode(self, x: torch.Tensor, raw: dict) -> torch.Tensor:
        raw["quat"] = F.normalize(x, dim=-1, eps=1e-12)
        return quat_to_matrix(raw["quat"])


class _SixD(_Part):
    dim = 6

    def prior(self) -> list[float]:
        return [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]

    def decode(self, x: torch.Tensor, raw: dict) -> torch.Tensor:
        return rot6d_to_matrix(x)


class _EulerBins(_Part):
    dim = sum(EULER_BINS)

    def decode(self, x: torch.Tensor, raw: dict) -> torch.Tensor:
        raw["euler_logits"] = list(torch.split(x, list(EULER_BINS), dim=-1))
        with torch.no_grad():
            idx = torch.stack([lg.argmax(-1) for lg in raw["euler_logits"]], -1)
            return matrix_from_euler(euler_bin_angles(idx).to(x.dtype))


class _T(_Part):
    dim = 3

    def __init__(self, mean=(0.0, 0.0, 0.0), std=(1.0, 1.0, 1.0)):
        self.mean, self.std = tuple(float(v) for v in mean), tuple(float(v) for v in std)

    def decode(self, x: torch.Tensor, raw: dict) -> torch.Tensor:
        if self.mean == (0.0, 0.0, 0.0) and self.std == (1.0, 1.0, 1.0):
            return x
        return x * x.new_tensor(self.std) + x.new_tensor(self.mean)  # normalised output -> metres


class _ScaleDir(_Part):
    dim = 4

    def prior(self) -> list[float]:
        return [1.0, 0.0, 0.0, 1.0]

    def decode(self, x: torch.Tensor, raw: dict) -> torch.Tensor:
        raw["scale"], raw["direction"] = x[..., 0].abs(), F.normalize(x[..., 1:4], dim=-1, eps=1e-12)
        return raw["scale"].unsqueeze(-1) * raw["direction"]


class _ScaleBins(_Part):
    dim = sum(SPHERICAL_BINS) + 1

    def prior(self) -> list[float]:
        return [0.0] * (self.dim - 1) + [1.0]

    def decode(self, x: torch.Tensor, raw: dict) -> torch.Tensor:
        raw["spherical_logits"] = list(torch.split(x[..., :-1], list(SPHERICAL_BINS), dim=-1))
        raw["scale"] = x[..., -1].abs()
        idx = torch.stack([lg.argmax(-1) for lg in raw["spherical_logits"]], -1)
        return raw["scale"].unsqueeze(-1) * spherical_to_direction(idx.to(x.dtype))


class Parameterisation:
    """How the network's output encodes a pose: a rotation part and a translation part, or [3D-3D] points.

    Args:
        rotation: ``quat``, ``6d``, ``euler_bins`` or ``3d3d`` (point sets aligned by Procrustes).
        translation: ``t``, ``s_tdir`` (scale and direction) or ``s_tbins`` (scale and direction bins).
        n_points: Points per image of ``3d3d``: 3, 6 or an even number above 6.
        basis: ``3d3d`` adds a fixed basis to the points (keeps the Procrustes gradient defined).
        t_mean: Mean of the training translations, metres (``t`` outputs are normalised by it).
        t_std: Their standard deviation, metres.
        R_mean: Mean training rotation (3 x 3, row-major), where the rotation output starts.

    Raises:
        ValueError: ``n_points`` does not suit ``3d3d``.
    """

    def __init__(
        self,
        rotation: str = "6d",
        translation: str = "t",
        n_points: int = 6,
        basis: bool = True,
        t_mean: Sequence[float] = (0.0, 0.0, 0.0),
        t_std: Sequence[float] = (1.0, 1.0, 1.0),
        R_mean: np.ndarray | Sequence[float] | None = None,
    ):
        self.rotation, self.translation = rotation, translation
        self.n_points, self.basis = n_points, basis
        self.R_mean = None if R_mean is None else np.asarray(R_mean, dtype=np.float64).reshape(3, 3)
        if rotation == "3d3d":
            if not (n_points == 3 or (n_points >= 6 and n_points % 2 == 0)):
                raise ValueError(f"3d3d needs n_points 3, 6 or an even number above 6, got {n_points}")
            self.dim = 3 * n_points
            self._rot: _Part | None = None
            self._trans: _Part | None = None
        else:
            self._rot = {"quat": _Quat, "6d": _SixD, "euler_bins": _EulerBins}[rotation]()
            self._trans = (
                _T(t_mean, t_std) if translation == "t" else {"s_tdir": _ScaleDir, "s_tbins": _ScaleBins}[translation]()
            )
            self.dim = self._rot.dim + self._trans.dim

    @property
    def name(self) -> str:
        if self.rotation == "3d3d":
            return "[3D-3D]"
        r = {"quat": "R(q)", "6d": "R(6D)", "euler_bins": "R(α,β,γ)"}[self.rotation]
        t = {"t": "t", "s_tdir": "s·t̂", "s_tbins": "s·t̂(φ,θ)"}[self.translation]
        return f"{r}+{t}"

    def prior(self) -> list[float]:
        """Bias of the last layer, so that a new network starts at a sensible pose (the mean rotation, forward)."""
        if self._rot is None or self._trans is None:  # [3D-3D]: neither part
            return [0.0] * self.dim
        rot = self._rot.prior()
        if self.R_mean is not None and self.rotation == "6d":  # start at the mean training rotation
            rot = [*self.R_mean[:, 0], *self.R_mean[:, 1]]
        elif self.R_mean is not None and self.rotation == "quat":
            rot = list(rotmat_to_quat(self.R_mean))
        return [float(v) for v in rot] + self._trans.prior()

    def decode(self, x: torch.Tensor) -> PoseOutput:
        """Decode the network's output into a pose.

        Args:
            x: (B, dim) output of the pose head's MLP.

        Returns:
            The pose and the intermediate tensors.
        """
        raw: dict = {}
        if self._rot is None or self._trans is None:  # [3D-3D]: neither part
            n = self.n_points
            pts = x.reshape(x.shape[0], n, 3)
            eye = torch.eye(3, dtype=x.dtype, device=x.device).expand(x.shape[0], 3, 3)
            P0, P1 = (eye, pts) if n == 3 else (pts[:, : n // 2], pts[:, n // 2 :])
            if self.basis:
                P0 = P0 + eye if n == 6 else P0
                P1 = P1 + eye if n in (3, 6) else P1
            raw["points0"], raw["points1"] = P0, P1
            R, t = procrustes(P0, P1)
            return PoseOutput(R, t, raw)
        R = self._rot.decode(x[..., : self._rot.dim], raw)
        t = self._trans.decode(x[..., self._rot.dim :], raw)
        return PoseOutput(R, t, raw)


def build_parameterisation(cfg) -> Parameterisation:
    """From a ``ModelConfig``."""
    return Parameterisation(cfg.rotation, cfg.translation, cfg.n_points, cfg.basis, cfg.t_mean, cfg.t_std, cfg.R_mean)
