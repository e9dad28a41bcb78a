"""Procedural driving town: layout, traffic, ego driver and a pinhole renderer with exact ground truth.

This is the default data source of the pipeline: it stands in for dashcam footage and comes with
exact odometry, metric depth and Cityscapes semantic labels. One file on purpose: the world, its
traffic and the numba renderer share private geometry that splitting would expose.

World model
-----------
World frame: x east, y north, z up, metres; the ground plane is z = 0.

* Roads form an irregular grid: roads running along x at the sorted positions ``Town.road_y`` and
  roads running along y at ``Town.road_x`` (blocks ``style.block_size_m`` apart). Every road has two
  lanes of ``style.lane_width_m`` with right-hand traffic and continues ``style.road_extension_m``
  beyond the town into open terrain.
* Each block between four roads is a raised slab (``style.kerb_height_m``, its side is the kerb)
  whose outer band is sidewalk; inside it holds buildings (axis-aligned boxes on lots with
  setbacks, some with an upper tier) or a park (lawn, trees, hedges). Street lamps and trees line
  the sidewalks, traffic signs stand at intersection corners. Trees (trunk box + ellipsoid canopy
  blobs) also fill a belt of terrain around the town; distant hills are huge flattened ellipsoids.
* Other cars drive straight along lanes at constant per-lane speeds and wrap around at the ends
  of the extended roads, so their state is a pure function of (town seed, t) (`Town.car_boxes`).
  They ignore each other and the ego: the ego follows them and gives way at junctions
  (`simulate_ego`), and `render_episode` hides a car that would drive through the ego from
  behind, from the moment it is out of view behind it.
* Lighting: a directional sun (Lambert, shadows from a precomputed "sun-ray height" map of the
  static scene plus exact shadows of nearby cars on the ground), a hemispheric ambient term,
  ambient occlusion near the ground and building walls, and exponential fog toward the horizon
  colour. Textures are tileable noise with mip levels picked from the pixel footprint; lane
  markings, windows and paving joints are box-filtered analytically.

Rendering (numba kernels, one thread): the G-buffer (z-depth, material kind, object index, face)
starts as the analytic ground plane below the horizon and sky above; vertical prisms are
z-buffered column by column (zero pitch and roll make every column one line on the ground
plane, so a slab test and two divisions per column decide the rows of side and top faces);
ellipsoids are intersected per pixel in their screen bounds; a deferred pass shades each pixel
once. Cost is a few milliseconds per 256x144 frame (benchmarks/bench_town.py).

Camera convention
-----------------
Pinhole camera at the ego pose (x, y, yaw) and height ``mount_height_m``, zero pitch and roll.
Camera axes: x right, y down, z forward (optical axis = ego heading). Pixel (u, v) has its centre
at integer coordinates (u = 0 is the left column, v = 0 the top row)::

    fx = fy = (W / 2) / tan(hfov / 2),   cx = (W - 1) / 2,   cy = (H - 1) / 2

so the ray through pixel (u, v) is ((u - cx) / fx, (v - cy) / fy, 1) in camera axes. ``depth`` is
the z-depth along the optical axis in metres (not the ray length); sky pixels have depth +inf.
A ground pixel in row v > cy therefore has depth ``mount_height_m * fy / (v - cy)``.

Odometry convention
-------------------
Native step k is at t_k = k / fps with pose (x_k, y_k, yaw_k): world position and heading, yaw
counter-clockwise from +x and unwrapped (continuous). The ego frame has x forward, y left.
``speed[k]`` (m/s, >= 0) and ``yaw_rate[k]`` (rad/s, CCW positive) are constant over
[t_k, t_{k+1}); pose k+1 is the exact arc integration of pose k under them
(`integrate_odometry`). Frame k is rendered from pose k at time t_k.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from dataclasses import dataclass
from typing import Iterator

import cv2
import numpy as np
from numba import njit

from orbis2.kinematics import integrate_odometry

__all__ = [
    "CITYSCAPES_TRAIN_IDS", "TownStyle", "TOWN_STYLES", "Camera", "Town", "Renderer", "EgoTrack",
    "simulate_ego", "integrate_odometry", "render_episode",
]

CITYSCAPES_TRAIN_IDS: dict[str, int] = {
    "road": 0, "sidewalk": 1, "building": 2, "pole": 5, "traffic sign": 7,
    "vegetation": 8, "terrain": 9, "sky": 10, "car": 13,
}
_ROAD, _SIDEWALK, _BUILDING, _POLE, _SIGN, _VEG, _TERRAIN, _SKY, _CAR = (
    CITYSCAPES_TRAIN_IDS[k] for k in ("road", "sidewalk", "building", "pole", "traffic sign",
                                      "vegetation", "terrain", "sky", "car"))


# ----------------------------------------------------------------------------- styles


@dataclass(frozen=True)
class TownStyle:
    """Layout, palette, texture and lighting parameters of one town domain.

    Colours are sRGB in [0, 1]; ranges are (low, high) for uniform draws.
    """

    blocks_per_axis: tuple[int, int] = (5, 7)
    block_size_m: tuple[float, float] = (30.0, 60.0)
    lane_width_m: float = 3.5
    sidewalk_m: float = 3.0
    kerb_height_m: float = 0.15
    road_extension_m: float = 220.0
    park_fraction: float = 0.15
    paved_yard_fraction: float = 0.3
    lot_size_m: tuple[float, float] = (10.0, 26.0)
    setback_m: tuple[float, float] = (0.0, 4.0)
    building_height_m: tuple[float, float] = (7.0, 38.0)
    height_skew: float = 2.2  # heights are low + (high - low) * u ** skew
    upper_tier_prob: float = 0.3
    floor_height_m: tuple[float, float] = (3.0, 3.7)
    window_spacing_m: tuple[float, float] = (2.2, 3.4)
    window_width: tuple[float, float] = (0.4, 0.7)
    window_height: tuple[float, float] = (0.45, 0.62)
    glass_tower_prob: float = 0.2
    facade_palette: tuple[tuple[float, float, float], ...] = (
        (0.56, 0.29, 0.22), (0.70, 0.60, 0.47), (0.60, 0.60, 0.58), (0.80, 0.78, 0.73),
        (0.38, 0.28, 0.23), (0.46, 0.51, 0.56), (0.83, 0.76, 0.60), (0.52, 0.50, 0.43),
        (0.64, 0.42, 0.33))
    glass_rgb: tuple[float, float, float] = (0.16, 0.22, 0.26)
    roof_rgb: tuple[float, float, float] = (0.35, 0.34, 0.33)
    asphalt_rgb: tuple[float, float, float] = (0.29, 0.29, 0.30)
    paint_rgb: tuple[float, float, float] = (0.86, 0.86, 0.83)
    centre_line_rgb: tuple[float, float, float] = (0.86, 0.86, 0.83)
    centre_line_double: bool = False
    dash_m: tuple[float, float] = (3.0, 9.0)  # dash length, dash period
    crosswalk_prob: float = 0.6
    sidewalk_rgb: tuple[float, float, float] = (0.62, 0.60, 0.57)
    kerb_rgb: tuple[float, float, float] = (0.72, 0.71, 0.68)
    tile_m: float = 0.5
    grass_rgb: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.26, 0.42, 0.15), (0.40, 0.46, 0.21))
    terrain_rgb: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.33, 0.44, 0.18), (0.50, 0.46, 0.30))
    tree_palette: tuple[tuple[float, float, float], ...] = (
        (0.17, 0.34, 0.11), (0.25, 0.40, 0.14), (0.14, 0.29, 0.15), (0.30, 0.38, 0.12))
    palm_fraction: float = 0.0
    bark_rgb: tuple[float, float, float] = (0.33, 0.26, 0.20)
    street_tree_prob: float = 0.7
    forest_trees: int = 420
    hedge_prob: float = 0.5
    metal_rgb: tuple[float, float, float] = (0.30, 0.32, 0.33)
    car_palette: tuple[tuple[float, float, float], ...] = (
        (0.85, 0.85, 0.85), (0.60, 0.61, 0.63), (0.08, 0.08, 0.09), (0.30, 0.31, 0.33),
        (0.62, 0.08, 0.07), (0.10, 0.22, 0.52), (0.06, 0.10, 0.26), (0.18, 0.32, 0.20),
        (0.70, 0.62, 0.48), (0.85, 0.68, 0.10))
    car_spacing_m: tuple[float, float] = (120.0, 300.0)
    car_speed_ms: tuple[float, float] = (5.5, 9.0)
    # Ego driving: cruise speed per leg, how often it goes straight at a junction (left and right
    # share the rest equally) and how often it stops at a junction without being forced to.
    # Tuned for a world that turns often, both ways (left arcs are wider and take longer, so
    # right turns are drawn a little more often to balance the turning frames).
    cruise_ms: tuple[float, float] = (8.0, 14.0)
    straight_weight: float = 0.15
    right_share: float = 0.56
    stop_prob: float = 0.05
    stop_wait_s: tuple[float, float] = (0.3, 1.5)
    sky_zenith_rgb: tuple[float, float, float] = (0.28, 0.47, 0.80)
    sky_horizon_rgb: tuple[float, float, float] = (0.74, 0.83, 0.93)
    cloud_cover: float = 0.45
    sun_elevation_deg: float = 40.0
    sun_azimuth_deg: float = 215.0
    sun_rgb: tuple[float, float, float] = (1.0, 0.95, 0.86)
    sun_intensity: float = 2.6
    ambient_rgb: tuple[float, float, float] = (0.50, 0.60, 0.78)
    ambient_intensity: float = 0.95
    fog_distance_m: float = 420.0
    exposure: float = 1.15


TOWN_STYLES: dict[str, TownStyle] = {
    "default": TownStyle(),
    # Sunny desert town: small low adobe-coloured blocks, dusty pale roads with a double yellow
    # centre line, sand terrain, palms, a high warm sun and a hazy pale sky.
    "heldout": TownStyle(
        blocks_per_axis=(6, 8), block_size_m=(34.0, 62.0), lane_width_m=3.2, sidewalk_m=3.6,
        park_fraction=0.1, paved_yard_fraction=0.8, lot_size_m=(8.0, 18.0), setback_m=(0.0, 2.5),
        building_height_m=(3.8, 13.0), height_skew=1.6, upper_tier_prob=0.35,
        floor_height_m=(3.2, 3.9), window_spacing_m=(3.0, 4.6), window_width=(0.28, 0.45),
        window_height=(0.35, 0.5), glass_tower_prob=0.0,
        facade_palette=((0.86, 0.73, 0.53), (0.78, 0.46, 0.31), (0.80, 0.62, 0.33),
                        (0.93, 0.90, 0.84), (0.88, 0.70, 0.62), (0.70, 0.53, 0.39),
                        (0.62, 0.70, 0.66)),
        glass_rgb=(0.10, 0.09, 0.08), roof_rgb=(0.62, 0.45, 0.33),
        asphalt_rgb=(0.44, 0.41, 0.37), paint_rgb=(0.90, 0.88, 0.80),
        centre_line_rgb=(0.90, 0.72, 0.15), centre_line_double=True, crosswalk_prob=0.35,
        sidewalk_rgb=(0.78, 0.70, 0.58), kerb_rgb=(0.86, 0.80, 0.70), tile_m=0.8,
        grass_rgb=((0.50, 0.50, 0.26), (0.66, 0.58, 0.38)),
        terrain_rgb=((0.80, 0.67, 0.47), (0.70, 0.55, 0.38)),
        tree_palette=((0.33, 0.42, 0.16), (0.40, 0.45, 0.20), (0.28, 0.36, 0.16)),
        palm_fraction=0.75, bark_rgb=(0.48, 0.40, 0.30), street_tree_prob=0.45, forest_trees=160,
        hedge_prob=0.2, metal_rgb=(0.45, 0.44, 0.42),
        car_palette=((0.90, 0.90, 0.88), (0.75, 0.72, 0.66), (0.55, 0.18, 0.12),
                     (0.20, 0.35, 0.45), (0.82, 0.78, 0.55), (0.35, 0.36, 0.30)),
        sky_zenith_rgb=(0.38, 0.57, 0.85), sky_horizon_rgb=(0.92, 0.88, 0.80), cloud_cover=0.12,
        sun_elevation_deg=63.0, sun_azimuth_deg=120.0, sun_rgb=(1.0, 0.92, 0.78),
        sun_intensity=2.9, ambient_rgb=(0.70, 0.70, 0.72), ambient_intensity=0.7,
        fog_distance_m=330.0, exposure=1.0),
}


# ----------------------------------------------------------------------------- camera


@dataclass(frozen=True)
class Camera:
    """Pinhole camera with zero pitch/roll; see the module docstring for the pixel convention."""

    width: int
    height: int
    hfov_deg: float = 90.0
    mount_height_m: float = 1.5

    @property
    def fx(self) -> float:
        return (self.width / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def fy(self) -> float:
        return self.fx

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2.0

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2.0

    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- numba kernels
#
# Scene arrays shared by the kernels:
#   boxes  float32 [N, 6]: x0, x1, y0, y1, z0, z1 of axis-aligned prisms
#   kinds  int32   [N]:    material kind (_K_*)
#   params float32 [N, 8]: linear albedo rgb + kind-specific values (documented where built)
#   sph    float32 [M, 5]: centre x, y, z, horizontal radius, vertical radius of ellipsoids
# G-buffer: z-depth, kind, index into the kind's table, face code.

_FM = {"nsz", "arcp", "contract", "afn", "reassoc"}  # fastmath without no-nan/no-inf


def _jit(fn):
    # error_model="numpy": float division by zero gives inf/nan instead of a checked exception.
    return njit(cache=True, fastmath=_FM, error_model="numpy")(fn)


_K_SKY, _K_GROUND, _K_BLOCK, _K_BUILDING, _K_HEDGE, _K_TRUNK, _K_POLE, _K_LAMP, _K_SIGN = range(9)
_K_CAR_BODY, _K_CAR_CABIN, _K_WHEEL, _K_CANOPY, _K_HILL = range(9, 14)
_F_NX, _F_PX, _F_NY, _F_PY, _F_TOP, _F_BOT, _F_SPH = range(7)
_NEAR = 0.05
_TONE_N, _TONE_SCALE = 4096, 512.0  # tone-map table: linear radiance 0 .. 8
_FAR = 1.0e30  # "no hit" depth inside the kernels (converted to +inf on output)

# Index layout of the per-town shading constants vector (`Town.shading`).
(_S_SUN, _S_SUNC, _S_AMB, _S_GAMB, _S_ASPH, _S_PAINT, _S_CLINE, _S_SIDEW, _S_KERBC, _S_GRASS,
 _S_GRASS2, _S_TERR, _S_TERR2, _S_ROOF, _S_GLASS) = range(0, 45, 3)
(_S_FOG, _S_EXPO, _S_HW, _S_SW, _S_EXT, _S_KERB, _S_TILE, _S_DASH, _S_DASHP, _S_DOUBLE,
 _S_SMX0, _S_SMY0, _S_SMRES, _S_SMKX, _S_SMKY, _S_AOX0, _S_AOY0, _S_AORES, _S_SKYEL0,
 _S_SKYEL1, _S_N) = range(45, 66)


@_jit
def _hash(i, j, seed):
    """Deterministic integer hash of a lattice cell -> float in [0, 1)."""
    h = (i * 73856093) ^ (j * 19349663) ^ (seed * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF) / 16777216.0


@_jit
def _smooth(e0, e1, x):
    t = min(max((x - e0) / (e1 - e0), 0.0), 1.0)
    return t * t * (3.0 - 2.0 * t)


@_jit
def _pulse_integral(x, lo, hi):
    f = math.floor(x)
    return f * (hi - lo) + min(max(x - f, lo), hi) - lo


@_jit
def _pulse(x, lo, hi, w):
    """Box-filtered periodic pulse: mean over [x - w/2, x + w/2] of 1{lo <= frac(x) < hi}."""
    if w < 1e-4:
        fr = x - math.floor(x)
        return 1.0 if lo <= fr < hi else 0.0
    return (_pulse_integral(x + 0.5 * w, lo, hi) - _pulse_integral(x - 0.5 * w, lo, hi)) / w


@_jit
def _band(d, half, w):
    """Box-filtered coverage of the strip |d| < half by a filter of width w."""
    w = max(w, 1e-4)
    return max(min(d + 0.5 * w, half) - max(d - 0.5 * w, -half), 0.0) / w


@_jit
def _bilerp(tex, ch, lev, u, v):
    n = tex.shape[2] >> lev
    x = u * n - 0.5
    y = v * n - 0.5
    fx0 = math.floor(x)
    fy0 = math.floor(y)
    tx = x - fx0
    ty = y - fy0
    m = n - 1
    ix = int(fx0) & m
    iy = int(fy0) & m
    jx = (ix + 1) & m
    jy = (iy + 1) & m
    a = tex[ch, lev, iy, ix] * (1.0 - tx) + tex[ch, lev, iy, jx] * tx
    b = tex[ch, lev, jy, ix] * (1.0 - tx) + tex[ch, lev, jy, jx] * tx
    return a * (1.0 - ty) + b * ty


@_jit
def _tex(tex, ch, u, v, fp):
    """Trilinear lookup of tileable noise channel `ch` at (u, v) in tiles; fp = footprint in tiles."""
    lod = math.log2(max(fp * tex.shape[2], 1.0))
    top = tex.shape[1] - 1
    if lod >= top:
        return tex[ch, top, 0, 0]
    l0 = int(lod)
    t = lod - l0
    return _bilerp(tex, ch, l0, u, v) * (1.0 - t) + _bilerp(tex, ch, l0 + 1, u, v) * t


@_jit
def _sky_rgb(sky, st, az, el):
    """Bilinear lookup of the sky panorama (rows: elevation, columns: absolute azimuth)."""
    hs = sky.shape[0]
    ws = sky.shape[1]
    fr = (el - st[_S_SKYEL0]) / (st[_S_SKYEL1] - st[_S_SKYEL0]) * (hs - 1)
    fr = min(max(fr, 0.0), hs - 1.001)
    fc = az * (ws / (2.0 * math.pi)) - 0.5
    c0f = math.floor(fc)
    tc = fc - c0f
    c0 = int(c0f) % ws
    c1 = (c0 + 1) % ws
    r0 = int(fr)
    tr = fr - r0
    w00 = (1.0 - tc) * (1.0 - tr)
    w01 = tc * (1.0 - tr)
    w10 = (1.0 - tc) * tr
    w11 = tc * tr
    return (sky[r0, c0, 0] * w00 + sky[r0, c1, 0] * w01 + sky[r0 + 1, c0, 0] * w10 + sky[r0 + 1, c1, 0] * w11,
            sky[r0, c0, 1] * w00 + sky[r0, c1, 1] * w01 + sky[r0 + 1, c0, 1] * w10 + sky[r0 + 1, c1, 1] * w11,
            sky[r0, c0, 2] * w00 + sky[r0, c1, 2] * w01 + sky[r0 + 1, c0, 2] * w10 + sky[r0 + 1, c1, 2] * w11)


@_jit
def _sun_visibility(smap, st, x, y, z):
    """Fraction of the sun visible from (x, y, z), 2x2 filtered lookup of the sun-ray height map.

    smap[q] is the highest occluder point on the sun ray through ground point q; a point is lit
    when it lies above that height.
    """
    qx = x - z * st[_S_SMKX]
    qy = y - z * st[_S_SMKY]
    gx = (qx - st[_S_SMX0]) / st[_S_SMRES] - 0.5
    gy = (qy - st[_S_SMY0]) / st[_S_SMRES] - 0.5
    ix = int(math.floor(gx))
    iy = int(math.floor(gy))
    tx = gx - ix
    ty = gy - iy
    ny, nx = smap.shape
    vis = 0.0
    for dy in range(2):
        for dx in range(2):
            jx = ix + dx
            jy = iy + dy
            w = (tx if dx else 1.0 - tx) * (ty if dy else 1.0 - ty)
            if jx < 0 or jy < 0 or jx >= nx or jy >= ny or z + 0.04 >= smap[jy, jx]:
                vis += w
    return vis


@_jit
def _ground_ao(aomap, st, x, y):
    gx = (x - st[_S_AOX0]) / st[_S_AORES] - 0.5
    gy = (y - st[_S_AOY0]) / st[_S_AORES] - 0.5
    ny, nx = aomap.shape
    if gx < 0 or gy < 0 or gx >= nx - 1 or gy >= ny - 1:
        return 1.0
    ix = int(gx)
    iy = int(gy)
    tx = gx - ix
    ty = gy - iy
    a = aomap[iy, ix] * (1 - tx) + aomap[iy, ix + 1] * tx
    b = aomap[iy + 1, ix] * (1 - tx) + aomap[iy + 1, ix + 1] * tx
    return a * (1 - ty) + b * ty


@_jit
def _alpha_keep(kind, prm, wx, wy, wz, face, x0, x1, y0, y1, z0, z1):
    """Cut-out test for round wheels and shaped sign panels (False = pixel is see-through)."""
    if kind == _K_WHEEL:
        along_x = prm[3] == 0
        if (face <= _F_PX) == along_x or face >= _F_TOP:
            return True
        p = (2.0 * (wx - x0) / (x1 - x0) - 1.0) if along_x else (2.0 * (wy - y0) / (y1 - y0) - 1.0)
        q = 2.0 * (wz - z0) / (z1 - z0) - 1.0
        return p * p + q * q <= 1.0
    p = (2.0 * (wx - x0) / (x1 - x0) - 1.0) if prm[4] == 0 else (2.0 * (wy - y0) / (y1 - y0) - 1.0)
    q = 2.0 * (wz - z0) / (z1 - z0) - 1.0
    shape = int(prm[3])
    if shape == 0 or shape == 4:
        return p * p + q * q <= 1.0
    if shape == 1:
        return abs(p) <= 0.5 * (q + 1.0)
    if shape == 2:
        return abs(p) + abs(q) <= 1.42
    return True


@_jit
def _row_range(va, vb, h):
    r0 = int(math.ceil(min(max(va, -1.0), h + 1.0)))
    r1 = int(math.floor(min(max(vb, -1.0), h + 1.0)))
    return max(r0, 0), min(r1, h - 1)


@_jit
def _begin_frame(cam, zbuf, kbuf, ibuf, fbuf):
    """Clear the G-buffer to sky above the horizon and the analytic ground plane below it."""
    hc, fy, cy = cam[2], cam[6], cam[8]
    h, w = zbuf.shape
    for v in range(h):
        z = hc * fy / (v - cy) if v > cy else _FAR
        k = _K_GROUND if v > cy else _K_SKY
        for u in range(w):
            zbuf[v, u] = z
            kbuf[v, u] = k
            ibuf[v, u] = -1
            fbuf[v, u] = _F_TOP


@_jit
def _raster_prisms(cam, boxes, kinds, params, zbuf, kbuf, ibuf, fbuf):
    """Z-buffer vertical prisms column by column.

    With zero pitch and roll a column's rays share one ground-plane line; a slab test gives the
    entry depth z_in (side face, constant over the column) and exit depth, then rows follow
    analytically: side face where the ray height at z_in is inside [z0, z1], top face (z1 below
    the camera) or bottom face (z0 above it) between z_in and z_out.
    """
    px, py, hc, cs, sn, fx, fy, cx, cy, maxd = (cam[0], cam[1], cam[2], cam[3], cam[4], cam[5],
                                                cam[6], cam[7], cam[8], cam[9])
    h, w = zbuf.shape
    for i in range(boxes.shape[0]):
        x0, x1, y0, y1, z0, z1 = (boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3], boxes[i, 4],
                                  boxes[i, 5])
        ddx = max(x0 - px, px - x1, 0.0)
        ddy = max(y0 - py, py - y1, 0.0)
        if ddx * ddx + ddy * ddy > maxd * maxd:
            continue
        k = kinds[i]
        if k == _K_POLE or k == _K_TRUNK:
            # Keep thin verticals at least ~1 px wide so they do not flicker in and out.
            mx = 0.5 * (x0 + x1)
            my = 0.5 * (y0 + y1)
            zc = (mx - px) * cs + (my - py) * sn
            if zc > _NEAR:
                wmin = 0.6 * zc / fx
                if x1 - x0 < 2.0 * wmin:
                    x0, x1 = mx - wmin, mx + wmin
                if y1 - y0 < 2.0 * wmin:
                    y0, y1 = my - wmin, my + wmin
        umin = 1e9
        umax = -1e9
        behind = 0
        for c in range(4):
            qx = (x0 if c & 1 == 0 else x1) - px
            qy = (y0 if c < 2 else y1) - py
            zc = qx * cs + qy * sn
            if zc <= _NEAR:
                behind += 1
            else:
                uu = cx + fx * (qx * sn - qy * cs) / zc
                umin = min(umin, uu)
                umax = max(umax, uu)
        if behind == 4:
            continue
        if behind > 0:
            iu0, iu1 = 0, w - 1
        else:
            iu0, iu1 = _row_range(umin, umax, w)
        masked = k == _K_SIGN or k == _K_WHEEL
        for u in range(iu0, iu1 + 1):
            a = (u - cx) / fx
            dx = cs + a * sn
            dy = sn - a * cs
            if abs(dx) < 1e-12:
                if px < x0 or px > x1:
                    continue
                tx0, tx1, fcx = -_FAR, _FAR, _F_NX
            elif dx > 0:
                tx0, tx1, fcx = (x0 - px) / dx, (x1 - px) / dx, _F_NX
            else:
                tx0, tx1, fcx = (x1 - px) / dx, (x0 - px) / dx, _F_PX
            if abs(dy) < 1e-12:
                if py < y0 or py > y1:
                    continue
                ty0, ty1, fcy = -_FAR, _FAR, _F_NY
            elif dy > 0:
                ty0, ty1, fcy = (y0 - py) / dy, (y1 - py) / dy, _F_NY
            else:
                ty0, ty1, fcy = (y1 - py) / dy, (y0 - py) / dy, _F_PY
            if tx0 > ty0:
                zin, face = tx0, fcx
            else:
                zin, face = ty0, fcy
            zout = min(tx1, ty1)
            if zout <= _NEAR or zout <= zin:
                continue
            ze = max(zin, _NEAR)
            if zin >= _NEAR:
                r0, r1 = _row_range(cy + fy * (hc - z1) / zin, cy + fy * (hc - z0) / zin, h)
                for v in range(r0, r1 + 1):
                    if zin < zbuf[v, u]:
                        if masked and not _alpha_keep(k, params[i], px + zin * dx, py + zin * dy,
                                                      hc - (v - cy) / fy * zin, face, x0, x1, y0,
                                                      y1, z0, z1):
                            continue
                        zbuf[v, u] = zin
                        kbuf[v, u] = k
                        ibuf[v, u] = i
                        fbuf[v, u] = face
            if z1 < hc:
                r0, r1 = _row_range(cy + fy * (hc - z1) / zout, cy + fy * (hc - z1) / ze, h)
                for v in range(r0, r1 + 1):
                    if v - cy < 1e-6:
                        continue
                    zz = fy * (hc - z1) / (v - cy)
                    if zz < zbuf[v, u]:
                        if masked and not _alpha_keep(k, params[i], px + zz * dx, py + zz * dy, z1,
                                                      _F_TOP, x0, x1, y0, y1, z0, z1):
                            continue
                        zbuf[v, u] = zz
                        kbuf[v, u] = k
                        ibuf[v, u] = i
                        fbuf[v, u] = _F_TOP
            if z0 > hc:
                r0, r1 = _row_range(cy - fy * (z0 - hc) / ze, cy - fy * (z0 - hc) / zout, h)
                for v in range(r0, r1 + 1):
                    if cy - v < 1e-6:
                        continue
                    zz = fy * (z0 - hc) / (cy - v)
                    if zz < zbuf[v, u]:
                        if masked and not _alpha_keep(k, params[i], px + zz * dx, py + zz * dy, z0,
                                                      _F_BOT, x0, x1, y0, y1, z0, z1):
                            continue
                        zbuf[v, u] = zz
                        kbuf[v, u] = k
                        ibuf[v, u] = i
                        fbuf[v, u] = _F_BOT


@_jit
def _raster_ellipsoids(cam, sph, skind, tex, zbuf, kbuf, ibuf, fbuf):
    """Z-buffer ellipsoids (tree canopies, hills) per pixel inside their screen bounding box.

    Canopy rims get a noisy cut-out so the crowns look leafy instead of perfectly round.
    """
    px, py, hc, cs, sn, fx, fy, cx, cy = (cam[0], cam[1], cam[2], cam[3], cam[4], cam[5], cam[6],
                                          cam[7], cam[8])
    h, w = zbuf.shape
    for i in range(sph.shape[0]):
        sx, sy, sz, r, rz = sph[i, 0], sph[i, 1], sph[i, 2], sph[i, 3], sph[i, 4]
        qx = sx - px
        qy = sy - py
        zc = qx * cs + qy * sn
        xc = qx * sn - qy * cs
        if zc < -r:
            continue
        if skind[i] == _K_CANOPY and qx * qx + qy * qy > 700.0 * 700.0:
            continue
        # Columns: the tangent rays to the crown's horizontal circle bound the view angles.
        d = math.sqrt(xc * xc + zc * zc)
        if d <= r:
            iu0, iu1 = 0, w - 1
        else:
            th = math.atan2(xc, zc)
            dt = math.asin(r / d)
            lim = 0.5 * math.pi - 1e-3
            if th - dt >= lim or th + dt <= -lim:
                continue
            iu0, iu1 = _row_range(cx + fx * math.tan(max(th - dt, -lim)),
                                  cx + fx * math.tan(min(th + dt, lim)), w)
        # Rows: the vertical extent seen from the nearest / farthest depth of the crown.
        lo, hi = sz - rz - hc, sz + rz - hc
        z_near, z_far = max(zc - r, _NEAR), zc + r
        iv0, iv1 = _row_range(cy - fy * hi / (z_near if hi > 0 else z_far),
                              cy - fy * lo / (z_far if lo > 0 else z_near), h)
        s = r / rz
        ox = px - sx
        oy = py - sy
        oz = (hc - sz) * s
        cc = ox * ox + oy * oy + oz * oz - r * r
        # Leafy cut-out of the crown's rim, unless it is only a few pixels wide.
        ragged = skind[i] == _K_CANOPY and fx * r > 4.0 * max(zc, _NEAR)
        zmin = zc - r  # no point of the ellipsoid is nearer (in z-depth) than this
        for v in range(iv0, iv1 + 1):
            dz = -(v - cy) / fy * s
            for u in range(iu0, iu1 + 1):
                if zmin >= zbuf[v, u]:
                    continue
                a = (u - cx) / fx
                dx = cs + a * sn
                dy = sn - a * cs
                aa = dx * dx + dy * dy + dz * dz
                bb = ox * dx + oy * dy + oz * dz
                disc = bb * bb - aa * cc
                if disc <= 0.0:
                    continue
                z = (-bb - math.sqrt(disc)) / aa
                if z < _NEAR or z >= zbuf[v, u]:
                    continue
                if ragged:
                    rim = math.sqrt(max(cc + r * r - bb * bb / aa, 0.0)) / r
                    if rim > 0.76:
                        # Noise over the crown's longitude / latitude (metres along its surface).
                        lon = math.atan2(oy + z * dy, ox + z * dx) * r + 13.0 * i
                        lat = math.asin(max(min((oz + z * dz) / r, 1.0), -1.0)) * rz
                        if _tex(tex, 2, lon / 5.0, lat / 5.0, z / (fx * 5.0)) < (rim - 0.76) * 3.2:
                            continue
                zbuf[v, u] = z
                kbuf[v, u] = skind[i]
                ibuf[v, u] = i
                fbuf[v, u] = _F_SPH


@_jit
def _face_normal(face):
    if face == _F_NX:
        return -1.0, 0.0, 0.0
    if face == _F_PX:
        return 1.0, 0.0, 0.0
    if face == _F_NY:
        return 0.0, -1.0, 0.0
    if face == _F_PY:
        return 0.0, 1.0, 0.0
    if face == _F_TOP:
        return 0.0, 0.0, 1.0
    return 0.0, 0.0, -1.0


@_jit
def _nearest(arr, x):
    best = 0
    bd = 1e30
    for i in range(arr.shape[0]):
        d = abs(x - arr[i])
        if d < bd:
            bd = d
            best = i
    return best, x - arr[best]


@_jit
def _road_markings(lat, along, dnode, fp_lat, fp_along, hw, xwalk, approach, st):
    """Paint coverage (edge/crosswalk paint, centre-line paint) on a road away from junctions.

    lat: signed offset from the road centre line; along: coordinate along the road; dnode:
    distance past the junction edge (>= 0); approach: True if this half of the road carries the
    traffic driving toward that junction (it gets the stop line).
    """
    paint = 0.0
    centre = 0.0
    alat = abs(lat)
    if xwalk and 0.6 < dnode < 3.6 and alat < hw - 0.35:
        paint = _pulse(lat / 1.0 + 0.25, 0.0, 0.5, fp_lat) * _band(dnode - 2.1, 1.5, fp_along)
    if approach and alat < hw - 0.3:
        paint = max(paint, _band(dnode - 4.2, 0.22, fp_along) * _band(alat - 0.5 * hw, 0.5 * hw - 0.3,
                                                                          fp_lat))
    if dnode > 4.6:
        paint = max(paint, _band(alat - (hw - 0.3), 0.075, fp_lat))
        if st[_S_DOUBLE] > 0.5:
            centre = _band(alat - 0.12, 0.06, fp_lat)
        else:
            dash = _pulse(along / st[_S_DASHP], 0.0, st[_S_DASH] / st[_S_DASHP], fp_along / st[_S_DASHP])
            centre = _band(lat, 0.07, fp_lat) * (dash if dnode > 16.0 else 1.0)
    return paint, centre


@_jit
def _set3(out, r, g, b, f):
    out[0] = r * f
    out[1] = g * f
    out[2] = b * f


@_jit
def _blend3(out, r, g, b, t):
    out[0] += (r - out[0]) * t
    out[1] += (g - out[1]) * t
    out[2] += (b - out[2]) * t


@_jit
def _ground_footprint(z, dx, dy, cs, sn, fx, fy, height):
    """World-space x/y extent of a pixel on the horizontal plane `height` below the camera.

    d(point)/du = z / fx * right and d(point)/dv = dz/dv * (horizontal ray), dz/dv = z^2 / (h fy).
    Returns (fpx, fpy, fiso): per-axis footprints and one for isotropic mip selection.
    """
    dzdv = z * z / (height * fy)
    fpx = abs(z / fx * sn) + abs(dzdv * dx)
    fpy = abs(z / fx * cs) + abs(dzdv * dy)
    fmax = max(fpx, fpy)
    return fpx, fpy, 0.5 * math.sqrt(fmax * min(fpx, fpy)) + 0.5 * fmax


@_jit
def _ground_material(alb, wx, wy, fpx, fpy, fiso, grain, patch, tex, road_x, road_y, xwalk, st):
    """Road (asphalt, markings, kerb occlusion) or open terrain on the z = 0 plane -> (label, ao)."""
    hw = st[_S_HW]
    ix, ddx = _nearest(road_x, wx)
    iy, ddy = _nearest(road_y, wy)
    on_xr = abs(ddy) < hw and road_x[0] - st[_S_EXT] <= wx <= road_x[-1] + st[_S_EXT]
    on_yr = abs(ddx) < hw and road_y[0] - st[_S_EXT] <= wy <= road_y[-1] + st[_S_EXT]
    if not (on_xr or on_yr):
        f = 0.62 + 0.76 * grain
        _set3(alb, st[_S_TERR], st[_S_TERR + 1], st[_S_TERR + 2], f)
        _blend3(alb, st[_S_TERR2] * f, st[_S_TERR2 + 1] * f, st[_S_TERR2 + 2] * f, _smooth(0.35, 0.7, patch))
        return _TERRAIN, 1.0
    wear = _tex(tex, 1, wx / 7.0, wy / 7.0, fiso / 7.0)
    # Cracks: thin iso-lines of band-passed noise, only up close and in worn patches.
    crack = 0.0
    if fiso < 0.08:
        crack = 1.0 - abs(_tex(tex, 2, wx / 9.0, wy / 9.0, fiso / 9.0) - 0.5) / 0.04
        crack = max(crack, 0.0) * (1.0 - fiso / 0.08) * _smooth(0.45, 0.6, patch)
    f = (0.55 + 0.9 * grain) * (0.7 + 0.6 * patch) * (0.8 + 0.4 * wear) * (1.0 - 0.5 * crack)
    paint, centre, tyre, ao = 0.0, 0.0, 0.0, 1.0
    if on_xr != on_yr:  # a road between junctions (lat: offset from the centre line)
        if on_xr:
            lat, along, to_node, fp_lat, fp_along = ddy, wx, ddx, fpy, fpx
            inside = road_x[0] - hw <= wx <= road_x[-1] + hw
        else:
            lat, along, to_node, fp_lat, fp_along = ddx, wy, ddy, fpx, fpy
            inside = road_y[0] - hw <= wy <= road_y[-1] + hw
        # Right-hand traffic: the half with lat * to_node > 0 (x roads) drives toward the junction.
        approach = ddx * ddy > 0 if on_xr else ddx * ddy < 0
        dnode = abs(to_node) - hw if inside else 100.0
        paint, centre = _road_markings(lat, along, dnode, fp_lat, fp_along, hw,
                                       inside and xwalk[ix, iy] > 0, approach, st)
        ao = 1.0 - 0.3 * math.exp(-(hw - abs(lat)) / 0.3)  # kerb occlusion
        tyre = _band(abs(abs(lat) - 0.5 * hw) - 0.75, 0.3, fp_lat)  # darker wheel tracks
    _set3(alb, st[_S_ASPH], st[_S_ASPH + 1], st[_S_ASPH + 2], f * (1.0 - 0.18 * tyre * patch))
    worn = 0.6 + 0.4 * wear
    _blend3(alb, st[_S_PAINT], st[_S_PAINT + 1], st[_S_PAINT + 2], paint * worn)
    _blend3(alb, st[_S_CLINE], st[_S_CLINE + 1], st[_S_CLINE + 2], centre * worn)
    return _ROAD, ao


@_jit
def _block_top_material(alb, box, paved, seed, wx, wy, fiso, grain, patch, st):
    """Top of a block slab: sidewalk tiles with a kerb stone band, then lawn or paved yard."""
    e = min(wx - box[0], box[1] - wx, wy - box[2], box[3] - wy)  # distance to the kerb edge
    sw = st[_S_SW]
    if e >= sw and not paved:
        f = 0.6 + 0.8 * grain
        _set3(alb, st[_S_GRASS], st[_S_GRASS + 1], st[_S_GRASS + 2], f)
        _blend3(alb, st[_S_GRASS2] * f, st[_S_GRASS2 + 1] * f, st[_S_GRASS2 + 2] * f, _smooth(0.3, 0.75, patch))
        return _TERRAIN
    ts = st[_S_TILE]
    tu, tv, ff = wx / ts, wy / ts, fiso / ts
    joint = 1.0 - _pulse(tu, 0.05, 0.95, ff) * _pulse(tv, 0.05, 0.95, ff)
    var = (_hash(int(math.floor(tu)), int(math.floor(tv)), seed) - 0.5) * 0.3 * max(0.0, 1.0 - ff)
    f = (0.8 + 0.4 * grain) * (0.85 + 0.3 * patch) * (1.0 + var) * (1.0 - 0.3 * joint)
    if e >= sw:
        f *= 0.9
    _set3(alb, st[_S_SIDEW], st[_S_SIDEW + 1], st[_S_SIDEW + 2], f)
    _blend3(alb, st[_S_KERBC] * f, st[_S_KERBC + 1] * f, st[_S_KERBC + 2] * f, _band(e, 0.3, fiso))
    return _SIDEWALK


@_jit
def _car_ground_effects(shadow_boxes, wx, wy, wz, lx, ly, lz):
    """Contact occlusion under nearby cars and whether a car body blocks the sun -> (ao, sun)."""
    ao = 1.0
    for j in range(shadow_boxes.shape[0]):
        sb = shadow_boxes[j]
        if wx < sb[6] or wx > sb[7] or wy < sb[8] or wy > sb[9]:
            continue
        ex = max(sb[0] - wx, wx - sb[1], 0.0)
        ey = max(sb[2] - wy, wy - sb[3], 0.0)
        dd = math.sqrt(ex * ex + ey * ey)
        if dd < 1.5:
            ao *= 1.0 - 0.55 * math.exp(-dd / 0.35)
        if sb[4] < 0.3:
            continue  # axles only darken, the body casts the sun shadow
        t0 = (sb[4] - wz) / lz
        t1 = (sb[5] - wz) / lz
        if abs(lx) > 1e-9:
            t0 = max(t0, min((sb[0] - wx) / lx, (sb[1] - wx) / lx))
            t1 = min(t1, max((sb[0] - wx) / lx, (sb[1] - wx) / lx))
        elif ex > 0:
            continue
        if abs(ly) > 1e-9:
            t0 = max(t0, min((sb[2] - wy) / ly, (sb[3] - wy) / ly))
            t1 = min(t1, max((sb[2] - wy) / ly, (sb[3] - wy) / ly))
        elif ey > 0:
            continue
        if t1 > t0:
            return ao, 0.0
    return ao, 1.0


@_jit
def _facade_material(alb, prm, box, face, wx, wy, wz, cosi, fp, tex, st):
    """Building wall: tinted dirty render, window grid with frames, shop fronts, cornice.

    prm: rgb, base z, floor height, window spacing, window width * 100 + height (fractions),
    hash seed. Returns (window coverage, per-window random) for the glass reflection.
    """
    if face <= _F_PX:
        s, flen = wy - box[2], box[3] - box[2]
    else:
        s, flen = wx - box[0], box[1] - box[0]
    fph = fp / max(cosi, 0.12)  # footprint along the wall, stretched at grazing angles
    hb = wz - prm[3]
    fh = prm[4]
    sp = flen / max(1.0, math.floor(flen / prm[5] + 0.5))  # whole number of window columns
    cu, cv = s / sp, hb / fh
    seed = int(prm[7])
    ww = math.floor(prm[6]) / 100.0
    wh = prm[6] - math.floor(prm[6])
    dirt = _tex(tex, 3, s / 9.0, hb / 14.0, fph / 9.0)
    f = (0.7 + 0.6 * dirt) * (0.85 + 0.3 * _tex(tex, 0, s / 3.0, hb / 3.0, fph / 3.0))
    rnd = _hash(int(math.floor(cu)), int(math.floor(cv)), seed)
    ground_type = seed % 3
    if hb < fh and ground_type == 0:  # shop front: large dark windows in frames
        win = _pulse(cu, 0.08, 0.92, fph / sp) * _band(hb - 1.6, 1.15, fp)
        frame = _pulse(cu, 0.05, 0.95, fph / sp) * _band(hb - 1.6, 1.3, fp) - win
        f *= 0.55
    elif hb < fh and ground_type == 1:  # plain darker plinth storey
        win, frame = 0.0, 0.0
        f *= 0.7
    elif box[5] - wz < 0.6:  # parapet above the top windows
        win, frame = 0.0, 0.0
    else:
        x0w = 0.5 - 0.5 * ww
        fw, fv = 0.06 / sp, 0.06 / fh
        win = _pulse(cu, x0w, 1.0 - x0w, fph / sp) * _pulse(cv, 0.28, 0.28 + wh, fp / fh)
        frame = (_pulse(cu, x0w - fw, 1.0 - x0w + fw, fph / sp)
                 * _pulse(cv, 0.28 - fv, 0.28 + wh + fv, fp / fh) - win)
    cornice = _band(box[5] - wz - 0.3, 0.3, fp)
    ledge = _pulse(cv, 0.0, 0.05, fp / fh) if hb > fh else 0.0
    _set3(alb, prm[0], prm[1], prm[2], f * (1.0 - 0.25 * cornice) * (1.0 + 0.12 * ledge))
    fb = 0.8 if seed % 2 == 0 else 0.12  # white or dark window frames
    _blend3(alb, fb, fb, fb * 0.95, max(frame, 0.0))
    fade = max(0.0, 1.0 - fph / sp)  # per-window variation fades out where windows blur together
    inter = 0.25 + 0.9 * rnd * fade  # interior brightness
    _blend3(alb, st[_S_GLASS] * inter, st[_S_GLASS + 1] * inter, st[_S_GLASS + 2] * inter, win)
    # Some windows have light blinds pulled down over their upper part.
    drop = _hash(int(math.floor(cu)), int(math.floor(cv)), seed + 1)
    if drop < 0.35 and hb >= fh:
        cover = 0.2 + 1.4 * drop
        top = (cv - math.floor(cv) - 0.28) / wh  # 0 at the sill, 1 at the lintel
        blind = win * _band(top - 1.0 + 0.5 * cover, 0.5 * cover, fp / (fh * wh)) * fade
        _blend3(alb, 0.45, 0.4, 0.32, blind)
        win -= blind
    return win, rnd


@_jit
def _ellipsoid_normal(e, wx, wy, wz):
    s = e[3] / e[4]
    nx, ny, nz = wx - e[0], wy - e[1], (wz - e[2]) * s * s
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    return nx / nn, ny / nn, nz / nn


@_jit
def _shade(cam, zbuf, kbuf, ibuf, fbuf, boxes, bparams, dboxes, dparams, sph, sparams, shadow_boxes,
           tex, sky, smap, aomap, road_x, road_y, xwalk, st, rgb, depth, labels):
    """Deferred shading: material, lighting, fog and tone mapping for every pixel."""
    px, py, hc, cs, sn, fx, fy, cx, cy = (cam[0], cam[1], cam[2], cam[3], cam[4], cam[5], cam[6],
                                          cam[7], cam[8])
    yaw = math.atan2(sn, cs)
    h, w = zbuf.shape
    lx, ly, lz = st[_S_SUN], st[_S_SUN + 1], st[_S_SUN + 2]
    fog_col = np.empty((w, 3))
    for u in range(w):
        fog_col[u, 0], fog_col[u, 1], fog_col[u, 2] = _sky_rgb(sky, st, yaw - math.atan((u - cx) / fx), 0.004)
    # Tone curve (exposure, soft shoulder, gamma 2) as a lookup table over linear radiance.
    tone = np.empty(_TONE_N, np.uint8)
    for j in range(_TONE_N):
        tone[j] = int(255.0 * math.sqrt(1.0 - math.exp(-st[_S_EXPO] * (j + 0.5) / _TONE_SCALE)) + 0.5)
    # Mild lens vignetting (separable): -12% in the corners.
    vignette = np.empty(w)
    for u in range(w):
        vignette[u] = 1.0 - 0.06 * ((u - cx) / cx) ** 2
    alb = np.empty(3)
    for v in range(h):
        b = -(v - cy) / fy
        vignette_v = 1.0 - 0.06 * ((v - cy) / cy) ** 2
        for u in range(w):
            z = zbuf[v, u]
            k = kbuf[v, u]
            a = (u - cx) / fx
            dx = cs + a * sn  # ray direction per unit z-depth: forward + a * right + b * up
            dy = sn - a * cs
            if k == _K_SKY:
                sr, sg, sb = _sky_rgb(sky, st, yaw - math.atan(a), math.atan(b / math.sqrt(1.0 + a * a)))
                vig = vignette[u] * vignette_v * _TONE_SCALE
                rgb[v, u, 0] = tone[min(int(sr * vig), _TONE_N - 1)]
                rgb[v, u, 1] = tone[min(int(sg * vig), _TONE_N - 1)]
                rgb[v, u, 2] = tone[min(int(sb * vig), _TONE_N - 1)]
                depth[v, u] = _FAR
                labels[v, u] = _SKY
                continue
            i = ibuf[v, u]
            face = fbuf[v, u]
            dnorm = math.sqrt(dx * dx + dy * dy + b * b)
            wx, wy, wz = px + z * dx, py + z * dy, hc + z * b
            ray = z * dnorm
            fp = ray / fx  # pixel footprint (m) on a surface facing the camera
            nx, ny, nz = _face_normal(face)
            ao = 1.0
            refl = 0.0  # weight of the mirror reflection of the sky (glass, paint)
            emit = 0.0
            wrap = 0.0  # wrap lighting for translucent foliage
            sun = 1.0  # 0 where a car shadows the ground
            if k == _K_GROUND or (k == _K_BLOCK and face == _F_TOP):
                fpx, fpy, fiso = _ground_footprint(z, dx, dy, cs, sn, fx, fy, hc - (wz if k == _K_BLOCK else 0.0))
                grain = _tex(tex, 0, wx / 3.0, wy / 3.0, fiso / 3.0)
                patch = _tex(tex, 1, wx / 37.0, wy / 37.0, fiso / 37.0)
                if k == _K_GROUND:
                    lab, ao = _ground_material(alb, wx, wy, fpx, fpy, fiso, grain, patch, tex, road_x, road_y,
                                               xwalk, st)
                else:
                    lab = _block_top_material(alb, boxes[i], bparams[i, 3] > 0.5, i, wx, wy, fiso, grain, patch, st)
                car_ao, sun = _car_ground_effects(shadow_boxes, wx, wy, wz, lx, ly, lz)
                ao *= _ground_ao(aomap, st, wx, wy) * car_ao
            elif k == _K_BLOCK:  # kerb face
                lab = _SIDEWALK
                _set3(alb, st[_S_KERBC], st[_S_KERBC + 1], st[_S_KERBC + 2],
                      0.75 + 0.5 * _tex(tex, 0, (wx + wy) / 2.0, wz / 2.0, fp / 2.0))
                ao = 0.75
            elif k == _K_BUILDING:
                lab = _BUILDING
                if face >= _F_TOP:
                    _set3(alb, st[_S_ROOF], st[_S_ROOF + 1], st[_S_ROOF + 2],
                          0.7 + 0.6 * _tex(tex, 0, wx / 4.0, wy / 4.0, fp / 4.0))
                else:
                    cosi = abs(nx * dx + ny * dy) / dnorm
                    win, rnd = _facade_material(alb, bparams[i], boxes[i], face, wx, wy, wz, cosi, fp, tex, st)
                    refl = win * (0.1 + 0.75 * (1.0 - cosi) ** 3) * (0.6 + 0.4 * rnd)  # Fresnel-ish
                    ao = 1.0 - 0.45 * math.exp(-(wz - st[_S_KERB]) / 0.9)
            elif k == _K_HEDGE or k == _K_CANOPY:
                lab = _VEG
                if k == _K_CANOPY:
                    nx, ny, nz = _ellipsoid_normal(sph[i], wx, wy, wz)
                    tint = sparams[i]
                    # Leaves mapped over the crown's longitude/latitude (metres along the surface).
                    lu = (math.atan2(ny, nx) * sph[i, 3] + 17.0 * i) / 2.5
                    lv = math.asin(max(min(nz, 1.0), -1.0)) * sph[i, 4] / 2.5
                    ao = 0.45 + 0.35 * (0.5 + 0.5 * nz)
                else:
                    tint = bparams[i]
                    lu, lv = (wx + wy) / 2.5, wz / 2.5
                    ao = 0.8
                leaf = _tex(tex, 2, lu, lv, fp / 2.5)
                clump = _tex(tex, 1, lu * 0.3, lv * 0.3, fp / 8.0)
                _set3(alb, tint[0], tint[1], tint[2], (0.45 + 1.1 * leaf) * (0.75 + 0.5 * clump))
                ao *= 0.7 + 0.3 * leaf
                wrap = 0.5
            elif k == _K_TRUNK:
                lab = _VEG
                _set3(alb, bparams[i, 0], bparams[i, 1], bparams[i, 2],
                      0.55 + 0.9 * _tex(tex, 3, (wx + wy) / 1.5, wz / 6.0, fp / 1.5))
                ao = 1.0 - 0.4 * math.exp(-wz / 0.6)
            elif k == _K_POLE or k == _K_LAMP:
                lab = _POLE
                _set3(alb, bparams[i, 0], bparams[i, 1], bparams[i, 2],
                      0.85 + 0.3 * _tex(tex, 0, (wx + wy) / 2.0, wz / 2.0, fp / 2.0))
                emit = 0.5 if k == _K_LAMP and face == _F_BOT else 0.0
                refl = 0.1
            elif k == _K_SIGN:
                lab = _SIGN
                prm, bx = bparams[i], boxes[i]
                if prm[4] == 0:
                    p = 2.0 * (wx - bx[0]) / (bx[1] - bx[0]) - 1.0
                    front = face == (_F_PY if prm[5] > 0 else _F_NY)
                else:
                    p = 2.0 * (wy - bx[2]) / (bx[3] - bx[2]) - 1.0
                    front = face == (_F_PX if prm[5] > 0 else _F_NX)
                q = 2.0 * (wz - bx[4]) / (bx[5] - bx[4]) - 1.0
                _sign_face(alb, int(prm[3]), p, q, front, fp / (0.5 * (bx[5] - bx[4])))
                refl = 0.05
            elif k == _K_HILL:
                lab = _TERRAIN
                nx, ny, nz = _ellipsoid_normal(sph[i], wx, wy, wz)
                _set3(alb, sparams[i, 0], sparams[i, 1], sparams[i, 2],
                      0.7 + 0.6 * _tex(tex, 1, wx / 60.0, wy / 60.0, fp / 60.0))
            else:
                lab = _CAR
                _car_material(alb, k, dparams[i], dboxes[i], face, wx, wy, wz, fp)
                cosi = abs(nx * dx + ny * dy + nz * b) / dnorm
                if k == _K_WHEEL:
                    refl = 0.0
                elif k == _K_CAR_CABIN and face < _F_TOP and alb[0] + alb[1] + alb[2] < 0.3:
                    refl = 0.25 + 0.6 * (1.0 - cosi) ** 2  # glass
                else:
                    refl = 0.04 + 0.5 * (1.0 - cosi) ** 4  # clear coat
                emit = 1.0 if alb[0] > 1.5 else 0.0  # lamps
                ao = 1.0 - 0.35 * math.exp(-wz / 0.4)
            # ---- lighting: sun (Lambert, shadowed), hemispheric ambient, sky reflection, fog
            ndl = (nx * lx + ny * ly + nz * lz + wrap) / (1.0 + wrap)
            direct = 0.0
            if ndl > 0.0 and sun > 0.0:
                direct = ndl * _sun_visibility(smap, st, wx + 0.25 * nx, wy + 0.25 * ny, wz + 0.25 * nz)
            hemi = 0.5 + 0.5 * nz
            for c in range(3):
                amb = (st[_S_GAMB + c] + (st[_S_AMB + c] - st[_S_GAMB + c]) * hemi) * ao
                alb[c] *= amb + st[_S_SUNC + c] * direct + emit
            if refl > 0.0:
                # Mirror direction of the view ray; below the horizon it sees the (dark) street.
                ddn = (dx * nx + dy * ny + b * nz) * 2.0
                rx, ry, rz = dx - ddn * nx, dy - ddn * ny, b - ddn * nz
                rel = math.atan2(rz, math.sqrt(rx * rx + ry * ry))
                rr, rg, rb = _sky_rgb(sky, st, math.atan2(ry, rx), max(rel, 0.0))
                street = (1.0 - 0.8 * _smooth(0.2, 0.0, rel)) * refl
                alb[0] = alb[0] * (1.0 - refl) + rr * street
                alb[1] = alb[1] * (1.0 - refl) + rg * street
                alb[2] = alb[2] * (1.0 - refl) + rb * street
            fog = 1.0 - math.exp(-ray / st[_S_FOG])
            vig = vignette[u] * vignette_v
            for c in range(3):
                col = (alb[c] + (fog_col[u, c] - alb[c]) * fog) * vig
                rgb[v, u, c] = tone[min(int(max(col, 0.0) * _TONE_SCALE), _TONE_N - 1)]
            depth[v, u] = z
            labels[v, u] = lab


@_jit
def _sign_face(alb, shape, p, q, front, fpn):
    """Albedo of a sign panel; (p, q) in [-1, 1] across the panel; the back is bare metal."""
    if not front:
        alb[0] = alb[1] = alb[2] = 0.35
        return
    r = math.sqrt(p * p + q * q)
    red = (0.55, 0.03, 0.03)
    white = (0.8, 0.8, 0.78)
    blue = (0.03, 0.12, 0.45)
    if shape == 0:  # speed limit: red ring, white disk, two dark digits
        ring = _band(r - 0.86, 0.14, fpn)
        digits = _band(abs(p) - 0.22, 0.1, fpn) * _band(q, 0.36, fpn)
        t = ring
        c0 = white[0] + (red[0] - white[0]) * t
        c1 = white[1] + (red[1] - white[1]) * t
        c2 = white[2] + (red[2] - white[2]) * t
        d = 1.0 - 0.9 * digits
        alb[0], alb[1], alb[2] = c0 * d, c1 * d, c2 * d
    elif shape == 1:  # yield: red border, white inside
        inner = 1.0 if abs(p) <= 0.5 * (q + 1.0) - 0.18 and q < 0.78 else 0.0
        alb[0] = red[0] + (white[0] - red[0]) * inner
        alb[1] = red[1] + (white[1] - red[1]) * inner
        alb[2] = red[2] + (white[2] - red[2]) * inner
    elif shape == 2:  # stop: red with a white text band
        t = _band(q, 0.16, fpn) * _band(p, 0.62, fpn) * 0.8
        alb[0] = red[0] + (white[0] - red[0]) * t
        alb[1] = red[1] + (white[1] - red[1]) * t
        alb[2] = red[2] + (white[2] - red[2]) * t
    else:  # blue info (square) / mandatory (round) sign with a white symbol
        t = _band(p + (0.2 if shape == 3 else 0.0), 0.11, fpn) * _band(q, 0.6, fpn)
        if shape == 3:
            t = max(t, _band(q - 0.3, 0.3, fpn) * _band(abs(p - 0.1) - 0.0, 0.3, fpn)
                    * (1.0 - _band(q - 0.3, 0.12, fpn) * _band(p - 0.05, 0.15, fpn)))
        else:
            t = max(t, _band(q - 0.35, 0.25, fpn) * _band(abs(p), 0.4 - (q - 0.1), fpn))
        alb[0] = blue[0] + (white[0] - blue[0]) * t
        alb[1] = blue[1] + (white[1] - blue[1]) * t
        alb[2] = blue[2] + (white[2] - blue[2]) * t


@_jit
def _car_material(alb, k, prm, box, face, wx, wy, wz, fp):
    """Albedo of car parts: painted body with lights and wheel arches, glazed cabin, tyres."""
    along_x = prm[3] == 0
    heading = prm[4]
    if along_x:
        al, lo, hi = wx, box[0], box[1]
        lat, llo, lhi = wy, box[2], box[3]
        front = (face == _F_PX) if heading > 0 else (face == _F_NX)
        back = (face == _F_NX) if heading > 0 else (face == _F_PX)
        side = face == _F_NY or face == _F_PY
    else:
        al, lo, hi = wy, box[2], box[3]
        lat, llo, lhi = wx, box[0], box[1]
        front = (face == _F_PY) if heading > 0 else (face == _F_NY)
        back = (face == _F_NY) if heading > 0 else (face == _F_PY)
        side = face == _F_NX or face == _F_PX
    p = 2.0 * (al - lo) / (hi - lo) - 1.0  # along the car, -1 .. 1
    pl = 2.0 * (lat - llo) / (lhi - llo) - 1.0  # across the car
    q = 2.0 * (wz - box[4]) / (box[5] - box[4]) - 1.0
    alb[0], alb[1], alb[2] = prm[0], prm[1], prm[2]
    fpn = fp / (0.5 * (box[5] - box[4]))
    if k == _K_WHEEL:
        t = 0.02
        if side:
            r = math.sqrt(p * p + q * q)
            t = 0.02 + 0.4 * _band(r, 0.55, fpn)
        alb[0] = alb[1] = alb[2] = t
        return
    if k == _K_CAR_CABIN:
        if face < _F_TOP:
            pillar = _band(abs(pl if (front or back) else p) - 0.94, 0.08, fpn)
            if side:
                pillar = max(pillar, _band(p + 0.1, 0.05, fpn))
            g = 0.03
            alb[0] = g + (alb[0] - g) * pillar
            alb[1] = g + (alb[1] - g) * pillar
            alb[2] = g + (alb[2] - g) * pillar
        return
    if face >= _F_TOP:
        return
    trim = 0.25 + 0.75 * (1.0 - _band(q + 0.85, 0.15, fpn))
    alb[0] *= trim
    alb[1] *= trim
    alb[2] *= trim
    if side:
        half_len = 0.5 * (hi - lo)
        for ax in (-0.64, 0.64):  # upper part of the wheels and the arches, continuing the axles

            dl = (p - ax) * half_len
            dz = wz - 0.34
            r = math.sqrt(dl * dl + dz * dz)
            if r < 0.44:
                t = 0.03 if r < 0.34 else 0.06
                if r < 0.19:
                    t = 0.42
                alb[0] = alb[1] = alb[2] = t
    elif front:
        light = _band(abs(pl) - 0.72, 0.14, fpn) * _band(q - 0.35, 0.2, fpn)
        grille = _band(pl, 0.4, fpn) * _band(q - 0.0, 0.25, fpn)
        g = 1.0 - 0.8 * grille
        alb[0] = (alb[0] * g) * (1.0 - light) + 2.0 * light
        alb[1] = (alb[1] * g) * (1.0 - light) + 2.0 * light
        alb[2] = (alb[2] * g) * (1.0 - light) + 1.8 * light
    elif back:
        light = _band(abs(pl) - 0.72, 0.16, fpn) * _band(q - 0.3, 0.2, fpn)
        plate = _band(pl, 0.22, fpn) * _band(q + 0.25, 0.16, fpn)
        alb[0] = alb[0] * (1.0 - light) + 0.7 * light
        alb[1] = alb[1] * (1.0 - light) + 0.02 * light
        alb[2] = alb[2] * (1.0 - light) + 0.02 * light
        alb[0] = alb[0] * (1.0 - plate) + 0.8 * plate
        alb[1] = alb[1] * (1.0 - plate) + 0.8 * plate
        alb[2] = alb[2] * (1.0 - plate) + 0.75 * plate


@_jit
def _build_shadow_map(boxes, sph, skind, smap, x0, y0, res, kx, ky):
    """For every ground cell q, the height of the highest occluder on the sun ray through q."""
    ny, nx = smap.shape
    for i in range(boxes.shape[0]):
        bx0, bx1, by0, by1, bz0, bz1 = (boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3],
                                        boxes[i, 4], boxes[i, 5])
        qx0 = min(bx0 - bz0 * kx, bx0 - bz1 * kx)
        qx1 = max(bx1 - bz0 * kx, bx1 - bz1 * kx)
        qy0 = min(by0 - bz0 * ky, by0 - bz1 * ky)
        qy1 = max(by1 - bz0 * ky, by1 - bz1 * ky)
        ix0 = max(int((qx0 - x0) / res), 0)
        ix1 = min(int((qx1 - x0) / res) + 1, nx - 1)
        iy0 = max(int((qy0 - y0) / res), 0)
        iy1 = min(int((qy1 - y0) / res) + 1, ny - 1)
        for iy in range(iy0, iy1 + 1):
            qy = y0 + (iy + 0.5) * res
            for ix in range(ix0, ix1 + 1):
                qx = x0 + (ix + 0.5) * res
                lo = bz0
                hi = bz1
                if abs(kx) > 1e-9:
                    ta, tb = (bx0 - qx) / kx, (bx1 - qx) / kx
                    lo = max(lo, min(ta, tb))
                    hi = min(hi, max(ta, tb))
                elif qx < bx0 or qx > bx1:
                    continue
                if abs(ky) > 1e-9:
                    ta, tb = (by0 - qy) / ky, (by1 - qy) / ky
                    lo = max(lo, min(ta, tb))
                    hi = min(hi, max(ta, tb))
                elif qy < by0 or qy > by1:
                    continue
                if hi >= lo and hi > smap[iy, ix]:
                    smap[iy, ix] = hi
    for i in range(sph.shape[0]):
        if skind[i] != _K_CANOPY:
            continue
        sx, sy, sz, r, rz = sph[i, 0], sph[i, 1], sph[i, 2], sph[i, 3], sph[i, 4]
        ext = r + (sz + rz) * max(abs(kx), abs(ky))
        ix0 = max(int((sx - sz * kx - ext - x0) / res), 0)
        ix1 = min(int((sx - sz * kx + ext - x0) / res) + 1, nx - 1)
        iy0 = max(int((sy - sz * ky - ext - y0) / res), 0)
        iy1 = min(int((sy - sz * ky + ext - y0) / res) + 1, ny - 1)
        s = r / rz
        for iy in range(iy0, iy1 + 1):
            qy = y0 + (iy + 0.5) * res
            for ix in range(ix0, ix1 + 1):
                qx = x0 + (ix + 0.5) * res
                # Line (qx + t kx, qy + t ky, t) against the ellipsoid; keep the upper root.
                ox, oy, oz = qx - sx, qy - sy, -sz * s
                aa = kx * kx + ky * ky + s * s
                bb = ox * kx + oy * ky + oz * s
                cc = ox * ox + oy * oy + oz * oz - r * r
                disc = bb * bb - aa * cc
                if disc > 0.0:
                    hi = (-bb + math.sqrt(disc)) / aa
                    if hi > smap[iy, ix]:
                        smap[iy, ix] = hi


# ----------------------------------------------------------------------------- textures & sky


def _lin(rgb) -> np.ndarray:
    """sRGB-ish [0, 1] -> linear."""
    return np.asarray(rgb, np.float64) ** 2.2


def _noise_textures(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Four tileable noise channels with full mip pyramids: float32 [4, levels, size, size].

    0: fine grain, 1: large patches, 2: leafy blobs, 3: vertical streaks (dirt on walls, bark).
    Periodic by construction (filtered white noise in the Fourier domain), in [0, 1].
    """
    f = np.fft.fftfreq(size) * size
    fx, fy = np.meshgrid(f, f)

    def spectral(amp):
        spec = np.fft.fft2(rng.standard_normal((size, size))) * amp
        n = np.real(np.fft.ifft2(spec))
        return (n - n.mean()) / (n.std() + 1e-9)

    r = np.hypot(fx, fy)
    r[0, 0] = 1.0
    grain = spectral(np.where((r >= 2) & (r <= size / 2), r ** -0.6, 0.0))
    patches = spectral(np.where(r <= 40, r ** -1.6, 0.0))
    leaves = spectral(np.where((r >= 10) & (r <= 42), 1.0, 0.0))
    leaves = 0.5 * spectral(np.where((r >= 3) & (r <= 10), 1.0, 0.0)) + leaves
    rs = np.hypot(fx, fy * 8.0)
    rs[0, 0] = 1.0
    streaks = spectral(np.where(rs <= 80, rs ** -1.2, 0.0))
    chans = [0.5 + 0.17 * grain, 0.5 + 0.2 * patches, 0.5 + 0.5 * np.tanh(1.3 * leaves),
             0.5 + 0.18 * streaks]
    levels = int(math.log2(size)) + 1
    tex = np.zeros((4, levels, size, size), np.float32)
    for c, img in enumerate(chans):
        img = np.clip(img, 0.0, 1.0)
        for lev in range(levels):
            n = size >> lev
            tex[c, lev, :n, :n] = img
            if n > 1:
                img = img.reshape(n // 2, 2, n // 2, 2).mean(axis=(1, 3))
    return tex


def _sky_panorama(style: TownStyle, sun: np.ndarray, tex: np.ndarray, rng: np.random.Generator,
                  el0: float, el1: float, width: int = 1024, height: int = 160) -> np.ndarray:
    """Sky colour over (elevation, absolute azimuth): gradient, sun glow and clouds, linear RGB."""
    el = np.linspace(el0, el1, height)[:, None]
    az = (np.arange(width) + 0.5) / width * 2 * np.pi
    az = az[None, :]
    t = np.clip(el / (np.pi / 2), 0, 1) ** 0.45
    zen, hor = _lin(style.sky_zenith_rgb), _lin(style.sky_horizon_rgb)
    col = hor * (1 - t[..., None]) + zen * t[..., None]
    d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), -1)
    cosang = d @ sun
    sunc = _lin(style.sun_rgb)
    glow = 0.35 * np.exp((cosang - 1) * 12) + 0.8 * np.exp((cosang - 1) * 400)
    # Clouds: noise on a flat layer above the camera, faded toward the horizon.
    elc = np.maximum(el, 0.03)
    cot = np.cos(elc) / np.sin(elc)
    size = tex.shape[2]
    scale = 0.12
    off = rng.uniform(0, 1, 2)
    mu = ((np.cos(az) * cot * scale + off[0]) * size).astype(np.float32)
    mv = ((np.sin(az) * cot * scale + off[1]) * size).astype(np.float32)
    base = (0.6 * tex[1, 0] + 0.4 * tex[0, 0]).astype(np.float32)
    base = (base - base.mean()) / base.std()
    n = cv2.remap(base, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    thr = 1.2 - 2.2 * style.cloud_cover
    cover = np.clip((n - thr) / 0.9, 0, 1) * np.clip((el - 0.02) / 0.18, 0, 1)
    lit = np.clip(0.75 + 0.25 * (n - thr), 0.6, 1.2)
    cloud = (0.55 + 0.45 * hor.mean()) * lit[..., None] * np.array([1.0, 1.0, 1.02]) * 1.1
    col = col * (1 - cover[..., None]) + cloud * cover[..., None]
    col = col + sunc * glow[..., None] * (1 - 0.7 * cover[..., None])
    return col.astype(np.float32)


# ----------------------------------------------------------------------------- town


def _rng(*keys: int) -> np.random.Generator:
    return np.random.default_rng([int(k) & 0xFFFFFFFF for k in keys])


@dataclass
class _Builder:
    """Accumulates static prisms and ellipsoids while a town is laid out."""

    boxes: list = dataclasses.field(default_factory=list)
    kinds: list = dataclasses.field(default_factory=list)
    params: list = dataclasses.field(default_factory=list)
    sph: list = dataclasses.field(default_factory=list)
    skinds: list = dataclasses.field(default_factory=list)
    sparams: list = dataclasses.field(default_factory=list)

    def box(self, x0, x1, y0, y1, z0, z1, kind, rgb=(0, 0, 0), *extra):
        self.boxes.append((x0, x1, y0, y1, z0, z1))
        self.kinds.append(kind)
        p = [*rgb, *extra]
        self.params.append(p + [0.0] * (8 - len(p)))

    def ellipsoid(self, x, y, z, r, rz, kind, rgb):
        self.sph.append((x, y, z, r, rz))
        self.skinds.append(kind)
        self.sparams.append([*rgb, 0.0])


class Town:
    """A generated town: static geometry, textures, sky, shadow/AO maps and traffic.

    Build with `Town.generate(style, seed)`; everything is a pure function of (style, seed).
    Layout attributes: ``road_x`` (x of the roads running along y), ``road_y`` (y of the roads
    running along x), ``half_width`` (road half width = lane width, m), ``crosswalks`` [i, j]
    per junction (road_x[i], road_y[j]). Traffic: one entry per car in the ``car_*`` arrays
    (axis 0 = driving along x, road index, direction +-1, lane centre, speed, ...).
    """

    def __init__(self, style_name: str, seed: int):
        self.style_name = style_name
        self.style = TOWN_STYLES[style_name]
        self.seed = int(seed)
        self._salt = zlib.crc32(style_name.encode())

    @classmethod
    def generate(cls, style: str = "default", seed: int = 0) -> "Town":
        if style not in TOWN_STYLES:
            raise ValueError(f"unknown town style {style!r}; expected one of {sorted(TOWN_STYLES)}")
        town = cls(style, seed)
        town._layout()
        town._traffic()
        town._precompute()
        return town

    # ---- layout

    def _layout(self) -> None:
        st = self.style
        rng = _rng(self.seed, self._salt, 1)
        self.half_width = st.lane_width_m  # two lanes: the road half width is one lane
        hw = self.half_width
        roads = []
        for _ in range(2):
            n = int(rng.integers(st.blocks_per_axis[0], st.blocks_per_axis[1] + 1))
            pos = np.concatenate([[0.0], np.cumsum(rng.uniform(*st.block_size_m, n))])
            roads.append(pos - pos[-1] / 2)
        self.road_x, self.road_y = roads
        nx, ny = len(self.road_x), len(self.road_y)
        self.crosswalks = (rng.random((nx, ny)) < st.crosswalk_prob).astype(np.uint8)
        b = _Builder()
        kerb = st.kerb_height_m
        for i in range(nx - 1):
            for j in range(ny - 1):
                rect = (self.road_x[i] + hw, self.road_x[i + 1] - hw, self.road_y[j] + hw,
                        self.road_y[j + 1] - hw)
                park = rng.random() < st.park_fraction
                paved = (not park) and rng.random() < st.paved_yard_fraction
                b.box(*rect, 0.0, kerb, _K_BLOCK, (0, 0, 0), float(paved))
                inner = (rect[0] + st.sidewalk_m, rect[1] - st.sidewalk_m,
                         rect[2] + st.sidewalk_m, rect[3] - st.sidewalk_m)
                if park:
                    self._park(b, rng, inner)
                else:
                    self._buildings(b, rng, inner)
                self._street_furniture(b, rng, rect)
        self._signs(b, rng)
        self._countryside(b, rng)
        self.boxes = np.asarray(b.boxes, np.float32)
        self.kinds = np.asarray(b.kinds, np.int32)
        self.params = np.asarray(b.params, np.float32)
        self.sph = np.asarray(b.sph, np.float32).reshape(-1, 5)
        self.skinds = np.asarray(b.skinds, np.int32)
        self.sparams = np.asarray(b.sparams, np.float32).reshape(-1, 4)

    def _tree(self, b: _Builder, rng, x, y, z0, scale=1.0) -> None:
        st = self.style
        tint = _lin(st.tree_palette[rng.integers(len(st.tree_palette))]) * rng.uniform(0.8, 1.15)
        bark = _lin(st.bark_rgb)
        if rng.random() < st.palm_fraction:
            th = rng.uniform(5.5, 9.0) * scale
            b.box(x - 0.14, x + 0.14, y - 0.14, y + 0.14, z0, z0 + th, _K_TRUNK, bark)
            r = rng.uniform(1.8, 2.6) * scale
            b.ellipsoid(x, y, z0 + th, r, 0.45 * r, _K_CANOPY, tint)
            return
        clear = rng.uniform(2.6, 3.6) * scale  # crown bottom above the ground
        r = rng.uniform(1.7, 3.0) * scale
        rz = r * rng.uniform(0.85, 1.15)
        tw = rng.uniform(0.13, 0.2) * scale
        b.box(x - tw, x + tw, y - tw, y + tw, z0, z0 + clear + rz, _K_TRUNK, bark)
        b.ellipsoid(x, y, z0 + clear + rz, r, rz, _K_CANOPY, tint)
        for _ in range(int(rng.integers(1, 3))):  # side blobs make the crown irregular
            a = rng.uniform(0, 2 * np.pi)
            rr = r * rng.uniform(0.55, 0.8)
            b.ellipsoid(x + 0.5 * r * np.cos(a), y + 0.5 * r * np.sin(a),
                        z0 + clear + rz + rng.uniform(-0.1, 0.5) * r, rr, rr * rng.uniform(0.8, 1.1),
                        _K_CANOPY, tint * rng.uniform(0.9, 1.1))

    def _park(self, b: _Builder, rng, rect) -> None:
        st = self.style
        kerb = st.kerb_height_m
        x0, x1, y0, y1 = rect
        n = int((x1 - x0) * (y1 - y0) / 140)
        for _ in range(n):
            self._tree(b, rng, rng.uniform(x0 + 2, x1 - 2), rng.uniform(y0 + 2, y1 - 2), kerb,
                       rng.uniform(0.9, 1.3))
        if rng.random() < st.hedge_prob:
            hedge = _lin(st.tree_palette[0]) * 1.1
            hh = kerb + rng.uniform(0.8, 1.3)
            for (a0, a1, c, along_x) in ((x0, x1, y0, True), (x0, x1, y1, True),
                                         (y0, y1, x0, False), (y0, y1, x1, False)):
                mid = 0.5 * (a0 + a1) + rng.uniform(-5, 5)  # entrance gap
                for s0, s1 in ((a0 + 0.5, mid - 2.0), (mid + 2.0, a1 - 0.5)):
                    if s1 - s0 < 2:
                        continue
                    if along_x:
                        b.box(s0, s1, c - 0.4, c + 0.4, kerb, hh, _K_HEDGE, hedge)
                    else:
                        b.box(c - 0.4, c + 0.4, s0, s1, kerb, hh, _K_HEDGE, hedge)

    def _buildings(self, b: _Builder, rng, rect) -> None:
        """Split the block interior into lots; lots on the block edge get a building."""
        st = self.style
        kerb = st.kerb_height_m
        lots = []
        stack = [rect]
        while stack:
            r = stack.pop()
            wdt, dep = r[1] - r[0], r[3] - r[2]
            if max(wdt, dep) <= st.lot_size_m[1] or max(wdt, dep) < 2 * st.lot_size_m[0]:
                lots.append(r)
                continue
            f = rng.uniform(0.35, 0.65)
            if wdt >= dep:
                m = r[0] + f * wdt
                stack += [(r[0], m, r[2], r[3]), (m, r[1], r[2], r[3])]
            else:
                m = r[2] + f * dep
                stack += [(r[0], r[1], r[2], m), (r[0], r[1], m, r[3])]
        setback = rng.uniform(*st.setback_m, 4)  # one street wall per block side
        for r in lots:
            edge = [abs(r[0] - rect[0]) < 1e-6, abs(r[1] - rect[1]) < 1e-6,
                    abs(r[2] - rect[2]) < 1e-6, abs(r[3] - rect[3]) < 1e-6]
            if not any(edge):
                if rng.random() < 0.6:
                    self._tree(b, rng, 0.5 * (r[0] + r[1]), 0.5 * (r[2] + r[3]), kerb)
                continue
            gap = rng.uniform(0.0, 1.6)
            x0 = r[0] + (setback[0] if edge[0] else gap)
            x1 = r[1] - (setback[1] if edge[1] else gap)
            y0 = r[2] + (setback[2] if edge[2] else gap)
            y1 = r[3] - (setback[3] if edge[3] else gap)
            if x1 - x0 < 4 or y1 - y0 < 4:
                continue
            lo, hi = st.building_height_m
            height = lo + (hi - lo) * rng.random() ** st.height_skew
            glass = rng.random() < st.glass_tower_prob and height > 18
            if glass:
                rgb = _lin(rng.choice([(0.25, 0.32, 0.36), (0.42, 0.45, 0.47), (0.2, 0.24, 0.3)]))
                ww, wh, spacing = 0.9, 0.8, rng.uniform(1.4, 1.9)
            else:
                rgb = _lin(st.facade_palette[rng.integers(len(st.facade_palette))]) * rng.uniform(0.85, 1.1)
                ww = rng.uniform(*st.window_width)
                wh = rng.uniform(*st.window_height)
                spacing = rng.uniform(*st.window_spacing_m)
            fh = rng.uniform(*st.floor_height_m)
            height = max(height, fh + 1.0)
            seed = int(rng.integers(1, 1 << 20))
            # params: rgb, base z, floor height, window spacing, window w*100 + h, hash seed
            prm = (kerb, fh, spacing, math.floor(ww * 100) + min(wh, 0.99), seed)
            b.box(x0, x1, y0, y1, kerb, kerb + height, _K_BUILDING, rgb, *prm)
            if rng.random() < st.upper_tier_prob and x1 - x0 > 9 and y1 - y0 > 9:
                ins = rng.uniform(1.5, 3.0)
                extra = fh * int(rng.integers(1, 4))
                b.box(x0 + ins, x1 - ins, y0 + ins, y1 - ins, kerb + height, kerb + height + extra,
                      _K_BUILDING, rgb * 0.95, *prm)

    def _street_furniture(self, b: _Builder, rng, rect) -> None:
        """Street trees and lamps along the four sides of a block's sidewalk."""
        st = self.style
        kerb = st.kerb_height_m
        metal = _lin(st.metal_rgb)
        x0, x1, y0, y1 = rect
        for side in range(4):
            along_x = side < 2
            a0, a1 = (x0, x1) if along_x else (y0, y1)
            sgn = 1.0 if side % 2 == 0 else -1.0  # inward normal of this side
            c = (y0, y1, x0, x1)[side]
            if rng.random() < st.street_tree_prob:
                s = a0 + rng.uniform(5, 9)
                while s < a1 - 5:
                    off = c + sgn * 1.3
                    self._tree(b, rng, *((s, off) if along_x else (off, s)), kerb, rng.uniform(0.8, 1.05))
                    s += rng.uniform(8, 13)
            if rng.random() < 0.85:
                s = a0 + rng.uniform(8, 14)
                while s < a1 - 6:
                    off = c + sgn * 0.45
                    px, py = (s + 4.0, off) if along_x else (off, s + 4.0)
                    b.box(px - 0.09, px + 0.09, py - 0.09, py + 0.09, kerb, kerb + 7.0, _K_POLE, metal)
                    # Arm reaching 1.8 m over the road (outward = -sgn) with the lamp head at its end.
                    arm = sorted((off, off - sgn * 1.8))
                    head = sorted((off - sgn * 1.5, off - sgn * 2.1))
                    if along_x:
                        b.box(px - 0.05, px + 0.05, *arm, kerb + 6.8, kerb + 6.92, _K_POLE, metal)
                        b.box(px - 0.18, px + 0.18, *head, kerb + 6.62, kerb + 6.82, _K_LAMP, metal)
                    else:
                        b.box(*arm, py - 0.05, py + 0.05, kerb + 6.8, kerb + 6.92, _K_POLE, metal)
                        b.box(*head, py - 0.18, py + 0.18, kerb + 6.62, kerb + 6.82, _K_LAMP, metal)
                    s += rng.uniform(26, 36)

    def _signs(self, b: _Builder, rng) -> None:
        """Traffic signs on the right-hand corner of some intersection approaches."""
        hw, kerb = self.half_width, self.style.kerb_height_m
        metal = _lin(self.style.metal_rgb)
        for x in self.road_x:
            for y in self.road_y:
                for hx, hy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                    if rng.random() > 0.45:
                        continue
                    # Corner to the right of traffic arriving with heading (hx, hy).
                    rx, ry = hy, -hx
                    sx = x - hx * (hw + 1.2) + rx * (hw + 0.7)
                    sy = y - hy * (hw + 1.2) + ry * (hw + 0.7)
                    if not (self.road_x[0] < sx < self.road_x[-1] and self.road_y[0] < sy < self.road_y[-1]):
                        continue
                    shape = int(rng.integers(0, 5))
                    b.box(sx - 0.04, sx + 0.04, sy - 0.04, sy + 0.04, kerb, kerb + 2.7, _K_POLE, metal)
                    hs = 0.34 if shape != 1 else 0.4
                    z0, z1 = kerb + 2.0, kerb + 2.0 + 2 * hs
                    # Thin panel on the traffic side of the pole, facing the arriving drivers;
                    # params: shape, axis along the panel's width (0: x, 1: y), facing sign.
                    px, py = sx - 0.06 * hx, sy - 0.06 * hy
                    if hx != 0:
                        b.box(px - 0.02, px + 0.02, py - hs, py + hs, z0, z1, _K_SIGN, (0, 0, 0), shape, 1, -hx)
                    else:
                        b.box(px - hs, px + hs, py - 0.02, py + 0.02, z0, z1, _K_SIGN, (0, 0, 0), shape, 0, -hy)

    def _countryside(self, b: _Builder, rng) -> None:
        """A belt of trees around the town and distant low hills."""
        st = self.style
        x0, x1, y0, y1 = self.road_x[0], self.road_x[-1], self.road_y[0], self.road_y[-1]
        margin = 15.0
        placed = 0
        while placed < st.forest_trees:
            x = rng.uniform(x0 - 170, x1 + 170)
            y = rng.uniform(y0 - 170, y1 + 170)
            if x0 - margin < x < x1 + margin and y0 - margin < y < y1 + margin:
                continue
            if (np.min(np.abs(self.road_x - x)) < self.half_width + 4
                    or np.min(np.abs(self.road_y - y)) < self.half_width + 4):
                continue
            self._tree(b, rng, x, y, 0.0, rng.uniform(0.9, 1.5))
            placed += 1
        cxm, cym = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
        g = _lin(st.terrain_rgb[0]) * 0.8
        for k in range(16):
            a = 2 * np.pi * (k + rng.uniform(-0.3, 0.3)) / 16
            d = rng.uniform(650, 1000)
            r = rng.uniform(150, 320)
            rz = rng.uniform(0.12, 0.3) * r
            b.ellipsoid(cxm + d * np.cos(a), cym + d * np.sin(a), -0.35 * rz, r, rz, _K_HILL,
                        g * rng.uniform(0.8, 1.2))

    # ---- traffic

    def _traffic(self) -> None:
        """Cars on every lane of every road, constant per-lane speed, spaced randomly."""
        st = self.style
        rng = _rng(self.seed, self._salt, 2)
        hw, ext = self.half_width, st.road_extension_m
        rows = []
        for axis, (positions, along) in enumerate(((self.road_y, self.road_x), (self.road_x, self.road_y))):
            lo, hi = along[0] - ext, along[-1] + ext
            for road, c in enumerate(positions):
                for d in (1, -1):
                    # Lane centre: right of the heading (d along the axis).
                    lat = c - d * hw / 2 if axis == 0 else c + d * hw / 2
                    speed = rng.uniform(*st.car_speed_ms)
                    s = lo + rng.uniform(0, 30)
                    while s < hi - 10:
                        kind = rng.choice(3, p=[0.55, 0.3, 0.15])
                        length = (rng.uniform(4.2, 4.8), rng.uniform(3.7, 4.2), rng.uniform(4.8, 5.4))[kind]
                        col = _lin(st.car_palette[rng.integers(len(st.car_palette))])
                        rows.append((axis, road, d, lat, s, speed, length, kind, lo, hi - lo, *col))
                        s += length + rng.uniform(*st.car_spacing_m)
        a = np.asarray(rows, np.float64)
        self.car_axis = a[:, 0].astype(np.int64)
        self.car_road = a[:, 1].astype(np.int64)
        self.car_dir = a[:, 2]
        self.car_lat = a[:, 3]
        self.car_s0 = a[:, 4]
        self.car_speed = a[:, 5]
        self.car_length = a[:, 6]
        self.car_type = a[:, 7].astype(np.int64)
        self.car_lo = a[:, 8]
        self.car_span = a[:, 9]
        self.car_rgb = a[:, 10:13]
        self.car_width = np.where(self.car_type == 2, 1.95, 1.8)
        self.car_body_top = np.select([self.car_type == 2, self.car_type == 1], [1.25, 1.05], 1.0)
        self.car_height = self.car_body_top + np.where(self.car_type == 2, 0.75, 0.47)

    def car_along(self, t) -> np.ndarray:
        """Position of every car along its road axis at time(s) t: shape t.shape + (n_cars,)."""
        t = np.asarray(t, np.float64)[..., None]
        return self.car_lo + np.mod(self.car_s0 + self.car_dir * self.car_speed * t - self.car_lo,
                                    self.car_span)

    def car_boxes(self, t: float) -> np.ndarray:
        """Other cars at time t: float64 [N, 7] rows (x, y, yaw, length, width, height, speed).

        (x, y) is the footprint centre (m), yaw the heading (rad, axis-aligned), height the roof
        height above the road (m), speed along the heading (m/s).
        """
        along = self.car_along(t)
        x = np.where(self.car_axis == 0, along, self.car_lat)
        y = np.where(self.car_axis == 0, self.car_lat, along)
        yaw = np.where(self.car_axis == 0, np.where(self.car_dir > 0, 0.0, np.pi),
                       np.where(self.car_dir > 0, np.pi / 2, -np.pi / 2))
        return np.stack([x, y, yaw, self.car_length, self.car_width, self.car_height, self.car_speed], 1)

    def _car_prisms(self, t: float, px: float, py: float, max_dist: float, hidden=None):
        """Prisms (body, cabin, two axles) of the cars within max_dist of (px, py).

        Cars listed in `hidden` and cars whose footprint contains the camera (traffic ignores the
        ego) are left out. Returns boxes [4n, 6], kinds [4n], params [4n, 8] with params =
        (rgb, heading axis, heading sign, 0, 0, 0), and the shadow casters near the camera
        [m, 10]: box (6 values) + the ground rectangle it can darken (x0, x1, y0, y1).
        """
        along = self.car_along(t)
        x = np.where(self.car_axis == 0, along, self.car_lat)
        y = np.where(self.car_axis == 0, self.car_lat, along)
        half_l, half_w = 0.5 * self.car_length, 0.5 * self.car_width
        near = (np.hypot(x - px, y - py) < max_dist) & ~(
            (np.abs(np.where(self.car_axis == 0, x - px, y - py)) < half_l + 0.6)
            & (np.abs(np.where(self.car_axis == 0, y - py, x - px)) < half_w + 0.6))
        if hidden is not None:
            near[hidden] = False
        idx = np.nonzero(near)[0]
        n = len(idx)
        ax, d, L = self.car_axis[idx], self.car_dir[idx], self.car_length[idx]
        c_al, c_lat = along[idx], self.car_lat[idx]
        hw_ = half_w[idx]
        top = self.car_body_top[idx]
        cab_half = np.where(self.car_type[idx] == 2, 0.38, 0.25) * L
        cab_c = c_al - d * np.where(self.car_type[idx] == 2, 0.06, 0.08) * L
        parts = [  # along_lo, along_hi, lat half, z0, z1, kind
            (c_al - L / 2, c_al + L / 2, hw_, np.full(n, 0.42), top, _K_CAR_BODY),
            (cab_c - cab_half, cab_c + cab_half, hw_ - 0.12, top, self.car_height[idx], _K_CAR_CABIN),
            (c_al + 0.32 * L - 0.34, c_al + 0.32 * L + 0.34, hw_ - 0.04, np.zeros(n), np.full(n, 0.68),
             _K_WHEEL),
            (c_al - 0.32 * L - 0.34, c_al - 0.32 * L + 0.34, hw_ - 0.04, np.zeros(n), np.full(n, 0.68),
             _K_WHEEL),
        ]
        boxes = np.empty((4 * n, 6), np.float32)
        kinds = np.empty(4 * n, np.int32)
        params = np.zeros((4 * n, 8), np.float32)
        for p, (a0, a1, lh, z0, z1, kind) in enumerate(parts):
            sl = slice(p * n, (p + 1) * n)
            xs0 = np.where(ax == 0, a0, c_lat - lh)
            xs1 = np.where(ax == 0, a1, c_lat + lh)
            ys0 = np.where(ax == 0, c_lat - lh, a0)
            ys1 = np.where(ax == 0, c_lat + lh, a1)
            boxes[sl] = np.stack([xs0, xs1, ys0, ys1, z0, z1], 1)
            kinds[sl] = kind
            params[sl, :3] = self.car_rgb[idx]
            params[sl, 3] = ax
            params[sl, 4] = d
        near_body = np.hypot(x[idx] - px, y[idx] - py) < 45.0
        sb = np.concatenate([boxes[:n][near_body], boxes[2 * n:][np.tile(near_body, 2)]])
        # Ground region each box can darken: contact margin plus the sun shadow's reach.
        kx, ky = self.sun[0] / self.sun[2], self.sun[1] / self.sun[2]
        reach = np.stack([np.minimum(sb[:, 0] - 1.5, sb[:, 0] - sb[:, 5] * kx),
                          np.maximum(sb[:, 1] + 1.5, sb[:, 1] - sb[:, 5] * kx),
                          np.minimum(sb[:, 2] - 1.5, sb[:, 2] - sb[:, 5] * ky),
                          np.maximum(sb[:, 3] + 1.5, sb[:, 3] - sb[:, 5] * ky)], 1)
        return boxes, kinds, params, np.concatenate([sb, reach], 1).astype(np.float32)

    def lane_cars(self, axis: int, road: int, direction: int) -> np.ndarray:
        """Indices of the cars driving on one lane (road `road` along `axis`, heading sign)."""
        return np.nonzero((self.car_axis == axis) & (self.car_road == road) & (self.car_dir == direction))[0]

    # ---- precomputation for the renderer

    def _precompute(self) -> None:
        st = self.style
        rng = _rng(self.seed, self._salt, 3)
        self.tex = _noise_textures(rng)
        el, az = math.radians(st.sun_elevation_deg), math.radians(st.sun_azimuth_deg)
        self.sun = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        sky_el = (-0.05, math.pi / 2)
        self.sky = _sky_panorama(st, self.sun, self.tex, rng, *sky_el)
        # Sun-ray height map over the town and the tree belt.
        x0, x1 = self.road_x[0] - 90, self.road_x[-1] + 90
        y0, y1 = self.road_y[0] - 90, self.road_y[-1] + 90
        res = max(0.25, max(x1 - x0, y1 - y0) / 2400)
        kx, ky = self.sun[0] / self.sun[2], self.sun[1] / self.sun[2]
        self.shadow_map = np.full((int((y1 - y0) / res) + 1, int((x1 - x0) / res) + 1), -1.0, np.float32)
        _build_shadow_map(self.boxes, self.sph, self.skinds, self.shadow_map, x0, y0, res, kx, ky)
        # Ground ambient occlusion: blurred footprint occupancy of things standing on the ground.
        ao_res = 0.5
        occ = np.zeros((int((y1 - y0) / ao_res) + 1, int((x1 - x0) / ao_res) + 1), np.float32)
        for (bx0, bx1, by0, by1, _, _), k in zip(self.boxes, self.kinds):
            if k in (_K_BUILDING, _K_HEDGE, _K_TRUNK):
                occ[max(int((by0 - y0) / ao_res), 0):int(math.ceil((by1 - y0) / ao_res)),
                    max(int((bx0 - x0) / ao_res), 0):int(math.ceil((bx1 - x0) / ao_res))] = 1.0
        blur = cv2.GaussianBlur(occ, (0, 0), 2.2)
        self.ao_map = np.clip(1.0 - 0.9 * blur, 0.35, 1.0).astype(np.float32)
        sh = np.zeros(_S_N)
        for idx, rgb in ((_S_ASPH, st.asphalt_rgb), (_S_PAINT, st.paint_rgb), (_S_CLINE, st.centre_line_rgb),
                         (_S_SIDEW, st.sidewalk_rgb), (_S_KERBC, st.kerb_rgb), (_S_GRASS, st.grass_rgb[0]),
                         (_S_GRASS2, st.grass_rgb[1]), (_S_TERR, st.terrain_rgb[0]),
                         (_S_TERR2, st.terrain_rgb[1]), (_S_ROOF, st.roof_rgb), (_S_GLASS, st.glass_rgb)):
            sh[idx:idx + 3] = _lin(rgb)
        sh[_S_SUN:_S_SUN + 3] = self.sun
        sh[_S_SUNC:_S_SUNC + 3] = _lin(st.sun_rgb) * st.sun_intensity
        amb = np.asarray(st.ambient_rgb) * st.ambient_intensity
        sh[_S_AMB:_S_AMB + 3] = amb
        sh[_S_GAMB:_S_GAMB + 3] = 0.35 * amb.mean() * _lin(st.terrain_rgb[0]) / _lin(st.terrain_rgb[0]).mean()
        sh[_S_FOG], sh[_S_EXPO], sh[_S_HW], sh[_S_SW] = st.fog_distance_m, st.exposure, self.half_width, st.sidewalk_m
        sh[_S_EXT], sh[_S_KERB], sh[_S_TILE] = st.road_extension_m, st.kerb_height_m, st.tile_m
        sh[_S_DASH], sh[_S_DASHP], sh[_S_DOUBLE] = st.dash_m[0], st.dash_m[1], float(st.centre_line_double)
        sh[_S_SMX0], sh[_S_SMY0], sh[_S_SMRES], sh[_S_SMKX], sh[_S_SMKY] = x0, y0, res, kx, ky
        sh[_S_AOX0], sh[_S_AOY0], sh[_S_AORES] = x0, y0, ao_res
        sh[_S_SKYEL0], sh[_S_SKYEL1] = sky_el
        self.shading = sh


# ----------------------------------------------------------------------------- renderer


class Renderer:
    """Renders RGB, z-depth and Cityscapes labels of a town from an ego pose (see module doc)."""

    def __init__(self, town: Town, camera: Camera):
        self.town = town
        self.camera = camera
        h, w = camera.height, camera.width
        self._z = np.empty((h, w), np.float32)
        self._k = np.empty((h, w), np.int32)
        self._i = np.empty((h, w), np.int32)
        self._f = np.empty((h, w), np.int32)

    def render(self, x: float, y: float, yaw: float, t: float,
               hidden_cars: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frame at ego pose (x, y, yaw) and time t: rgb uint8 [H,W,3], depth float32 [H,W], labels uint8.

        hidden_cars: optional indices (rows of `Town.car_boxes`) of traffic cars not to draw.
        """
        town, c = self.town, self.camera
        cam = np.array([x, y, c.mount_height_m, math.cos(yaw), math.sin(yaw), c.fx, c.fy, c.cx, c.cy, 800.0])
        dboxes, dkinds, dparams, shadow = town._car_prisms(t, x, y, 400.0, hidden_cars)
        z, k, i, f = self._z, self._k, self._i, self._f
        _begin_frame(cam, z, k, i, f)
        _raster_prisms(cam, town.boxes, town.kinds, town.params, z, k, i, f)
        _raster_prisms(cam, dboxes, dkinds, dparams, z, k, i, f)
        _raster_ellipsoids(cam, town.sph, town.skinds, town.tex, z, k, i, f)
        rgb = np.empty((c.height, c.width, 3), np.uint8)
        depth = np.empty((c.height, c.width), np.float32)
        labels = np.empty((c.height, c.width), np.uint8)
        _shade(cam, z, k, i, f, town.boxes, town.params, dboxes, dparams, town.sph, town.sparams, shadow,
               town.tex, town.sky, town.shadow_map, town.ao_map, town.road_x, town.road_y, town.crosswalks,
               town.shading, rgb, depth, labels)
        depth[depth >= _FAR] = np.inf
        return rgb, depth, labels


# ----------------------------------------------------------------------------- ego


@dataclass
class EgoTrack:
    """Ego trajectory at the native rate `fps`; see the module docstring for the convention.

    Arrays of length T: t (s), x, y (m, world), yaw (rad, unwrapped), speed (m/s), yaw_rate (rad/s).
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    yaw_rate: np.ndarray
    fps: int = 10

    def total_abs_yaw(self) -> float:
        """Total absolute heading change (rad): sum |yaw_rate| / fps."""
        return float(np.sum(np.abs(self.yaw_rate)) / self.fps)


_A_ACCEL, _A_BRAKE, _A_PLAN = 2.5, 4.5, 2.5  # m/s^2: accelerate, strongest braking, planned braking
_EGO_HALF_LEN = 2.3
_ROUTE_DS = 0.2  # m between route polyline points
_V_TURN_LEFT, _V_TURN_RIGHT = 4.5, 3.2  # m/s on the turn arcs (radius 1.5 and 1 lane widths)


@dataclass
class _Route:
    """Dense lane-centre polyline of a planned route with its junction events."""

    xy: np.ndarray  # [n, 2] points every ~ds metres
    s: np.ndarray  # arc length at each point
    heading: np.ndarray  # unwrapped tangent heading
    curvature: np.ndarray  # signed (left positive)
    lane: np.ndarray  # [n, 3] (axis, road, direction) on straight lane pieces, -1 on turn arcs
    turns: list  # (s_arc_start, s_arc_end, v_turn)
    nodes: list  # per junction: s_stop, ij, lane, stop, wait, cruise (for the leg after it)


def _plan_route(town: Town, rng: np.random.Generator, length: float, ds: float = _ROUTE_DS) -> _Route:
    """Random lane-following route over the road grid: straight, left or right at each junction.

    Lanes are the right-hand lane centres (lane width = road half width ``hw``). Turns are quarter
    circles tangent to both lane centres: radius hw for right turns, 1.5 hw for left turns.
    """
    hw, st = town.half_width, town.style
    roads = (town.road_y, town.road_x)  # axis-0 roads run along x and sit at y = road_y[j]
    along = (town.road_x, town.road_y)  # junction coordinates along each axis

    def lane_point(axis, road, d, s):
        lat = roads[axis][road] + (-d if axis == 0 else d) * hw / 2
        return np.array([s, lat]) if axis == 0 else np.array([lat, s])

    axis = int(rng.integers(2))
    road = int(rng.integers(len(roads[axis])))
    d = int(rng.choice([-1, 1]))
    seg = int(rng.integers(len(along[axis]) - 1))
    s0 = rng.uniform(along[axis][seg] + hw + 8, along[axis][seg + 1] - hw - 8)
    nxt = seg + 1 if d > 0 else seg
    cur = lane_point(axis, road, d, s0)
    pts, heads, kaps, lanes, turns, nodes = [], [], [], [], [], []
    count = 0
    total = 0.0

    def add_line(p0, p1, ln):
        nonlocal count, total
        L = float(np.linalg.norm(p1 - p0))
        n = max(int(math.ceil(L / ds)), 1)
        pts.append(p0 + (p1 - p0) * (np.arange(n)[:, None] / n))
        heads.append(np.full(n, math.atan2(p1[1] - p0[1], p1[0] - p0[0])))
        kaps.append(np.zeros(n))
        lanes.append(np.tile(np.asarray(ln, np.float64), (n, 1)))
        count += n
        total += L

    while total < length:
        h = np.array([d, 0.0]) if axis == 0 else np.array([0.0, d])
        node_s = along[axis][nxt]
        ij = (nxt, road) if axis == 0 else (road, nxt)
        options, weights = [], []
        if 0 <= nxt + d < len(along[axis]):
            options.append(0)
            weights.append(st.straight_weight)
        for sign, share in ((1, 1.0 - st.right_share), (-1, st.right_share)):  # left, right
            new_d = int(round((np.array([-h[1], h[0]]) * sign)[1 - axis]))
            if 0 <= road + new_d < len(along[1 - axis]):
                options.append(sign)
                weights.append((1.0 - st.straight_weight) * share)
        choice = options[rng.choice(len(options), p=np.asarray(weights) / np.sum(weights))]
        nodes.append({"stop_xy": lane_point(axis, road, d, node_s - d * (hw + 6.3)), "ij": ij,
                      "lane": (axis, road, d), "stop": rng.random() < st.stop_prob,
                      "wait": rng.uniform(*st.stop_wait_s),
                      "cruise": rng.uniform(*st.cruise_ms), "first": count})
        if choice == 0:
            end = lane_point(axis, road, d, node_s + d * (hw + 1.0))
            add_line(cur, end, (axis, road, d))
            cur = end
            nxt += d
            continue
        sign = float(choice)
        left = np.array([-h[1], h[0]])
        new_h = left * sign
        radius = hw * (1.5 if sign > 0 else 1.0)
        # Where the incoming and outgoing lane centres cross; the arc is tangent to both.
        corner = lane_point(axis, road, d, node_s) + np.array([new_h[1], -new_h[0]]) * hw / 2
        start = corner - h * radius
        end = corner + new_h * radius
        centre = start + left * sign * radius
        add_line(cur, start, (axis, road, d))
        n = max(int(math.ceil(radius * np.pi / 2 / ds)), 1)
        a0 = math.atan2(start[1] - centre[1], start[0] - centre[0])
        ang = a0 + sign * (np.pi / 2) * np.arange(n) / n
        pts.append(centre + radius * np.stack([np.cos(ang), np.sin(ang)], 1))
        heads.append(ang + sign * np.pi / 2)
        kaps.append(np.full(n, sign / radius))
        lanes.append(np.full((n, 3), -1.0))
        turns.append((count, count + n, _V_TURN_LEFT if sign > 0 else _V_TURN_RIGHT))
        count += n
        total += radius * np.pi / 2
        new_axis = 1 - axis
        new_d = int(round(new_h[new_axis]))
        axis, road, d, nxt = new_axis, nxt, new_d, road + new_d
        cur = end
    add_line(cur, cur + (np.array([d, 0.0]) if axis == 0 else np.array([0.0, d])) * 50.0, (axis, road, d))
    xy = np.concatenate(pts)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    for nd in nodes:  # stop point: nearest route point after the previous junction
        i = nd.pop("first")
        win = xy[i:i + int(200 / ds)]
        nd["s_stop"] = float(s[i + int(np.argmin(np.linalg.norm(win - nd.pop("stop_xy"), axis=1)))])
    turns = [(float(s[a]), float(s[min(b, len(s) - 1)]), v) for a, b, v in turns]
    return _Route(xy, s, np.unwrap(np.concatenate(heads)), np.concatenate(kaps), np.concatenate(lanes),
                  turns, nodes)


def _junction_busy(town: Town, ij, own_lane, t0: float, t1: float) -> bool:
    """Whether any car other than those on the ego's own lane is inside junction ij during [t0, t1]."""
    i, j = ij
    hw = town.half_width
    sel = ((town.car_axis == 0) & (town.car_road == j)) | ((town.car_axis == 1) & (town.car_road == i))
    axis, road, d = own_lane
    sel &= ~((town.car_axis == axis) & (town.car_road == road) & (town.car_dir == d))
    idx = np.nonzero(sel)[0]
    if len(idx) == 0:
        return False
    times = np.arange(t0, t1, 0.25)
    al = town.car_along(times)[:, idx]
    centre = np.where(town.car_axis[idx] == 0, town.road_x[i], town.road_y[j])
    return bool(np.any(np.abs(al - centre) < hw + 1.5 + 0.5 * town.car_length[idx]))


def simulate_ego(town: Town, seed: int, duration_s: float, fps: int) -> EgoTrack:
    """Drive the ego through the town for duration_s seconds; deterministic per (town, seed).

    The ego follows the right lane of a random route, cruises at 6-12 m/s per leg, slows for turn
    arcs, follows slower cars in its lane, and stops at the stop line of some junctions (always
    when crossing traffic would be in the junction on arrival), waiting 1-3 s and then until the
    junction is clear (at most 6 s). Planned stops are skipped when a car behind would run into
    the waiting ego.
    Steering is a curvature feed-forward plus heading/lateral-error feedback; poses are the exact
    integration of the per-step controls (`integrate_odometry`).
    """
    dt = 1.0 / fps
    steps = int(round(duration_s * fps))
    rng = _rng(seed, town.seed, town._salt, 7)
    route = _plan_route(town, rng, town.style.cruise_ms[1] * duration_s + 120.0)
    lane_cache: dict = {}
    x0, y0 = route.xy[0]
    yaw0 = float(route.heading[0])
    x, y, yaw = float(x0), float(y0), yaw0
    cruise = rng.uniform(*town.style.cruise_ms)
    v = cruise * rng.uniform(0.5, 1.0)
    speed = np.zeros(steps)
    yaw_rate = np.zeros(steps)
    idx, node_i, waited = 0, 0, 0.0
    n_pts = len(route.s)
    for k in range(steps):
        t = k * dt
        # Project onto the route (local forward search).
        hi = min(idx + int((v * dt + 3.0) / _ROUTE_DS) + 10, n_pts)
        idx += int(np.argmin(np.hypot(route.xy[idx:hi, 0] - x, route.xy[idx:hi, 1] - y)))
        hp = route.heading[idx]
        ex, ey = x - route.xy[idx, 0], y - route.xy[idx, 1]
        s = route.s[idx] + math.cos(hp) * ex + math.sin(hp) * ey  # continuous arc length
        e_y = -math.sin(hp) * ex + math.cos(hp) * ey  # lateral offset, left positive
        v_t = cruise
        for s_a, s_b, v_turn in route.turns:
            if s_b > s and s_a < s + 80.0:
                v_t = min(v_t, v_turn if s >= s_a else math.sqrt(v_turn ** 2 + 2 * _A_PLAN * (s_a - s)))
        stopping = False
        if node_i < len(route.nodes):
            nd = route.nodes[node_i]
            d_stop = nd["s_stop"] - s
            if d_stop < -2.0 and not nd.get("active"):
                node_i += 1
                cruise = nd["cruise"]
            else:
                if "decided" not in nd and d_stop < v * v / (2 * _A_PLAN) + 12.0:
                    nd["decided"] = True
                    t_arr = t + max(d_stop, 0.0) / max(v, 2.0)
                    rear = _rear_traffic(town, lane_cache, nd["lane"], x, y, t, t_arr - t + nd["wait"] + 4.0)
                    nd["active"] = nd["stop"] and not rear
                if "decided" in nd and not nd.get("active") and not nd.get("released") and (
                        d_stop > v * v / (2 * _A_BRAKE) + 0.3):
                    # Give way: stop if crossing traffic will be in the junction when we get there.
                    t_arr = t + d_stop / max(v, 2.0)
                    nd["active"] = _junction_busy(town, nd["ij"], nd["lane"], t_arr - 0.3, t_arr + 2.0)
                if nd.get("active"):
                    gap = max(d_stop, 0.0)
                    v_t = min(v_t, math.sqrt(2 * _A_PLAN * gap), gap + 0.1)
                    stopping = True
                    if gap < 0.3 and v <= _A_BRAKE * dt:
                        v_t = 0.0
                        waited += dt
                        clear = not _junction_busy(town, nd["ij"], nd["lane"], t, t + 2.5)
                        if waited >= nd["wait"] and (clear or waited > 6.0):
                            nd["active"] = False
                            nd["released"] = True
                            waited = 0.0
        lane = route.lane[idx]
        if lane[0] >= 0:
            v_t = min(v_t, _follow_speed(town, lane_cache, lane, x, y, t))
        v_new = min(max(v + min(max(v_t - v, -_A_BRAKE * dt), _A_ACCEL * dt), 0.0), town.style.cruise_ms[1])
        if stopping and v_t == 0.0:
            v_new = 0.0
        # Steering: curvature feed-forward + critically damped heading / lateral feedback.
        e_psi = (yaw - hp + math.pi) % (2 * math.pi) - math.pi
        ahead = min(idx + int(0.5 * v_new * dt / _ROUTE_DS), n_pts - 1)  # curvature mid-step
        lc = max(4.0, 2.5 * v_new * dt)
        w = v_new * (route.curvature[ahead] - 2.0 * e_psi / lc - e_y / (lc * lc))
        w = min(max(w, -1.8), 1.8)
        speed[k], yaw_rate[k] = v_new, w
        xs, ys, yaws = integrate_odometry([v_new, 0.0], [w, 0.0], fps, x, y, yaw)
        x, y, yaw, v = float(xs[1]), float(ys[1]), float(yaws[1]), v_new
    xs, ys, yaws = integrate_odometry(speed, yaw_rate, fps, x0, y0, yaw0)
    return EgoTrack(np.arange(steps) / fps, xs, ys, yaws, speed, yaw_rate, fps)


def _lane_along(town: Town, cache: dict, lane, x: float, y: float, t: float):
    """Cars on a lane: signed distance ahead of the ego (m, bumper to bumper) and their speeds."""
    axis, road, d = (int(c) for c in lane)
    key = (axis, road, d)
    if key not in cache:
        cache[key] = town.lane_cars(axis, road, d)
    idx = cache[key]
    ego = x if axis == 0 else y
    gap = d * (town.car_along(t)[idx] - ego) - 0.5 * town.car_length[idx] - _EGO_HALF_LEN
    return gap, town.car_speed[idx]


def _follow_speed(town: Town, cache: dict, lane, x: float, y: float, t: float) -> float:
    """Speed limit that keeps a safe gap to the nearest car ahead in the ego's lane."""
    gap, vc = _lane_along(town, cache, lane, x, y, t)
    ahead = (gap > -1.0) & (gap < 60.0)
    if not np.any(ahead):
        return town.style.cruise_ms[1]
    g, v = gap[ahead], vc[ahead]
    lim = np.minimum(v + 0.5 * (g - 7.0), np.sqrt(v * v + 2 * 3.0 * np.maximum(g - 4.0, 0.0)))
    return float(max(np.min(lim), 0.0))


def _rear_traffic(town: Town, cache: dict, lane, x: float, y: float, t: float, horizon: float) -> bool:
    """Whether a car behind on the ego's lane would reach the ego within `horizon` seconds."""
    gap, vc = _lane_along(town, cache, lane, x, y, t)
    behind = -gap - 2 * _EGO_HALF_LEN  # positive: distance from their front to our rear
    return bool(np.any((behind > -1.0) & (behind < vc * horizon + 8.0)))


def _rear_ghosts(town: Town, track: EgoTrack) -> np.ndarray:
    """[T, n_cars] mask of traffic cars to hide because they drive through the ego from behind.

    Traffic ignores the ego, so a car catching up with a waiting ego would pass through it and
    pop up right in front of the camera. Such a car is hidden from the first frame of its
    approach from behind (already out of view) to the end of the episode.
    """
    along = town.car_along(track.t)
    dx = np.where(town.car_axis == 0, along, town.car_lat) - track.x[:, None]
    dy = np.where(town.car_axis == 0, town.car_lat, along) - track.y[:, None]
    c, s = np.cos(track.yaw)[:, None], np.sin(track.yaw)[:, None]
    fwd, side = dx * c + dy * s, dy * c - dx * s
    overlap = (np.abs(fwd) < 0.5 * town.car_length + _EGO_HALF_LEN + 0.3) & (np.abs(side) < 2.1)
    hidden = np.zeros_like(overlap)
    for car in np.nonzero(overlap.any(axis=0))[0]:
        k = int(np.argmax(overlap[:, car]))
        while k > 0 and fwd[k - 1, car] < 0 and np.abs(side[k - 1, car]) < 2.1:
            k -= 1
        hidden[k:, car] = True
    return hidden


def render_episode(town: Town, camera: Camera, track: EgoTrack) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Frames (rgb, depth, labels) of an ego track in order, rendered lazily one at a time."""
    renderer = Renderer(town, camera)
    hidden = _rear_ghosts(town, track)
    for k in range(len(track.t)):
        yield renderer.render(float(track.x[k]), float(track.y[k]), float(track.yaw[k]), float(track.t[k]),
                              np.nonzero(hidden[k])[0])
