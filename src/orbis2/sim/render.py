"""Frames of a town: `Renderer` (one frame from an ego pose) and `render_episode` (an ego track).

A frame: the traffic cars near the camera become prisms at time t (`Town._car_prisms`), the
G-buffer is cleared and z-buffered (`orbis2.sim.raster`: static prisms, cars, ellipsoids), and one
deferred pass shades every pixel (`orbis2.sim.shade`). Outputs: RGB uint8 [H, W, 3], z-depth
float32 [H, W] in metres (+inf for sky) and Cityscapes train-id labels uint8 [H, W], with the
conventions of `orbis2.sim.camera`. Cost is a few milliseconds per 256x144 frame
(benchmarks/bench_town.py).
"""

from __future__ import annotations

import math
from typing import Iterator

import numpy as np

from orbis2.sim.camera import Camera
from orbis2.sim.ego import EgoTrack, _rear_ghosts
from orbis2.sim.kernels import _FAR
from orbis2.sim.raster import _begin_frame, _raster_ellipsoids, _raster_prisms
from orbis2.sim.shade import _shade
from orbis2.sim.town import Town


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


def render_episode(town: Town, camera: Camera, track: EgoTrack) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Frames (rgb, depth, labels) of an ego track in order, rendered lazily one at a time."""
    renderer = Renderer(town, camera)
    hidden = _rear_ghosts(town, track)
    for k in range(len(track.t)):
        yield renderer.render(float(track.x[k]), float(track.y[k]), float(track.yaw[k]), float(track.t[k]),
                              np.nonzero(hidden[k])[0])
