"""What a predictor sees is built once (orbis2.hierarchy): a training step and a rollout step on the same clip
hand the networks the same context, conditioning and steering tensors, bit for bit."""

import numpy as np
import pytest
import torch
from test_predictors import SPAN, tiny_cfg, write_cache

from orbis2.hierarchy import condition_frames, detail_condition, detail_condition_slots, steering_rows
from orbis2.latents import collate
from orbis2.rollout import cascaded_rollout, rollout_schedule, steering_sequences
from orbis2.tasks.predictors import PredictorTask, predictor_meta


class Recorder:
    """A velocity function that keeps the inputs a network would get, and predicts zero velocity."""

    def __init__(self):
        self.calls = []

    def __call__(self, x, tau, **cond):
        self.calls.append((x.clone(), cond))
        return torch.zeros_like(x)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One train clip with odometry (row r: speed r, yaw rate -r / 10) and several windows."""
    return write_cache(tmp_path_factory.mktemp("cache"), {"train": [SPAN + 6], "val": [SPAN + 5]})


def training_inputs(stage, cache, smoke_cfg, window):
    """The window's batch and what the stage's training step hands its network (no augmentation)."""
    task = PredictorTask(stage, tiny_cfg(smoke_cfg, stage), smoke_cfg.data, cache)
    batch = collate([task.train_set[window]])
    network = Recorder()
    task.objective(network, batch, torch.Generator().manual_seed(0), augment=False)
    (frames, cond), = network.calls
    return task, batch, frames, cond


def rollout_step(task, cache, cfg, window, steered):
    """Step 0 of a cascaded rollout of the same clip, its last context frame at the window's anchor, with the
    real subgoal (unsteered) or the clip's odometry as the command, scaled as the predictor's file says
    (steered); returns both networks' inputs."""
    data = cfg.data
    clip, anchor = (int(v) for v in task.train_set.items[window])
    offset = task.train_set.clips[clip]["offset"]
    arrays = cache.arrays("train")
    step, = rollout_schedule(data, anchor, 1)

    def latents(kind, frames):
        return cache.normalize(kind, arrays[kind][offset + np.asarray(frames)])[None]

    odometry = arrays["odometry"][offset:].astype(np.float64)
    top, bottom = Recorder(), Recorder()
    cascaded_rollout(
        top, bottom, latents("detail", step.detail_context), latents("abstract", step.abstract_context), 1,
        torch.Generator().manual_seed(0), abstract_nfe=1, detail_nfe=1, abstract_hz=data.abstract_hz,
        detail_hz=data.detail_hz, kv_cache=False,
        subgoals=None if steered else latents("abstract", [step.abstract_target]),
        steering=steering_sequences([step], odometry[:, 0], odometry[:, 1],
                                    predictor_meta(task.stage, cfg, cache, {})["steering"]["scale"])[None]
        if steered else None)
    return top.calls, bottom.calls


@pytest.mark.parametrize("window", [0, 3])
def test_the_detail_predictor_sees_the_same_inputs_in_training_and_rollout(cache, smoke_cfg, window):
    task, batch, frames, cond = training_inputs("detail", cache, smoke_cfg, window)
    _, (rolled,) = rollout_step(task, cache, smoke_cfg, window, steered=False)
    frames_r, cond_r = rolled
    n_context = smoke_cfg.data.detail_context
    assert torch.equal(frames_r[:, :n_context], frames[:, :n_context])
    assert torch.equal(frames_r[:, :n_context], batch["detail"][:, :n_context])
    assert torch.equal(cond_r["cond_frames"], cond["cond_frames"])
    assert tuple(cond_r["cond_mask"]) == tuple(cond["cond_mask"]) == tuple(sorted(detail_condition_slots(
        smoke_cfg.data)))
    assert cond_r["frame_rate"] == cond["frame_rate"] == smoke_cfg.data.detail_hz
    assert cond["cond_frames"].abs().sum() > 0  # real latents, not zeros on both sides


@pytest.mark.parametrize("window", [0, 3])
def test_the_steered_predictor_sees_the_same_inputs_in_training_and_rollout(cache, smoke_cfg, window):
    task, batch, frames, cond = training_inputs("action", cache, smoke_cfg, window)
    (rolled,), _ = rollout_step(task, cache, smoke_cfg, window, steered=True)
    frames_r, cond_r = rolled
    n_context = smoke_cfg.data.abstract_context
    assert torch.equal(frames_r[:, :n_context], frames[:, :n_context])
    assert torch.equal(cond_r["steering"], cond["steering"])
    assert not cond["steering_drop"].any() and "steering_drop" not in cond_r  # known steering, no dropout
    assert cond_r["frame_rate"] == cond["frame_rate"] == smoke_cfg.data.abstract_hz
    assert cond["steering"].abs().sum() > 0


def test_steering_rows_run_from_the_last_context_frame_to_the_prediction(smoke_cfg):
    data = smoke_cfg.data
    step, = rollout_schedule(data, 40, 1)
    assert steering_rows(data, 40) == range(step.abstract_context[-1], step.abstract_target) == range(40, 45)


def test_training_conditioning_is_the_rollout_builder_on_the_slotted_latents(smoke_cfg):
    data = smoke_cfg.data
    slow = torch.randn(2, data.abstract_window, 4, 3, 4)
    frames, mask = detail_condition(slow, data)
    built, slots = condition_frames(slow[:, data.abstract_context - 1], slow[:, -1], data.detail_context,
                                    data.detail_window - data.detail_context)
    assert torch.equal(frames, built)
    assert mask[0].nonzero().flatten().tolist() == list(slots)
