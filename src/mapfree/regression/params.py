"""Output parameterisations: raw network outputs -> (R, t), plus what each loss needs (SPEC §4).

Rotation: R(q), R(6D), R(α,β,γ) bins. Translation: t, s·t̂, s·t̂(φ,θ) bins. Joint: [3D-3D] point pairs
aligned by differentiable Procrustes. The pose is of image 1 (query) relative to image 0 (reference):
``X_1 = R X_0 + t``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from ..geometry import rotmat_to_quat

from .procrustes import procrustes
from .rotations import (
    EULER_BINS, SPHERICAL_BINS, bin_center, matrix_from_euler, quat_to_matrix, rot6d_to_matrix,
    spherical_to_direction,
)

__all__ = ["PoseOutput", "Parameterisation", "build_parameterisation", "BASIS"]

#: Fixed scalene triangle added to the [3D-3D] points: keeps Procrustes well conditioned at initialisation.
BASIS = ((1.0, 0.0, 0.0), (0.0, 2.0, 0.0), (0.0, 0.0, 3.0))


@dataclass
class PoseOutput:
    """Decoded pose (B,3,3), (B,3) with the intermediate tensors the losses read (logits, scale, points)."""

    R: torch.Tensor
    t: torch.Tensor
    raw: dict[str, torch.Tensor] = field(default_factory=dict)
    log_sigma: torch.Tensor | None = None  # (B,2): log-scale of rotation (rad) and translation (m) error


class _Part:
    dim: int = 0

    def prior(self) -> list[float]:
        """Bias of the last layer: the output that decodes to a sensible prior (identity, forward)."""
        return [0.0] * self.dim


class _Quat(_Part):
    dim = 4

    def prior(self) -> list[float]:
        return [1.0, 0.0, 0.0, 0.0]

    def decode(self, x: torch.Tensor, raw: dict) -> torch.Tensor:
        raw["quat"] = F.normalize(x, dim=-1, eps=1e-8)
        return quat_to_matrix(x)


class _SixD(_Part):
    dim = 6

    def prior(self) -> list[float]:
        return [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]

    def decode(self, x: torch.Tensor, raw: dict) -> torch.Tensor:
        return rot6d_to_matrix(x)


def _split_bins(x: torch.Tensor, bins) -> list[torch.Tensor]:
    return list(torch.split(x, [b[2] for b in bins], dim=-1))


def _argmax_centers(logits: list[torch.Tensor], bins) -> torch.Tensor:
    return torch.stack([bin_center(l.argmax(-1), lo, hi, n).to(l.dtype) for l, (lo, hi, n) in zip(logits, bins)], -1)


class _EulerBins(_Part):
    dim = sum(b[2] for b in EULER_BINS)

    def decode(self, x: torch.Tensor, raw: dict) -> torch.Tensor:
        raw["euler_logits"] = _split_bins(x, EULER_BINS)
        return matrix_from_euler(_argmax_centers(raw["euler_logits"], EULER_BINS))


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
        raw["scale"], raw["direction"] = x[..., 0], F.normalize(x[..., 1:4], dim=-1, eps=1e-8)
        return raw["scale"].unsqueeze(-1) * raw["direction"]


class _ScaleBins(_Part):
    dim = 1 + sum(b[2] for b in SPHERICAL_BINS)

    def prior(self) -> list[float]:
        return [1.0] + [0.0] * (self.dim - 1)

    def decode(self, x: torch.Tensor, raw: dict) -> torch.Tensor:
        raw["scale"] = x[..., 0]
        raw["spherical_logits"] = _split_bins(x[..., 1:], SPHERICAL_BINS)
        d = spherical_to_direction(_argmax_centers(raw["spherical_logits"], SPHERICAL_BINS))
        return raw["scale"].unsqueeze(-1) * d


class Parameterisation:
    """Splits the MLP output into a rotation and a translation part, or [3D-3D] point pairs."""

    def __init__(self, rotation: str = "6d", translation: str = "t", n_points: int = 3, basis: bool = True,
                 t_mean=(0.0, 0.0, 0.0), t_std=(1.0, 1.0, 1.0), R_mean=None):
        self.rotation, self.translation = rotation, translation
        self.n_points, self.basis = n_points, basis
        self.R_mean = None if R_mean is None else np.asarray(R_mean, dtype=np.float64).reshape(3, 3)
        if rotation == "3d3d":
            if n_points < 3:
                raise ValueError("3d3d needs at least 3 point pairs")
            self.dim = 6 * n_points
            self._rot = self._trans = None
        else:
            self._rot = {"quat": _Quat, "6d": _SixD, "euler_bins": _EulerBins}[rotation]()
            self._trans = _T(t_mean, t_std) if translation == "t" else {"s_tdir": _ScaleDir, "s_tbins": _ScaleBins}[translation]()
            self.dim = self._rot.dim + self._trans.dim

    @property
    def name(self) -> str:
        if self.rotation == "3d3d":
            return "[3D-3D]"
        r = {"quat": "R(q)", "6d": "R(6D)", "euler_bins": "R(α,β,γ)"}[self.rotation]
        t = {"t": "t", "s_tdir": "s·t̂", "s_tbins": "s·t̂(φ,θ)"}[self.translation]
        return f"{r}+{t}"

    def prior(self) -> list[float]:
        if self._rot is None:
            return [0.0] * self.dim
        rot = self._rot.prior()
        if self.R_mean is not None and self.rotation == "6d":  # start at the mean training rotation
            rot = [*self.R_mean[:, 0], *self.R_mean[:, 1]]
        elif self.R_mean is not None and self.rotation == "quat":
            rot = list(rotmat_to_quat(self.R_mean))
        return [float(v) for v in rot] + self._trans.prior()

    def basis_points(self, like: torch.Tensor) -> torch.Tensor:
        """(n,3) fixed points: the scalene triangle, then further generic points for n > 3."""
        g = torch.Generator().manual_seed(0)
        extra = torch.randn(max(self.n_points - 3, 0), 3, generator=g, dtype=torch.float64)
        pts = torch.cat([torch.tensor(BASIS, dtype=torch.float64), extra])[: self.n_points]
        return pts.to(device=like.device, dtype=like.dtype)

    def decode(self, x: torch.Tensor) -> PoseOutput:
        raw: dict = {}
        if self._rot is None:
            n = self.n_points
            P0, P1 = x[..., : 3 * n].reshape(-1, n, 3), x[..., 3 * n:].reshape(-1, n, 3)
            if self.basis:
                b = self.basis_points(x)
                P0, P1 = P0 + b, P1 + b
            raw["points0"], raw["points1"] = P0, P1
            R, t = procrustes(P0, P1)
            return PoseOutput(R, t, raw)
        R = self._rot.decode(x[..., : self._rot.dim], raw)
        t = self._trans.decode(x[..., self._rot.dim:], raw)
        return PoseOutput(R, t, raw)


def build_parameterisation(cfg) -> Parameterisation:
    """From a ``ModelConfig``."""
    return Parameterisation(cfg.rotation, cfg.translation, cfg.n_points, cfg.basis, cfg.t_mean, cfg.t_std, cfg.R_mean)
