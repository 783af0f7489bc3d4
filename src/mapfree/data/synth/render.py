"""Vectorised rendering of a ``World``: z-buffered quads, trilinear-mipmapped texture lookup, simple lighting.

Each quad is clipped to the view frustum, filled as a convex polygon (OpenCV) and depth-tested with the exact
plane depth of every pixel centre, so the image and the depth map come from the same per-pixel surface hit.
Texture coordinates of all pixels are then computed at once and looked up with one ``cv2.remap`` per mip level.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ...geometry import Intrinsics, Pose
from .textures import TextureAtlas
from .world import World

__all__ = ["Lighting", "ShadowMap", "random_lighting", "rasterize", "shade", "render", "camera_rays"]

NEAR = 0.05  # metres: nearest visible surface


@dataclass(frozen=True)
class Lighting:
    """One scan's light and camera response: sun, ambient/diffuse mix, gain, gamma, white balance, sky."""

    sun: np.ndarray  # (3,) unit vector towards the sun (world)
    ambient: float
    diffuse: float
    gain: float
    gamma: float
    cast: np.ndarray  # (3,) per-channel white-balance multiplier
    shadow: float  # fraction of light removed in the object's shadow
    sky_zenith: np.ndarray  # (3,) RGB in [0,1]
    sky_horizon: np.ndarray

    def lut(self, exposure: float = 1.0) -> np.ndarray:
        """(256,1,3) uint8 tone curve: gain × exposure × cast, then gamma."""
        x = np.arange(256, dtype=np.float64)[:, None] / 255.0
        y = np.clip(x * self.gain * exposure * self.cast[None, :], 0.0, 1.0) ** self.gamma
        return np.rint(255 * y).astype(np.uint8).reshape(256, 1, 3)


def random_lighting(rng: np.random.Generator, strength: float = 1.0) -> Lighting:
    """A random daylight; ``strength`` scales how far it strays from neutral."""
    elev = np.radians(rng.uniform(25, 70))
    azim = rng.uniform(0, 2 * np.pi)
    sun = np.array([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)])
    overcast = rng.random() < 0.3
    diffuse = rng.uniform(0.1, 0.25) if overcast else rng.uniform(0.35, 0.55)
    s = strength
    return Lighting(
        sun=sun,
        ambient=1.0 - diffuse * rng.uniform(0.4, 0.8),
        diffuse=diffuse,
        gain=float(np.exp(rng.normal(0, 0.15 * s))),
        gamma=float(np.exp(rng.normal(0, 0.1 * s))),
        cast=np.exp(rng.normal(0, 0.04 * s, 3)),
        shadow=0.0 if overcast else rng.uniform(0.3, 0.5),
        sky_zenith=np.clip(np.array([0.35, 0.55, 0.9]) * np.exp(rng.normal(0, 0.1, 3)), 0, 1),
        sky_horizon=np.clip(np.array([0.85, 0.9, 0.95]) * np.exp(rng.normal(0, 0.05, 3)), 0, 1),
    )


def camera_rays(K: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Per-column x and per-row y of the z=1 rays through pixel centres (integer coordinates)."""
    rx = ((np.arange(K.width) - K.cx) / K.fx).astype(np.float32)
    ry = ((np.arange(K.height) - K.cy) / K.fy).astype(np.float32)
    return rx, ry


def _frustum_planes(K: Intrinsics, margin: float = 2.0) -> np.ndarray:
    """(5,4) half-spaces ``a·X + d >= 0`` in camera coordinates: near plane and the four image borders."""
    umin, umax = (-margin - K.cx) / K.fx, (K.width - 1 + margin - K.cx) / K.fx
    vmin, vmax = (-margin - K.cy) / K.fy, (K.height - 1 + margin - K.cy) / K.fy
    return np.array(
        [[0, 0, 1, -NEAR], [1, 0, -umin, 0], [-1, 0, umax, 0], [0, 1, -vmin, 0], [0, -1, vmax, 0]], np.float64
    )


def _clip(poly: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Sutherland–Hodgman clipping of a convex 3D polygon (N,3) by half-spaces."""
    for p in planes:
        if len(poly) == 0:
            break
        s = poly @ p[:3] + p[3]
        if np.all(s >= 0):
            continue
        out = []
        for i in range(len(poly)):
            j = (i + 1) % len(poly)
            if s[i] >= 0:
                out.append(poly[i])
            if (s[i] >= 0) != (s[j] >= 0):
                out.append(poly[i] + (s[i] / (s[i] - s[j])) * (poly[j] - poly[i]))
        poly = np.array(out).reshape(-1, 3)
    return poly


def rasterize(world: World, pose: Pose, K: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Nearest quad per pixel: ``(qid (H,W) int32, -1 = sky; depth (H,W) float32 z in metres, 0 = sky)``."""
    W, H = K.width, K.height
    rx, ry = camera_rays(K)
    zbuf = np.full((H, W), np.inf, np.float32)
    qid = np.full((H, W), -1, np.int32)
    R, t = pose.R, pose.t
    o = world.origin @ R.T + t
    e1, e2, n = world.e1 @ R.T, world.e2 @ R.T, world.normal @ R.T
    planes = _frustum_planes(K)
    Kf = K.K
    for q in range(len(world)):
        delta = float(n[q] @ o[q])  # plane: n·X = delta; the camera sees the front when delta < 0
        if abs(delta) < 1e-9 or (delta > 0 and not world.two_sided[q]):
            continue
        poly = _clip(np.stack([o[q], o[q] + e1[q], o[q] + e1[q] + e2[q], o[q] + e2[q]]), planes)
        if len(poly) < 3:
            continue
        uv = poly[:, :2] / poly[:, 2:3] * [Kf[0, 0], Kf[1, 1]] + [Kf[0, 2], Kf[1, 2]]
        x0, y0 = np.maximum(np.floor(uv.min(0)).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(uv.max(0)).astype(int), [W - 1, H - 1])
        if x0 > x1 or y0 > y1:
            continue
        mask = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.uint8)
        cv2.fillConvexPoly(mask, np.round((uv - [x0, y0]) * 256).astype(np.int32), 1, cv2.LINE_8, 8)
        den = (n[q, 0] * rx[x0 : x1 + 1])[None, :] + (n[q, 1] * ry[y0 : y1 + 1] + n[q, 2])[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.float32(delta) / den
        zb = zbuf[y0 : y1 + 1, x0 : x1 + 1]
        hit = mask.view(bool) & (z > NEAR) & (z < zb)
        zb[hit] = z[hit]
        qid[y0 : y1 + 1, x0 : x1 + 1][hit] = q
    zbuf[qid < 0] = 0.0
    return qid, zbuf


def _mirror(x: np.ndarray, size: np.floating | np.ndarray) -> np.ndarray:
    """Mirrored repeat of texel coordinates into [0, size] (seamless tiling of any photo)."""
    period = 2 * size
    m = x - np.floor(x / period) * period
    return size - np.abs(m - size)


def _quad_tables(world: World, atlas: TextureAtlas, pose: Pose, K: Intrinsics, light: Lighting) -> np.ndarray:
    """Per-quad constants (Q, 16), four groups of four:

    texel u = z (c0 x + c1 y + c2) + c3 and v likewise (c4..c7), with (x, y) the pixel's z=1 ray;
    c8: mip footprint constant, c9, c10: atlas offset of the texture, c11: ground flag; c12..c14: RGB light × tint.
    """
    R, t = pose.R, pose.t
    Q = len(world)
    o, e1, e2, n = world.origin @ R.T + t, world.e1 @ R.T, world.e2 @ R.T, world.normal @ R.T
    len1, len2 = np.linalg.norm(world.e1, axis=1), np.linalg.norm(world.e2, axis=1)
    S = atlas.size
    A1 = e1 / (len1**2)[:, None] * (world.repeats[:, :1] * S)
    A2 = e2 / (len2**2)[:, None] * (world.repeats[:, 1:] * S)
    dens = np.maximum(world.repeats[:, 0] / len1, world.repeats[:, 1] / len2) * S  # texels per metre
    delta = np.abs((n * o).sum(1))
    tab = np.zeros((Q, 16), np.float64)
    tab[:, 0:3], tab[:, 3] = A1, -(o * A1).sum(1)
    tab[:, 4:7], tab[:, 7] = A2, -(o * A2).sum(1)
    # footprint (texels per pixel) = dens z / (f sqrt(|r| cos_inc)) and |r| cos_inc = |n.r| = delta / z
    tab[:, 8] = dens / (K.mean_focal * np.sqrt(np.maximum(delta, 1e-6)))
    tab[:, 9:11] = atlas.offsets[world.texture, 0]
    tab[world.ground_quad, 11] = 1
    lam = light.ambient + light.diffuse * np.clip(world.normal @ light.sun, 0, None)
    lam = np.where(world.two_sided, light.ambient + light.diffuse * np.abs(world.normal @ light.sun), lam)
    tab[:, 12:15] = world.tint * lam[:, None]
    return tab


def _gather(tab: np.ndarray, qid: np.ndarray) -> list[np.ndarray]:
    """Per-pixel values of per-quad constants: one contiguous (H,W) float32 array per column; sky gets 0.

    ``cv2.LUT`` on the quad id as a byte is several times faster than numpy fancy indexing.
    """
    Q, k = tab.shape
    if Q >= 255:
        full = np.vstack([tab, np.zeros((1, k))]).astype(np.float32)  # row -1 (sky) is zeros
        return [np.take(full[:, i], qid) for i in range(k)]
    q8 = np.where(qid < 0, 255, qid).astype(np.uint8)
    lut = np.zeros((256, k), np.float32)
    lut[:Q] = tab
    return [cv2.LUT(q8, np.ascontiguousarray(lut[:, i : i + 1])) for i in range(k)]


def shade(
    world: World,
    atlas: TextureAtlas,
    pose: Pose,
    K: Intrinsics,
    qid: np.ndarray,
    depth: np.ndarray,
    light: Lighting,
    noise: np.ndarray | None = None,
    exposure: float = 1.0,
    shadow_map: ShadowMap | None = None,
) -> np.ndarray:
    """(H,W,3) uint8 RGB of the rasterised frame: textured, lit, tone-mapped; ``noise`` (H,W) is added."""
    f32 = np.float32
    rx, ry = camera_rays(K)
    X, Y = rx[None, :], ry[:, None]
    c = _gather(_quad_tables(world, atlas, pose, K, light), qid)

    Xc, Yc = depth * X, depth * Y  # camera coordinates of each pixel's surface point
    tu = Xc * c[0] + Yc * c[1] + depth * c[2] + c[3]
    tv = Xc * c[4] + Yc * c[5] + depth * c[6] + c[7]
    r2 = X * X + Y * Y + 1
    foot = c[8] * depth * np.sqrt(depth) / np.sqrt(np.sqrt(r2))
    level = np.clip(np.log2(np.maximum(foot, f32(1e-6))), 0, atlas.levels - 1)
    l0 = np.floor(level)
    w = level - l0
    # Mirroring commutes with the power-of-two scaling of mip levels: mirror once at level 0.
    mu, mv = _mirror(tu, f32(atlas.size)), _mirror(tv, f32(atlas.size))
    ox, oy = c[9] - f32(0.5), c[10] - f32(0.5)
    S, pad = f32(atlas.size), f32(atlas.offsets[0, 1, 0] - atlas.offsets[0, 0, 0] - atlas.size) / 2
    looks = []
    for lv in (l0, np.minimum(l0 + 1, f32(atlas.levels - 1))):
        scale = np.exp2(-lv)
        level_x = 2 * S * (1 - scale) + 2 * pad * lv  # where this level starts in the texture's atlas row
        looks.append(
            cv2.remap(
                atlas.image, ox + level_x + mu * scale, oy + mv * scale, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
            )
        )
    tex = cv2.blendLinear(looks[0], looks[1], 1 - w, w)

    lit = cv2.merge(c[12:15])
    if shadow_map is not None and shadow_map.strength > 0:
        lit *= shadow_map.factor(tu, tv, c[11] > 0)[..., None]
    col = cv2.multiply(tex, lit, dtype=cv2.CV_32F)

    # Sky (lit = 0 there): a vertical gradient on the ray's elevation, smooth enough to compute at 1/8 size.
    sky_mask = (qid < 0).astype(np.uint8)
    if sky_mask.any():
        H, W = qid.shape
        Rt = pose.R.T  # camera-to-world rotation
        xs, ys = X[:, ::8], Y[::8, :]
        elev = (Rt[2, 0] * xs + Rt[2, 1] * ys + Rt[2, 2]) / np.sqrt(xs * xs + ys * ys + 1)
        s = np.sqrt(np.clip(elev, 0, 1))[..., None]
        sky = (255 * (light.sky_horizon + (light.sky_zenith - light.sky_horizon) * s)).astype(f32)
        cv2.copyTo(cv2.resize(sky, (W, H), interpolation=cv2.INTER_LINEAR), sky_mask, col)
    if noise is not None:
        col = cv2.add(col, cv2.merge([noise] * 3))
    return cv2.LUT(cv2.convertScaleAbs(col), light.lut(exposure))


@dataclass(frozen=True)
class ShadowMap:
    """The object's shadow on the ground, rasterised over the ground quad (looked up by its texel coordinates)."""

    lit: np.ndarray  # (N,N) float32 in [0,1], 1 = lit; row = ground e2 direction, column = e1
    texels: tuple[float, float]  # ground texel coordinates spanned by the map (u, v)
    strength: float

    @classmethod
    def build(cls, world: World, atlas: TextureAtlas, light: Lighting, cells: int = 1024) -> ShadowMap:
        g = world.ground_quad
        o, e1, e2 = world.origin[g], world.e1[g], world.e2[g]
        grid = np.zeros((cells, cells), np.uint8)
        if light.sun[2] > 0:
            d = light.sun / light.sun[2]
            for q in range(world.object_quads):
                corners = np.stack(
                    [
                        world.origin[q],
                        world.origin[q] + world.e1[q],
                        world.origin[q] + world.e1[q] + world.e2[q],
                        world.origin[q] + world.e2[q],
                    ]
                )
                flat = corners - corners[:, 2:3] * d  # along the sun ray down to z = 0
                ab = np.stack([(flat - o) @ e1 / (e1 @ e1), (flat - o) @ e2 / (e2 @ e2)], 1)
                pts = np.round((ab * cells - 0.5) * 16).astype(np.int32)
                cv2.fillConvexPoly(grid, pts, 255, cv2.LINE_8, 4)
        soft = cv2.GaussianBlur(grid.astype(np.float32) / 255, (0, 0), 1.5)
        span_u, span_v = (float(x) for x in world.repeats[g] * atlas.size)
        return cls(1.0 - np.clip(soft, 0, 1), (span_u, span_v), light.shadow)

    def factor(self, tu: np.ndarray, tv: np.ndarray, ground: np.ndarray) -> np.ndarray:
        """(H,W) light multiplier: ``1 - strength`` in full shadow on the ground, 1 elsewhere."""
        n = self.lit.shape[0]
        mx = (tu * (n / self.texels[0]) - 0.5).astype(np.float32)
        my = (tv * (n / self.texels[1]) - 0.5).astype(np.float32)
        lit = cv2.remap(self.lit, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return np.where(ground, 1.0 - self.strength * (1.0 - lit), np.float32(1.0)).astype(np.float32)


def render(
    world: World,
    atlas: TextureAtlas,
    pose: Pose,
    K: Intrinsics,
    light: Lighting,
    noise: np.ndarray | None = None,
    exposure: float = 1.0,
    shadow_map: ShadowMap | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``(image (H,W,3) uint8 RGB, depth (H,W) float32 metres, 0 = sky)`` of one frame."""
    qid, depth = rasterize(world, pose, K)
    img = shade(world, atlas, pose, K, qid, depth, light, noise, exposure, shadow_map)
    return img, depth
