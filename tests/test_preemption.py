"""Stopping on a scheduler's signal, resuming at another number of processes, and the global sample order."""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import signal
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.distributed as dist
from test_predictors import SPAN, tiny_cfg, write_cache
from test_train import DIM, Regression, assert_states_equal, config, saved_state
from torch import nn

from orbis2.errors import TrainingStopped
from orbis2.tasks.predictors import PredictorTask, window_index_batches
from orbis2.train import (
    DataSpec,
    ResumeError,
    _save_checkpoint,
    load_checkpoint,
    load_weights,
    spawn_cpu_processes,
    train,
)


def rank() -> int:
    return dist.get_rank() if dist.is_initialized() else 0


class Signalled:
    """A task that sends its own process ``signum`` in the middle of step ``at`` on rank ``on_rank``, as a
    scheduler would (Slurm's ``--signal=USR1@<seconds>``, or SIGTERM at preemption)."""

    def __init__(self, at: int | None = None, signum: int = signal.SIGUSR1, on_rank: int = 0, **kwargs):
        super().__init__(**kwargs)
        self.at, self.signum, self.on_rank = at, signum, on_rank

    def loss(self, model, batch, step):
        if step == self.at and rank() == self.on_rank:
            os.kill(os.getpid(), self.signum)
        return super().loss(model, batch, step)


class SignalledRegression(Signalled, Regression):
    pass


@pytest.mark.parametrize("signum", [signal.SIGUSR1, signal.SIGURG, signal.SIGTERM])
def test_a_signal_checkpoints_within_one_step_and_the_resume_is_bit_identical(tmp_path, signum):
    cfg = config(steps=20, checkpoint_every=7)
    handler = signal.getsignal(signum)
    train(Regression(noise=0.1), cfg, tmp_path / "straight")
    with pytest.raises(TrainingStopped) as stopped:
        train(SignalledRegression(at=10, signum=signum, noise=0.1), cfg, tmp_path / "stopped")
    assert (stopped.value.step, stopped.value.signal_name) == (11, signum.name)  # the step it arrived in
    assert f"stopped by {signum.name} at step 11 of 20" in str(stopped.value)
    checkpoint = load_checkpoint(tmp_path / "stopped" / "checkpoints" / "last.pt")
    assert checkpoint["step"] == checkpoint["data_position"] == 11
    assert not (tmp_path / "stopped" / "model.pt").exists()
    assert signal.getsignal(signum) == handler  # the process's own handling is back
    resumed = train(Regression(noise=0.1), cfg, tmp_path / "stopped")  # the requeued job
    assert (resumed.start_step, resumed.step) == (11, 20)
    assert_states_equal(saved_state(tmp_path / "straight"), saved_state(tmp_path / "stopped"))


class Windows:
    """Windows 0..n-1 of a synthetic split drawn through the predictors' sampler, recording the windows of every
    step; the batches depend on the global batch only (``global_order``)."""

    global_order = True

    def __init__(self, n: int = 30):
        self.n, self.seen = n, []
        self.features = torch.randn(n, DIM, generator=torch.Generator().manual_seed(5))

    def build_model(self) -> nn.Module:
        return nn.Sequential(nn.Linear(DIM, 16), nn.Tanh(), nn.Linear(16, 1))

    def batches(self, spec: DataSpec):
        for indices in window_index_batches(self.n, spec, "train"):
            yield torch.tensor(indices)

    def loss(self, model, batch, step):
        self.seen.append((step, batch.tolist()))
        x = self.features[batch]
        return (model(x) - x.sum(1, keepdim=True)).pow(2).mean(), {}


class SignalledWindows(Signalled, Windows):
    pass


WINDOWS_CFG = dict(steps=16, batch_size=6, checkpoint_every=100, ema_decay=0.9)


def _windows(out: Path, straight: bool, at: int | None) -> dict:
    """A leg of the run in ``out/stopped`` (and, with ``straight``, the whole run in ``out/straight`` first)."""
    torch.set_num_threads(1)
    cfg = config(**WINDOWS_CFG)
    seen = {}
    if straight:
        task = Windows()
        train(task, cfg, out / "straight")
        seen["straight"] = task.seen
    task = SignalledWindows(at=at, on_rank=1 if dist.is_initialized() else 0)
    try:
        train(task, cfg, out / "stopped")
    except TrainingStopped:
        pass
    return {**seen, "stopped": task.seen}


def global_batches(legs: list[list[dict]], which: str) -> dict[int, list[int]]:
    """{step: the sorted windows every rank saw at that step} over the legs (each a list of ranks' records)."""
    steps: dict[int, list[int]] = {}
    for ranks in legs:
        for record in ranks:
            for step, indices in record[which]:
                steps.setdefault(step, []).extend(indices)
    return {step: sorted(indices) for step, indices in steps.items()}


def test_a_run_resumes_at_another_number_of_processes_on_the_same_global_batches(tmp_path):
    """2 processes to step 4 (rank 1 alone signalled: both stop), 1 process to step 10, 2 processes to the end:
    every step sees the global batch of the uninterrupted run; the weights differ only by the order of the
    gradients' sums. (tests/test_multinode.py checks a signalled and resumed run of 2 processes bit for bit.)"""
    first = spawn_cpu_processes(_windows, 2, tmp_path, True, 3, timeout_s=180)
    checkpoint = load_checkpoint(tmp_path / "stopped" / "checkpoints" / "last.pt")
    assert (checkpoint["step"], checkpoint["world_size"]) == (4, 2)
    assert [max(step for step, _ in rank["stopped"]) for rank in first] == [3, 3]  # no rank trained on
    second = [_windows(tmp_path, False, 9)]  # resumes the 2 processes' checkpoint alone, stops at 10
    checkpoint = load_checkpoint(tmp_path / "stopped" / "checkpoints" / "last.pt")
    assert (checkpoint["step"], checkpoint["world_size"]) == (10, 1)
    third = spawn_cpu_processes(_windows, 2, tmp_path, False, None, timeout_s=180)
    straight = global_batches([first], "straight")
    legs = global_batches([first, second, third], "stopped")
    assert sorted(legs) == sorted(straight) == list(range(16))
    assert legs == straight
    assert Counter(i for b in legs.values() for i in b) == Counter(i for b in straight.values() for i in b)
    a, b = (load_weights(tmp_path / name / "model.pt") for name in ("straight", "stopped"))
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-4, atol=1e-5)


def test_a_task_whose_batches_follow_the_ranks_resumes_only_at_its_number_of_processes(tmp_path):
    cfg = config(steps=4)
    train(Regression(), cfg, tmp_path)
    path = tmp_path / "checkpoints" / "last.pt"
    saved = load_checkpoint(path)
    _save_checkpoint({**saved, "world_size": 2, "rng": saved["rng"] * 2}, path)  # as 2 processes write it
    with pytest.raises(ResumeError, match=f"{path} was written by 2 processes, this run has 1, and this task's "
                                          "batches depend on the number of processes; resume with 2 or delete"):
        train(Regression(), cfg, tmp_path)


@pytest.mark.parametrize("repeats", [None, np.array([1, 3, 1, 1, 2] * 5)])
def test_no_window_repeats_or_goes_missing_within_an_epoch_for_any_number_of_processes(repeats):
    n, size = 25, 6
    pool = Counter(range(n)) if repeats is None else Counter(dict(enumerate(repeats.tolist())))
    per_epoch = sum(pool.values()) // size
    reference = None
    for world in (1, 2, 3):
        ranks = [window_index_batches(n, DataSpec(r, world, size // world, seed=4, start=0, num_workers=0),
                                      "train", repeats) for r in range(world)]
        batches = [[i for stream in ranks for i in next(stream)] for _ in range(2 * per_epoch)]
        assert all(len(batch) == size for batch in batches)
        for epoch in range(2):
            seen = Counter(i for batch in batches[epoch * per_epoch:(epoch + 1) * per_epoch] for i in batch)
            assert seen <= pool  # nothing more often than it is listed
            assert sum((pool - seen).values()) == sum(pool.values()) % size  # only the remainder is left out
        batches = [sorted(batch) for batch in batches]
        reference = reference or batches
        assert batches == reference  # the same global batches, whatever the number of processes
        # A resume mid-epoch continues the same order, reading nothing before it.
        start = per_epoch + 1
        resumed = [window_index_batches(n, DataSpec(r, world, size // world, 4, start, 0), "train", repeats)
                   for r in range(world)]
        assert [sorted(i for stream in resumed for i in next(stream)) for _ in range(3)] == batches[start:start + 3]


class SignalledLoading(PredictorTask):
    """Sends SIGUSR1 during step ``at`` to its process and to its DataLoader's workers, as Slurm signals every
    process of a job step."""

    def __init__(self, *args, at: int):
        super().__init__(*args)
        self.at = at

    def loss(self, model, batch, step):
        if step == self.at:
            workers = multiprocessing.active_children()
            assert workers, "no DataLoader workers to signal"
            for pid in [os.getpid(), *(worker.pid for worker in workers)]:
                os.kill(pid, signal.SIGUSR1)
        return super().loss(model, batch, step)


def test_data_loader_workers_outlive_the_signal_and_the_resume_is_bit_identical(tmp_path, smoke_cfg):
    cache = write_cache(tmp_path / "cache", {"train": [SPAN + 7], "val": [SPAN + 5]})
    cfg = tiny_cfg(smoke_cfg, "abstract_tf")
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=8, eval_every=0, num_workers=1))
    args = ("abstract_tf", cfg, smoke_cfg.data, cache)
    train(PredictorTask(*args), cfg.train, tmp_path / "straight")
    with pytest.raises(TrainingStopped, match="stopped by SIGUSR1 at step 4 of 8"):
        train(SignalledLoading(*args, at=3), cfg.train, tmp_path / "stopped")
    assert train(PredictorTask(*args), cfg.train, tmp_path / "stopped").start_step == 4
    straight, stopped = (load_weights(tmp_path / name / "model.pt") for name in ("straight", "stopped"))
    assert all(torch.equal(straight[k], stopped[k]) for k in straight)
