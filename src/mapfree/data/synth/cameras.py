"""Phone cameras for the synthetic scenes: look-at poses, walking trajectories and refocusing intrinsics."""

from __future__ import annotations

import numpy as np

from ...geometry import Intrinsics, Pose
from .world import UP, World

__all__ = ["look_at", "look_along", "jitter_intrinsics", "walk", "orbit_point"]


def look_along(center: np.ndarray, forward: np.ndarray, roll_deg: float = 0.0) -> Pose:
    """World-to-camera pose of an OpenCV camera at ``center`` looking along ``forward`` (z up, small roll)."""
    z = np.asarray(forward, float) / np.linalg.norm(forward)
    x = np.cross(z, UP)
    if np.linalg.norm(x) < 1e-6:  # looking straight up/down: any horizontal right vector
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    x, y = c * x + s * y, -s * x + c * y
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    return Pose(R, -R @ np.asarray(center, float))


def look_at(center: np.ndarray, target: np.ndarray, roll_deg: float = 0.0) -> Pose:
    return look_along(center, np.asarray(target, float) - np.asarray(center, float), roll_deg)


def jitter_intrinsics(rng: np.random.Generator, width: int, height: int, focal: float, n: int) -> list[Intrinsics]:
    """``n`` per-frame intrinsics around ``focal`` and the image centre (phones refocus between frames)."""
    f = focal * np.exp(rng.normal(0, 0.01, n))
    aspect = 1 + rng.normal(0, 0.002, n)
    cx = (width - 1) / 2 + rng.normal(0, 1.5, n)
    cy = (height - 1) / 2 + rng.normal(0, 1.5, n)
    return [
        Intrinsics(float(f[i]), float(f[i] * aspect[i]), float(cx[i]), float(cy[i]), width, height) for i in range(n)
    ]


def _smooth(rng: np.random.Generator, n: int, sigma: float, waves: int = 3) -> np.ndarray:
    """A smooth random curve over ``n`` samples: a few random slow sinusoids, standard deviation ~ ``sigma``."""
    s = np.linspace(0.0, 1.0, n)[:, None]
    freq = rng.uniform(0.3, 1.5, waves)
    phase = rng.uniform(0, 2 * np.pi, waves)
    amp = rng.normal(0, 1, waves)
    return sigma * np.sqrt(2.0 / waves) * (amp * np.sin(2 * np.pi * freq * s + phase)).sum(1)


def orbit_point(world: World, theta: float, radius: float, height: float) -> np.ndarray:
    return np.array([radius * np.cos(theta), radius * np.sin(theta), height]) + world.target * [1, 1, 0]


def walk(
    rng: np.random.Generator,
    world: World,
    n: int,
    theta0: float,
    sweep: float,
    r_range: tuple[float, float],
    min_radius: float = 1.0,
    max_radius: float = 10.0,
    aim_noise: float = 0.4,
) -> list[Pose]:
    """``n`` poses of a person walking round the object, 1–10 m from it, phone aimed roughly at it."""
    s = np.linspace(0, 1, n)
    theta = theta0 + sweep * s + _smooth(rng, n, 0.15)
    r_lo = max(r_range[0], world.object_radius + min_radius)
    r_hi = min(max(r_range[1], r_lo + 0.5), world.object_radius + max_radius, 10.5)
    r0, r1 = rng.uniform(r_lo, r_hi, 2)
    radius = np.clip(r0 + (r1 - r0) * s + _smooth(rng, n, 0.6), r_lo, r_hi)
    height = np.clip(rng.uniform(1.35, 1.75) + _smooth(rng, n, 0.08) + 0.02 * np.sin(40 * s), 1.1, 2.0)
    aim = world.target + np.stack(
        [_smooth(rng, n, aim_noise), _smooth(rng, n, aim_noise), _smooth(rng, n, aim_noise * 0.5)], 1
    )
    roll = _smooth(rng, n, 3.0) + rng.normal(0, 0.5, n)
    return [look_at(orbit_point(world, theta[i], radius[i], height[i]), aim[i], roll[i]) for i in range(n)]
