"""Shards: round trip, deterministic plain-tar bytes, two-rate windows, rank/worker partitioning through
webdataset (local paths and pipe: URLs), decoding in worker processes, corruption."""

import dataclasses
import subprocess
import tarfile

import numpy as np
import pytest
import torch
import webdataset as wds

from orbis2.data.episodes import EpisodeRecord, RawIndex, write_labels, write_odometry
from orbis2.data.shards import (
    Clip,
    ClipStream,
    ShardError,
    WindowDataset,
    anchor_range,
    clip_window,
    interleave,
    iter_samples,
    load_manifest,
    read_clips,
    shard_paths,
    shard_urls,
    verify_shards,
    window_indices,
    write_shards,
)
from orbis2.data.video import read_video, write_video

from conftest import moving_pattern


def make_raw(root, cfg, episodes=(("train", 3, 64), ("val", 1, 40), ("probe", 1, 40))):
    """Raw episodes whose frame k carries k in a corner and odometry speed = k, so windows are checkable."""
    data = cfg.data
    records = []
    for split, count, n in episodes:
        (root / split).mkdir(parents=True, exist_ok=True)
        for e in range(count):
            stem = f"ep_{split}_{e:05d}"
            frames = moving_pattern(n, data.width, data.height, seed=e)
            frames[:, :16, :16] = (np.arange(n) * 3 % 256)[:, None, None, None]
            write_video(root / split / f"{stem}.mp4", frames, data.fps)
            k = np.arange(n, dtype=float)
            write_odometry(root / split / f"{stem}.parquet", data.fps, k, -k, (k, 2 * k, 3 * k))
            label_frames = list(range(0, n, 5)) if split == "probe" else []
            if label_frames:
                depth = np.full((len(label_frames), data.height, data.width), 7.5, np.float32)
                sem = np.tile(np.array(label_frames, np.uint8)[:, None, None], (1, data.height, data.width))
                write_labels(root / split / f"{stem}.labels.npz", label_frames, depth, sem)
            records.append(EpisodeRecord(split, stem, n, True, True, label_frames, origin="test"))
    RawIndex("test", data.fps, data.width, data.height, None, records).write(root)


@pytest.fixture(scope="module")
def shards(tmp_path_factory, smoke_cfg):
    tmp = tmp_path_factory.mktemp("shards")
    make_raw(tmp / "raw", smoke_cfg)
    cfg = dataclasses.replace(smoke_cfg.shards, max_shard_mb=0.3)
    manifest = write_shards(tmp / "raw", tmp / "out", smoke_cfg.data, cfg)
    return tmp, manifest, cfg


def test_round_trip(shards, smoke_cfg):
    tmp, manifest, cfg = shards
    clip_frames = round(cfg.clip_seconds["train"] * smoke_cfg.data.fps)  # 30
    assert manifest["splits"]["train"]["samples"] == 3 * (64 // clip_frames)
    assert len(manifest["splits"]["train"]["shards"]) > 1  # rolled over at the size limit
    keys = []
    for path in shard_paths(tmp / "out", "train"):
        for sample in iter_samples(path):
            clip = Clip.from_sample(sample)
            keys.append(clip.key)
            start = clip.meta["start_frame"]
            np.testing.assert_array_equal(clip.odometry[:, 0], np.arange(start, start + len(clip)))
            np.testing.assert_array_equal(clip.pose[:, 2], 3 * np.arange(start, start + len(clip)))
            corner = clip.frames([0, len(clip) - 1])[:, 4:12, 4:12].mean(axis=(1, 2, 3))
            np.testing.assert_allclose(corner, [start * 3 % 256, (start + len(clip) - 1) * 3 % 256], atol=6)
    assert len(keys) == len(set(keys)) and keys[0] == "ep_train_00000_0000"
    raw = read_video(tmp / "raw/train/ep_train_00000.mp4")
    clip = Clip.from_sample(next(iter_samples(shard_paths(tmp / "out", "train")[0])))
    err = [np.abs(clip.frames([3])[0].astype(int) - raw[k].astype(int)).mean() for k in (3, 11)]
    assert err[0] < 10 and err[0] < err[1] / 4  # frame 3 up to JPEG loss, clearly not another frame


def test_labels_travel_with_their_frames(shards):
    tmp, _, _ = shards
    clip = Clip.from_sample(next(iter_samples(shard_paths(tmp / "out", "probe")[0])))
    np.testing.assert_array_equal(clip.labels["frames"], np.arange(0, 40, 5))
    assert clip.labels["semantic"][:, 0, 0].tolist() == list(range(0, 40, 5))
    assert clip.labels["depth"].dtype == np.float16 and float(clip.labels["depth"].max()) == 7.5


def test_same_input_same_bytes(shards, smoke_cfg, tmp_path):
    tmp, manifest, cfg = shards
    again = write_shards(tmp / "raw", tmp_path / "again", smoke_cfg.data, cfg)
    assert again == manifest
    verify_shards(tmp / "out")


def test_window_indices_hand_computed(smoke_cfg):
    detail, abstract = window_indices(smoke_cfg.data, anchor=20)
    assert detail.tolist() == [16, 17, 18, 19, 20, 21, 22, 23, 24, 25]  # 10 Hz: 5 context ending on 20, 5 predicted
    assert abstract.tolist() == [0, 5, 10, 15, 20, 25]                  # 2 Hz: 5 context ending on 20, then 25
    assert detail[-1] == abstract[-1]                                  # subgoal lands on the last detail frame
    assert anchor_range(smoke_cfg.data, 30) == range(20, 25)
    data20 = dataclasses.replace(smoke_cfg.data, fps=20)
    detail, abstract = window_indices(data20, anchor=40)
    assert detail.tolist() == list(range(32, 51, 2)) and abstract.tolist() == [0, 10, 20, 30, 40, 50]


def test_clip_window_content(shards, smoke_cfg):
    tmp, _, _ = shards
    clip = Clip.from_sample(next(iter_samples(shard_paths(tmp / "out", "train")[0])))
    w = clip_window(clip, smoke_cfg.data, 22)
    assert w["detail_frames"].shape == (10, smoke_cfg.data.height, smoke_cfg.data.width, 3)
    assert w["abstract_frames"].shape[0] == 6
    np.testing.assert_array_equal(w["detail_odometry"][:, 0], np.arange(18, 28))
    np.testing.assert_array_equal(w["abstract_odometry"][:, 1], -np.arange(2, 28, 5))
    np.testing.assert_array_equal(w["odometry"][:, 0], np.arange(2, 28))
    with pytest.raises(ValueError, match="outside"):
        clip_window(clip, smoke_cfg.data, 5)


@pytest.mark.parametrize("world, workers", [(1, 1), (2, 1), (2, 2), (3, 2)])
def test_ranks_and_workers_partition_the_clips(shards, smoke_cfg, world, workers):
    tmp, manifest, _ = shards
    seen = []
    for rank in range(world):
        ds = WindowDataset(tmp / "out", "train", smoke_cfg.data, anchors="first", rank=rank, world=world)
        loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=workers)
        seen += [w["key"] for w in loader]
    assert sorted(seen) == sorted(set(seen)) and len(seen) == manifest["splits"]["train"]["samples"]


def test_random_anchors_are_seeded(shards, smoke_cfg):
    tmp, _, _ = shards
    a = [w["anchor"] for w in WindowDataset(tmp / "out", "train", smoke_cfg.data, seed=1)]
    b = [w["anchor"] for w in WindowDataset(tmp / "out", "train", smoke_cfg.data, seed=1)]
    c = [w["anchor"] for w in WindowDataset(tmp / "out", "train", smoke_cfg.data, seed=1, epoch=1)]
    assert a == b and a != c


def test_readable_by_the_webdataset_library(shards):
    wds = pytest.importorskip("webdataset")
    tmp, manifest, _ = shards
    urls = [str(p) for p in shard_paths(tmp / "out", "val")]
    samples = list(wds.WebDataset(urls, shardshuffle=False))
    assert len(samples) == manifest["splits"]["val"]["samples"]
    assert "0000.jpg" in samples[0] and "odometry.npy" in samples[0]


def test_truncated_and_corrupt_shards_name_the_file(shards, tmp_path):
    tmp, _, _ = shards
    path = shard_paths(tmp / "out", "train")[0]
    truncated = tmp_path / "truncated.tar"
    truncated.write_bytes(path.read_bytes()[: path.stat().st_size // 3 + 100])
    with pytest.raises(ShardError, match="truncated.tar"):
        list(iter_samples(truncated))
    garbage = tmp_path / "garbage.tar"
    garbage.write_bytes(b"\x00\x01not a tar" * 200)
    with pytest.raises(ShardError, match="garbage.tar"):
        for sample in iter_samples(garbage):
            Clip.from_sample(sample, str(garbage))
    missing_member = tmp_path / "missing.tar"
    with tarfile.open(path) as src, tarfile.open(missing_member, "w") as dst:
        for m in src:
            if not m.name.endswith("odometry.npy"):
                dst.addfile(m, src.extractfile(m))
    with pytest.raises(ShardError, match="missing.tar.*incomplete"):
        for sample in iter_samples(missing_member):
            Clip.from_sample(sample, str(missing_member))


def test_manifest_hash_detects_modification(shards, tmp_path):
    import shutil
    tmp, _, _ = shards
    copy = tmp_path / "copy"
    shutil.copytree(tmp / "out", copy)
    shard = shard_paths(copy, "val")[0]
    data = bytearray(shard.read_bytes())
    data[2000] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(ShardError, match="does not match the manifest"):
        verify_shards(copy)
    assert load_manifest(copy)["fps"] == 10


def test_shards_are_plain_tar_with_fixed_headers(shards):
    tmp, _, _ = shards
    path = shard_paths(tmp / "out", "probe")[0]
    listing = subprocess.run(["tar", "--numeric-owner", "-tvf", str(path)], capture_output=True, text=True,
                             check=True).stdout.splitlines()
    sample = next(iter_samples(path))
    names = [f"{sample['__key__']}.{ext}" for ext in sorted(k for k in sample if not k.startswith("__"))]
    assert [line.split()[-1] for line in listing][:len(names)] == names
    assert {tuple(line.split()[:2]) for line in listing} == {("-rw-r--r--", "0/0")}
    assert {line.split()[3] for line in listing} == {"1970-01-01"}
    member = subprocess.run(["tar", "-xOf", str(path), names[-1]], capture_output=True, check=True).stdout
    assert member == sample[names[-1].split(".", 1)[1]]


@pytest.fixture(scope="module")
def many_shards(shards, smoke_cfg):
    """The same clips, one per shard: enough shards for 2 ranks x 2 workers to split whole shards."""
    tmp, _, cfg = shards
    manifest = write_shards(tmp / "raw", tmp / "many", smoke_cfg.data, dataclasses.replace(cfg, max_shard_mb=0.01))
    return tmp / "many", manifest


@pytest.mark.parametrize("layout", ["few", "many"])
def test_webloader_covers_every_clip_once_over_2_ranks_x_2_workers(shards, many_shards, smoke_cfg, layout):
    root, manifest = (shards[0] / "out", shards[1]) if layout == "few" else many_shards
    shard_count = len(manifest["splits"]["train"]["shards"])
    assert (shard_count >= 4) == (layout == "many")
    per_rank = []
    for rank in range(2):
        ds = WindowDataset(root, "train", smoke_cfg.data, anchors="first", rank=rank, world=2)
        per_rank.append([w["key"] for w in wds.WebLoader(ds, batch_size=None, num_workers=2)])
    seen = per_rank[0] + per_rank[1]
    assert sorted(seen) == sorted(set(seen)) and len(seen) == manifest["splits"]["train"]["samples"]
    assert abs(len(per_rank[0]) - len(per_rank[1])) <= (1 if layout == "few" else 2)


def test_ranks_from_the_environment(many_shards, smoke_cfg, monkeypatch):
    root, manifest = many_shards
    keys = []
    for rank in range(2):
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("WORLD_SIZE", "2")
        keys.append({w["key"] for w in WindowDataset(root, "train", smoke_cfg.data, anchors="first")})
    assert not keys[0] & keys[1] and len(keys[0] | keys[1]) == manifest["splits"]["train"]["samples"]


def test_read_clips_decodes_in_worker_processes(shards):
    tmp, manifest, _ = shards
    lazy = {clip.key: clip for path in shard_paths(tmp / "out", "train") for clip in map(Clip.from_sample,
                                                                                        iter_samples(path))}
    decoded = list(read_clips(tmp / "out", "train", workers=2))
    assert sorted(c.key for c in decoded) == sorted(lazy) and len(decoded) == manifest["splits"]["train"]["samples"]
    for clip in decoded:
        assert clip.pixels is not None and len(clip) == len(lazy[clip.key])
        np.testing.assert_array_equal(clip.frames([0, 5]), lazy[clip.key].frames([0, 5]))


def test_shards_through_pipe_urls(shards, smoke_cfg, monkeypatch):
    tmp, _, _ = shards
    local = [w["key"] for w in WindowDataset(tmp / "out", "val", smoke_cfg.data, anchors="first")]
    monkeypatch.setenv("ORBIS2_SHARDS_URL", f"pipe:cat {tmp / 'out'}/{{}}")
    assert shard_urls(tmp / "out", "val")[0].startswith("pipe:cat ")
    piped = [w["key"] for w in WindowDataset(tmp / "out", "val", smoke_cfg.data, anchors="first")]
    assert piped == local and piped
    assert shard_urls(tmp / "out", "val", "https://host/shards/")[0] == "https://host/shards/val/val-000000.tar"


def test_a_broken_shard_in_a_worker_names_the_file(shards, tmp_path):
    import shutil
    tmp, _, _ = shards
    copy = tmp_path / "copy"
    shutil.copytree(tmp / "out", copy)
    shard = shard_paths(copy, "train")[-1]
    shard.write_bytes(shard.read_bytes()[:5000])
    with pytest.raises(ShardError, match=shard.name):
        list(read_clips(copy, "train", workers=2))


def test_interleave_takes_an_item_from_each_open_stream_in_turn():
    streams = [iter(["a1", "a2", "a3"]), iter(["b1"]), iter(["c1", "c2"]), iter(["d1"])]
    assert list(interleave(iter(streams), 3)) == ["a1", "b1", "c1", "a2", "d1", "c2", "a3"]
    assert list(interleave(iter([iter([1, 2]), iter([3])]), 1)) == [1, 2, 3]
    started = []
    lazy = interleave((started.append(i) or iter([i]) for i in range(10)), 2)
    assert next(lazy) == 0 and started == [0, 1]  # a stream starts when its turn comes, no sooner


def test_interleaved_ranks_still_split_the_clips_exactly(shards):
    tmp, _, _ = shards
    every = sorted(clip.key for clip in ClipStream(tmp / "out", "train", rank=0, world=1))
    for world in (1, 2, 5):  # 5 readers for fewer shards: every reader keeps every 5th sample
        taken = [clip.key for rank in range(world) for clip in ClipStream(tmp / "out", "train", rank=rank,
                                                                           world=world, interleave=2)]
        assert sorted(taken) == every
