"""The procedural driving town: road grid, blocks, buildings, vegetation, signs and traffic.

This is the default data source of the pipeline: it stands in for dashcam footage and comes with
exact odometry, metric depth and Cityscapes semantic labels (the `orbis2.sim` package renders it;
`orbis2.data.town_dataset` turns it into episodes).

World model
-----------
World frame: x east, y north, z up, metres; the ground plane is z = 0.

* Roads form an irregular grid: roads running along x at the sorted positions ``Town.road_y`` and
  roads running along y at ``Town.road_x`` (blocks ``style.block_size_m`` apart, the outermost
  ``style.corner_block_m``). Every road has two lanes of ``style.lane_width_m`` with right-hand
  traffic and continues ``style.road_extension_m`` beyond the town into open terrain, except at
  the four corners of the grid: there the two boundary roads meet in a bend, a quarter circle of
  road-centre radius ``Town.bend_radius[c]`` (corner c = (x high) + 2 (y high)), so the boundary
  roads form a ring road with curves. A corner block is a verge with trees, not a kerbed block.
* Each block between four roads is a raised slab (``style.kerb_height_m``, its side is the kerb)
  whose outer band is sidewalk; inside it holds buildings (axis-aligned boxes on lots with
  setbacks, some with an upper tier) or a park (lawn, trees, hedges). Street lamps and trees line
  the sidewalks, traffic signs stand at intersection corners. Trees (trunk box + ellipsoid canopy
  blobs) also fill a belt of terrain around the town; distant hills are huge flattened ellipsoids.
* Other cars drive straight along lanes at constant per-lane speeds and wrap around at the ends
  of the extended roads, so their state is a pure function of (town seed, t) (`Town.car_boxes`).
  The ring road carries no traffic: cars are axis-aligned prisms and could not follow a bend.
  They ignore each other and the ego: the ego follows them and gives way at junctions
  (`orbis2.sim.ego.simulate_ego`), and `orbis2.sim.render.render_episode` hides a car that would
  drive through the ego from behind, from the moment it is out of view behind it.
* Lighting (`orbis2.sim.shade`) uses what `Town._precompute` prepares: textures and sky
  (`orbis2.sim.textures`), the sun-ray height map, the ground ambient-occlusion map and the
  shading constants vector ``Town.shading``.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from dataclasses import dataclass

import cv2
import numpy as np

from orbis2.sim.kernels import (
    _K_BLOCK,
    _K_BUILDING,
    _K_CANOPY,
    _K_CAR_BODY,
    _K_CAR_CABIN,
    _K_HEDGE,
    _K_HILL,
    _K_LAMP,
    _K_POLE,
    _K_SIGN,
    _K_TRUNK,
    _K_WHEEL,
    _S_AMB,
    _S_AORES,
    _S_AOX0,
    _S_AOY0,
    _S_ASPH,
    _S_BEND,
    _S_CLINE,
    _S_DASH,
    _S_DASHP,
    _S_DOUBLE,
    _S_EXPO,
    _S_EXT,
    _S_FOG,
    _S_GAMB,
    _S_GLASS,
    _S_GRASS,
    _S_GRASS2,
    _S_HW,
    _S_KERB,
    _S_KERBC,
    _S_N,
    _S_PAINT,
    _S_ROOF,
    _S_SIDEW,
    _S_SKYEL0,
    _S_SKYEL1,
    _S_SMKX,
    _S_SMKY,
    _S_SMRES,
    _S_SMX0,
    _S_SMY0,
    _S_SUN,
    _S_SUNC,
    _S_SW,
    _S_TERR,
    _S_TERR2,
    _S_TILE,
)
from orbis2.sim.raster import _build_shadow_map
from orbis2.sim.style import TOWN_STYLES
from orbis2.sim.textures import _lin, _noise_textures, _sky_panorama


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
    per junction (road_x[i], road_y[j]), ``bend_radius`` [4] per corner bend (`Town.corner`).
    Traffic: one entry per car in the ``car_*`` arrays
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
            gaps = rng.uniform(*st.block_size_m, n)
            gaps[[0, -1]] = rng.uniform(*st.corner_block_m, 2)
            pos = np.concatenate([[0.0], np.cumsum(gaps)])
            roads.append(pos - pos[-1] / 2)
        self.road_x, self.road_y = roads
        nx, ny = len(self.road_x), len(self.road_y)
        # A bend ends at least 12 m plus a half road before the next junction on either road.
        room = np.minimum(np.diff(self.road_x)[[0, -1, 0, -1]], np.diff(self.road_y)[[0, 0, -1, -1]])
        self.bend_radius = np.minimum(rng.uniform(*st.bend_radius_m, 4), room - hw - 12.0)
        self.crosswalks = (rng.random((nx, ny)) < st.crosswalk_prob).astype(np.uint8)
        b = _Builder()
        kerb = st.kerb_height_m
        for i in range(nx - 1):
            for j in range(ny - 1):
                rect = (self.road_x[i] + hw, self.road_x[i + 1] - hw, self.road_y[j] + hw,
                        self.road_y[j + 1] - hw)
                if i in (0, nx - 2) and j in (0, ny - 2):
                    self._corner_verge(b, rng, rect)
                    continue
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

    def _corner_verge(self, b: _Builder, rng, rect) -> None:
        """A corner block: open terrain cut by the bend. Trees stand only in the bend's zone (the
        part of the block toward the corner), 2.5 m or more off the road; the rest is open."""
        x0, x1, y0, y1 = rect
        n = int((x1 - x0) * (y1 - y0) / 220)
        xy = rng.uniform((x0 + 2.5, y0 + 2.5), (x1 - 2.5, y1 - 2.5), (n, 2))
        for x, y in xy[np.abs(self.bend_offset(xy[:, 0], xy[:, 1])) > self.half_width + 2.5]:
            self._tree(b, rng, x, y, 0.0, rng.uniform(0.9, 1.3))

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
        for i, x in enumerate(self.road_x):
            for j, y in enumerate(self.road_y):
                if self.corner(i, j) is not None:  # a bend, not a junction
                    continue
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
        """Cars on every lane of every road but the ring road, constant per-lane speed, spaced randomly."""
        st = self.style
        rng = _rng(self.seed, self._salt, 2)
        hw, ext = self.half_width, st.road_extension_m
        rows = []
        for axis, (positions, along) in enumerate(((self.road_y, self.road_x), (self.road_x, self.road_y))):
            lo, hi = along[0] - ext, along[-1] + ext
            for road, c in enumerate(positions):
                if road in (0, len(positions) - 1):  # the ring road
                    continue
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

    # ---- corner bends

    def corner(self, i: int, j: int) -> int | None:
        """Index of the corner bend at grid node (road_x[i], road_y[j]), or None for a junction."""
        nx, ny = len(self.road_x), len(self.road_y)
        if i % (nx - 1) or j % (ny - 1):
            return None
        return int(i == nx - 1) + 2 * int(j == ny - 1)

    def bend_offset(self, x, y) -> np.ndarray:
        """Lateral offset (m) from the centre line of the nearest corner bend; NaN outside its zone.

        The numpy twin of the ground shader's `_corner_bend`: the zone is the quarter plane beyond
        the bend's centre toward its corner; the offset is R minus the distance to that centre.
        """
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        hi_x = x > 0.5 * (self.road_x[0] + self.road_x[-1])
        hi_y = y > 0.5 * (self.road_y[0] + self.road_y[-1])
        r = self.bend_radius[hi_x.astype(int) + 2 * hi_y.astype(int)]
        sx, sy = np.where(hi_x, -1.0, 1.0), np.where(hi_y, -1.0, 1.0)
        dx = x - np.where(hi_x, self.road_x[-1], self.road_x[0]) - sx * r
        dy = y - np.where(hi_y, self.road_y[-1], self.road_y[0]) - sy * r
        return np.where((dx * sx < 0) & (dy * sy < 0), r - np.hypot(dx, dy), np.nan)

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
        sh[_S_BEND:_S_BEND + 4] = self.bend_radius
        self.shading = sh
