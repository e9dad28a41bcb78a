"""Deferred shading kernel: material, lighting, fog and tone mapping of every G-buffer pixel.

`_shade` turns the G-buffer of `orbis2.sim.raster` into the RGB image, the metric z-depth and
the Cityscapes labels; per pixel it picks the material (`orbis2.sim.materials`), then lights it.

Lighting: a directional sun (Lambert, shadows from the precomputed "sun-ray height" map of the
static scene plus exact shadows of nearby cars on the ground), a hemispheric ambient term,
ambient occlusion near the ground and building walls, and exponential fog toward the horizon
colour. Textures are tileable noise with mip levels picked from the pixel footprint; lane
markings, windows and paving joints are box-filtered analytically.
"""

from __future__ import annotations

import math

import numpy as np

from orbis2.sim.kernels import (
    _BUILDING,
    _CAR,
    _F_BOT,
    _F_NX,
    _F_NY,
    _F_PX,
    _F_PY,
    _F_TOP,
    _FAR,
    _K_BLOCK,
    _K_BUILDING,
    _K_CANOPY,
    _K_CAR_CABIN,
    _K_GROUND,
    _K_HEDGE,
    _K_HILL,
    _K_LAMP,
    _K_POLE,
    _K_SIGN,
    _K_SKY,
    _K_TRUNK,
    _K_WHEEL,
    _POLE,
    _S_AMB,
    _S_EXPO,
    _S_FOG,
    _S_GAMB,
    _S_KERB,
    _S_KERBC,
    _S_ROOF,
    _S_SUN,
    _S_SUNC,
    _SIDEWALK,
    _SIGN,
    _SKY,
    _TERRAIN,
    _TONE_N,
    _TONE_SCALE,
    _VEG,
    _ground_ao,
    _jit,
    _set3,
    _sky_rgb,
    _smooth,
    _sun_visibility,
    _tex,
)
from orbis2.sim.materials import _block_top_material, _car_material, _facade_material, _ground_material, _sign_face


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
