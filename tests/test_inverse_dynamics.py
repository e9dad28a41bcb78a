"""The learned inverse-dynamics instrument learns ego-motion from town frames (well above a shuffled control)
and plugs into the steering evaluation's interface."""

import numpy as np
import pytest
import torch

from orbis2.config.sections import InverseDynamicsConfig
from orbis2.eval.inverse_dynamics import ClipFrames, Instrument, evaluate_instrument, pair_index, train_instrument
from orbis2.eval.odometry import camera_intrinsics, trajectory_ade
from orbis2.sim import Camera, Town, render_episode, simulate_ego

FPS = 10


def episodes(town, seeds, seconds=12.0):
    frames, odometry, keys = [], [], []
    for seed in seeds:
        track = simulate_ego(town, seed, seconds, FPS)
        frames.append(np.stack([rgb for rgb, _, _ in render_episode(town, Camera(128, 72), track)]))
        odometry.append(np.stack([track.speed, track.yaw_rate], axis=1))
        keys.append(f"episode{seed}")
    return ClipFrames(frames, odometry, keys)


@pytest.fixture(scope="module")
def trained():
    town = Town.generate("default", 11)
    train, val = episodes(town, range(6)), episodes(town, (20, 21, 22))
    cfg = InverseDynamicsConfig(steps=200, batch_size=32, lr=2e-3, weight_decay=1e-4, width=16, scale=0.5,
                                max_train_clips=None, eval_pairs=512, seed=0)
    torch.set_num_threads(2)
    return train_instrument(train, cfg, FPS, torch.device("cpu")), val


def test_instrument_learns_town_ego_motion_well_above_the_shuffled_control(trained):
    instrument, val = trained
    result = evaluate_instrument(instrument, val, max_pairs=300, seed=0)
    real, shuffled = result["real"], result["shuffled"]
    assert real["yaw_rate_r2"] > 0.5 and real["yaw_rate_r2"] > shuffled["yaw_rate_r2"] + 0.4
    assert real["speed_r2"] > shuffled["speed_r2"] + 0.2


def test_instrument_round_trips_and_serves_the_odometry_interface(trained, tmp_path):
    instrument, val = trained
    instrument.save(tmp_path / "model.pt", {"note": "test"})
    loaded = Instrument.load(tmp_path / "model.pt")
    first, second = val.frames[0][:5], val.frames[0][1:6]
    assert np.allclose(loaded.predict(first, second), instrument.predict(first, second), atol=1e-6)
    video, odo = val.frames[1][:31], val.odometry[1]
    result = trajectory_ade(video, odo[:30, 0], odo[:30, 1], FPS, camera_intrinsics(128, 72), loaded)
    assert result["estimated"].shape == (31, 2) and np.isfinite(result["ade"])
    assert len(pair_index(val)) == sum(len(f) - 1 for f in val.frames)
