"""Tokenizer training tasks: the resumable image stream, both tasks in the loop, scale, FID and the saved file."""

from __future__ import annotations

import dataclasses
import itertools
import warnings

import numpy as np
import pytest
import torch
from test_shards import make_raw
from torch import nn

from orbis2.data import shards
from orbis2.data.shards import write_shards
from orbis2.models.files import load_tokenizer
from orbis2.models.tokenizer import build_detail_tokenizer
from orbis2.tasks.tokenizers import (
    AbstractTokenizerTask,
    DetailTokenizerTask,
    _train_refs,
    frame_batches,
    image_batches,
    latent_statistics,
    read_frames,
    train_detail_tokenizer,
)
from orbis2.train import DataSpec, TrainConfig, load_weights, train

from conftest import train_config


@pytest.fixture(scope="module")
def shard_root(tmp_path_factory, smoke_cfg):
    """Three 30-frame train clips and one val clip at the smoke resolution."""
    tmp = tmp_path_factory.mktemp("tok_shards")
    make_raw(tmp / "raw", smoke_cfg, episodes=(("train", 3, 30), ("val", 1, 30)))
    write_shards(tmp / "raw", tmp / "shards", smoke_cfg.data, smoke_cfg.shards)
    return tmp / "shards"


class Recorder:
    def __init__(self):
        self.calls: list[tuple[int, dict]] = []

    def log_metrics(self, metrics, step):
        self.calls.append((step, dict(metrics)))


def spec(start=0, rank=0, world=1, batch=4, seed=5):
    return DataSpec(rank=rank, world_size=world, batch_size=batch, seed=seed, start=start, num_workers=0)


def take(stream, n):
    return [next(stream) for _ in range(n)]


def test_stream_is_deterministic_and_resumes_without_decoding_skipped_frames(shard_root, monkeypatch):
    # 3 clips x 4 frames = 12 frames per epoch, so 9 batches of 4 span three epochs.
    fresh = take(image_batches(shard_root, spec(), per_clip=4), 9)
    again = take(image_batches(shard_root, spec(), per_clip=4), 9)
    assert all(torch.equal(a, b) for a, b in zip(fresh, again))
    assert fresh[0].shape == (4, 3, 72, 128) and fresh[0].dtype == torch.float32
    assert -1.0 <= float(torch.cat(fresh).min()) and float(torch.cat(fresh).max()) <= 1.0
    epochs = [torch.cat(fresh[3 * e:3 * e + 3]) for e in range(3)]
    assert not torch.equal(epochs[0], epochs[1])  # epochs are re-drawn, not replayed

    decoded = []
    original = shards.Clip.frames
    monkeypatch.setattr(shards.Clip, "frames", lambda clip, idx: decoded.extend(idx) or original(clip, idx))
    resumed = take(image_batches(shard_root, spec(start=5), per_clip=4), 4)
    assert all(torch.equal(a, b) for a, b in zip(resumed, fresh[5:]))
    assert len(decoded) == 4 * 4  # only the frames of the batches it yields

    with_threads = take(image_batches(shard_root, dataclasses.replace(spec(), num_workers=2), per_clip=4), 4)
    assert all(torch.equal(a, b) for a, b in zip(with_threads, fresh))


def test_ranks_read_different_clips(shard_root):
    first = [take(image_batches(shard_root, spec(rank=r, world=2, batch=2), per_clip=4), 1)[0] for r in (0, 1)]
    assert not torch.equal(first[0], first[1])


def test_evaluation_frames_are_fixed(shard_root):
    frames = read_frames(shard_root, "val", 6, seed=1)
    assert frames.shape == (6, 72, 128, 3) and frames.dtype == np.uint8
    batches = list(frame_batches(shard_root, "val", 6, 4, seed=1))
    assert [len(b) for b in batches] == [4, 2]
    np.testing.assert_array_equal(((torch.cat(batches) + 1) * 127.5).round().byte().permute(0, 2, 3, 1), frames)


class IdentityEncoder(nn.Module):
    def __init__(self):
        super().__init__()
        self.anchor = nn.Parameter(torch.zeros(()))

    def encode(self, images):
        return images


def test_latent_statistics_global_and_per_position():
    g = torch.Generator().manual_seed(0)
    template = torch.randn(3, 16, 16, generator=g)
    spread = torch.tensor([0.5, 1.0, 2.0])[:, None, None]
    frames = [template + spread * torch.randn(8, 3, 16, 16, generator=g) for _ in range(8)]
    scale, shift, stats = latent_statistics(IdentityEncoder(), frames, per_position=False)
    assert shift is None and float(scale) == pytest.approx(stats["latent_scale"])
    expected_var = 1.0 + float(spread.square().mean())  # template variance + mean noise variance
    assert stats["latent_scale"] == pytest.approx(expected_var ** -0.5, rel=0.1)
    assert stats["template_share"] == pytest.approx(1.0 / expected_var, rel=0.15)
    scale, shift, _ = latent_statistics(IdentityEncoder(), frames, per_position=True)
    assert float(((shift - template) / spread).abs().max()) < 0.6  # 64 samples: standard error 1/8 of the spread
    torch.testing.assert_close(scale, 1.0 / spread.flatten(), rtol=0.08, atol=0)


def tiny_train(**overrides) -> TrainConfig:
    values = dict(steps=8, batch_size=4, lr=2e-3, warmup_steps=1, log_every=1, eval_every=8, checkpoint_every=4,
                  mixed_precision="none", optimizer="adam", betas=(0.5, 0.9), seed=3)
    return train_config(**{**values, **overrides})


def fake_inception(path):
    """A TorchScript stand-in for the FID network: image -> a small feature vector."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.script(nn.Sequential(nn.AdaptiveAvgPool2d(3), nn.Flatten())).save(str(path))


def test_discriminator_waits_for_disc_start(shard_root, smoke_cfg, tmp_path):
    tc = dataclasses.replace(smoke_cfg.tokenizer_detail, train=tiny_train(steps=2, eval_every=0), disc_start=2)
    task = DetailTokenizerTask(tc, shard_root, tmp_path)
    torch.manual_seed(tc.train.seed)  # the loop builds the model under the config seed
    initial = task.build_model().state_dict()
    train(task, tc.train, tmp_path)
    final = load_weights(tmp_path / "model.pt")
    assert all(torch.equal(final[k], v) for k, v in initial.items() if k.startswith("discriminator."))
    assert not torch.equal(final["tokenizer.decoder.conv_out.weight"], initial["tokenizer.decoder.conv_out.weight"])


def test_detail_tokenizer_stage_trains_saves_and_resumes(shard_root, smoke_cfg, tmp_path):
    tc = dataclasses.replace(smoke_cfg.tokenizer_detail, train=tiny_train(), disc_start=4, eval_images=4,
                             fid_images=6, scale_images=4)
    cfg = smoke_cfg.with_section("tokenizer_detail", tc)
    fake_inception(tmp_path / "inception_v3_fid.pt")
    out, log = tmp_path / "detail", Recorder()
    metrics = train_detail_tokenizer(cfg, shard_root, out, tmp_path, log)

    steps = [(step, m) for step, m in log.calls if "loss" in m]
    # Metrics logged at step s describe the update of step s - 1: the discriminator joins at update 4.
    assert [("loss_disc" in m) for _, m in steps] == [s - 1 >= 4 for s, _ in steps]
    assert all(("g_loss" in m) == (s - 1 >= 4) for s, m in steps)
    assert np.mean([m["l1"] for _, m in steps[-3:]]) < np.mean([m["l1"] for _, m in steps[:2]])

    assert {"val_psnr", "val_ssim", "val_psnr_continuous", "val_perplexity", "val_dead_codes",
            "val_used_fraction", "rfid", "latent_scale", "steps"} <= set(metrics)
    assert metrics["steps"] == 8 and np.isfinite(metrics["rfid"]) and 1.0 < metrics["latent_scale"] < 20.0
    torch.manual_seed(tc.train.seed)
    initial = DetailTokenizerTask(tc, shard_root, out).build_model().state_dict()
    trained = load_weights(out / "model.pt")
    assert not any(torch.equal(trained[k], v) for k, v in initial.items() if k.startswith("discriminator.main."))
    assert (out / "samples" / "step_000008.png").is_file() and (out / "checkpoints" / "last.pt").is_file()

    saved = load_tokenizer(out / "tokenizer.pt")
    assert saved.kind == "detail" and saved.scale.shape == (16, 1, 1) and saved.shift.shape == (16, 9, 16)
    trained = build_detail_tokenizer(tc.preset).eval()
    trained.load_state_dict({k[len("tokenizer."):]: v for k, v in load_weights(out / "model.pt").items()
                             if k.startswith("tokenizer.")})
    images = next(frame_batches(shard_root, "val", 2, 2, seed=0))
    with torch.no_grad():
        latent = saved.model.encode(images)
        assert latent.shape == (2, 16, 9, 16) and torch.equal(latent, trained.encode(images))

    again = train_detail_tokenizer(cfg, shard_root, out, tmp_path, Recorder())  # finished: only re-measures
    assert again == metrics


class PatchTeacher(nn.Module):
    """A frozen random patch embedding: a stand-in teacher with an 8x8-pixel, 8-channel feature map."""

    feature_dim = 8

    def __init__(self):
        super().__init__()
        self.proj = nn.Conv2d(3, self.feature_dim, 8, stride=8)
        with torch.no_grad():
            self.proj.weight.copy_(torch.randn(self.proj.weight.shape, generator=torch.Generator().manual_seed(1)))
        self.requires_grad_(False)

    def forward(self, images):
        return torch.tanh(self.proj(images))


def test_abstract_task_aligns_to_the_teacher(shard_root, smoke_cfg, tmp_path):
    tc = dataclasses.replace(smoke_cfg.tokenizer_abstract, train=tiny_train(steps=12, lr=3e-3, eval_every=12),
                             eval_images=4)
    task = AbstractTokenizerTask(tc, shard_root, tmp_path, PatchTeacher())
    result = train(task, tc.train, tmp_path)
    align = [m["align"] for _, m in result.history if "align" in m]
    assert np.mean(align[-3:]) < 0.7 * np.mean(align[:2])
    evaluated = result.history[-1][1]
    assert {"val_align", "val_cosine", "val_psnr"} <= set(evaluated) and -1.0 <= evaluated["val_cosine"] <= 1.0
    assert (tmp_path / "samples" / "step_000012.png").is_file()


def test_interleaved_shards_feed_the_shuffle_buffer_from_more_videos(tmp_path, smoke_cfg):
    """A shard holds minutes of one video: read one after another, a rank's shuffle buffer holds one street.
    Interleaved, the same frames of the epoch arrive from that many videos at once."""
    make_raw(tmp_path / "raw", smoke_cfg, episodes=(("train", 8, 120), ("val", 1, 30)))
    write_shards(tmp_path / "raw", tmp_path / "probe", smoke_cfg.data, smoke_cfg.shards)
    manifest = shards.load_manifest(tmp_path / "probe")["splits"]["train"]
    clip_mb = sum(s["bytes"] for s in manifest["shards"]) / manifest["samples"] / 2**20
    # about 4 clips (one 120-frame video) per shard
    write_shards(tmp_path / "raw", tmp_path / "shards", smoke_cfg.data,
                 dataclasses.replace(smoke_cfg.shards, max_shard_mb=3.5 * clip_mb))
    train = shards.load_manifest(tmp_path / "shards")["splits"]["train"]
    assert len(train["shards"]) >= 6 and train["samples"] == 32

    def epoch(interleave):
        refs = _train_refs(tmp_path / "shards", spec(batch=8), per_clip=4, interleave=interleave, buffer=8)
        return [(clip.key, index) for clip, index in itertools.islice(refs, 32 * 4)]

    def videos_per_batch(refs):
        return np.mean([len({key.rsplit("_", 1)[0] for key, _ in refs[b:b + 8]}) for b in range(0, len(refs), 8)])

    one, eight = epoch(1), epoch(8)
    assert sorted(one) == sorted(eight)  # the same frames of the epoch
    assert videos_per_batch(eight) >= 1.5 * videos_per_batch(one), (videos_per_batch(one), videos_per_batch(eight))
