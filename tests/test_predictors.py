"""Predictor tasks: each overfits a tiny batch, hierarchy and steering inputs, initialisation, resume, DDP."""

import dataclasses
import math
import warnings

import numpy as np
import pytest
import torch

from orbis2.data.motion import TURN_THRESHOLD
from orbis2.errors import OrbisError
from orbis2.hierarchy import (
    detail_condition,
    detail_condition_slots,
    rate_geometry,
    steering_features,
    steering_interval,
    window_indices,
    window_span,
)
from orbis2.latents import FORMAT, LatentWindowDataset, clip_table, open_cache, write_chunk, write_meta, write_split
from orbis2.models.deviations import best_sideways_shift, translate_columns
from orbis2.tasks.predictors import (
    STAGES,
    PredictorTask,
    offset_yaw,
    turn_columns_per_yaw_rate,
    turn_repeats,
    window_batches,
)
from orbis2.train import DataSpec, load_weights, spawn_cpu_processes, train

from conftest import train_config

C, H, W = 4, 3, 4
SPAN = 26  # native frames of one training window (smoke data section)


def write_cache(root, clips: dict[str, list[int]], odometry=None, per_chunk: int = 2):
    """A latent cache in the `latents` stage's format: smooth moving latents, odometry row r = (r, -r / 10), rows
    numbered across each split's chunks of ``per_chunk`` clips (the shards a cache is made from hold several)."""
    meta = {"format": FORMAT, "dtype": "float16", "encoder": "cpu float32",
            "data": {"source": "town", "fps": 10, "width": 128, "height": 72},
            "tokenizers": {kind: {"checksum": kind * 8, "file": None, "shape": [C, H, W]}
                           for kind in ("detail", "abstract")},
            "splits": {}}
    grid = np.arange(C * H * W).reshape(C, H, W) / (C * H * W)
    for split, lengths in clips.items():
        frames = sum(lengths)
        t = np.arange(frames)[:, None, None, None]
        arrays = {kind: np.sin(0.3 * t + 6 * grid + phase).astype(np.float16)
                  for kind, phase in (("detail", 0.0), ("abstract", 1.0))}
        rows = np.arange(frames, dtype=np.float32)
        arrays["odometry"] = np.stack([rows, -rows / 10], 1) if odometry is None else odometry
        starts = np.cumsum([0, *lengths])
        chunks = []
        for first in range(0, len(lengths), per_chunk):
            last = min(first + per_chunk, len(lengths))
            name, part = f"{split}-{first // per_chunk:06d}", slice(starts[first], starts[last])
            table = clip_table([(f"{split}-{i:03d}", lengths[i], True, str(i), 0) for i in range(first, last)])
            digests = write_chunk(root / split / name, {k: v[part] for k, v in arrays.items()}, table)
            chunks.append({"chunk": name, "source": f"{split}/{name}.tar", "frames": int(starts[last] - starts[first]),
                           "clips": last - first, "sha256": digests})
        meta["splits"][split] = write_split(root / split, chunks)
    write_meta(root, meta, normalization={f"{kind}_{part}": value for kind in ("detail", "abstract")
                                          for part, value in (("shift", np.zeros((C, H, W), np.float32)),
                                                              ("scale", np.ones((C, 1, 1), np.float32)))})
    return open_cache(root)


@pytest.fixture(scope="module")
def tiny_cache(tmp_path_factory):
    """One train clip of 4 windows (one batch), one val clip."""
    return write_cache(tmp_path_factory.mktemp("cache"), {"train": [SPAN + 3], "val": [SPAN + 5]})


def tiny_cfg(smoke_cfg, stage, **changes):
    """The stage's smoke section on the tiny cache; its 4-column grids are too narrow for counterfactual turns."""
    cfg = smoke_cfg.section(stage)
    if hasattr(cfg, "yaw_offset_prob"):
        changes = {"yaw_offset_prob": 0.0, **changes}
    train_cfg = train_config(steps=80, batch_size=4, lr=0.003, warmup_steps=5, log_every=1, eval_every=80,
                             checkpoint_every=1000, seed=3)
    return dataclasses.replace(cfg, **{"train": train_cfg, "init_from": None, "val_batches": 1, **changes})


@pytest.mark.parametrize("stage", sorted(s for s in STAGES if STAGES[s].objective != "reflow"))  # test_distill.py
def test_each_task_overfits_a_tiny_batch(stage, tiny_cache, smoke_cfg, tmp_path):
    torch.set_num_threads(1)
    changes = {"context_noise_prob": 0.0, "context_drop_prob": 0.0} if stage != "abstract_df" else {}
    task = PredictorTask(stage, tiny_cfg(smoke_cfg, stage, **changes), smoke_cfg.data, tiny_cache)
    result = train(task, task.cfg.train, tmp_path)
    losses = [m["loss"] for _, m in result.history if "loss" in m]
    first, last = np.mean(losses[:10]), np.mean(losses[-10:])
    assert last < 0.5 * first, (first, last)
    final = dict(result.history[-1][1])
    assert final["val_loss"] < final["val_loss_init"]


def test_validation_loss_is_fixed_and_init_is_the_untrained_network(tiny_cache, smoke_cfg):
    task = PredictorTask("abstract_tf", tiny_cfg(smoke_cfg, "abstract_tf"), smoke_cfg.data, tiny_cache)
    model = task.build_model().eval()
    first = task.evaluate(model, 0)
    assert first["val_loss"] == task.val_loss(model) == first["val_loss_init"]
    assert "val_loss_init" not in task.evaluate(model, 1)  # logged once


def test_detail_condition_slots(smoke_cfg):
    # detail frames: anchor + (i - 4) at 10 Hz; abstract: anchor + 5 (j - 4) at 2 Hz.
    # Slot 4 (anchor) <- abstract 4 (anchor); slot 9 (anchor + 5) <- abstract 5 (anchor + 5).
    assert detail_condition_slots(smoke_cfg.data) == {4: 4, 9: 5}
    abstract = torch.arange(6.0).reshape(1, 6, 1, 1, 1).expand(2, 6, C, H, W)
    frames, mask = detail_condition(abstract, smoke_cfg.data)
    assert frames.shape == (2, 10, C, H, W)
    assert mask[0].tolist() == [False] * 4 + [True] + [False] * 4 + [True]
    assert (frames[:, 4] == 4).all() and (frames[:, 9] == 5).all()
    assert (frames[:, [0, 1, 2, 3, 5, 6, 7, 8]] == 0).all()


def test_action_features_from_odometry(smoke_cfg):
    cfg = smoke_cfg.action
    rows = torch.arange(SPAN, dtype=torch.float32)
    odometry = torch.stack([rows, -rows / 10], 1).expand(3, SPAN, 2).clone()  # row r: speed r, yaw rate -r/10
    odometry[1, 22, 1] = math.nan
    has = torch.tensor([True, True, False])
    values, unknown = steering_features(odometry, has, smoke_cfg.data, (cfg.speed_scale, cfg.yaw_rate_scale))
    # The last context frame is native row 20 (4 abstract steps of 5 frames), the predicted one row 25;
    # rows 20..24 hold the controls that drive the ego from one to the other.
    speed = torch.tensor([20.0, 21, 22, 23, 24]) / cfg.speed_scale
    yaw = -torch.tensor([2.0, 2.1, 2.2, 2.3, 2.4]) / cfg.yaw_rate_scale
    assert torch.allclose(values[0], torch.stack([speed, yaw], 1))
    assert unknown.tolist() == [False, True, True]
    assert (values[1:] == 0).all()


def test_unknown_steering_runs_unconditionally(tiny_cache, smoke_cfg):
    cfg = tiny_cfg(smoke_cfg, "action", steering_dropout=0.0)
    task = PredictorTask("action", cfg, smoke_cfg.data, tiny_cache)
    model = task.build_model()
    for p in model.parameters():  # a trained network: the zero-initialised paths carry signal
        torch.nn.init.normal_(p, std=0.1)
    batch = task.val_windows()[0]
    x, tau = batch["abstract"], torch.rand(len(batch["abstract"]), 6)
    values, _ = steering_features(batch["odometry"], batch["has_odometry"], smoke_cfg.data,
                                  (cfg.speed_scale, cfg.yaw_rate_scale))
    unconditional = model(x, tau, frame_rate=2.0)
    unknown = torch.ones(len(x), dtype=torch.bool)
    assert torch.equal(model(x, tau, frame_rate=2.0, steering=values, steering_drop=unknown), unconditional)
    assert not torch.allclose(model(x, tau, frame_rate=2.0, steering=values, steering_drop=~unknown), unconditional)


def test_fine_tunes_start_from_their_source(tiny_cache, smoke_cfg):
    df = PredictorTask("abstract_df", tiny_cfg(smoke_cfg, "abstract_df"), smoke_cfg.data, tiny_cache)
    source = df.build_model()
    for p in source.parameters():
        p.data.normal_()
    state = source.state_dict()
    tf_cfg = tiny_cfg(smoke_cfg, "abstract_tf", init_from="abstract_df")
    tf = PredictorTask("abstract_tf", tf_cfg, smoke_cfg.data, tiny_cache, state).build_model()
    assert all(torch.equal(v, state[k]) for k, v in tf.state_dict().items())
    scratch = PredictorTask("abstract_tf", tiny_cfg(smoke_cfg, "abstract_tf"), smoke_cfg.data, tiny_cache)
    assert not torch.equal(scratch.build_model().x_embedder.weight, state["x_embedder.weight"])

    action_cfg = tiny_cfg(smoke_cfg, "action", init_from="abstract_tf")
    action = PredictorTask("action", action_cfg, smoke_cfg.data, tiny_cache, tf.state_dict()).build_model()
    x, tau = torch.randn(2, 6, C, H, W), torch.rand(2, 6)
    steering = torch.randn(2, 6, 2)
    assert torch.allclose(action(x, tau, frame_rate=2.0, steering=steering), tf(x, tau, frame_rate=2.0))


def test_batch_stream_resumes(tmp_path, smoke_cfg):
    cache = write_cache(tmp_path, {"train": [SPAN + 6, SPAN + 4], "val": [SPAN]})
    dataset = LatentWindowDataset(cache, "train", smoke_cfg.data)
    assert len(dataset) == 12  # 3 batches of 4 per epoch
    fresh = window_batches(dataset, DataSpec(0, 1, 4, seed=5, start=0, num_workers=0))
    head = [next(fresh) for _ in range(8)]
    resumed = window_batches(dataset, DataSpec(0, 1, 4, seed=5, start=5, num_workers=0))
    for expected in head[5:]:
        got = next(resumed)
        assert all(torch.equal(got[k], expected[k]) for k in expected)
    epoch = torch.cat([b["odometry"][:, 0, 0] for b in head[:3]])  # every window once per epoch
    assert sorted(epoch.tolist()) == sorted(float(dataset.clips[c]["offset"] + a - 20) for c, a in dataset.items)


def per_window_turn_repeats(dataset, data, cfg):
    """turn_repeats as it was written before it was vectorised: one window at a time."""
    steer = steering_interval(data)
    before = slice(steer.start - (steer.stop - steer.start), steer.start)
    offsets = window_span(*window_indices(data, 0))
    odometry = dataset.cache.arrays(dataset.split)["odometry"]
    repeats = np.ones(len(dataset), np.int64)
    for i, (c, anchor) in enumerate(dataset.items):
        yaw = odometry[dataset.clips[c]["offset"] + anchor + offsets, 1]
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            turning = max(abs(np.nanmean(yaw[steer])), abs(np.nanmean(yaw[before]))) > TURN_THRESHOLD
        repeats[i] = cfg.turn_repeat if turning else 1
    return repeats


def test_turn_repeats_equal_the_per_window_loop(tmp_path, smoke_cfg):
    """The vectorised turn_repeats gives the loop's repeats exactly: yaw rates around the threshold, unknown (NaN)
    rows and whole unknown windows, over several chunks and blocks."""
    lengths = [SPAN + 17, SPAN + 3, SPAN + 30, SPAN]
    rng = np.random.default_rng(4)
    odometry = np.stack([np.full(sum(lengths), 5.0), rng.normal(0, 2 * TURN_THRESHOLD, sum(lengths))], 1)
    odometry[rng.random(sum(lengths)) < 0.2, 1] = np.nan
    odometry[sum(lengths[:2]):sum(lengths[:2]) + 15, 1] = np.nan  # whole intervals unknown
    cache = write_cache(tmp_path, {"train": lengths, "val": [SPAN]}, odometry.astype(np.float32), per_chunk=1)
    dataset = LatentWindowDataset(cache, "train", smoke_cfg.data)
    cfg = dataclasses.replace(smoke_cfg.section("action"), turn_repeat=4)
    expected = per_window_turn_repeats(dataset, smoke_cfg.data, cfg)
    assert 0 < (expected == 4).sum() < len(dataset)
    for block in (1, 7, 1 << 16):
        assert np.array_equal(turn_repeats(dataset, smoke_cfg.data, cfg, block=block), expected)


@pytest.mark.parametrize("stage", ["action", "detail"])
def test_turning_windows_are_oversampled(tmp_path, smoke_cfg, stage):
    # Clip 0 drives straight; clip 1 turns from its native frame 30 on (yaw rate 0.4 rad/s).
    lengths = [SPAN + 6, SPAN + 12]
    odometry = np.zeros((sum(lengths), 2), np.float32)
    odometry[:, 0] = 5.0
    odometry[lengths[0] + 30:, 1] = 0.4
    cache = write_cache(tmp_path, {"train": lengths, "val": [SPAN]}, odometry)
    dataset = LatentWindowDataset(cache, "train", smoke_cfg.data)
    cfg = dataclasses.replace(smoke_cfg.section(stage), turn_repeat=3)
    repeats = turn_repeats(dataset, smoke_cfg.data, cfg)
    # The steering interval of anchor a is native rows a..a+4, the interval before it a-5..a-1:
    # a window turns when either mean |yaw rate| exceeds 0.05, i.e. when a + 4 >= 30 on clip 1.
    turning = [c == 1 and a + 4 >= 30 for c, a in dataset.items]
    assert any(turning) and not all(turning)
    assert repeats.tolist() == [3 if t else 1 for t in turning]
    assert turn_repeats(dataset, smoke_cfg.data, dataclasses.replace(cfg, turn_repeat=1)).tolist() == [1] * len(dataset)

    per_epoch = int(repeats.sum()) // 2
    batches = window_batches(dataset, DataSpec(0, 1, 2, seed=5, start=0, num_workers=0), repeats)
    drawn = torch.cat([next(batches)["odometry"][:, 0, 1] for _ in range(per_epoch)])  # yaw rate at the first row
    first_rows = {(c, a): float(odometry[dataset.clips[c]["offset"] + a - 20, 1]) for c, a in dataset.items}
    assert len(drawn) == repeats.sum()  # one epoch lists window i repeats[i] times
    assert sorted(drawn.tolist()) == sorted(v for v, r in zip(first_rows.values(), repeats) for _ in range(r))

    plain = window_batches(dataset, DataSpec(0, 1, 2, seed=5, start=0, num_workers=0))
    same = window_batches(dataset, DataSpec(0, 1, 2, seed=5, start=0, num_workers=0), np.ones(len(dataset), int))
    assert all(torch.equal(next(plain)["odometry"], next(same)["odometry"]) for _ in range(3))


def test_variants_read_their_own_latents_and_window(tiny_cache, smoke_cfg):
    """Each ablation models the latents and rate its spec names, with the matching network."""
    shapes = {"abstract_df": (6, True, None), "detail": (10, False, C), "flat_detail": (10, False, None),
              "flat_abstract": (10, False, None), "top_detail": (6, True, None), "detail_on_detail": (10, False, C)}
    for stage, (frames, causal, cond) in shapes.items():
        task = PredictorTask(stage, tiny_cfg(smoke_cfg, stage), smoke_cfg.data, tiny_cache)
        batch = task.val_windows()[0]
        assert batch[task.batch_key].shape[1] == frames, stage
        assert (task.build["causal"], task.build["abstract_channels"]) == (causal, cond), stage
    batch = PredictorTask("flat_abstract", tiny_cfg(smoke_cfg, "flat_abstract"), smoke_cfg.data,
                          tiny_cache).val_windows()[0]
    # Same native frames, other latent space: the fast abstract window's frames 4 and 9 are the slow window's 4 and 5.
    assert torch.equal(batch["abstract_fast"][:, [4, 9]], batch["abstract"][:, [4, 5]])
    assert torch.equal(batch["detail_slow"][:, [4, 5]], batch["detail"][:, [4, 9]])


class Killed(RuntimeError):
    """Stands in for the process being killed mid-run."""


class KilledAt(PredictorTask):
    def __init__(self, *args, kill_at: int):
        super().__init__(*args)
        self.kill_at = kill_at

    def loss(self, model, batch, step):
        if step == self.kill_at:
            raise Killed(step)
        return super().loss(model, batch, step)


def test_predictor_resumes_bit_identically_after_a_kill(tiny_cache, smoke_cfg, tmp_path):
    torch.set_num_threads(1)
    cfg = tiny_cfg(smoke_cfg, "detail")
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=12, checkpoint_every=5, eval_every=0))
    args = ("detail", cfg, smoke_cfg.data, tiny_cache)
    train(PredictorTask(*args), cfg.train, tmp_path / "straight")
    with pytest.raises(Killed):
        train(KilledAt(*args, kill_at=8), cfg.train, tmp_path / "killed")
    resumed = train(PredictorTask(*args), cfg.train, tmp_path / "killed")
    assert (resumed.start_step, resumed.step) == (5, 12)
    straight, killed = (load_weights(tmp_path / name / "model.pt") for name in ("straight", "killed"))
    assert all(torch.equal(straight[k], killed[k]) for k in straight)


def _ddp_predictor(cache_root, cfg, data, out_dir):
    torch.set_num_threads(1)
    result = train(PredictorTask("abstract_tf", cfg, data, open_cache(cache_root)), cfg.train, out_dir)
    return result.history


def test_predictor_trains_under_ddp_on_two_processes(tmp_path, smoke_cfg):
    """Two gloo ranks split each batch, agree on every training metric, and rank 0 writes weights that improved."""
    cache = write_cache(tmp_path / "cache", {"train": [SPAN + 7], "val": [SPAN + 5]})  # 8 windows: 2 x 4 per epoch
    cfg = tiny_cfg(smoke_cfg, "abstract_tf", context_noise_prob=0.0, context_drop_prob=0.0)
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=30, eval_every=30))
    rank0, rank1 = spawn_cpu_processes(_ddp_predictor, 2, cache.root, cfg, smoke_cfg.data, tmp_path / "ddp",
                                       timeout_s=300)
    steps = [[entry for entry in history if "loss" in entry[1]] for history in (rank0, rank1)]
    assert steps[0] == steps[1] and len(steps[0]) == 30  # training metrics are averaged over ranks
    final = dict(rank0[-1][1])  # validation runs on rank 0 only
    assert final["val_loss"] < final["val_loss_init"]
    assert (tmp_path / "ddp" / "model.pt").is_file()


def smooth_grids(n: int, width: int = 16, seed: int = 0) -> torch.Tensor:
    """[n, C, H, width] grids of smooth random content (a sideways move of them is well defined)."""
    columns = torch.linspace(0, 2 * math.pi, width)
    phases = torch.rand(n, C, H, 1, generator=torch.Generator().manual_seed(seed)) * 2 * math.pi
    return torch.sin(columns + phases) + 0.5 * torch.cos(2 * columns + 2 * phases)


def test_counterfactual_turns_move_the_target_as_far_as_the_offset(smoke_cfg):
    targets = smooth_grids(64)[:, None]
    steering = torch.zeros(64, 5, 2)
    active = torch.arange(64) % 4 != 0
    moved, offset = offset_yaw(targets, steering, active, torch.Generator().manual_seed(0), prob=0.5,
                               max_offset=0.5, columns_per_yaw_rate=4.0, yaw_rate_scale=0.2)
    delta = offset[:, :, 1] * 0.2
    assert torch.allclose(delta, delta[:, :1].expand_as(delta)) and float(delta.abs().max()) <= 0.5
    assert torch.equal(offset[..., 0], steering[..., 0])
    changed = delta[:, 0] != 0
    assert not changed[~active].any() and 0.25 < changed[active].float().mean() < 0.75  # prob 0.5 of the active
    assert torch.equal(moved[~changed], targets[~changed])
    expected = translate_columns(targets[changed, 0], 4.0 * delta[changed, 0])
    assert torch.allclose(moved[changed, 0], expected, atol=1e-4)
    found = best_sideways_shift(targets[changed, 0], moved[changed, 0], 3.0, 1 / 16)
    assert torch.allclose(found, 4.0 * delta[changed, 0], atol=1 / 16)
    assert torch.equal(offset_yaw(targets, steering, active, torch.Generator(), 0.0, 0.5, 4.0, 0.2)[0], targets)


class TurningWindows:
    """Windows whose abstract target is the last context latent moved 3 columns per rad/s of yaw rate."""

    def __init__(self, data, yaw_rates):
        self.cache, self.split = type("Cache", (), {"root": "synthetic"})(), "train"
        _, self.n_frames, self.n_context = rate_geometry(data, "slow")
        self.span = len(window_span(*window_indices(data, 0)))
        self.yaw_rates, self.grids = yaw_rates, smooth_grids(len(yaw_rates))

    def __len__(self):
        return len(self.yaw_rates)

    def __getitem__(self, i):
        frames = self.grids[i:i + 1].repeat(self.n_frames, 1, 1, 1)
        frames[-1] = translate_columns(self.grids[i:i + 1], torch.tensor([3.0 * self.yaw_rates[i]]))[0]
        odometry = torch.tensor([[8.0, self.yaw_rates[i]]]).repeat(self.span, 1)
        return {"detail": frames, "abstract": frames, "detail_slow": frames, "abstract_fast": frames,
                "odometry": odometry, "has_odometry": True}


def test_the_turn_slope_is_measured_from_the_windows(smoke_cfg):
    windows = TurningWindows(smoke_cfg.data, [-1.0, -0.5, 0.0, 0.5, 1.0, 0.25])
    assert turn_columns_per_yaw_rate(windows, smoke_cfg.data) == pytest.approx(3.0, abs=0.05)
    with pytest.raises(OrbisError, match="yaw_offset_prob: 0"):
        turn_columns_per_yaw_rate(TurningWindows(smoke_cfg.data, [0.0, 0.0]), smoke_cfg.data)
