"""The true view along a commanded path (orbis2.sim.counterfactual) and the truth-based steering claim."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from orbis2.data.shards import Clip
from orbis2.data.truth import Command, TruthError, counterfactual_clip, read_truth, render_commands, write_truth
from orbis2.eval.metrics.pixels import psnr
from orbis2.eval.protocols.truth import horizon_frames, latent_errors, truth_claim
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


def test_advancing_without_rendering_keeps_the_path(town, drive):
    """orbis2 play's true view switched off for a step and on again: the next frames are those of a renderer
    that rendered throughout (the same poses, bit for bit)."""
    track, _ = drive
    speed, yaw_rate = np.full(10, 6.0), np.full(10, 0.4)
    shown, skipping = PathRenderer(town, CAM, track, 20), PathRenderer(town, CAM, track, 20)
    shown.step(speed[:5], yaw_rate[:5])
    assert skipping.advance(speed[:5], yaw_rate[:5]).tolist() == list(range(21, 26))
    want, got = shown.step(speed[5:], yaw_rate[5:]), skipping.step(speed[5:], yaw_rate[5:])
    assert got.frames.tolist() == list(range(26, 31))
    for name in ("rgb", "x", "y", "yaw"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


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


# --------------------------------------------------------------------------- the truth-based claim


def _synthetic(follow: bool, n_clips: int = 16, per_clip: int = 2, seed: int = 0):
    """Latent truths of three commands that differ by known offsets, and rollouts that follow their command
    (the truth under it plus noise) or ignore it (the truth under the recorded command plus noise)."""
    rng = np.random.default_rng(seed)
    n = n_clips * per_clip
    base = torch.from_numpy(rng.normal(size=(n, 6, 4, 3, 5))).float()
    offsets = {"original": 0.0, "yaw_rate_x0.5": -0.6, "yaw_rate_x1.5": 0.6}
    truths = {m: base + off for m, off in offsets.items()}
    noise = {m: 0.5 * torch.from_numpy(rng.normal(size=base.shape)).float() for m in offsets}
    rollouts = {m: (truths[m] if follow else truths["original"]) + noise[m] for m in offsets}
    clusters = [f"clip{i // per_clip}" for i in range(n)]
    distances = {c: {o: latent_errors(rollouts[c], truths[o]).mean(axis=1) for o in truths} for c in rollouts}
    return distances, clusters


def test_truth_claim_holds_when_rollouts_follow_their_command():
    """Known answer: noise variance 0.25, offsets 0.6 apart -> own MSE 0.25, others 0.25 + 0.36 or + 0.72; the
    margin of every command is far above 10 %."""
    distances, clusters = _synthetic(follow=True)
    claim = truth_claim(distances, clusters, material=0.1, seed=1)
    assert claim["verdict"] == "holds"
    for cells in claim["modes"].values():
        assert cells["own"] == pytest.approx(0.25, rel=0.1) and cells["margin"]["low"] > 0.1
    assert claim["pairs"]["original"]["yaw_rate_x1.5"] == pytest.approx(0.25 + 0.36, rel=0.1)
    assert claim["modes"]["original"]["margin"]["estimate"] == pytest.approx(0.36 / 0.25, rel=0.15)


def test_truth_claim_fails_when_rollouts_ignore_the_command():
    """Rollouts that always show the recorded path are closer to another command's truth under x0.5 / x1.5."""
    distances, clusters = _synthetic(follow=False)
    claim = truth_claim(distances, clusters, material=0.1, seed=1)
    assert claim["modes"]["yaw_rate_x1.5"]["verdict"] == "does not hold"
    assert claim["modes"]["yaw_rate_x1.5"]["margin"]["high"] < 0 and claim["verdict"] == "does not hold"


def test_truth_claim_is_unresolved_when_clips_disagree():
    """Two clips, one 45 % closer to its own truth, one 20 % further: a margin of 12.5 % whose clip resamples
    straddle the 10 % threshold."""
    own, others = np.ones(2), np.array([0.8, 1.45])
    distances = {"a": {"a": own, "b": others}, "b": {"a": others, "b": own}}
    claim = truth_claim(distances, ["clip0", "clip1"], material=0.1, seed=0)
    assert claim["modes"]["a"]["margin"]["estimate"] == pytest.approx(0.125)
    assert claim["verdict"] == "not resolved at this sample size"


def test_horizons_and_psnr():
    assert horizon_frames([0.5, 1.0, 2.0, 3.0], 10, 20) == {0.5: 4, 1.0: 9, 2.0: 19}
    frames = np.full((1, 2, 4, 4, 3), 100, np.uint8)
    other = frames.copy()
    other[0, 1] += 10
    np.testing.assert_allclose(psnr(other, frames)[0], [100.0, 10 * np.log10(255 ** 2 / 100)])


def test_psnr_one_start_at_a_time_equals_all_at_once_bit_for_bit():
    """The memory-bounded PSNR (a start at a time) against the all-at-once float64 formula it replaced."""
    rng = np.random.default_rng(0)
    generated, truth = (rng.integers(0, 256, (5, 7, 24, 40, 3), dtype=np.uint8) for _ in range(2))
    diff = generated.astype(np.float64) - truth.astype(np.float64)
    mse = (diff ** 2).reshape(*diff.shape[:2], -1).mean(-1)
    whole = np.minimum(10.0 * np.log10(255.0 ** 2 / np.maximum(mse, 1e-10)), 100.0)
    assert np.array_equal(psnr(generated, truth), whole)


def _clip(smoke_cfg, town_seed=11, ego_seed=3, start_frame=10, frames=40):
    """A town clip as the shards hold it (metadata and recorded poses; its frames are not read)."""
    track = simulate_ego(Town.generate("default", town_seed), ego_seed, smoke_cfg.town.episode_seconds["val"], FPS)
    span = slice(start_frame, start_frame + frames)
    meta = {"source": "town", "split": "val", "episode": "town_val_00000", "fps": FPS, "start_frame": start_frame,
            "frames": frames, "origin": f"town style=default town_seed={town_seed} ego_seed={ego_seed}"}
    pose = np.stack([track.x[span], track.y[span], track.yaw[span]], 1)
    return Clip("town_val_00000_0000", meta, [], np.zeros((frames, 2), np.float32), pose, None), track


def test_truth_cache_round_trip_and_stale_clips(smoke_cfg, tmp_path):
    """The stage's library: a clip's commands rendered, stored, read back with their events; a clip whose recorded
    poses the town no longer drives is refused."""
    clip, track = _clip(smoke_cfg)
    data = dataclasses.replace(smoke_cfg.data, width=CAM.width, height=CAM.height)
    commands = [Command(clip.key, 5, "original", 1.0, 1.0), Command(clip.key, 5, "yaw_rate_x1.5", 1.0, 1.5)]
    rendered = render_commands(clip, commands, 10, data, smoke_cfg.town, 95)
    write_truth(tmp_path, rendered, {"split": "val"}, 1.0)
    truth = read_truth(tmp_path)
    assert sorted(truth) == ["town_val_00000_0000_0005_original", "town_val_00000_0000_0005_yaw_rate_x1-5"]
    recorded = truth["town_val_00000_0000_0005_original"]
    assert recorded.frames.shape == (11, CAM.height, CAM.width, 3)
    np.testing.assert_array_equal(recorded.pose, clip.pose[5:16])
    np.testing.assert_allclose(recorded.yaw_rate[:10], track.yaw_rate[15:25], rtol=1e-6)
    turned = truth["town_val_00000_0000_0005_yaw_rate_x1-5"]
    np.testing.assert_allclose(turned.pose[-1, 2] - turned.pose[0, 2], 1.5 * track.yaw_rate[15:25].sum() / FPS)
    with pytest.raises(TruthError, match="re-run the `truth` stage"):
        read_truth(tmp_path, ["town_val_00000_0000_0006_original"])
    clip.pose[3, 0] += 1e-9
    with pytest.raises(TruthError, match="does not drive the clip's recorded poses"):
        render_commands(clip, commands, 10, data, smoke_cfg.town, 95)


def test_a_counterfactual_train_clip_is_the_whole_clip_driven_again(smoke_cfg, tmp_path):
    """The instrument's extra training data: a clip from its first frame with its controls scaled, its frames as the
    truth cache (and the shards) would hold them, its odometry the scaled controls."""
    clip, track = _clip(smoke_cfg)
    data = dataclasses.replace(smoke_cfg.data, width=CAM.width, height=CAM.height)
    frames, odometry = counterfactual_clip(clip, 1.0, 1.5, data, smoke_cfg.town, 95)
    assert frames.shape == (40, CAM.height, CAM.width, 3) and odometry.shape == (40, 2)
    np.testing.assert_allclose(odometry[:39, 1], 1.5 * track.yaw_rate[10:49])
    np.testing.assert_allclose(odometry[:39, 0], track.speed[10:49])
    write_truth(tmp_path, render_commands(clip, [Command(clip.key, 0, "yaw", 1.0, 1.5)], 39, data, smoke_cfg.town, 95),
                {"split": "val"}, 1.0)
    np.testing.assert_array_equal(frames, read_truth(tmp_path)["town_val_00000_0000_0000_yaw"].frames)
