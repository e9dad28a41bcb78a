"""Material kernels: procedural albedo of the surfaces the shading pass meets.

Road asphalt with lane markings, stop lines, crosswalks and the corner bends, or open terrain
(`_ground_material`); block tops with sidewalk tiles, kerb stones, lawn or paved yard
(`_block_top_material`); building facades with floors, windows, frames, blinds and shop fronts
(`_facade_material`); traffic sign faces (`_sign_face`); car bodies, cabins and wheels
(`_car_material`). Each writes linear RGB into ``alb``; `orbis2.sim.shade` lights it.
"""

from __future__ import annotations

import math

from orbis2.sim.kernels import (
    _F_NX,
    _F_NY,
    _F_PX,
    _F_PY,
    _F_TOP,
    _K_CAR_CABIN,
    _K_WHEEL,
    _ROAD,
    _S_ASPH,
    _S_BEND,
    _S_CLINE,
    _S_DASH,
    _S_DASHP,
    _S_DOUBLE,
    _S_EXT,
    _S_GLASS,
    _S_GRASS,
    _S_GRASS2,
    _S_HW,
    _S_KERBC,
    _S_PAINT,
    _S_SIDEW,
    _S_SW,
    _S_TERR,
    _S_TERR2,
    _S_TILE,
    _SIDEWALK,
    _TERRAIN,
    _band,
    _blend3,
    _hash,
    _jit,
    _pulse,
    _set3,
    _smooth,
    _tex,
)


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
def _corner_bend(wx, wy, road_x, road_y, st):
    """(in a bend zone, lateral offset) of a ground point relative to the nearest corner bend.

    Corner c of the grid is a quarter circle of road-centre radius R = ``st[_S_BEND + c]`` whose
    centre lies R inside the corner on both axes. Its zone is the quarter plane beyond that centre
    toward the corner: there the bend replaces the corner junction and the roads' extensions.
    The offset is R minus the distance to the centre (positive toward the outside of the bend).
    """
    hi_x = wx > 0.5 * (road_x[0] + road_x[-1])
    hi_y = wy > 0.5 * (road_y[0] + road_y[-1])
    r = st[_S_BEND + int(hi_x) + 2 * int(hi_y)]
    sx = -1.0 if hi_x else 1.0  # from the corner into the town
    sy = -1.0 if hi_y else 1.0
    dx = wx - (road_x[-1] if hi_x else road_x[0]) - sx * r
    dy = wy - (road_y[-1] if hi_y else road_y[0]) - sy * r
    if dx * sx >= 0.0 or dy * sy >= 0.0:
        return False, 0.0
    return True, r - math.hypot(dx, dy)


@_jit
def _ground_material(alb, wx, wy, fpx, fpy, fiso, grain, patch, tex, road_x, road_y, xwalk, st):
    """Road (asphalt, markings, kerb occlusion) or open terrain on the z = 0 plane -> (label, ao)."""
    hw = st[_S_HW]
    in_bend, bend_lat = _corner_bend(wx, wy, road_x, road_y, st)
    ix, ddx = _nearest(road_x, wx)
    iy, ddy = _nearest(road_y, wy)
    on_bend = in_bend and abs(bend_lat) < hw
    on_xr = not in_bend and abs(ddy) < hw and road_x[0] - st[_S_EXT] <= wx <= road_x[-1] + st[_S_EXT]
    on_yr = not in_bend and abs(ddx) < hw and road_y[0] - st[_S_EXT] <= wy <= road_y[-1] + st[_S_EXT]
    if not (on_xr or on_yr or on_bend):
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
    elif on_bend:  # edge lines and a solid (or double) centre line: no overtaking in a bend
        fp = max(fpx, fpy)
        alat = abs(bend_lat)
        paint = _band(alat - (hw - 0.3), 0.075, fp)
        centre = _band(alat - 0.12, 0.06, fp) if st[_S_DOUBLE] > 0.5 else _band(bend_lat, 0.07, fp)
        tyre = _band(abs(alat - 0.5 * hw) - 0.75, 0.3, fp)
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
