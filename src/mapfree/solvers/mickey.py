"""MicKey's probabilistic Procrustes: a metric pose from scored 3D-3D candidates, batched in torch.

As the public ``estimate_pose_vectorized``: ``draws`` times, ``draw_size`` correspondences are drawn without
replacement with probability proportional to their score (from every keypoint pair of the two images); from
each draw, ``hypotheses`` rigid poses are fitted (Kabsch) to ``sample_size`` of its correspondences drawn in
proportion to their scores; every hypothesis is scored by a soft inlier count over its draw (a sigmoid of the
3-D distance at ``soft_threshold``); the best one is refitted up to ``refine_steps`` times to its inliers
(``inlier_threshold``) while their number grows. The confidence is the soft inlier count at ``inlier_threshold``.
The draws use ``torch.multinomial`` with a generator seeded by ``seed``, in the public order, so that the same
scores and seed on the CPU draw the same correspondences as the public code after ``torch.manual_seed(seed)``.

Everything runs on the scores' device, all pairs of a batch and all hypotheses at once
(``probabilistic_procrustes``); ``MickeySolver`` is the ``solvers`` interface for one pair of ``mickey`` matches.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..estimate import Estimate, Signals
from ..geometry import Pose
from ..matching.base import CandidateMatches
from ..options import OptionError, option
from .base import SolverOptions
from .common import GuardedSolver, SolverError, Timer, rotation_is_valid
from .confidence import CONFIDENCE_MODES, ConfidenceMode, choose

if TYPE_CHECKING:
    import torch

__all__ = [
    "MickeySolverOptions",
    "MickeySolver",
    "ProcrustesResult",
    "probabilistic_procrustes",
    "lift",
    "kabsch_torch",
]


@dataclass
class MickeySolverOptions(SolverOptions):
    """The published values (MicKey's config, section ``PROCRUSTES``)."""

    draws: int = option(20, min=1)  # IT_MATCHES
    draw_size: int = option(2048, min=3)  # NUM_SAMPLED_MATCHES, at least sample_size
    hypotheses: int = option(100, min=1)  # IT_RANSAC, per draw
    sample_size: int = option(3, min=3)  # NUM_CORR_3D_3D
    refine_steps: int = option(4, min=0)  # NUM_REFINEMENTS
    inlier_threshold: float = option(0.15, min=0, min_open=True)  # TH_INLIER, metres
    soft_threshold: float = option(0.3, min=0, min_open=True)  # TH_SOFT_INLIER, metres
    # "inliers": the public soft inlier count; "score": times the fraction of the draw it fits
    confidence: ConfidenceMode = option("inliers", choices=CONFIDENCE_MODES)
    seed: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.draw_size < self.sample_size:
            why = f"expected an integer >= sample_size ({self.sample_size})"
            raise OptionError(f"option draw_size={self.draw_size!r}: {why}", "draw_size", self.draw_size, why)


@dataclass
class ProcrustesResult:
    """Per pair of a batch: the pose (``X1 = R X0 + t``), the soft and hard inlier counts over the best draw."""

    R: torch.Tensor  # (B, 3, 3)
    t: torch.Tensor  # (B, 3)
    soft_inliers: torch.Tensor  # (B,)
    inliers: torch.Tensor  # (B,) hard count at inlier_threshold
    drawn: int  # correspondences per draw


def lift(kpts: torch.Tensor, depth: torch.Tensor, K: np.ndarray) -> torch.Tensor:
    """Keypoints to camera points: ``depth * K^-1 (u, v, 1)``.

    Args:
        kpts: (N, 2) pixels.
        depth: (N,) metres.
        K: (3, 3) camera matrix.

    Returns:
        (N, 3) float32 points in metres.
    """
    import torch

    Kinv = torch.as_tensor(np.linalg.inv(np.asarray(K, dtype=np.float64)), device=kpts.device)
    uv1 = torch.cat([kpts.double(), torch.ones_like(kpts[:, :1], dtype=torch.float64)], dim=1)
    return (depth.double()[:, None] * (uv1 @ Kinv.T)).float()


def kabsch_torch(A: torch.Tensor, B: torch.Tensor, w: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid (R, t) with ``B ~ R A + t``, batched over leading axes.

    Args:
        A: (..., N, 3) points.
        B: (..., N, 3) corresponding points.
        w: (..., N) weights: the means are weighted by ``w / sum w`` and the cross-covariance by ``w`` (MicKey's
            refinement on an inlier mask); None for plain means.

    Returns:
        R (..., 3, 3) and t (..., 3).
    """
    import torch

    if w is None:
        a_mean, b_mean = A.mean(dim=-2, keepdim=True), B.mean(dim=-2, keepdim=True)
        H = (A - a_mean).transpose(-1, -2) @ (B - b_mean)
    else:
        wn = (w / (w.abs().sum(-1, keepdim=True) + 1e-16))[..., None]
        a_mean, b_mean = (wn * A).sum(-2, keepdim=True), (wn * B).sum(-2, keepdim=True)
        H = (A - a_mean).transpose(-1, -2) @ (w[..., None] * (B - b_mean))
    U, _, Vh = torch.linalg.svd(H)
    V = Vh.transpose(-1, -2)
    d = torch.sign(torch.linalg.det(U @ Vh))
    Z = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), torch.where(d == 0, 1.0, d)], -1))
    R = V @ Z @ U.transpose(-1, -2)
    t = b_mean - a_mean @ R.transpose(-1, -2)
    return R, t[..., 0, :]


def _distance(X: torch.Tensor, Y: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """|R X + t - Y| (with the public code's 1e-6 under the root), X, Y (..., N, 3), R (..., 3, 3), t (..., 3)."""
    return (((X @ R.transpose(-1, -2) + t[..., None, :] - Y) ** 2).sum(-1) + 1e-6).sqrt()


def _hypothesis_distances(X: torch.Tensor, Y: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``_distance`` of every hypothesis of a draw over the draw: X, Y (D, k, 3), R (D, H, 3, 3), t (D, H, 3) ->
    (D, H, k), as one matrix product per draw (3x3 products batched one by one are ~10x slower)."""
    d, h = R.shape[:2]
    k = X.shape[1]
    RT = R.transpose(-1, -2).permute(0, 2, 1, 3).reshape(d, 3, h * 3)  # [j, (h, i)] = R[h][i, j]
    moved = (X @ RT).view(d, k, h, 3) + t[:, None]
    return (((moved - Y[:, :, None]) ** 2).sum(-1) + 1e-6).sqrt().transpose(1, 2)


def _soft_count(dist: torch.Tensor, th: float) -> torch.Tensor:
    import torch

    return torch.sigmoid(5.0 / th * (th - dist)).sum(-1)


def probabilistic_procrustes(
    scores: torch.Tensor,
    X0: torch.Tensor,
    X1: torch.Tensor,
    options: MickeySolverOptions | None = None,
    generator: torch.Generator | None = None,
) -> ProcrustesResult:
    """MicKey's probabilistic Procrustes RANSAC for a batch of pairs.

    Each draw takes ``draw_size`` candidates by score (or as many as the pair with the fewest positive scores
    has), each hypothesis ``sample_size`` of them; the best hypothesis by soft inlier count is refined on its
    inliers while their number grows.

    Args:
        scores: (B, N0, N1) candidate scores >= 0, at least ``sample_size`` positive per pair.
        X0: (B, N0, 3) keypoints in camera 0's frame, metres.
        X1: (B, N1, 3) keypoints in camera 1's frame, metres.
        options: The solver's options (MicKey's published values by default).
        generator: The random stream (seeded per pair by the solver).

    Returns:
        Per pair: the pose (``X1 = R X0 + t``) and its soft and hard inlier counts.

    Raises:
        SolverError: Fewer positive scores than ``sample_size``.
    """
    import torch

    o = options or MickeySolverOptions()
    B, n0, n1 = scores.shape
    flat = torch.where(torch.isfinite(scores) & (scores > 0), scores, 0).reshape(B, n0 * n1).float()
    positives = int((flat > 0).sum(-1).min())
    if positives < o.sample_size:
        raise SolverError(f"only {positives} candidate matches have a positive score (< {o.sample_size})")
    k, D, Hy = min(o.draw_size, positives), o.draws, o.hypotheses
    # draws: one multinomial per (pair, draw) row; the same stream as one call on the rows tiled (public)
    idx = torch.cat([torch.multinomial(flat[b : b + 1], k, generator=generator) for b in range(B) for _ in range(D)])
    pair = torch.arange(B, device=scores.device).repeat_interleave(D)[:, None]  # (B*D, 1)
    X = X0[pair, torch.div(idx, n1, rounding_mode="trunc")]  # (B*D, k, 3)
    Y = X1[pair, idx % n1]
    w = flat[pair, idx]  # (B*D, k)
    # hypotheses: sample_size of each draw's correspondences per hypothesis, by score
    sub = torch.multinomial(w[:, None].expand(-1, Hy, -1).reshape(-1, k), o.sample_size, generator=generator)
    row = torch.arange(B * D, device=scores.device).repeat_interleave(Hy)[:, None]
    R, t = kabsch_torch(X[row, sub], Y[row, sub])  # (B*D*Hy, 3, 3), (B*D*Hy, 3)
    R, t = R.view(B * D, Hy, 3, 3), t.view(B * D, Hy, 3)
    step = max(1, (1 << 24) // (Hy * k * 3))  # draws scored at once: about 64 MB of float32 per temporary
    soft = torch.cat(
        [
            _soft_count(
                _hypothesis_distances(X[i : i + step], Y[i : i + step], R[i : i + step], t[i : i + step]),
                o.soft_threshold,
            )
            for i in range(0, B * D, step)
        ]
    )  # (B*D, Hy)
    soft = torch.nan_to_num(soft, nan=-1.0).view(B, D * Hy)
    best = soft.argmax(dim=1)
    b = torch.arange(B, device=scores.device)
    draw = b * D + torch.div(best, Hy, rounding_mode="trunc")
    Rb, tb = R[draw, best % Hy].clone(), t[draw, best % Hy].clone()
    Xb, Yb = X[draw], Y[draw]
    # refinement on the inliers of the best hypothesis, while their number grows
    mask = torch.zeros(B, k, device=scores.device, dtype=Xb.dtype)
    before = torch.full((B,), float(o.sample_size), device=scores.device, dtype=Xb.dtype)
    for _ in range(o.refine_steps):
        inl = (o.inlier_threshold - _distance(Xb, Yb, Rb, tb) >= 0).to(Xb.dtype)
        n = inl.sum(-1)
        grow = (n >= o.sample_size) & (n > before)
        if not bool(grow.any()):
            break
        before[grow] = n[grow]
        mask[grow] = inl[grow]
        Rb[grow], tb[grow] = kabsch_torch(Xb[grow], Yb[grow], mask[grow])
    dist = _distance(Xb, Yb, Rb, tb)
    return ProcrustesResult(Rb, tb, _soft_count(dist, o.inlier_threshold), (dist <= o.inlier_threshold).sum(-1), k)


class MickeySolver(GuardedSolver[MickeySolverOptions]):
    """MicKey's own solver on the ``mickey`` matcher's candidates (every keypoint pair, scored, with each
    keypoint's metric depth); depth maps are not used. Never raises on bad input."""

    name = "mickey"
    Options = MickeySolverOptions
    depth_needs = ()

    def _solve(self, matches: Any, K_ref, K_query, depth_ref, depth_query, timer: Timer) -> Estimate:
        import torch

        if not isinstance(matches, CandidateMatches) or matches.candidates is None:
            if len(matches) == 0:
                raise SolverError("no matches")
            raise SolverError(
                "the mickey solver draws from the mickey matcher's scored candidates (every keypoint "
                "pair with its metric depth); these matches carry none"
            )
        c = matches.candidates
        o = self.options
        with timer("ransac"):
            X0 = lift(c.kpts0, c.depth0, K_ref.K)
            X1 = lift(c.kpts1, c.depth1, K_query.K)
            gen = torch.Generator(device=c.scores.device).manual_seed(int(o.seed))
            res = probabilistic_procrustes(c.scores[None], X0[None], X1[None], o, gen)
        R = res.R[0].double().cpu().numpy()
        t = res.t[0].double().cpu().numpy()
        if not rotation_is_valid(R) or not np.all(np.isfinite(t)):
            raise SolverError("degenerate rigid alignment")
        soft, hard = float(res.soft_inliers[0]), int(res.inliers[0])
        values = {"confidence_inliers": soft, "confidence_score": soft * hard / res.drawn}
        extras = {
            **values,
            "n_matches": len(matches),
            "n_drawn": res.drawn,
            "n_inliers": hard,
            "inlier_ratio": hard / res.drawn,
            "metric": True,
        }
        signals = Signals(
            n_matches=len(matches),
            n_inliers=hard,
            inlier_ratio=hard / res.drawn,
            score=values["confidence_score"],
            learned_confidence=float(c.scores.max()) if c.scores.numel() else None,
        )
        return Estimate(Pose(R, t), choose(o.confidence, values), hard, extras=extras, signals=signals)
