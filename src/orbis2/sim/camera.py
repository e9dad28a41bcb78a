"""The pinhole camera a town is rendered with.

Camera convention
-----------------
Pinhole camera at the ego pose (x, y, yaw) and height ``mount_height_m``, zero pitch and roll.
Camera axes: x right, y down, z forward (optical axis = ego heading). Pixel (u, v) has its centre
at integer coordinates (u = 0 is the left column, v = 0 the top row)::

    fx = fy = (W / 2) / tan(hfov / 2),   cx = (W - 1) / 2,   cy = (H - 1) / 2

so the ray through pixel (u, v) is ((u - cx) / fx, (v - cy) / fy, 1) in camera axes. ``depth`` is
the z-depth along the optical axis in metres (not the ray length); sky pixels have depth +inf.
A ground pixel in row v > cy therefore has depth ``mount_height_m * fy / (v - cy)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


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
