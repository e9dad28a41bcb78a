"""Visibility kernels: the G-buffer of a frame, and the town's sun-ray height map.

The G-buffer (z-depth, material kind, object index, face) starts as the analytic ground plane
below the horizon and sky above (`_begin_frame`); vertical prisms are z-buffered column by column
(`_raster_prisms`: zero pitch and roll make every column one line on the ground plane, so a slab
test and two divisions per column decide the rows of side and top faces); ellipsoids are
intersected per pixel in their screen bounds (`_raster_ellipsoids`). `orbis2.sim.shade` then
shades each pixel once.

`_build_shadow_map` casts the static scene along the sun direction once per town: for every
ground cell, the height of the highest occluder on the sun ray through it.
"""

from __future__ import annotations

import math

from orbis2.sim.kernels import (
    _F_BOT,
    _F_NX,
    _F_NY,
    _F_PX,
    _F_PY,
    _F_SPH,
    _F_TOP,
    _FAR,
    _K_CANOPY,
    _K_GROUND,
    _K_POLE,
    _K_SIGN,
    _K_SKY,
    _K_TRUNK,
    _K_WHEEL,
    _NEAR,
    _jit,
    _tex,
)


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
