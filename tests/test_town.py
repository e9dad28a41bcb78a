"""The procedural town: renderer ground truth, odometry convention, ego behaviour, styles."""

from __future__ import annotations

import math

import numpy as np
import pytest

from orbis2.kinematics import integrate_odometry
from orbis2.sim import (
    CITYSCAPES_TRAIN_IDS,
    TOWN_STYLES,
    Camera,
    EgoTrack,
    Renderer,
    Town,
    render_episode,
    simulate_ego,
)

FPS = 10
CAM = Camera(128, 72)
IDS = CITYSCAPES_TRAIN_IDS


@pytest.fixture(scope="module")
def town():
    return Town.generate("default", 11)


@pytest.fixture(scope="module")
def heldout():
    return Town.generate("heldout", 12)


@pytest.fixture(scope="module")
def tracks(town):
    return [simulate_ego(town, seed, 20.0, FPS) for seed in range(6)]


def lane_pose(town, block=1, road=2):
    """Mid-block pose on the right lane of an x-running road, heading +x."""
    x = 0.5 * (town.road_x[block] + town.road_x[block + 1])
    return x, town.road_y[road] - town.half_width / 2, 0.0


def test_camera_intrinsics_follow_documented_convention():
    cam = Camera(256, 144, hfov_deg=90.0)
    assert cam.fx == pytest.approx(128.0) and cam.fy == cam.fx
    assert (cam.cx, cam.cy) == (127.5, 71.5)
    np.testing.assert_allclose(cam.K(), [[128.0, 0, 127.5], [0, 128.0, 71.5], [0, 0, 1]])
    assert Camera(100, 50, hfov_deg=60.0).fx == pytest.approx(50 / math.tan(math.radians(30)))


def test_render_is_deterministic_and_seed_dependent(town):
    x, y, yaw = lane_pose(town)
    a = Renderer(town, CAM).render(x, y, yaw, 3.0)
    b = Renderer(Town.generate("default", 11), CAM).render(x, y, yaw, 3.0)
    for u, v in zip(a, b):
        np.testing.assert_array_equal(u, v)
    rgb, depth, labels = a
    assert rgb.shape == (72, 128, 3) and rgb.dtype == np.uint8
    assert depth.shape == (72, 128) and depth.dtype == np.float32
    assert labels.shape == (72, 128) and labels.dtype == np.uint8
    other = Town.generate("default", 12)
    c = Renderer(other, CAM).render(*lane_pose(other), 3.0)
    assert np.mean(np.abs(rgb.astype(int) - c[0].astype(int))) > 5.0


def test_road_depth_matches_analytic_ground_plane(town):
    x, y, yaw = lane_pose(town)
    rgb, depth, labels = Renderer(town, CAM).render(x, y, yaw, 0.0)
    rows = np.arange(CAM.height)[:, None] * np.ones((1, CAM.width))
    expected = CAM.mount_height_m * CAM.fy / (rows - CAM.cy)
    road = (labels == IDS["road"]) & (rows > CAM.cy + 5)
    assert road[-10:, 40:88].all()  # the lower central rows look at the road
    np.testing.assert_allclose(depth[road], expected[road], rtol=1e-4)
    # Sky is +inf depth; everything else finite and positive.
    sky = labels == IDS["sky"]
    assert sky[0].any() and np.all(np.isinf(depth[sky]))
    assert np.all(np.isfinite(depth[~sky])) and np.all(depth[~sky] > 0)


def test_car_ahead_has_exact_depth_and_label(town):
    t = 4.0
    car = town.car_boxes(t)[0]  # x, y, yaw, length, width, height, speed
    x, y, yaw, length = car[0], car[1], car[2], car[3]
    gap = 9.0
    cx, cy = x - (gap + length / 2) * math.cos(yaw), y - (gap + length / 2) * math.sin(yaw)
    rgb, depth, labels = Renderer(town, CAM).render(cx, cy, yaw, t)
    u, z = int(CAM.cx), gap  # centre column, rear face of the car
    v = int(round(CAM.cy + CAM.fy * (CAM.mount_height_m - 0.8) / z))  # a point 0.8 m above ground
    assert labels[v, u] == IDS["car"]
    assert depth[v, u] == pytest.approx(z, rel=1e-4)


def test_car_boxes_are_a_pure_function_of_time(town):
    a, b = town.car_boxes(10.0), Town.generate("default", 11).car_boxes(10.0)
    np.testing.assert_array_equal(a, b)
    assert a.shape[1] == 7 and len(a) > 20
    later = town.car_boxes(10.5)
    moved = np.hypot(later[:, 0] - a[:, 0], later[:, 1] - a[:, 1])
    wrapped = moved > 50  # cars wrapping around the end of their road
    np.testing.assert_allclose(moved[~wrapped], 0.5 * a[~wrapped, 6], rtol=1e-9)
    heading = np.stack([np.cos(a[:, 2]), np.sin(a[:, 2])], 1)
    step = (later[:, :2] - a[:, :2])[~wrapped]
    np.testing.assert_allclose(np.sum(step * heading[~wrapped], 1), moved[~wrapped], rtol=1e-9)


def test_integrate_odometry_convention():
    # Constant controls: a circle of radius v / w through the start, centre to the left.
    v, w, n = 5.0, 0.4, 30
    x, y, yaw = integrate_odometry(np.full(n, v), np.full(n, w), FPS, 1.0, 2.0, 0.3)
    t = np.arange(n) / FPS
    r = v / w
    np.testing.assert_allclose(yaw, 0.3 + w * t, atol=1e-12)
    np.testing.assert_allclose(x, 1.0 + r * (np.sin(0.3 + w * t) - math.sin(0.3)), atol=1e-9)
    np.testing.assert_allclose(y, 2.0 - r * (np.cos(0.3 + w * t) - math.cos(0.3)), atol=1e-9)
    # Zero yaw rate is the straight-line limit; the last control does not affect the poses.
    x, y, yaw = integrate_odometry([2.0, 2.0, 99.0], [0.0, 0.0, 5.0], FPS)
    np.testing.assert_allclose(x, [0.0, 0.2, 0.4], atol=1e-12)
    np.testing.assert_allclose(y, 0.0, atol=1e-12)
    np.testing.assert_allclose(yaw, 0.0, atol=1e-12)


def euler(track: EgoTrack, sub: int = 200):
    """Independent fine forward-Euler integration of the track's controls."""
    x, y, yaw = track.x[0], track.y[0], track.yaw[0]
    out = [(x, y, yaw)]
    h = 1.0 / (FPS * sub)
    for v, w in zip(track.speed[:-1], track.yaw_rate[:-1]):
        for _ in range(sub):
            x, y, yaw = x + v * math.cos(yaw) * h, y + v * math.sin(yaw) * h, yaw + w * h
        out.append((x, y, yaw))
    return np.array(out).T


def test_ego_poses_are_the_integrated_controls(tracks):
    for tr in tracks[:3]:
        assert len(tr.t) == 200 and np.allclose(tr.t, np.arange(200) / FPS)
        x, y, yaw = integrate_odometry(tr.speed, tr.yaw_rate, FPS, tr.x[0], tr.y[0], tr.yaw[0])
        np.testing.assert_allclose(x, tr.x, atol=1e-6)
        np.testing.assert_allclose(y, tr.y, atol=1e-6)
        np.testing.assert_allclose(yaw, tr.yaw, atol=1e-9)
        ex, ey, eyaw = euler(tr)
        assert np.max(np.hypot(ex - tr.x, ey - tr.y)) < 0.05
        assert np.max(np.abs(eyaw - tr.yaw)) < 1e-6
    assert tracks[0].total_abs_yaw() == pytest.approx(np.sum(np.abs(tracks[0].yaw_rate)) / FPS)


def test_simulate_ego_is_deterministic(town, tracks):
    again = simulate_ego(town, 0, 20.0, FPS)
    for name in ("x", "y", "yaw", "speed", "yaw_rate"):
        np.testing.assert_array_equal(getattr(again, name), getattr(tracks[0], name))
    assert not np.allclose(tracks[0].x, tracks[1].x)


def longest_run(mask: np.ndarray) -> int:
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    return int(np.max(edges[1::2] - edges[::2])) if len(edges) else 0


def test_ego_behaviour_stops_turns_and_stays_in_bounds(town, tracks):
    stops = [longest_run(tr.speed == 0.0) for tr in tracks]
    turns = [np.degrees(np.ptp(tr.yaw)) for tr in tracks]
    assert max(stops) >= FPS  # stands still for at least a second somewhere
    assert sum(s >= FPS for s in stops) >= 2
    assert max(turns) > 60 and sum(t > 60 for t in turns) >= 2
    for tr in tracks:
        assert np.all(tr.speed >= 0) and np.all(tr.speed <= town.style.cruise_ms[1])
        assert tr.speed.max() > 5.0  # it does cruise
        assert np.all(np.abs(np.diff(tr.speed)) * FPS <= 4.5 + 1e-9)  # bounded accel / braking
        assert np.all(np.abs(tr.yaw_rate) < 2.0)
        hw = town.half_width
        on_straight = (np.min(np.abs(town.road_x[None] - tr.x[:, None]), 1) < hw) | (
            np.min(np.abs(town.road_y[None] - tr.y[:, None]), 1) < hw)
        bend = town.bend_offset(tr.x, tr.y)
        assert np.where(np.isnan(bend), on_straight, np.abs(bend) < hw).all()
        # Driving along a road (heading within ~2 deg of an axis) means near a lane centre.
        along_x, along_y = np.abs(np.cos(tr.yaw)) > 0.9995, np.abs(np.sin(tr.yaw)) > 0.9995
        lanes_y = np.concatenate([town.road_y - hw / 2, town.road_y + hw / 2])
        lanes_x = np.concatenate([town.road_x - hw / 2, town.road_x + hw / 2])
        assert along_x.sum() + along_y.sum() > 0.5 * len(tr.t)
        assert np.all(np.min(np.abs(tr.y[along_x, None] - lanes_y), 1) < 0.25)
        assert np.all(np.min(np.abs(tr.x[along_y, None] - lanes_x), 1) < 0.25)


def test_corners_are_bends_the_ego_drives_in_lane(town):
    """A grid corner is a quarter-circle bend without traffic; the ego follows its lane round it
    at the yaw rate of the lane's circle, and the camera sees road below it."""
    hw = town.half_width
    driven = []
    for seed in range(6, 60):
        tr = simulate_ego(town, seed, 20.0, FPS)
        in_bend = ~np.isnan(town.bend_offset(tr.x, tr.y))
        if in_bend.sum() >= 3 * FPS:
            driven.append((tr, in_bend))
    assert len(driven) >= 2
    for tr, in_bend in driven[:2]:
        offset = town.bend_offset(tr.x, tr.y)[in_bend]
        assert np.all(np.abs(np.abs(offset) - hw / 2) < 0.35)  # on a lane centre
        # Curvature of the driven path against its lane circle's (radius: distance to the centre).
        turning = in_bend & (np.abs(tr.yaw_rate) > 0.05) & (tr.speed > 1.0)
        corner = (tr.x > np.mean(town.road_x[[0, -1]])).astype(int) + 2 * (tr.y > np.mean(town.road_y[[0, -1]]))
        lane_radius = town.bend_radius[corner[turning]] - town.bend_offset(tr.x[turning], tr.y[turning])
        ratio = np.abs(tr.yaw_rate[turning]) / tr.speed[turning] * lane_radius
        assert turning.sum() >= 2 * FPS and abs(np.median(ratio) - 1.0) < 0.1
        frames = np.flatnonzero(in_bend)[::10]
        short = EgoTrack(tr.t[frames], tr.x[frames], tr.y[frames], tr.yaw[frames], tr.speed[frames],
                         tr.yaw_rate[frames])
        for _, _, labels in render_episode(town, CAM, short):
            assert labels[-1, CAM.width // 2] == IDS["road"]
    for t in (0.0, 7.0, 30.0):  # the ring road carries no traffic
        cars = town.car_boxes(t)
        offset = town.bend_offset(cars[:, 0], cars[:, 1])
        assert np.all(np.isnan(offset) | (np.abs(offset) > hw + 0.5))


def test_ego_keeps_its_lane_in_the_rendered_frames(town, tracks):
    for tr in tracks[:3]:
        below = np.array([labels[-1, CAM.width // 2] for _, _, labels in render_episode(town, CAM, tr)])
        assert np.mean(below == IDS["road"]) >= 0.98


def test_episode_labels_cover_the_street_classes(town, tracks):
    tr = tracks[0]
    short = EgoTrack(tr.t[::20], tr.x[::20], tr.y[::20], tr.yaw[::20], tr.speed[::20], tr.yaw_rate[::20])
    frames = list(render_episode(town, CAM, short))
    assert len(frames) == len(short.t)
    seen = set(np.unique(np.stack([f[2] for f in frames])))
    for name in ("road", "sidewalk", "building", "vegetation", "sky", "car", "terrain"):
        assert IDS[name] in seen, name
    assert IDS["pole"] in seen or IDS["traffic sign"] in seen
    assert seen <= set(IDS.values())


def test_heldout_style_looks_different(town, heldout):
    assert set(TOWN_STYLES) >= {"default", "heldout"}
    means = []
    for t in (town, heldout):
        rgbs = []
        for seed in (1, 2):
            tr = simulate_ego(t, seed, 10.0, FPS)
            rgbs += [Renderer(t, CAM).render(tr.x[k], tr.y[k], tr.yaw[k], tr.t[k])[0] for k in (0, 50, 99)]
        means.append(np.mean(np.stack(rgbs).reshape(-1, 3), 0))
    warmth = [m[0] - m[2] for m in means]  # the heldout desert town is sunny and sandy
    assert warmth[1] - warmth[0] > 15.0
    assert np.max(np.abs(means[0] - means[1])) > 10.0


def test_unknown_style_is_rejected():
    with pytest.raises(ValueError, match="unknown town style"):
        Town.generate("mars", 0)


def test_world_turns_often_both_ways_at_graded_rates():
    """The ego turns in a large share of frames, left and right alike, at graded yaw rates."""
    from orbis2.data.motion import TURN_THRESHOLD, motion_statistics

    town = Town.generate("default", 3)
    tracks = [simulate_ego(town, seed, 20.0, FPS) for seed in range(32)]
    yaw_rate = np.concatenate([t.yaw_rate for t in tracks])
    x, y = np.concatenate([t.x for t in tracks]), np.concatenate([t.y for t in tracks])
    m = motion_statistics(np.concatenate([t.speed for t in tracks]), yaw_rate,
                          on_bend=~np.isnan(town.bend_offset(x, y)))
    assert m["turning"] >= 0.2
    # Curves as well as junctions: the corner bends, gentler than a junction turn.
    assert m["bend_turning"] >= 0.02 and 0.15 <= m["bend_yaw_rate_median"] <= 0.45
    assert 0.6 <= m["left_right_ratio"] <= 1.6
    # Cruising 8-14 m/s between junctions a few seconds apart, 1.9-13.5 m/s on the turn arcs: an urban
    # drive's 6-14 m/s when moving.
    assert 6.0 <= m["speed_moving_mean"] <= 14.0
    assert m["stopped"] <= 0.2
    turning = np.abs(yaw_rate[np.abs(yaw_rate) > TURN_THRESHOLD])
    assert np.mean(turning < 0.6) >= 0.15  # slow arcs: half a typical turn rate is in the data
    assert np.mean(turning > 1.1) >= 0.1  # and fast ones: one and a half times it


def test_motion_statistics_known_answer():
    from orbis2.data.motion import motion_statistics

    speed = np.array([0.0, 5.0, 10.0, 10.0])
    yaw = np.array([0.0, 0.1, -0.1, 0.01])
    m = motion_statistics(speed, yaw)
    assert m["turning"] == 0.5 and m["left"] == 0.25 and m["right"] == 0.25 and m["left_right_ratio"] == 1.0
    assert m["stopped"] == 0.25 and m["speed_moving_mean"] == pytest.approx(25 / 3)
    assert sum(v for k, v in m.items() if k.startswith("speed_hist")) == pytest.approx(1.0)
    assert sum(v for k, v in m.items() if k.startswith("yaw_hist")) == pytest.approx(1.0)
    assert m["turning_yaw_rate_median"] == pytest.approx(0.1) and m["turning_yaw_rate_p99"] == pytest.approx(0.1)
    graded = motion_statistics(np.full(5, 5.0), np.array([0.0, 0.2, -0.4, 0.6, 0.01]))
    assert graded["turning_yaw_rate_median"] == pytest.approx(0.4)
    assert graded["turning_yaw_rate_p99"] == pytest.approx(0.2 + 0.99 * 0.4)
    assert motion_statistics(np.ones(3), np.zeros(3))["turning_yaw_rate_median"] == 0.0
    bends = motion_statistics(speed, yaw, on_bend=np.array([False, True, True, True]))
    assert bends["bend"] == 0.75 and bends["bend_turning"] == 0.5
    assert bends["bend_yaw_rate_median"] == pytest.approx(0.1)
    with pytest.raises(ValueError, match="on_bend"):
        motion_statistics(speed, yaw, on_bend=np.ones(3, bool))
