"""The synthetic "place of interest": textured planar quads in a z-up metric world.

A scene is a sculpture (a few stacked, rotated boxes covered in photos) or a free-standing mural at the
origin, on a textured square of ground, surrounded by building facades with posters and a few props.
Cameras walk 1–10 m from the object; the props and walls stay farther out so that no camera is inside them.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .textures import GROUNDS, PHOTOS, SURFACES, TextureAtlas

__all__ = ["World", "make_world", "UP"]

UP = np.array([0.0, 0.0, 1.0])


@dataclass
class World:
    """Q textured quads: corner ``origin``, edges ``e1`` (texture x) and ``e2`` (texture y), outward ``normal``."""

    origin: np.ndarray  # (Q,3)
    e1: np.ndarray  # (Q,3)
    e2: np.ndarray  # (Q,3)
    normal: np.ndarray  # (Q,3) unit; the visible side (single-sided quads are culled from behind)
    texture: np.ndarray  # (Q,) int atlas index
    repeats: np.ndarray  # (Q,2) texture repeats along e1, e2
    tint: np.ndarray  # (Q,3) RGB multiplier
    two_sided: np.ndarray  # (Q,) bool
    target: np.ndarray  # (3,) the point cameras look at
    object_radius: float  # horizontal radius of the object's footprint (m)
    half_size: float  # the ground spans [-half_size, half_size]^2
    object_quads: int  # the first object_quads quads form the object (used for shadows)
    facing: tuple[float, ...] = ()  # azimuths (rad) from which the object is meant to be seen; () = all round

    def __len__(self) -> int:
        return len(self.texture)

    @property
    def ground_quad(self) -> int:
        """Index of the ground quad (it follows the object's quads)."""
        return self.object_quads

    @property
    def area(self) -> np.ndarray:
        return np.linalg.norm(np.cross(self.e1, self.e2), axis=1)


class _Builder:
    def __init__(self, atlas: TextureAtlas):
        self.atlas = atlas
        self.rows: list[tuple] = []

    def quad(
        self,
        origin: ArrayLike,
        e1: ArrayLike,
        e2: ArrayLike,
        normal: ArrayLike,
        texture: str,
        repeats: ArrayLike = (1.0, 1.0),
        tint: ArrayLike = (1.0, 1.0, 1.0),
        two_sided: bool = False,
    ) -> None:
        n = np.asarray(normal, float)
        self.rows.append(
            (
                np.asarray(origin, float),
                np.asarray(e1, float),
                np.asarray(e2, float),
                n / np.linalg.norm(n),
                self.atlas.index(texture),
                np.asarray(repeats, float),
                np.asarray(tint, float),
                bool(two_sided),
            )
        )

    def facade(
        self,
        center: ArrayLike,
        normal: ArrayLike,
        width: float,
        height: float,
        texture: str,
        repeats: ArrayLike = (1.0, 1.0),
        tint: ArrayLike = (1, 1, 1),
    ) -> None:
        """An upright rectangle whose bottom edge is centred at ``center``; its image is upright seen from ``normal``."""
        n = np.asarray(normal, float)
        right = np.cross(-n, UP)
        right /= np.linalg.norm(right)
        top_left = np.asarray(center, float) - right * width / 2 + UP * height
        self.quad(top_left, right * width, -UP * height, n, texture, repeats, tint)

    def box(
        self,
        center_xy: Sequence[float] | np.ndarray,
        base_z: float,
        size: Sequence[float],
        yaw: float,
        side_textures: Sequence[str],
        top_texture: str,
        tint: ArrayLike = (1, 1, 1),
        side_repeats: Sequence[ArrayLike] | None = None,
    ) -> None:
        """A yawed box (no bottom face): four photo-covered sides and a top."""
        sx, sy, sz = size
        c, s = np.cos(yaw), np.sin(yaw)
        ax, ay = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
        ctr = np.array([center_xy[0], center_xy[1], base_z])
        faces = [(ax, sy, sx), (-ax, sy, sx), (ay, sx, sy), (-ay, sx, sy)]
        for k, (n, width, depth) in enumerate(faces):
            rep = (1.0, 1.0) if side_repeats is None else side_repeats[k]
            self.facade(ctr + n * depth / 2, n, width, sz, side_textures[k], rep, tint)
        corner = ctr + UP * sz - ax * sx / 2 - ay * sy / 2
        self.quad(corner, ax * sx, ay * sy, UP, top_texture, (max(sx / 1.5, 1), max(sy / 1.5, 1)), tint)

    def build(
        self, target: ArrayLike, object_radius: float, half_size: float, object_quads: int, facing: Sequence[float] = ()
    ) -> World:
        cols = list(zip(*self.rows))
        return World(
            np.stack(cols[0]),
            np.stack(cols[1]),
            np.stack(cols[2]),
            np.stack(cols[3]),
            np.array(cols[4], np.int64),
            np.stack(cols[5]),
            np.stack(cols[6]),
            np.array(cols[7], bool),
            np.asarray(target, float),
            float(object_radius),
            float(half_size),
            int(object_quads),
            tuple(float(a) for a in facing),
        )


def _tint(rng: np.random.Generator, strength: float) -> np.ndarray:
    return np.clip(np.exp(rng.normal(0.0, strength, 3)), 0.5, 1.6)


def _material_tint(rng: np.random.Generator) -> np.ndarray:
    """Colour for a grey material photo (brick, gravel, grass): earthy hues."""
    palette = np.array([[1.15, 0.85, 0.7], [0.95, 0.9, 0.8], [0.8, 0.95, 0.75], [0.9, 0.9, 1.0], [1.1, 1.0, 0.85]])
    return palette[rng.integers(len(palette))] * np.exp(rng.normal(0, 0.05, 3))


def make_world(rng: np.random.Generator, atlas: TextureAtlas, half_size: float = 15.0) -> World:
    """A random place of interest (sculpture or mural), its ground, facades, posters and props."""
    b = _Builder(atlas)
    photos = list(PHOTOS)
    rng.shuffle(photos)
    pick = itertools.cycle(photos).__next__  # each photo used in turn, so neighbours differ

    facing: tuple[float, ...] = ()
    if rng.random() < 0.6:  # sculpture: 1–3 stacked boxes on a plinth
        radius, z = 0.0, 0.0
        for level in range(int(rng.integers(1, 4))):
            w = rng.uniform(1.6, 3.0) * (0.75**level)
            d = rng.uniform(1.2, 2.4) * (0.75**level)
            h = rng.uniform(1.0, 1.8) * (0.85**level)
            yaw = rng.uniform(0, np.pi)
            off = rng.normal(0, 0.1, 2)
            b.box(off, z, (w, d, h), yaw, [pick() for _ in range(4)], "gravel", _tint(rng, 0.05))
            radius = max(radius, np.hypot(w, d) / 2 + np.linalg.norm(off))
            z += h
        target = np.array([0.0, 0.0, 0.5 * z])
    else:  # mural: a free-standing painted wall
        w, h, d = rng.uniform(3.0, 5.0), rng.uniform(2.2, 3.2), 0.3
        yaw = rng.uniform(0, 2 * np.pi)
        b.box(
            (0.0, 0.0),
            0.0,
            (d, w, h),
            yaw,
            [pick(), pick(), "brick", "brick"],
            "brick",
            (1, 1, 1),
            side_repeats=[(1, 1), (1, 1), (1, h / 1.2), (1, h / 1.2)],
        )
        radius = w / 2
        facing = (yaw, yaw + np.pi)  # the two painted sides
        target = np.array([0.0, 0.0, 0.45 * h])
    object_quads = len(b.rows)

    G = half_size
    ground = GROUNDS[rng.integers(len(GROUNDS))]  # brick paving, gravel or grass
    tile = rng.uniform(2.5, 4.0)
    b.quad((-G, -G, 0.0), (2 * G, 0, 0), (0, 2 * G, 0), UP, ground, (2 * G / tile, 2 * G / tile), _material_tint(rng))

    # Facades: each side of the square is a row of 2–4 buildings of varying height and material, with posters.
    for side in range(4):
        ang = side * np.pi / 2
        n = -np.array([np.cos(ang), np.sin(ang), 0.0])  # inward
        along = np.cross(UP, n)
        cuts = np.sort(rng.uniform(-G, G, int(rng.integers(1, 4))))
        edges = np.concatenate([[-G], cuts, [G]])
        for a0, a1 in zip(edges[:-1], edges[1:]):
            width = a1 - a0
            if width < 0.5:
                continue
            height = rng.uniform(4.0, 9.0)
            mid = -n * G + along * (a0 + a1) / 2
            tex = ["brick", "brick", "gravel", "grass"][rng.integers(4)]
            tile = rng.uniform(3.0, 5.0)
            b.facade(mid, n, width, height, tex, (width / tile, height / tile), _material_tint(rng))
            slots = int(width // 4.5)  # posters and murals at eye level, one per 4.5 m of facade at most
            for k in range(slots):
                if rng.random() < 0.3:
                    continue
                pw = rng.uniform(1.8, 3.5)
                ph = min(pw * rng.uniform(0.6, 1.0), height - 2.0)
                at = mid + along * (a0 - (a0 + a1) / 2 + (k + 0.5) * width / slots + rng.uniform(-0.3, 0.3)) + n * 0.02
                b.facade(at + UP * rng.uniform(0.6, 1.4), n, pw, ph, pick(), (1, 1), _tint(rng, 0.03))

    # Props (benches, planters, kiosks) between the cameras' walking area and the facades.
    for _ in range(int(rng.integers(3, 7))):
        r = rng.uniform(12.0, G - 1.5)
        a = rng.uniform(0, 2 * np.pi)
        size = (rng.uniform(0.5, 1.8), rng.uniform(0.5, 1.2), rng.uniform(0.4, 1.5))
        texs = [pick() if rng.random() < 0.5 else SURFACES[rng.integers(3)] for _ in range(4)]
        b.box((r * np.cos(a), r * np.sin(a)), 0.0, size, rng.uniform(0, np.pi), texs, "gravel", _material_tint(rng))

    return b.build(target, radius, G, object_quads, facing)
