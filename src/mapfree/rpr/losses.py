"""The paper's pose losses (per sample), their weighting, and the uncertainty NLL (beyond the paper)."""

from __future__ import annotations

from typing import cast

import torch
import torch.nn as nn
import torch.nn.functional as F

from .config import LossConfig
from .metrics import virtual_points
from .params import PoseOutput
from .rotations import (
    _safe_norm,
    angle_between,
    direction_to_spherical,
    euler_bin_index,
    euler_from_matrix,
    geodesic_angle,
    spherical_bin_index,
)

__all__ = [
    "rotation_loss",
    "translation_loss",
    "virtual_point_loss",
    "PoseLoss",
    "ROTATION_LOSSES",
    "TRANSLATION_LOSSES",
]

ROTATION_LOSSES = ("geodesic", "frobenius", "l1", "quat_l1", "ce")
TRANSLATION_LOSSES = ("l1", "l2", "angle", "scale_dir", "ce")


def _bins_ce(logits: list[torch.Tensor], index: torch.Tensor) -> torch.Tensor:
    """Mean over bin groups of the cross-entropy against each group's target bin: (B,)."""
    total = sum(F.cross_entropy(g.float(), index[..., i], reduction="none") for i, g in enumerate(logits))
    return cast(torch.Tensor, total) / len(logits)  # a tensor: there is at least one group


def rotation_loss(kind: str, out: PoseOutput, R_gt: torch.Tensor, q_gt: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) rotation loss; 0 exactly at the ground truth. Element means as in the public release (its batch mean
    is ``PoseLoss``'s); geodesic: the angle in radians."""
    if kind == "geodesic":
        return geodesic_angle(out.R, R_gt)
    if kind == "frobenius":
        return ((out.R - R_gt) ** 2).mean((-1, -2))  # = the public mean((R_gt^T R - I)^2) for rotations
    if kind == "l1":
        return (
            (out.R.transpose(-1, -2) @ R_gt - torch.eye(3, dtype=R_gt.dtype, device=R_gt.device)).abs().mean((-1, -2))
        )
    if kind == "quat_l1":
        if "quat" not in out.raw or q_gt is None:
            raise ValueError("quat_l1 needs a quaternion output and a ground-truth quaternion")
        q = out.raw["quat"]
        return torch.minimum((q - q_gt).abs().mean(-1), (q + q_gt).abs().mean(-1))  # q and -q are one rotation
    if kind == "ce":
        return _bins_ce(out.raw["euler_logits"], euler_bin_index(euler_from_matrix(R_gt)))
    raise ValueError(f"unknown rotation loss {kind!r} (known: {', '.join(ROTATION_LOSSES)})")


def translation_loss(kind: str, out: PoseOutput, t_gt: torch.Tensor) -> torch.Tensor:
    """(B,) translation loss; 0 exactly at the ground truth. l1/l2: mean over x, y, z (public ``F.l1_loss``);
    scale_dir: |Δscale| + L1 of the unit directions; ce: |Δscale| + mean of the two bin cross-entropies."""
    if kind == "l1":
        return (out.t - t_gt).abs().mean(-1)
    if kind == "l2":
        return ((out.t - t_gt) ** 2).mean(-1)
    if kind == "angle":
        return angle_between(out.t, t_gt)
    scale = out.raw.get("scale")
    scale = _safe_norm(out.t) if scale is None else scale
    scale_err = (scale - _safe_norm(t_gt)).abs()
    if kind == "scale_dir":
        d = out.raw.get("direction", F.normalize(out.t, dim=-1, eps=1e-12))
        return scale_err + (d - F.normalize(t_gt, dim=-1, eps=1e-12)).abs().mean(-1)
    if kind == "ce":
        return scale_err + _bins_ce(out.raw["spherical_logits"], spherical_bin_index(direction_to_spherical(t_gt)))
    raise ValueError(f"unknown translation loss {kind!r} (known: {', '.join(TRANSLATION_LOSSES)})")


def virtual_point_loss(out: PoseOutput, R_gt: torch.Tensor, t_gt: torch.Tensor) -> torch.Tensor:
    """(B,) mean 3D distance (m) by which the estimate moves the VCRE's virtual points: the metric's 3D analogue.

    Beyond the paper: it weighs rotation and translation the way the benchmark does (a rotation error
    displaces points metres away), where ``L_R + λ L_t`` weighs them by a hand-picked λ.
    """
    dt = torch.promote_types(out.R.dtype, torch.float32)  # float32 at least, also under mixed precision
    X = torch.as_tensor(virtual_points(), device=R_gt.device, dtype=dt)  # in the true query camera
    R_rel = out.R.to(dt) @ R_gt.to(dt).transpose(1, 2)  # true query camera -> estimated query camera
    Xe = (
        torch.einsum("bij,nj->bni", R_rel, X)
        - (R_rel @ t_gt.to(dt).unsqueeze(-1)).transpose(1, 2)
        + out.t.to(dt).unsqueeze(1)
    )
    return _safe_norm(Xe - X).mean(-1)


class PoseLoss(nn.Module):
    """The training loss: ``L_R + λ L_t`` or ``L_R e^{-s_R} + L_t e^{-s_t} + s_R + s_t`` (learned s), plus the NLL.

    The NLL is a Laplace likelihood of the (detached) rotation angle and translation error given the
    predicted log-scales, so it teaches the confidence without pulling on the pose itself.

    Args:
        cfg: The loss section of the configuration.
    """

    def __init__(self, cfg: LossConfig):
        super().__init__()
        self.cfg = cfg
        if cfg.weighting == "learned":
            # Shape (1,), as the public release's s_r / s_t (its checkpoints load into these).
            self.s_rot = nn.Parameter(torch.full((1,), float(cfg.init_s_rot)))
            self.s_trans = nn.Parameter(torch.full((1,), float(cfg.init_s_trans)))

    def forward(
        self, out: PoseOutput, R_gt: torch.Tensor, t_gt: torch.Tensor, q_gt: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor]:
        """The loss of a batch and its terms.

        Args:
            out: The network's output.
            R_gt: (B, 3, 3) true rotations.
            t_gt: (B, 3) true translations, metres.
            q_gt: (B, 4) true quaternions, for the ``quat_l1`` loss.

        Returns:
            ``loss`` (to minimise), ``loss_pose``, and the detached ``loss_rot``, ``loss_trans``, ``loss_vp``,
                ``loss_nll`` where they apply.
        """
        l_rot = rotation_loss(self.cfg.rotation, out, R_gt, q_gt).mean()
        l_trans = translation_loss(self.cfg.translation, out, t_gt).mean()
        if self.cfg.weighting == "learned":
            s_r, s_t = self.s_rot[0], self.s_trans[0]
            pose = l_rot * torch.exp(-s_r) + l_trans * torch.exp(-s_t) + s_r + s_t
        else:
            pose = l_rot + self.cfg.lam * l_trans
        terms = {"loss_rot": l_rot.detach(), "loss_trans": l_trans.detach()}
        if self.cfg.virtual_points > 0:
            l_vp = virtual_point_loss(out, R_gt, t_gt).mean()
            terms["loss_vp"] = l_vp.detach()
            pose = pose + self.cfg.virtual_points * l_vp
        terms["loss_pose"] = pose
        total = pose
        if out.log_sigma is not None:
            nll = uncertainty_nll(out, R_gt, t_gt)
            terms["loss_nll"] = nll.detach()
            total = total + self.cfg.uncertainty_weight * nll
        terms["loss"] = total
        return terms


def pose_errors(out: PoseOutput, R_gt: torch.Tensor, t_gt: torch.Tensor) -> torch.Tensor:
    """(B,2) rotation angle (rad) and translation error (m, ‖t − t_gt‖), detached."""
    with torch.no_grad():
        return torch.stack(
            [geodesic_angle(out.R.float(), R_gt.float()), (out.t.float() - t_gt.float()).norm(dim=-1)], -1
        )


def uncertainty_nll(out: PoseOutput, R_gt: torch.Tensor, t_gt: torch.Tensor) -> torch.Tensor:
    """Laplace NLL ``e / b + log b`` of each error e with predicted b = exp(log_sigma); minimised at b = e."""
    if out.log_sigma is None:
        raise ValueError("uncertainty_nll needs the uncertainty head's output (log_sigma)")
    err = pose_errors(out, R_gt, t_gt)
    s = out.log_sigma.float().clamp(-12.0, 12.0)
    return (err * torch.exp(-s) + s).sum(-1).mean()
