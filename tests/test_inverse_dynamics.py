"""The learned inverse-dynamics instrument learns ego-motion from town frames (well above a shuffled control),
plugs into the steering evaluation's interface, and trains through the shared loop: bit for bit the plain
AdamW + cosine loop it is specified by, resumable after a kill."""

import dataclasses

import numpy as np
import pandas as pd
import pytest
import torch
import torch.nn.functional as F

from orbis2.accel import conv_layout
from orbis2.config.training import InverseDynamicsConfig
from orbis2.eval.metrics.inverse_dynamics import ClipFrames, Instrument, evaluate_instrument, pair_flow, pair_index
from orbis2.eval.metrics.odometry import camera_intrinsics, trajectory_ade
from orbis2.models.inverse_dynamics import InverseDynamicsNet
from orbis2.sim import Camera, Town, render_episode, simulate_ego
from orbis2.tasks.instrument import InstrumentTask, train_instrument
from orbis2.train import load_checkpoint, load_weights, train

FPS = 10


def episodes(town, seeds, seconds=12.0):
    frames, odometry, keys = [], [], []
    for seed in seeds:
        track = simulate_ego(town, seed, seconds, FPS)
        frames.append(np.stack([rgb for rgb, _, _ in render_episode(town, Camera(128, 72), track)]))
        odometry.append(np.stack([track.speed, track.yaw_rate], axis=1))
        keys.append(f"episode{seed}")
    return ClipFrames(frames, odometry, keys)


def instrument_config(smoke_cfg, **train) -> InverseDynamicsConfig:
    """The smoke profile's instrument settings (so the optimiser and schedule are params.yaml's), resized."""
    ic = smoke_cfg.inverse_dynamics
    return dataclasses.replace(ic, train=dataclasses.replace(ic.train, **train))


@pytest.fixture(scope="module")
def trained(smoke_cfg, tmp_path_factory):
    town = Town.generate("default", 11)
    train, val = episodes(town, range(6)), episodes(town, (20, 21, 22))
    cfg = dataclasses.replace(instrument_config(smoke_cfg, steps=200, batch_size=32, seed=0), width=16, scale=0.5)
    return train_instrument(train, cfg, FPS, tmp_path_factory.mktemp("instrument"), torch.device("cpu")), val


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


def random_clips(seed: int = 0, clips: int = 3, frames: int = 8) -> ClipFrames:
    """Small textured frames drifting by random offsets, with random controls: flows that vary per pair."""
    rng = np.random.default_rng(seed)
    base = np.repeat(np.repeat(rng.integers(0, 255, (clips, 12, 16, 3), dtype=np.uint8), 4, 1), 4, 2)
    shifts = rng.integers(-3, 4, (clips, frames, 2)).cumsum(axis=1)
    videos = [np.stack([np.roll(base[c], tuple(shifts[c, t]), axis=(0, 1))[8:32, 8:40] for t in range(frames)])
              for c in range(clips)]
    odometry = [np.column_stack([rng.uniform(0, 10, frames), rng.normal(0, 0.2, frames)]) for _ in range(clips)]
    return ClipFrames(videos, odometry, [f"clip{c}" for c in range(clips)])


def reference_weights(data: ClipFrames, cfg: InverseDynamicsConfig) -> dict[str, torch.Tensor]:
    """The plain loop the instrument is specified by: AdamW on every parameter, CosineAnnealingLR, seeded
    pair picks and flips; trained here on its own, as the reference for the shared loop."""
    tc = cfg.train
    index = pair_index(data)
    targets = np.stack([data.odometry[c][t] for c, t in index])
    mean, std = targets.mean(axis=0), targets.std(axis=0) + 1e-6
    flows = pair_flow(np.stack([data.frames[c][t] for c, t in index]),
                      np.stack([data.frames[c][t + 1] for c, t in index]))
    mirrored = np.ascontiguousarray(flows[..., ::-1] * np.array([-1.0, 1.0], np.float32)[:, None, None])
    torch.manual_seed(tc.seed)
    net = conv_layout(InverseDynamicsNet(cfg.width))
    opt = torch.optim.AdamW(net.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, tc.steps)
    rng = np.random.default_rng(tc.seed)
    sign = np.array([1.0, -1.0])
    for _ in range(tc.steps):
        pick = rng.integers(0, len(index), tc.batch_size)
        flip = rng.random(tc.batch_size) < 0.5
        x = np.where(flip[:, None, None, None], mirrored[pick], flows[pick])
        y = np.where(flip[:, None], targets[pick] * sign, targets[pick])
        loss = F.mse_loss(net(torch.from_numpy(x)), torch.from_numpy((y - mean) / std).float())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
    return net.state_dict()


def test_shared_loop_reproduces_the_plain_adamw_cosine_loop_bit_for_bit(smoke_cfg, tmp_path):
    # 30 steps: enough for the scheduler's recursive cosine to differ from lr_at's closed form in the last bits.
    data = random_clips()
    cfg = dataclasses.replace(instrument_config(smoke_cfg, steps=30, batch_size=8, seed=5), width=8)
    expected = reference_weights(data, cfg)
    instrument = train_instrument(data, cfg, FPS, tmp_path, torch.device("cpu"))
    got = instrument.net.state_dict()
    assert got.keys() == expected.keys()
    for key in expected:
        assert torch.equal(got[key], expected[key]), f"{key} differs"
    torch.manual_seed(cfg.train.seed)
    untrained = InverseDynamicsNet(cfg.width).state_dict()
    assert not torch.equal(got["head.weight"], untrained["head.weight"])
    assert np.allclose(instrument.std, np.stack([o[:-1] for o in data.odometry]).reshape(-1, 2).std(0) + 1e-6)


class Killed(RuntimeError):
    """Stands in for the process being killed mid-run."""


class KillableTask(InstrumentTask):
    kill_at: int | None = None

    def loss(self, model, batch, step):
        if step == self.kill_at:
            raise Killed(f"killed at step {step}")
        return super().loss(model, batch, step)


def test_killed_run_resumes_to_the_uninterrupted_weights(smoke_cfg, tmp_path):
    data = random_clips(seed=1)
    cfg = dataclasses.replace(instrument_config(smoke_cfg, steps=20, batch_size=8, seed=2, log_every=5,
                                                checkpoint_every=6), width=8)
    train(InstrumentTask(data, cfg), cfg.train, tmp_path / "straight")
    task = KillableTask(data, cfg)
    task.kill_at = 14
    with pytest.raises(Killed):
        train(task, cfg.train, tmp_path / "killed")
    assert load_checkpoint(tmp_path / "killed" / "checkpoints" / "last.pt")["data_position"] == 12
    task.kill_at = None
    result = train(task, cfg.train, tmp_path / "killed")
    assert (result.start_step, result.step) == (12, 20)
    straight, killed = (load_weights(tmp_path / run / "model.pt") for run in ("straight", "killed"))
    for key in straight:
        assert torch.equal(straight[key], killed[key]), f"{key} differs"
    assert list(pd.read_csv(tmp_path / "killed" / "curves" / "train.csv")["step"]) == [5, 10, 15, 20]
