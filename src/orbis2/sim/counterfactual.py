"""The true view along any ego path: a recorded episode re-rendered under a commanded (speed, yaw rate).

No driving video has a ground truth for "what if the ego had turned harder": the town has. From a
recorded episode's state at frame ``start`` (the same town, seed, traffic and lighting: traffic is a
function of time, so it replays as recorded), the ego follows commanded controls instead of its
own, and the camera renders what it would see, with depth, labels and the poses it followed.

The counterfactual episode is the recorded one with its controls over the commanded steps
replaced (odometry convention of :mod:`orbis2.sim.ego`: control k drives pose k to pose k + 1),
integrated from the episode's first pose exactly as the recording was
(:func:`~orbis2.kinematics.integrate_odometry`). So the recorded command reproduces the
recorded poses, hence the recorded frames, bit for bit. Traffic cars that would drive through
the ego from behind are hidden as in the recording (:func:`~orbis2.sim.ego._rear_ghosts`), decided
on the path driven so far continued by the recording's remaining controls.

Traffic does not react to the new path. Where the path interferes, nothing stops or crashes:
each frame records ``collision`` (the ego's footprint overlaps a drawn traffic car: the renderer
leaves out a car whose footprint holds the camera) and ``off_road`` (the ego's position is on no
road surface: kerb, sidewalk, block or terrain; the camera goes on through whatever stands
there). The ego's own speed and yaw rate are followed exactly: no tyre, kerb or collision physics.

:class:`PathRenderer` renders step by step (an interactive caller gives one rollout step of
commands at a time); :func:`render_path` renders a whole commanded sequence with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from orbis2.kinematics import integrate_odometry
from orbis2.sim.camera import Camera
from orbis2.sim.ego import _EGO_HALF_LEN, EgoTrack, _rear_ghosts
from orbis2.sim.render import Renderer
from orbis2.sim.town import Town

_EGO_HALF_WIDTH = 0.9  # m: the ego's footprint, with _EGO_HALF_LEN, for the collision flag


@dataclass
class PathFrames:
    """Frames rendered along a path, in order: rgb uint8 [T, H, W, 3], depth float32 [T, H, W] (metres, inf for
    sky), Cityscapes labels uint8 [T, H, W], the native frame indices [T], the poses followed (x, y, yaw [T]),
    the controls driven from each frame (speed, yaw_rate [T]; the last frame's is the recording's where it
    has one, else 0) and per frame whether the ego overlaps a traffic car (``collision``) or stands off
    every road (``off_road``)."""

    rgb: np.ndarray
    depth: np.ndarray
    labels: np.ndarray
    frames: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    yaw_rate: np.ndarray
    collision: np.ndarray
    off_road: np.ndarray

    @classmethod
    def concatenate(cls, parts: list[PathFrames]) -> PathFrames:
        return cls(*(np.concatenate([getattr(p, name) for p in parts]) for name in cls.__dataclass_fields__))


def on_road(town: Town, x, y) -> np.ndarray:
    """Whether ground points (x, y) lie on a road surface: the numpy twin of the ground shader's road test
    (:func:`orbis2.sim.materials._ground_material`): a straight road's band (half width ``half_width``,
    extending ``road_extension_m`` beyond the grid) outside the corner bends' zones, or within a bend's band."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    hw, ext = town.half_width, town.style.road_extension_m
    bend = town.bend_offset(x, y)
    in_bend = ~np.isnan(bend)
    near_x = np.min(np.abs(x[..., None] - town.road_x), axis=-1)
    near_y = np.min(np.abs(y[..., None] - town.road_y), axis=-1)
    along_x = (x >= town.road_x[0] - ext) & (x <= town.road_x[-1] + ext)
    along_y = (y >= town.road_y[0] - ext) & (y <= town.road_y[-1] + ext)
    straight = ~in_bend & (((near_y < hw) & along_x) | ((near_x < hw) & along_y))
    return straight | (in_bend & (np.abs(np.nan_to_num(bend, nan=np.inf)) < hw))


def overlapping_cars(town: Town, t: float, x: float, y: float, yaw: float) -> np.ndarray:
    """Indices of the traffic cars whose footprint overlaps the ego's at pose (x, y, yaw) and time t (boxes in
    the ego's frame, the cars' extent taken along the ego's axes: conservative in a turn)."""
    boxes = town.car_boxes(t)
    dx, dy = boxes[:, 0] - x, boxes[:, 1] - y
    c, s = np.cos(yaw), np.sin(yaw)
    fwd, side = dx * c + dy * s, dy * c - dx * s
    along_ego = np.abs(np.cos(boxes[:, 2] - yaw))  # 1 when the car is parallel to the ego, 0 across it
    half_fwd = 0.5 * (boxes[:, 3] * along_ego + boxes[:, 4] * (1 - along_ego))
    half_side = 0.5 * (boxes[:, 4] * along_ego + boxes[:, 3] * (1 - along_ego))
    return np.nonzero((np.abs(fwd) < half_fwd + _EGO_HALF_LEN) & (np.abs(side) < half_side + _EGO_HALF_WIDTH))[0]


class PathRenderer:
    """Renders a recorded episode from frame ``start`` on under commanded controls, one step at a time.

    ``recorded`` is the episode as driven (its full track: the controls before ``start`` and the start
    pose come from it, exactly). :meth:`first` renders frame ``start`` (the recorded pose); each
    :meth:`step` call takes the controls for the next steps and renders the frames they reach.
    Commands may run past the recording's end (traffic keeps moving).
    """

    def __init__(self, town: Town, camera: Camera, recorded: EgoTrack, start: int):
        if not 0 <= start < len(recorded.t):
            raise ValueError(f"start frame {start} lies outside the recorded episode (0..{len(recorded.t) - 1})")
        self.town, self.recorded, self.fps = town, recorded, recorded.fps
        self.renderer = Renderer(town, camera)
        self.speed = np.asarray(recorded.speed, np.float64).copy()
        self.yaw_rate = np.asarray(recorded.yaw_rate, np.float64).copy()
        self.frame = start  # the last frame rendered (or about to be, before first())

    def _track(self, length: int) -> EgoTrack:
        """The episode driven so far, continued by the recording's remaining controls (zeros past its end)."""
        pad = max(length - len(self.speed), 0)
        speed, yaw_rate = np.append(self.speed, np.zeros(pad)), np.append(self.yaw_rate, np.zeros(pad))
        r = self.recorded
        x, y, yaw = integrate_odometry(speed, yaw_rate, self.fps, r.x[0], r.y[0], r.yaw[0])
        return EgoTrack(np.arange(len(speed)) / self.fps, x, y, yaw, speed, yaw_rate, self.fps)

    def _render(self, track: EgoTrack, frames: np.ndarray) -> PathFrames:
        hidden = _rear_ghosts(self.town, track)
        shots, collision = [], []
        for k in frames:
            pose = (float(track.x[k]), float(track.y[k]), float(track.yaw[k]), float(track.t[k]))
            drawn = np.setdiff1d(overlapping_cars(self.town, pose[3], *pose[:3]), np.nonzero(hidden[k])[0])
            collision.append(len(drawn) > 0)
            shots.append(self.renderer.render(*pose, np.nonzero(hidden[k])[0]))
        rgb, depth, labels = (np.stack(parts) for parts in zip(*shots))
        return PathFrames(rgb, depth, labels, frames.copy(), track.x[frames], track.y[frames], track.yaw[frames],
                          track.speed[frames], track.yaw_rate[frames], np.array(collision, bool),
                          ~on_road(self.town, track.x[frames], track.y[frames]))

    def first(self) -> PathFrames:
        """Frame ``start``, from its recorded pose."""
        return self._render(self._track(len(self.speed)), np.array([self.frame]))

    def step(self, speed, yaw_rate) -> PathFrames:
        """Drive the controls (m/s, rad/s, CCW positive; one per native step) from the last frame rendered and
        render the frames they reach (as many as controls)."""
        frames = self.advance(speed, yaw_rate)
        return self._render(self._track(max(len(self.speed), len(self.recorded.t))), frames)

    def advance(self, speed, yaw_rate) -> np.ndarray:
        """Drive the controls as :meth:`step` does without rendering (a caller not showing the view for a while
        keeps the path); returns the frames they reach."""
        speed, yaw_rate = np.asarray(speed, np.float64).reshape(-1), np.asarray(yaw_rate, np.float64).reshape(-1)
        if speed.shape != yaw_rate.shape or not len(speed):
            raise ValueError(f"a step needs as many speeds as yaw rates, at least one (got {speed.shape} and "
                             f"{yaw_rate.shape})")
        if not (np.isfinite(speed).all() and np.isfinite(yaw_rate).all()) or speed.min() < 0:
            raise ValueError("commanded speeds must be finite and >= 0, yaw rates finite")
        k0, n = self.frame, len(speed)
        end = k0 + n + 1  # controls k0 .. k0 + n - 1 reach frames k0 + 1 .. k0 + n
        if end > len(self.speed):
            self.speed = np.append(self.speed, np.zeros(end - len(self.speed)))
            self.yaw_rate = np.append(self.yaw_rate, np.zeros(end - len(self.yaw_rate)))
        self.speed[k0:k0 + n], self.yaw_rate[k0:k0 + n] = speed, yaw_rate
        self.frame = k0 + n
        return np.arange(k0 + 1, k0 + n + 1)


def render_path(town: Town, camera: Camera, recorded: EgoTrack, start: int, speed, yaw_rate) -> PathFrames:
    """Frames ``start`` .. ``start + len(speed)`` of the recorded episode with its controls from ``start`` on
    replaced by ``speed`` and ``yaw_rate`` (see the module docstring)."""
    renderer = PathRenderer(town, camera, recorded, start)
    return PathFrames.concatenate([renderer.first(), renderer.step(speed, yaw_rate)])
