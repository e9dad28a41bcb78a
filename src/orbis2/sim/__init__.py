"""The embedded driving simulator: a procedural town, its traffic, an ego driver and a numba renderer.

It renders RGB frames with exact odometry, metric depth and Cityscapes semantic labels, and is the
default data source of the pipeline (`orbis2.data.town_dataset` writes its episodes). How a frame
is made, and which module does what: README.md next to this file.

Modules, from the world to the pixels: `style` (TownStyle, TOWN_STYLES), `town` (Town: layout,
traffic, precomputed maps), `textures` (noise textures, sky), `ego` (route planning, simulate_ego,
EgoTrack), `camera` (Camera), `render` (Renderer, render_episode) and the numba kernels `kernels`
(shared codes and helpers), `raster` (G-buffer), `materials` and `shade` (deferred shading).
The simulator imports nothing from the rest of orbis2 but `orbis2.kinematics`.
"""

from orbis2.kinematics import integrate_odometry
from orbis2.sim.camera import Camera
from orbis2.sim.ego import EgoTrack, simulate_ego
from orbis2.sim.kernels import CITYSCAPES_TRAIN_IDS
from orbis2.sim.render import Renderer, render_episode
from orbis2.sim.style import TOWN_STYLES, TownStyle
from orbis2.sim.town import Town

__all__ = [
    "CITYSCAPES_TRAIN_IDS", "TownStyle", "TOWN_STYLES", "Camera", "Town", "Renderer", "EgoTrack",
    "simulate_ego", "integrate_odometry", "render_episode",
]
