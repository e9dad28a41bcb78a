"""The true view along a commanded path (orbis2.sim.counterfactual) and the truth-based steering claim."""

from __future__ import annotations

import numpy as np
import pytest

from orbis2.sim import Camera, Town, render_episode, simulate_ego
from orbis2.sim.counterfactual import PathFrames, PathRenderer, on_road, render_path

FPS = 10
CAM = Camera(64, 40)


@pytest.fixture(scope="module")
def town():
    return Town.generate("default", 11)


@pytest.fixture(scope="module")
def drive(town):
    """An 8-s drive and its recorded frames."""
    track = simulate_ego(town, 3, 8.0, FPS)
    return track, list(render_episode(town, CAM, track))


def test_recorded_command_reproduces_the_recorded_frames_bit_for_bit(town, drive):
    track, recorded = drive
    start, n = 20, 45
    for path in (render_path(town, CAM, track, start, track.speed[start:start + n], track.yaw_rate[start:start + n]),
                 _stepwise(town, track, start, track.speed[start:start + n], track.yaw_rate[start:start + n])):
        assert path.frames.tolist() == list(range(start, start + n + 1))
        for i, k in enumerate(path.frames):
            for want, got in zip(recorded[k], (path.rgb[i], path.depth[i], path.labels[i])):
                np.testing.assert_array_equal(got, want)
        for name in ("x", "y", "yaw"):
            np.testing.assert_array_equal(getattr(path, name), getattr(track, name)[path.frames])
        assert not path.collision.any() and not path.off_road.any()


def _stepwise(town, track, start, speed, yaw_rate, per_step=5) -> PathFrames:
    renderer = PathRenderer(town, CAM, track, start)
    parts = [renderer.first()]
    for i in range(0, len(speed), per_step):
        parts.append(renderer.step(speed[i:i + per_step], yaw_rate[i:i + per_step]))
    return PathFrames.concatenate(parts)


def test_a_left_command_renders_a_left_turn(town, drive):
    """The town's own odometry turns left (yaw grows by the command) and so does the picture: the scene
    slides right across the frames (the image reading of the steering evaluation)."""
    from orbis2.eval.protocols.steering import image_turns

    track, _ = drive
    start, n, rate = 20, 15, 0.6
    turns = {}
    for name, yaw_rate in (("left", rate), ("right", -rate)):
        path = render_path(town, CAM, track, start, np.full(n, 4.0), np.full(n, yaw_rate))
        np.testing.assert_allclose(path.yaw[-1] - path.yaw[0], yaw_rate * n / FPS, atol=1e-9)
        np.testing.assert_allclose(np.hypot(np.diff(path.x), np.diff(path.y)).sum(), 4.0 * n / FPS, rtol=1e-3)
        reading = image_turns([path.rgb], [(path.speed, np.full(n + 1, rate))], FPS, CAM.hfov_deg)
        turns[name] = reading["turn_deg"][0]  # signed so that a left turn is positive
    commanded = np.degrees(rate * n / FPS)
    assert turns["left"] > 0.5 * commanded and turns["right"] < -0.5 * commanded


def test_interference_is_recorded_not_raised(town, drive):
    """Driving straight on through a junction's corner leaves the road; the frames are still rendered."""
    track, _ = drive
    path = render_path(town, CAM, track, 20, np.full(40, 8.0), np.full(40, 1.2))
    assert path.off_road.any() and len(path.rgb) == 41 and np.isfinite(path.x).all()
    lane = (0.5 * (town.road_x[1] + town.road_x[2]), town.road_y[2] - town.half_width / 2)
    assert on_road(town, *lane) and not on_road(town, lane[0], town.road_y[2] + 1.5 * town.half_width + 3)


def test_commands_are_checked(town, drive):
    renderer = PathRenderer(town, CAM, drive[0], 5)
    with pytest.raises(ValueError, match="as many speeds"):
        renderer.step([1.0, 2.0], [0.0])
    with pytest.raises(ValueError, match=">= 0"):
        renderer.step([-1.0], [0.0])
    with pytest.raises(ValueError, match="outside"):
        PathRenderer(town, CAM, drive[0], 500)
