"""Latent cache: equal to fresh encoding, the clip table, stale-tokenizer refusal, sampler partitioning; in parts (any
number gives the same bytes), resumed at the chunk, read as numpy arrays whatever the number of windows."""

import dataclasses
import json
import os
import pickle
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from test_import import stage_env
from test_shards import make_raw
from torch.utils.data import DataLoader, DistributedSampler

from orbis2.data.parts import PART_LOG, WORK_KEY, part_name
from orbis2.data.shards import MANIFEST, Clip, anchor_range, clip_window, iter_samples, shard_paths, write_shards
from orbis2.hierarchy import window_indices
from orbis2.latents import (
    CHUNKS,
    CLIPS,
    FORMAT,
    LatentCacheError,
    LatentWindowDataset,
    build_latent_cache,
    encode_window,
    latent_work,
    load_encoders,
    open_cache,
    sha256_file,
    window_counts,
)
from orbis2.models.files import load_tokenizer, save_tokenizer
from orbis2.models.tokenizer import build_abstract_tokenizer, build_detail_tokenizer

from conftest import ROOT

DETAIL_SCALE, ABSTRACT_SCALE = 0.8, 1.7


def save_detail(path, seed):
    torch.manual_seed(seed)
    save_tokenizer(path, "detail", build_detail_tokenizer("smoke"), DETAIL_SCALE, {"preset": "smoke"})
    return path


@pytest.fixture(scope="module")
def setup(tmp_path_factory, smoke_cfg):
    """Shards of 6 train clips (30 frames) in 3 shards and 1 val clip (40 frames), two smoke tokenizers, the cache."""
    tmp = tmp_path_factory.mktemp("latents")
    make_raw(tmp / "raw", smoke_cfg, episodes=(("train", 3, 64), ("val", 1, 40)))
    write_shards(tmp / "raw", tmp / "shards", smoke_cfg.data, dataclasses.replace(smoke_cfg.shards, max_shard_mb=0.25))
    detail_path = save_detail(tmp / "detail.pt", seed=0)
    torch.manual_seed(1)
    save_tokenizer(tmp / "abstract.pt", "abstract", build_abstract_tokenizer("smoke", teacher_dim=32),
                   ABSTRACT_SCALE, {"preset": "smoke", "teacher_dim": 32, "compress": True})
    meta = build_latent_cache(tmp / "shards", tmp / "cache", detail_path, tmp / "abstract.pt", batch_size=7,
                              device="cpu")
    assert len(shard_paths(tmp / "shards", "train")) == 3
    return tmp, meta, load_tokenizer(detail_path), load_tokenizer(tmp / "abstract.pt")


def clips(root, split):
    return [Clip.from_sample(s) for path in shard_paths(root, split) for s in iter_samples(path)]


def files(root):
    """Every file of a folder and its bytes' SHA-256."""
    return {str(f.relative_to(root)): sha256_file(f) for f in sorted(root.rglob("*")) if f.is_file()}


def test_cache_equals_fresh_encoding(setup, smoke_cfg):
    tmp, _, detail, abstract = setup
    data = smoke_cfg.data
    for split in ("train", "val"):
        ds = LatentWindowDataset(tmp / "cache", split, data)
        where = {(ds.keys[c], a): i for i, (c, a) in enumerate(ds.items)}
        for clip in clips(tmp / "shards", split)[:2]:
            valid = anchor_range(data, len(clip))
            for anchor in (valid[0], valid[-1]):
                fresh = encode_window(clip_window(clip, data, anchor), detail, abstract)
                cached = ds[where[clip.key, anchor]]
                assert cached["detail"].shape == (data.detail_window, 16, 9, 16)
                assert cached["abstract"].shape == (data.abstract_window, 16, 9, 16)
                assert cached["detail"].dtype == torch.float32
                for name, scale in (("detail", DETAIL_SCALE), ("abstract", ABSTRACT_SCALE)):
                    torch.testing.assert_close(cached[name], fresh[name], rtol=0, atol=1e-3 * scale)
                for name in ("detail_odometry", "abstract_odometry", "odometry"):
                    torch.testing.assert_close(cached[name], fresh[name], rtol=0, atol=0)
                assert (cached["key"], cached["anchor"], cached["has_odometry"]) == (clip.key, anchor, True)


def test_clip_table_chunks_and_meta_round_trip(setup):
    tmp, meta, detail, abstract = setup
    cache = open_cache(tmp / "cache", detail.checksum, abstract.checksum)
    for split in ("train", "val"):
        index, arrays = cache.index(split), cache.arrays(split)
        expected = clips(tmp / "shards", split)
        assert index.keys.tolist() == [c.key for c in expected]
        shards = json.loads((tmp / "shards" / MANIFEST).read_text())["splits"][split]["shards"]
        assert index.chunks["source"].tolist() == [s["path"] for s in shards]  # one chunk per shard, named by it
        assert index.chunks["name"].tolist() == [s["path"].split("/")[-1].removesuffix(".tar") for s in shards]
        offset = 0
        for row, clip in zip(index.clips, expected):
            assert (int(row["offset"]), int(row["length"]), bool(row["has_odometry"]), str(row["episode"]),
                    int(row["start_frame"])) == (offset, len(clip), True, clip.meta["episode"],
                                                 clip.meta["start_frame"])
            chunk = index.chunks[row["chunk"]]
            assert row["offset"] == chunk["first_row"] + row["row"]
            np.testing.assert_array_equal(arrays["odometry"][offset:offset + len(clip)], clip.odometry)
            np.testing.assert_array_equal(cache.chunk(split, int(row["chunk"]))["odometry"][
                row["row"]:row["row"] + len(clip)], clip.odometry)
            offset += len(clip)
        assert len(arrays["detail"]) == len(arrays["abstract"]) == offset == meta["splits"][split]["frames"]
        assert arrays["detail"].dtype == np.float16 and arrays["odometry"].shape == (offset, 2)
        assert index.find([c.key for c in expected[::-1]]).tolist() == list(range(len(expected)))[::-1]
        with pytest.raises(KeyError, match="no clip nowhere_0000"):
            index.find(["nowhere_0000"])
    assert cache.splits == ["train", "val"] and meta["format"] == FORMAT and meta["encoder"] == "cpu float32"
    assert meta["shards"]["manifest_sha256"] == sha256_file(tmp / "shards" / MANIFEST)
    assert meta["tokenizers"]["detail"]["checksum"] == sha256_file(tmp / "detail.pt") == detail.checksum
    z = torch.from_numpy(cache.arrays("val")["abstract"][:3].astype(np.float32))
    torch.testing.assert_close(cache.normalize("abstract", z), abstract.normalize(z))
    torch.testing.assert_close(cache.normalize("detail", z), z * DETAIL_SCALE)
    assert meta["data"]["fps"] == 10 and meta["data"]["width"] == 128


def test_split_arrays_index_like_one_array(setup):
    """Rows numbered across chunks: rows, slices (across chunk ends), arrays of rows and extra axes read what one
    concatenated array would."""
    tmp, _, _, _ = setup
    cache = open_cache(tmp / "cache")
    index = cache.index("train")
    for name in ("detail", "odometry"):
        view = cache.arrays("train")[name]
        whole = np.concatenate([cache.chunk("train", c)[name] for c in range(len(index.chunks))])
        assert view.shape == whole.shape and len(view) == len(whole) and view.ndim == whole.ndim
        end = int(index.chunks["first_row"][1])  # the first chunk's end
        rows = np.array([[end - 1, end, 0], [len(whole) - 1, 3, end + 2]])
        for key in (5, -1, slice(None), slice(end - 3, end + 4), slice(1, None, 7), slice(end, end), rows,
                    [end + 1, 2], (rows, 1), (slice(end - 2, end + 2), 0), np.zeros(0, int)):
            np.testing.assert_array_equal(view[key], whole[key], err_msg=str(key))
    with pytest.raises(IndexError):
        view[len(whole)]
    with pytest.raises(TypeError):
        view[np.ones(len(whole), bool)]


def test_window_counts_match_anchor_range(smoke_cfg):
    lengths = np.arange(0, 80)
    for stride in (1, 2, 3, 7):
        counts, first = window_counts(smoke_cfg.data, lengths, stride)
        for n, count in zip(lengths, counts):
            anchors = anchor_range(smoke_cfg.data, int(n))[::stride]
            assert count == len(anchors) and (count == 0 or anchors[0] == first)


def test_cache_from_another_tokenizer_is_refused(setup):
    tmp, _, detail, abstract = setup
    retrained = load_tokenizer(save_detail(tmp / "retrained.pt", seed=5))
    assert retrained.checksum != detail.checksum
    folder = re.escape(str(tmp / "cache"))
    with pytest.raises(LatentCacheError, match=f"{folder}.*detail.pt.*re-run the `latents` stage"):
        open_cache(tmp / "cache", detail_checksum=retrained.checksum)
    with pytest.raises(LatentCacheError, match="abstract.pt"):
        open_cache(tmp / "cache", abstract_checksum=retrained.checksum)
    with pytest.raises(LatentCacheError, match="missing; run the `latents` stage"):
        open_cache(tmp / "nowhere")
    open_cache(tmp / "cache", detail.checksum, abstract.checksum)


def test_dataset_length_and_distributed_partition(setup, smoke_cfg):
    tmp, _, _, _ = setup
    ds = LatentWindowDataset(tmp / "cache", "train", smoke_cfg.data)
    assert len(ds) == 6 * len(anchor_range(smoke_cfg.data, 30)) == 30
    strided = LatentWindowDataset(tmp / "cache", "train", smoke_cfg.data, anchor_stride=2)
    assert len(strided) == 6 * 3 and strided.items[:3].tolist() == [[0, 20], [0, 22], [0, 24]]
    assert ds[-1]["key"] == ds[len(ds) - 1]["key"] == str(ds.keys[-1])
    with pytest.raises(IndexError):
        ds[len(ds)]
    seen = []
    for rank in range(2):
        sampler = DistributedSampler(ds, num_replicas=2, rank=rank, shuffle=True, seed=3)
        loader = DataLoader(ds, batch_size=4, sampler=sampler, num_workers=2 if rank else 0)
        for batch in loader:
            assert batch["detail"].shape[:2] == (len(batch["key"]), 10)
            seen += list(zip(batch["key"], batch["anchor"].tolist()))
    assert len(seen) == len(set(seen)) == len(ds)
    assert set(seen) == {(ds.keys[c], a) for c, a in ds.items.tolist()}


def test_the_window_index_holds_arrays_per_clip_not_objects_per_window(setup, smoke_cfg):
    """What a dataset holds grows with the clips (numpy rows), not with the windows: no list, dict or array with
    one entry per window, at any anchor stride; its items are made only when asked for."""
    tmp, _, _, _ = setup
    ds = LatentWindowDataset(tmp / "cache", "train", smoke_cfg.data)
    n_clips = len(ds.clips)
    for name, value in vars(ds).items():
        assert not isinstance(value, (list, dict, tuple)), name
        if isinstance(value, np.ndarray):
            assert len(value) <= n_clips + 1, name  # the clip table, its keys, where each clip's windows start
    assert len(ds) > 2 * n_clips
    clip, anchor = ds.windows(3, 9)
    assert np.stack([clip, anchor], 1).tolist() == ds.items[3:9].tolist()


def test_pickled_dataset_maps_instead_of_copying(setup, smoke_cfg):
    tmp, _, _, _ = setup
    ds = LatentWindowDataset(tmp / "cache", "train", smoke_cfg.data)
    item = ds[7]
    blob = pickle.dumps(ds)  # what spawn-started DataLoader workers receive
    norm_bytes = sum(t.numel() * t.element_size() for t in ds.cache.norm.values())  # fixed size, not data
    assert len(blob) < 20_000 + norm_bytes
    torch.testing.assert_close(pickle.loads(blob)[7]["detail"], item["detail"])


def block_cache(root, frames=640, clip=160, shape=(4, 3, 4)):
    """A cache of one train chunk of ``frames`` frames (``frames // BLOCK_ROWS`` blocks) in clips of ``clip``, random
    latents: bigger than a window by far, small enough to write in a test."""
    from orbis2.latents import clip_table, write_chunk, write_meta, write_split

    rng = np.random.default_rng(0)
    arrays = {kind: rng.standard_normal((frames, *shape)).astype(np.float16) for kind in ("detail", "abstract")}
    arrays["odometry"] = rng.standard_normal((frames, 2)).astype(np.float32)
    table = clip_table([(f"clip-{i:03d}", clip, True, str(i), 0) for i in range(frames // clip)])
    digests = write_chunk(root / "train" / "train-000000", arrays, table)
    meta = {"format": FORMAT, "dtype": "float16", "encoder": "cpu float32",
            "data": {"source": "town", "fps": 10, "width": 128, "height": 72},
            "tokenizers": {kind: {"checksum": kind * 8, "file": None, "shape": list(shape)}
                           for kind in ("detail", "abstract")},
            "splits": {"train": write_split(root / "train", [{"chunk": "train-000000", "source": "train/x.tar",
                                                                "frames": frames, "clips": len(table),
                                                                "sha256": digests}])}}
    write_meta(root, meta, normalization={f"{kind}_{part}": value for kind in ("detail", "abstract")
                                          for part, value in (("shift", np.zeros(shape, np.float32)),
                                                              ("scale", np.ones((shape[0], 1, 1), np.float32)))})
    return root, arrays


def count_hashing(monkeypatch, root):
    """Record every hash a reader computes: whole files (their paths) and blocks (their rows' bytes)."""
    from orbis2 import latents

    files, blocks = [], []
    real_file, real_block = latents.sha256_file, latents.block_digest
    monkeypatch.setattr(latents, "sha256_file", lambda path: files.append(str(path.relative_to(root))) or
                        real_file(path))
    monkeypatch.setattr(latents, "block_digest", lambda rows: blocks.append(rows.nbytes) or real_block(rows))
    return files, blocks


def test_a_window_hashes_the_blocks_that_hold_it_not_the_chunk(tmp_path, smoke_cfg, monkeypatch):
    """Reading one window of a big chunk hashes the blocks that hold its rows (at most its span and a block at each
    end, in each array) and the chunk's small blocks.npy: not the chunk's files."""
    from orbis2.latents import BLOCK_ROWS, BLOCKS

    root, arrays = block_cache(tmp_path / "cache")
    files, blocks = count_hashing(monkeypatch, root)
    ds = LatentWindowDataset(root, "train", smoke_cfg.data)
    assert sorted(files) == ["normalization.npz", f"train/{CHUNKS}", f"train/{CLIPS}"]
    files.clear()
    item = ds[len(ds) // 2]
    assert files == [f"train/train-000000/{BLOCKS}"]  # 3 x 32 bytes a block
    span = smoke_cfg.data.window_span_frames
    row_bytes = sum(a[0].nbytes for a in arrays.values())
    whole = sum(a.nbytes for a in arrays.values())
    assert 0 < sum(blocks) <= (span + 2 * BLOCK_ROWS) * row_bytes < whole / 8, (sum(blocks), whole)
    clip, anchor = (int(a[0]) for a in ds.windows(len(ds) // 2, len(ds) // 2 + 1))
    detail, _ = window_indices(smoke_cfg.data, anchor)
    np.testing.assert_array_equal(item["detail"].numpy(), arrays["detail"][int(ds.clips[clip]["row"]) + detail])
    blocks.clear()
    ds[len(ds) // 2]
    assert blocks == [] and files == [f"train/train-000000/{BLOCKS}"]  # checked once per process


def test_checked_blocks_travel_with_the_pickled_cache(tmp_path, smoke_cfg, monkeypatch):
    """What a process checked (the tables, blocks.npy, each block read) travels to the processes started from it
    (pickled: spawned DataLoader workers, DDP): they hash only the blocks it did not read."""
    root, _ = block_cache(tmp_path / "cache")
    files, blocks = count_hashing(monkeypatch, root)
    ds = LatentWindowDataset(root, "train", smoke_cfg.data)
    ds[3]
    files.clear(), blocks.clear()
    child = pickle.loads(pickle.dumps(ds))
    torch.testing.assert_close(child[3]["detail"], ds[3]["detail"])
    assert files == [] and blocks == []  # checked already, in the process it came from
    assert child.cache._checked.keys() == ds.cache._checked.keys()
    for name, bits in ds.cache._checked.items():
        np.testing.assert_array_equal(child.cache._checked[name], bits)
    child[len(child) - 1]  # another clip's window: its own blocks, nothing else
    assert files == [] and 0 < len(blocks) <= 3 * 4


def test_a_reader_of_the_odometry_hashes_no_latents(setup, monkeypatch):
    """The turn repeats and the steering evaluation read the odometry alone: its blocks and blocks.npy are hashed,
    not a byte of the latents."""
    from orbis2.latents import BLOCK_ROWS, BLOCKS

    tmp, _, _, _ = setup
    files, blocks = count_hashing(monkeypatch, tmp / "cache")
    cache = open_cache(tmp / "cache")
    odometry = cache.arrays("train")["odometry"]
    files.clear()
    odometry[0]
    assert files == [f"train/{cache.index('train').chunks['name'][0]}/{BLOCKS}"]
    assert blocks == [BLOCK_ROWS * 2 * 4]  # one block of float32 [16, 2]
    assert "detail" not in str(cache._checked) and "abstract" not in str(cache._checked)


def test_any_parts_give_the_same_cache_bytes(setup, tmp_path):
    """parts=N encodes each shard where parts=1 does (batches never cross a shard): the same files, byte for byte,
    with decode workers or without; every part's work stays in its own folder."""
    tmp, _, _, _ = setup
    one = files(tmp / "cache")
    for parts, workers in ((2, 0), (4, 2)):  # 4: more parts than the val split's shards
        out = tmp_path / f"cache{parts}"
        build_latent_cache(tmp / "shards", out, tmp / "detail.pt", tmp / "abstract.pt", batch_size=7, device="cpu",
                           parts=parts, workers=workers)
        assert files(out) == one
        assert sorted(p.name for p in (tmp_path / f"cache{parts}.parts").iterdir()) == sorted(
            [WORK_KEY, *(part_name(i, parts) for i in range(parts))])


class Killed(BaseException):
    """Stands for SIGKILL: nothing after it runs (not an Exception, so no handler catches it)."""


@pytest.mark.parametrize("when", ["mid-encoding", "mid-write", "before-its-line", "torn-log"])
def test_a_stopped_part_resumes_at_the_chunk(setup, tmp_path, monkeypatch, when):
    """A part stopped while encoding a shard, while writing its chunk, after writing it but before recording it,
    or while appending its line: started again, it encodes only the shards not recorded (each once), and ends
    with the bytes of a run never stopped."""
    from orbis2 import latents

    tmp, _, _, _ = setup
    tokenizers, _ = load_encoders(tmp / "detail.pt", tmp / "abstract.pt", "cpu")
    encoded = []
    real_encode, real_write, real_save = latents.encode_frames, latents.write_chunk, latents._save

    def encode(tokenizer, frames, autocast=False):
        encoded.append(len(frames) if tokenizer.kind == "detail" else 0)
        if when == "mid-encoding" and len(encoded) == 24:  # a shard holds 60 frames, 9 batches: the second shard
            raise Killed
        return real_encode(tokenizer, frames, autocast)

    def save(path, array):
        if when == "mid-write" and path.parent.name == ".train-000001.partial" and path.name == "abstract.npy":
            raise Killed
        return real_save(path, array)

    def write(folder, arrays, clips):
        digests = real_write(folder, arrays, clips)
        if folder.name == "train-000001" and when == "before-its-line":
            raise Killed
        return digests

    monkeypatch.setattr(latents, "encode_frames", encode)
    monkeypatch.setattr(latents, "_save", save)
    monkeypatch.setattr(latents, "write_chunk", write)
    work = latent_work(tmp_path / "work", tmp / "shards", tokenizers, 7)
    folder = work / part_name(0, 1)
    if when == "torn-log":  # the whole part ran; then the line of its last chunk is torn
        latents.encode_part(tmp / "shards", work, tokenizers, 7)
        lines = (folder / PART_LOG).read_text().splitlines()
        (folder / PART_LOG).write_text("\n".join(lines[:-1]) + "\n" + lines[-1][:25])
    else:
        with pytest.raises(Killed):
            latents.encode_part(tmp / "shards", work, tokenizers, 7)
    lines = (folder / PART_LOG).read_text().splitlines()
    in_place = sum(json.loads(line)["frames"] for line in (lines[:-1] if when == "torn-log" else lines))
    assert in_place == (180 if when == "torn-log" else 60)
    if when == "mid-write":
        assert (folder / "train/.train-000001.partial").is_dir()  # the chunk being written when it stopped
    if when == "before-its-line":
        assert (folder / "train/train-000001").is_dir()  # in place, not recorded: written again

    monkeypatch.setattr(latents, "_save", real_save)
    monkeypatch.setattr(latents, "write_chunk", real_write)
    before = sum(encoded)
    written = latents.encode_part(tmp / "shards", work, tokenizers, 7)
    assert sum(encoded) - before == 220 - in_place  # the frames of the chunks not recorded, once each
    assert not list(folder.glob("*/.*.partial"))
    assert [c["chunk"] for c in written["splits"]["train"]] == ["train-000000", "train-000001", "train-000002"]
    out, before = tmp_path / "cache", sum(encoded)
    latents.build_latent_cache(tmp / "shards", out, tmp / "detail.pt", tmp / "abstract.pt", batch_size=7,
                               device="cpu", work=work)
    assert sum(encoded) - before == 1  # found finished: only the gather's probe of the latents' shape
    assert files(out) == files(tmp / "cache")


def test_a_work_folder_of_other_inputs_is_not_resumed(setup, tmp_path):
    tmp, _, detail, abstract = setup
    work = tmp_path / "work"
    build_latent_cache(tmp / "shards", tmp_path / "a", detail, abstract, batch_size=7, work=work)
    retrained = load_tokenizer(save_detail(tmp_path / "retrained.pt", seed=5))
    build_latent_cache(tmp / "shards", tmp_path / "b", retrained, abstract, batch_size=7, work=work)
    assert json.loads((work / WORK_KEY).read_text())["tokenizers"]["detail"] == retrained.checksum
    a, b = open_cache(tmp_path / "a"), open_cache(tmp_path / "b")
    assert not np.array_equal(a.arrays("train")["detail"][:], b.arrays("train")["detail"][:])
    np.testing.assert_array_equal(a.arrays("train")["abstract"][:], b.arrays("train")["abstract"][:])


def test_a_failure_leaves_no_cache_and_the_finished_chunks(setup, tmp_path):
    """A failed build leaves no cache (nothing half-written at its path); the chunks finished before the failure
    stay in the work folder, for the run that resumes."""
    tmp, _, _, abstract = setup
    detail = load_tokenizer(tmp / "detail.pt")
    calls = {"n": 0}
    encode = detail.model.encode

    def failing(images):
        calls["n"] += 1
        if calls["n"] == 12:  # the second shard's (a shard holds 60 frames: 8 batches)
            raise RuntimeError("tokenizer failed mid-way")
        return encode(images)

    detail.model.encode = failing
    with pytest.raises(RuntimeError, match="mid-way"):
        build_latent_cache(tmp / "shards", tmp_path / "out" / "latents", detail, abstract, batch_size=8)
    assert calls["n"] == 12
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["latents.parts"]
    assert len((tmp_path / "out/latents.parts" / part_name(0, 1) / PART_LOG).read_text().splitlines()) == 1


def test_normalisation_round_trips_through_decoding(setup):
    """normalize -> denormalize -> decode gives the frames decoding the raw latent gives."""
    tmp, _, detail, _ = setup
    g = torch.Generator().manual_seed(0)
    shift = torch.randn(16, 9, 16, generator=g)
    scale = torch.rand(16, generator=g) + 0.5
    save_tokenizer(tmp / "normed.pt", "detail", detail.model, scale, {"preset": "smoke"}, shift=shift)
    tok = load_tokenizer(tmp / "normed.pt")
    z = detail.model.encode(torch.rand(2, 3, 72, 128, generator=g) * 2 - 1)
    x = tok.normalize(z)
    torch.testing.assert_close(x, (z - shift) * scale[:, None, None])
    torch.testing.assert_close(tok.denormalize(x), z, rtol=1e-5, atol=1e-5)
    with torch.no_grad():
        torch.testing.assert_close(tok.model.decode(tok.denormalize(x)), tok.model.decode(z), rtol=1e-4, atol=1e-4)


def test_the_stage_in_parts_then_the_gather(setup, tmp_path):
    """`stages/latents.py --part 1 --parts 2` (what one of the DAG's `latents_part` jobs runs), then the stage without
    --part (the gather, which encodes the part not yet encoded and finds the other done): the cache a one-part
    library build writes."""
    tmp, _, _, _ = setup
    for level, file in (("detail", "detail.pt"), ("abstract", "abstract.pt")):
        (tmp_path / level).mkdir()
        shutil.copy(tmp / file, tmp_path / level / "tokenizer.pt")
    (tmp_path / "params.yaml").write_text(
        (ROOT / "params.yaml").read_text().replace("    batch_size: 32\n", "    batch_size: 7\n", 1))
    stage = [sys.executable, str(ROOT / "stages/latents.py"), "--profile", "smoke", "--shards", str(tmp / "shards"),
             "--detail-tokenizer", str(tmp_path / "detail"), "--abstract-tokenizer", str(tmp_path / "abstract"),
             "--parts", "2"]
    proc = subprocess.run([*stage, "--part", "1"], cwd=tmp_path, capture_output=True, text=True,
                          env=stage_env(tmp_path))
    assert proc.returncode == 0 and "part 0001-of-0002: 160 frames (cpu float32)" in proc.stdout, proc.stderr
    written = json.loads((tmp_path / "data/latent_parts/latents" / f"{part_name(1, 2)}.json").read_text())
    assert [c["chunk"] for c in written["splits"]["train"]] == ["train-000001", "train-000002"]  # 60 frames each
    assert [c["chunk"] for c in written["splits"]["val"]] == ["val-000000"]  # 40: part 0 has no val shard
    proc = subprocess.run([*stage, "--out", str(tmp_path / "cache")], cwd=tmp_path, capture_output=True, text=True,
                          env=stage_env(tmp_path))
    assert proc.returncode == 0 and "220 frames encoded" in proc.stdout and "in 2 parts" in proc.stdout, proc.stderr
    ours, theirs = files(tmp_path / "cache"), files(tmp / "cache")
    assert {**ours, "meta.json": None} == {**theirs, "meta.json": None}
    meta = json.loads((tmp_path / "cache/meta.json").read_text())
    assert meta["tokenizers"]["detail"]["file"] == str(tmp_path / "detail/tokenizer.pt")


def test_the_parts_benchmark_runs_tiny(tmp_path):
    """benchmarks/bench_latent_parts.py at the smoke profile's size: a part's frames/s and each job's peak memory at
    1x and 2x the corpus, flat (the lead measures the paper profile's figures, on a machine of its own)."""
    out = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, "benchmarks/bench_latent_parts.py", "--profile", "smoke", "--episodes", "2",
                           "--seconds", "6", "--scale", "2", "--shard-mb", "0.3", "--json", str(out)], cwd=ROOT,
                          capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    figures = json.loads(out.read_text())
    assert figures["frames_scaled"] == 2 * figures["frames_1x"] == 240 and figures["part_frames_per_s"] > 0
    assert figures["encoder"] == "cpu float32" and figures["chunk_mb"] < 1
    assert figures["peak_ratio"] < 1.1 and figures["gather_peak_ratio"] < 1.1
