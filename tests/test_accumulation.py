"""Gradient accumulation: a process's share of the global batch run as micro-batches (``micro_batch_size``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
from test_predictors import SPAN, tiny_cfg, write_cache
from test_preemption import SignalledWindows, Windows, global_batches
from test_train import config

from orbis2.config.params import load_config
from orbis2.config.training import TrainConfig
from orbis2.errors import ConfigError, TrainingStopped
from orbis2.tasks.predictors import PredictorTask, step_generator
from orbis2.train import batch_split, load_checkpoint, load_weights, spawn_cpu_processes, train

ROOT = Path(__file__).resolve().parents[1]
CFG = dict(steps=12, batch_size=6, checkpoint_every=100, ema_decay=0.9)


def _windows_run(out: Path, micro: int | None, task: Windows | None = None) -> list[tuple[int, list[int]]]:
    torch.set_num_threads(1)
    task = task or Windows()
    try:
        train(task, config(**CFG, micro_batch_size=micro), out)
    except TrainingStopped:
        pass
    return task.seen


def _two_processes(out: Path) -> dict[str, list]:
    """Under 2 processes: shares of 3, as one micro-batch and as three of one."""
    return {"whole": _windows_run(out / "w2", None), "micro": _windows_run(out / "w2a3", 1)}


@pytest.mark.slow
def test_accumulated_micro_batches_see_the_global_batches_of_any_split_and_end_at_the_same_weights(tmp_path):
    """W=1 with 2 micro-batches of 3, W=2 with one of 3, W=2 with three of 1 (DDP's no_sync on the first two):
    every optimiser step trains on the global batch of W=1 without accumulation, and the weights agree within
    float tolerance: each split sums the same per-sample gradients in another order."""
    one = _windows_run(tmp_path / "w1", None)
    accumulated = _windows_run(tmp_path / "w1a2", 3)
    assert [len(indices) for _, indices in accumulated] == [3] * 24  # two micro-batches a step
    two = spawn_cpu_processes(_two_processes, 2, tmp_path, timeout_s=180)
    reference = global_batches([[{"seen": one}]], "seen")
    assert sorted(reference) == list(range(12))
    assert global_batches([[{"seen": accumulated}]], "seen") == reference
    assert global_batches([two], "whole") == reference
    assert global_batches([two], "micro") == reference
    base = load_weights(tmp_path / "w1" / "model.pt")
    for name in ("w1a2", "w2", "w2a3"):
        other = load_weights(tmp_path / name / "model.pt")
        for key in base:
            torch.testing.assert_close(other[key], base[key], rtol=1e-5, atol=1e-6)


def test_a_signal_during_accumulation_checkpoints_at_the_optimiser_step_and_resumes_bit_identically(tmp_path):
    """SIGUSR1 in the first micro-batch of step 4: the step's second micro-batch still runs, the checkpoint is
    step 5's, and the resumed run's weights equal the uninterrupted accumulated run's bit for bit."""
    straight = _windows_run(tmp_path / "straight", 3)
    stopped = _windows_run(tmp_path / "stopped", 3, SignalledWindows(at=4))
    assert [step for step, _ in stopped] == [s for s in range(5) for _ in range(2)]  # both halves of step 4
    checkpoint = load_checkpoint(tmp_path / "stopped" / "checkpoints" / "last.pt")
    assert checkpoint["step"] == checkpoint["data_position"] == 5
    resumed = _windows_run(tmp_path / "stopped", 3)
    assert stopped + resumed == straight
    a, b = (load_weights(tmp_path / name / "model.pt") for name in ("straight", "stopped"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_without_accumulation_the_micro_batch_setting_changes_nothing(tmp_path):
    """A cap at or above the share is one micro-batch: the very run of no cap, bit for bit, and the same resume
    fingerprint (the setting is how a share is computed, not what is trained on)."""
    _windows_run(tmp_path / "none", None)
    _windows_run(tmp_path / "cap", 6)
    a, b = (load_weights(tmp_path / name / "model.pt") for name in ("none", "cap"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert config(**CFG, micro_batch_size=2).fingerprint() == config(**CFG).fingerprint()


@pytest.mark.parametrize("batch, world, micro, split", [
    (64, 8, 8, (8, 8, 1)), (64, 64, 8, (1, 1, 1)), (64, 4, 8, (16, 8, 2)), (64, 8, 2, (8, 2, 4)),
    (128, 8, 16, (16, 16, 1)), (128, 2, 16, (64, 16, 4)), (64, 8, None, (8, 8, 1))])
def test_the_global_batch_is_micro_batch_times_processes_times_accumulation(batch, world, micro, split):
    cfg = config(batch_size=batch, micro_batch_size=micro)
    assert batch_split(cfg, world) == split
    share, size, accumulation = split
    assert size * world * accumulation == batch


def test_a_split_that_does_not_come_out_whole_is_refused():
    with pytest.raises(ConfigError, match="batch_size = 64 over 4 processes is 16 samples a process, which "
                                          "micro_batch_size = 6 does not divide; set micro_batch_size to a "
                                          r"divisor of 16 \(e.g. 4, 2, 1\)"):
        batch_split(config(batch_size=64, micro_batch_size=6), 4)
    with pytest.raises(ConfigError, match="batch_size = 64 is not divisible by the 3 processes"):
        batch_split(config(batch_size=64, micro_batch_size=8), 3)
    with pytest.raises(ConfigError, match="micro_batch_size = 0 must be >= 1, or null for no cap"):
        config(micro_batch_size=0)


def test_accumulation_refuses_a_stage_with_a_second_update(tmp_path):
    """The detail tokenizer's discriminator scores the main update's outputs of the same batch."""
    from test_train import Regression

    from orbis2.train import Update

    class TwoUpdates(Regression):
        def extra_updates(self, model):
            last = model[-1]
            return [Update("head", list(last.parameters()), lambda m, batch, step: None)]

    with pytest.raises(ConfigError, match="micro_batch_size = 2 accumulates 4 micro-batches a step, and this "
                                          "stage also trains head on the same batch"):
        train(TwoUpdates(), config(micro_batch_size=2), tmp_path)


def test_a_predictor_accumulates_its_window_batches_with_independent_noise_per_micro_batch(tmp_path, smoke_cfg):
    """A real predictor batch (a dict of window tensors) splits into micro-batches, and each draws its own noise
    (the first the step's noise of a run without accumulation)."""
    cpu = torch.device("cpu")
    seeds = [step_generator(1, 0, 5, cpu, micro).initial_seed() for micro in range(3)]
    assert len(set(seeds)) == 3
    cache = write_cache(tmp_path / "cache", {"train": [SPAN + 7], "val": [SPAN + 5]})
    cfg = tiny_cfg(smoke_cfg, "abstract_tf")
    train_cfg = dataclasses.replace(cfg.train, steps=3, eval_every=0, micro_batch_size=cfg.train.batch_size // 2)
    cfg = dataclasses.replace(cfg, train=train_cfg)
    result = train(PredictorTask("abstract_tf", cfg, smoke_cfg.data, cache), cfg.train, tmp_path / "run")
    assert result.step == 3 and torch.isfinite(torch.tensor(result.metrics["loss"]))


def test_the_paper_profile_caps_a_gpu_at_what_80_gb_holds_and_the_small_profiles_do_not_accumulate():
    for profile in ("smoke", "default", "gpu"):
        cfg = load_config(ROOT / "params.yaml", profile)
        assert all(cfg.section(s).train.micro_batch_size is None for s in ("detail", "abstract_df", "action"))
    paper = load_config(ROOT / "params.yaml", "paper")
    for stage, (batch, micro) in {"detail": (64, 8), "detail_distill": (64, 8), "abstract_df": (128, 16),
                                  "abstract_tf": (128, 16), "action": (128, 16)}.items():
        train_cfg: TrainConfig = paper.section(stage).train
        assert (train_cfg.batch_size, train_cfg.micro_batch_size) == (batch, micro)
        assert batch_split(train_cfg, 8)[2] == 1 and batch_split(train_cfg, 64)[2] == 1
        assert batch_split(train_cfg, 4)[2] == 2
