"""The shared training loop: convergence, bit-identical resume, DDP equivalence, GAN updates."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pandas as pd
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from orbis2.errors import ConfigError
from orbis2.train import (
    DataSpec,
    ResumeError,
    TrainConfig,
    Update,
    load_checkpoint,
    load_weights,
    lr_at,
    spawn_cpu_processes,
    train,
)

from conftest import train_config

DIM = 6


class Killed(RuntimeError):
    """Stands in for the process being killed mid-run."""


class Regression:
    """A small MLP fitting a fixed random linear map.

    Batch ``i`` of the global stream is drawn from ``(seed, i)`` and each rank keeps
    its slice, so the data position matters on resume and two ranks together see
    exactly the single-process batch. ``noise`` perturbs inputs from the global torch
    RNG (as flow matching does), so the RNG state matters on resume too.
    """

    def __init__(self, fixed_batch: bool = False, noise: float = 0.0, kill_at: int | None = None):
        self.fixed_batch, self.noise, self.kill_at = fixed_batch, noise, kill_at
        self.target = torch.randn(DIM, 1, generator=torch.Generator().manual_seed(99))
        self.evaluated: list[tuple[int, bool, bool]] = []

    def build_model(self) -> nn.Module:
        return nn.Sequential(nn.Linear(DIM, 32), nn.LayerNorm(32), nn.Tanh(), nn.Linear(32, 1))

    def batches(self, spec: DataSpec):
        index = spec.start
        while True:
            g = torch.Generator().manual_seed(spec.seed * 1_000_003 + (0 if self.fixed_batch else index))
            x = torch.randn(spec.batch_size * spec.world_size, DIM, generator=g)
            lo = spec.rank * spec.batch_size
            x = x[lo: lo + spec.batch_size]
            yield x, x @ self.target
            index += 1

    def loss(self, model, batch, step):
        if step == self.kill_at:
            raise Killed(f"killed at step {step}")
        x, y = batch
        if self.noise:
            x = x + self.noise * torch.randn_like(x)
        loss = F.mse_loss(model(x), y)
        return loss, {"rmse": loss.detach().sqrt()}

    def evaluate(self, model, step):
        """Draws from the global RNG on purpose: training's streams must not notice."""
        self.evaluated.append((step, model.training, any(p.requires_grad for p in model.parameters())))
        x = torch.randn(64, DIM)
        return {"val_loss": F.mse_loss(model(x), x @ self.target).item()}


class TinyGan(nn.Module):
    def __init__(self):
        super().__init__()
        self.generator = nn.Linear(2, 2)
        self.discriminator = nn.Sequential(nn.Linear(2, 16), nn.LeakyReLU(0.2), nn.Linear(16, 1))

    def forward(self, z, real=None):
        """Generator logits on fakes, or (with ``real``) discriminator logits on both."""
        if real is None:
            return self.discriminator(self.generator(z))
        return self.discriminator(real), self.discriminator(self.generator(z).detach())


class Gan:
    """Generator and discriminator trained alternately; the discriminator starts late."""

    def __init__(self, disc_start: int = 0):
        self.disc_start = disc_start

    def build_model(self) -> nn.Module:
        return TinyGan()

    def batches(self, spec: DataSpec):
        index = spec.start
        while True:
            g = torch.Generator().manual_seed(spec.seed * 1_000_003 + index)
            z = torch.randn(spec.batch_size * spec.world_size, 2, generator=g)
            real = 3.0 + 0.5 * torch.randn(spec.batch_size * spec.world_size, 2, generator=g)
            lo = spec.rank * spec.batch_size
            yield z[lo: lo + spec.batch_size], real[lo: lo + spec.batch_size]
            index += 1

    def loss(self, model, batch, step):
        z, _ = batch
        return F.softplus(-model(z)).mean(), {}

    def disc_loss(self, model, batch, step):
        if step < self.disc_start:
            return None
        z, real = batch
        real_logits, fake_logits = model(z, real)
        return F.softplus(-real_logits).mean() + F.softplus(fake_logits).mean(), {}

    def extra_updates(self, model):
        return [Update("disc", list(model.discriminator.parameters()), self.disc_loss, lr_scale=0.5)]


class Recorder:
    def __init__(self):
        self.calls: list[tuple[int, dict]] = []

    def log_metrics(self, metrics, step):
        self.calls.append((step, dict(metrics)))


def config(**overrides) -> TrainConfig:
    values = dict(steps=30, batch_size=8, lr=1e-2, weight_decay=0.01, warmup_steps=4, min_lr_ratio=0.1,
                  grad_clip=1.0, ema_decay=0.9, mixed_precision="none", log_every=5, checkpoint_every=7, seed=3)
    return train_config(**{**values, **overrides})


def saved_state(out_dir: Path) -> dict[str, dict[str, torch.Tensor]]:
    return {"model": load_weights(out_dir / "model.pt"), "raw": load_weights(out_dir / "model.pt", raw=True)}


def assert_states_equal(a: dict, b: dict) -> None:
    for which in a:
        assert a[which].keys() == b[which].keys()
        for key in a[which]:
            assert torch.equal(a[which][key], b[which][key]), f"{which}.{key} differs"


def test_lr_schedule_warms_up_then_decays_to_floor():
    cfg = config(steps=100, lr=1.0, warmup_steps=10, min_lr_ratio=0.1)
    assert lr_at(0, cfg) == pytest.approx(0.1)
    assert lr_at(9, cfg) == pytest.approx(1.0)
    assert lr_at(10, cfg) == pytest.approx(1.0)
    assert lr_at(55, cfg) == pytest.approx(0.55)  # half-way down the cosine
    assert lr_at(100, cfg) == pytest.approx(0.1)
    assert lr_at(500, cfg) == pytest.approx(0.1)
    rates = [lr_at(s, cfg) for s in range(10, 101)]
    assert all(a >= b for a, b in zip(rates, rates[1:]))
    assert lr_at(0, config(warmup_steps=0, lr=0.5)) == pytest.approx(0.5)


def test_config_rejects_impossible_values():
    with pytest.raises(ConfigError, match="optimizer"):
        config(optimizer="sgd")
    with pytest.raises(ConfigError, match="ema_decay"):
        config(ema_decay=1.0)
    assert config(betas=[0.9, 0.95]).betas == (0.9, 0.95)


def test_loss_falls_on_a_fixed_batch(tmp_path):
    recorder = Recorder()
    result = train(Regression(fixed_batch=True), config(steps=150, lr=3e-3, log_every=10, checkpoint_every=1000),
                   tmp_path, logger=recorder)
    losses = [metrics["loss"] for _, metrics in result.history]
    assert losses[-1] < 0.02 * losses[0]
    assert recorder.calls == result.history
    assert {"loss", "rmse", "grad_norm", "lr"} <= set(result.metrics)
    # The EMA weights (what model.pt serves) trail the raw ones but have learned too.
    task, state = Regression(fixed_batch=True), saved_state(tmp_path)
    x, y = next(iter(task.batches(DataSpec(rank=0, world_size=1, batch_size=8, seed=3, start=0, num_workers=0))))
    model = task.build_model()
    model.load_state_dict(state["model"])
    assert F.mse_loss(model(x), y).item() < 0.05 * losses[0]
    assert not torch.equal(state["model"]["0.weight"], state["raw"]["0.weight"])


def test_resume_after_kill_is_bit_identical(tmp_path):
    cfg = config(steps=30, checkpoint_every=7)
    train(Regression(noise=0.1), cfg, tmp_path / "straight")
    with pytest.raises(Killed):
        train(Regression(noise=0.1, kill_at=17), cfg, tmp_path / "killed")
    checkpoint = load_checkpoint(tmp_path / "killed" / "checkpoints" / "last.pt")
    assert checkpoint["step"] == checkpoint["data_position"] == 14
    assert not (tmp_path / "killed" / "model.pt").exists()
    # Evaluation is bookkeeping: turning it on for the rest of the run changes nothing.
    task = Regression(noise=0.1)
    result = train(task, dataclasses.replace(cfg, eval_every=5), tmp_path / "killed")
    assert (result.start_step, result.step) == (14, 30)
    assert task.evaluated == [(15, False, False), (20, False, False), (25, False, False), (30, False, False)]
    assert [step for step, metrics in result.history if "val_loss" in metrics] == [15, 20, 25, 30]
    assert_states_equal(saved_state(tmp_path / "straight"), saved_state(tmp_path / "killed"))
    # The curves carry every logged row once: those before the kill come back from the checkpoint.
    straight, killed = (pd.read_csv(tmp_path / run / "curves" / "train.csv") for run in ("straight", "killed"))
    assert list(killed["step"]) == list(range(cfg.log_every, 31, cfg.log_every))
    spans_resume = killed["step"] == 15  # averages only step 15, the first after the resume at 14
    pd.testing.assert_frame_equal(straight[~spans_resume], killed[~spans_resume])
    assert list(pd.read_csv(tmp_path / "killed" / "curves" / "eval.csv")["step"]) == [15, 20, 25, 30]
    # A second re-run finds the work done and leaves the weights alone.
    again = train(Regression(noise=0.1), cfg, tmp_path / "killed")
    assert again.start_step == again.step == 30
    assert_states_equal(saved_state(tmp_path / "straight"), saved_state(tmp_path / "killed"))


def test_resume_with_a_changed_config_is_refused(tmp_path):
    train(Regression(), config(steps=5), tmp_path)
    train(Regression(), config(steps=5, log_every=1), tmp_path)  # bookkeeping may change
    with pytest.raises(ResumeError) as caught:
        train(Regression(), config(steps=5, lr=5e-3), tmp_path)
    message = str(caught.value)
    assert str(tmp_path / "checkpoints" / "last.pt") in message
    assert "lr: 0.01 -> 0.005" in message and "Delete" in message


@pytest.mark.parametrize("damage", ["bit flip", "truncated", "foreign"])
def test_corrupt_or_foreign_checkpoint_is_refused_by_name(tmp_path, damage):
    cfg = config(steps=6, checkpoint_every=3)
    with pytest.raises(Killed):
        train(Regression(kill_at=4), cfg, tmp_path)
    path = tmp_path / "checkpoints" / "last.pt"
    blob = bytearray(path.read_bytes())
    if damage == "bit flip":
        blob[len(blob) * 3 // 4] ^= 0x10  # inside the tensors, where torch.load alone notices nothing
    elif damage == "truncated":
        del blob[len(blob) // 2:]
    else:
        blob = bytearray()
        torch.save(nn.Linear(2, 2).state_dict(), path)
        blob = bytearray(path.read_bytes())
    path.write_bytes(bytes(blob))
    with pytest.raises(ResumeError) as caught:
        train(Regression(), cfg, tmp_path)
    assert str(path) in str(caught.value) and "delete" in str(caught.value)
    assert not (tmp_path / "model.pt").exists()


def _ddp_worker(out_dir: Path):
    """Two runs in one process, as a stage that trains twice under torchrun would do."""
    torch.set_num_threads(1)
    return [train(Regression(), config(steps=12), out_dir / "regression").history,
            train(Gan(disc_start=3), config(steps=8, ema_decay=None), out_dir / "gan").history]


def test_ddp_on_two_cpu_processes_matches_one_process(tmp_path):
    single = [train(Regression(), config(steps=12), tmp_path / "single" / "regression").history,
              train(Gan(disc_start=3), config(steps=8, ema_decay=None), tmp_path / "single" / "gan").history]
    rank0, rank1 = spawn_cpu_processes(_ddp_worker, 2, tmp_path / "ddp", timeout_s=120)
    assert rank0 == rank1  # metrics are averaged over ranks, so every rank logs the same
    for single_history, ddp_history in zip(single, rank0):
        assert [step for step, _ in single_history] == [step for step, _ in ddp_history]
        for (_, a), (_, b) in zip(single_history, ddp_history):
            for key in ("loss", "lr"):
                assert a[key] == pytest.approx(b[key], rel=1e-5, abs=1e-7)
    for task in ("regression", "gan"):
        a, b = saved_state(tmp_path / "single" / task), saved_state(tmp_path / "ddp" / task)
        for which in a:
            for key in a[which]:
                torch.testing.assert_close(a[which][key], b[which][key], rtol=1e-5, atol=1e-6)


def test_gan_task_steps_generator_and_discriminator_separately(tmp_path):
    task = Gan(disc_start=2)
    torch.manual_seed(3)  # the loop builds the model under the config seed
    initial = task.build_model().state_dict()
    train(task, config(steps=2, ema_decay=None, checkpoint_every=100), tmp_path / "early")
    early = load_weights(tmp_path / "early" / "model.pt")
    # The generator's loss back-propagates into the discriminator, but only its own optimiser steps.
    assert all(torch.equal(early[k], initial[k]) for k in initial if k.startswith("discriminator"))
    assert not torch.equal(early["generator.weight"], initial["generator.weight"])

    result = train(task, config(steps=120, lr=2e-2, ema_decay=None, log_every=10), tmp_path / "full")
    final = load_weights(tmp_path / "full" / "model.pt")
    assert all(not torch.equal(final[k], initial[k]) for k in initial)
    assert {"loss", "loss_disc", "grad_norm_disc"} <= set(result.metrics)
    checkpoint = load_checkpoint(tmp_path / "full" / "checkpoints" / "last.pt")
    assert set(checkpoint["optimizers"]) == {"main", "disc"}
    disc_lr = checkpoint["optimizers"]["disc"]["param_groups"][0]["lr"]
    assert disc_lr == pytest.approx(0.5 * lr_at(119, config(steps=120, lr=2e-2)))


def test_ema_warmup_follows_training_over_short_runs(tmp_path):
    """After a short run the EMA weights sit closer to the trained weights than to the initialisation."""
    from orbis2.train import ema_decay_at

    assert ema_decay_at(0, 0.9999) == pytest.approx(0.1)
    assert ema_decay_at(10_000, 0.99) == 0.99
    task = Regression()
    cfg = config(steps=40, ema_decay=0.999, lr=2e-2)
    torch.manual_seed(cfg.seed)  # as the loop does before building the model
    init = {k: v.clone() for k, v in task.build_model().state_dict().items()}
    out = tmp_path / "short"
    train(task, cfg, out)
    state = saved_state(out)
    ema, raw = state["model"], state["raw"]
    to_raw = sum(float((ema[k] - raw[k]).pow(2).sum()) for k in raw if raw[k].is_floating_point())
    to_init = sum(float((ema[k] - init[k]).pow(2).sum()) for k in raw if raw[k].is_floating_point())
    assert to_raw < to_init
