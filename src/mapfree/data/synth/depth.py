"""A simulated monocular depth estimate: what a network like DPT would give for a synthetic frame.

Wrong by a per-image scale (log-normal), bent by a smooth low-frequency field, blurred at edges, with
pixel noise, and dense (the sky gets a far value), so that depth-scale solvers face realistic errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["MonoDepthModel", "simulate_mono_depth"]


@dataclass(frozen=True)
class MonoDepthModel:
    """How wrong the simulated estimate is (all multiplicative, in log space)."""

    scale_sigma: float = 0.10  # per-image log-scale bias
    warp_sigma: float = 0.06  # smooth low-frequency distortion
    warp_cells: tuple[int, int] = (3, 4)  # knots of the distortion field (x, y)
    noise_sigma: float = 0.01  # per-pixel noise
    blur_px: float = 1.0  # edge smoothing (networks blur depth discontinuities)
    sky_depth: float = 60.0  # value given to pixels without ground-truth depth (before the scale bias)


def simulate_mono_depth(
    depth: np.ndarray, rng: np.random.Generator, model: MonoDepthModel = MonoDepthModel()
) -> tuple[np.ndarray, float]:
    """``(estimate (H,W) float32 metres, its scale bias)`` for a ground-truth depth map (0 = invalid)."""
    H, W = depth.shape
    scale = float(np.exp(rng.normal(0.0, model.scale_sigma)))
    knots = rng.normal(0.0, model.warp_sigma, (model.warp_cells[1], model.warp_cells[0])).astype(np.float32)
    field = cv2.resize(knots, (W, H), interpolation=cv2.INTER_CUBIC)
    h2, w2 = (H + 1) // 2, (W + 1) // 2  # noise in 2x2 blocks, like a network's output stride
    blocks = rng.normal(0.0, model.noise_sigma, (h2, w2)).astype(np.float32)
    noise = cv2.resize(blocks, (w2 * 2, h2 * 2), interpolation=cv2.INTER_NEAREST)[:H, :W]
    filled: np.ndarray = np.where(depth > 0, depth, np.float32(model.sky_depth)).astype(np.float32)
    if model.blur_px > 0:
        filled = cv2.GaussianBlur(filled, (0, 0), model.blur_px)
    est = filled * np.exp(field + noise) * np.float32(scale)
    return np.clip(est, 0.0, 65.0).astype(np.float32), scale
