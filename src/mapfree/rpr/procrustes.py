"""Differentiable weighted Procrustes (Kabsch): the rigid (R, t) with ``Y ≈ R X + t``, batched via SVD."""

from __future__ import annotations

import torch

__all__ = ["procrustes"]


def procrustes(
    X: torch.Tensor, Y: torch.Tensor, weights: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable weighted Procrustes: the rigid motion that best maps source points onto target points.

    Gradients flow through ``torch.linalg.svd``; they are well defined while the cross-covariance has
    distinct singular values (generic point sets), which the 3D–3D head keeps by adding a fixed basis.

    Args:
        X: (B, N, 3) source points, N >= 3 and not collinear.
        Y: (B, N, 3) target points.
        weights: (B, N) non-negative weights; uniform when None.

    Returns:
        R (B, 3, 3) with det +1 and t (B, 3) such that ``Y ≈ R X + t``.
    """
    w = torch.ones(X.shape[:-1], dtype=X.dtype, device=X.device) if weights is None else weights
    w = (w / w.sum(-1, keepdim=True)).unsqueeze(-1)
    mx, my = (w * X).sum(-2, keepdim=True), (w * Y).sum(-2, keepdim=True)
    H = ((X - mx) * w).transpose(-1, -2) @ (Y - my)  # (B,3,3) cross-covariance
    U, _, Vh = torch.linalg.svd(H)
    V = Vh.transpose(-1, -2)
    # Flip the last singular direction when the best orthogonal map is a reflection.
    d = torch.sign(torch.linalg.det(V @ U.transpose(-1, -2)))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    R = V @ D @ U.transpose(-1, -2)
    t = my.squeeze(-2) - (R @ mx.transpose(-1, -2)).squeeze(-1)
    return R, t
