"""What the numba render kernels share: JIT settings, codes and layouts, small sampling helpers.

Scene arrays shared by the kernels (built by `orbis2.sim.town.Town`):

* ``boxes``  float32 [N, 6]: x0, x1, y0, y1, z0, z1 of axis-aligned prisms
* ``kinds``  int32   [N]:    material kind (``_K_*``)
* ``params`` float32 [N, 8]: linear albedo rgb + kind-specific values (documented where built)
* ``sph``    float32 [M, 5]: centre x, y, z, horizontal radius, vertical radius of ellipsoids

G-buffer (filled by `orbis2.sim.raster`, read by `orbis2.sim.shade`): z-depth, kind, index into
the kind's table, face code (``_F_*``). ``Town.shading`` holds the per-town shading constants at
the ``_S_*`` indices. Labels are Cityscapes train ids (`CITYSCAPES_TRAIN_IDS`).

The helpers here: hashes, box-filtered pulses and bands, lookups of the tileable noise textures,
the sky panorama, the sun-ray height map and the ground ambient-occlusion map, and the colour
writes (`_set3`, `_blend3`) the materials and the shading share.
"""

from __future__ import annotations

import math

from numba import njit

CITYSCAPES_TRAIN_IDS: dict[str, int] = {
    "road": 0, "sidewalk": 1, "building": 2, "pole": 5, "traffic sign": 7,
    "vegetation": 8, "terrain": 9, "sky": 10, "car": 13,
}
_ROAD, _SIDEWALK, _BUILDING, _POLE, _SIGN, _VEG, _TERRAIN, _SKY, _CAR = (
    CITYSCAPES_TRAIN_IDS[k] for k in ("road", "sidewalk", "building", "pole", "traffic sign",
                                      "vegetation", "terrain", "sky", "car"))


_FM = {"nsz", "arcp", "contract", "afn", "reassoc"}  # fastmath without no-nan/no-inf


def _jit(fn):
    # error_model="numpy": float division by zero gives inf/nan instead of a checked exception. nogil: the
    # kernels touch no Python object, so a render can run in a thread beside torch (orbis2 play's true view).
    return njit(cache=True, fastmath=_FM, error_model="numpy", nogil=True)(fn)


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
 _S_SKYEL1) = range(45, 65)
_S_BEND = 65  # four corner-bend radii (m): corners (x lo, y lo), (x hi, y lo), (x lo, y hi), (x hi, y hi)
_S_N = _S_BEND + 4


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
def _set3(out, r, g, b, f):
    out[0] = r * f
    out[1] = g * f
    out[2] = b * f


@_jit
def _blend3(out, r, g, b, t):
    out[0] += (r - out[0]) * t
    out[1] += (g - out[1]) * t
    out[2] += (b - out[2]) * t
