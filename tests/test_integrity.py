"""No silent corruption: a damaged shard or latent cache stops the stage that reads it (exit 2, the file named); a
cache's rows are checked, a block of them at a time, by whoever reads them, when it first does.

The stage scripts run as subprocesses on small synthetic shards and a smoke-tokenizer cache built here.
"""

import dataclasses
import os
import shutil
import subprocess
import sys
import tarfile

import numpy as np
import pytest
import torch
from test_latents import save_detail
from test_shards import make_raw

from orbis2 import dag
from orbis2.data import shards as shards_module
from orbis2.data.shards import (
    FrameDataset,
    ShardError,
    iter_clips,
    iter_samples,
    shard_paths,
    split_clips,
    verify_shards,
    write_shards,
)
from orbis2.latents import BLOCK_ROWS, LatentCacheError, LatentWindowDataset, build_latent_cache, open_cache
from orbis2.models.files import save_tokenizer
from orbis2.models.tokenizer import build_abstract_tokenizer
from orbis2.tasks.tokenizers import frame_batches

from conftest import ROOT


@pytest.fixture(scope="module")
def project(tmp_path_factory, smoke_cfg):
    """A project folder: params.yaml, shards (two train clips, a shard each, and one val clip), both tokenizers,
    the latent cache (a chunk per shard)."""
    root = tmp_path_factory.mktemp("project")
    (root / "params.yaml").write_text((ROOT / "params.yaml").read_text())
    make_raw(root / "raw", smoke_cfg, episodes=(("train", 2, 30), ("val", 1, 30)))
    shards = dataclasses.replace(smoke_cfg.shards, max_shard_mb=0.05)  # a shard per clip
    write_shards(root / "raw", root / "shards", smoke_cfg.data, shards)
    (root / "detail").mkdir()
    (root / "abstract").mkdir()
    save_detail(root / "detail" / "tokenizer.pt", seed=0)
    torch.manual_seed(1)
    save_tokenizer(root / "abstract" / "tokenizer.pt", "abstract", build_abstract_tokenizer("smoke", teacher_dim=32),
                   1.0, {"preset": "smoke", "teacher_dim": 32, "compress": True})
    build_latent_cache(root / "shards", root / "latents", root / "detail" / "tokenizer.pt",
                       root / "abstract" / "tokenizer.pt", batch_size=16, device="cpu")
    return root


def copy_of(project, tmp_path, name):
    shutil.copytree(project / name, tmp_path / name)
    return tmp_path / name


def flip(path, offset):
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x5A
    path.write_bytes(bytes(data))


def run_stage(cwd, project, script, *args):
    env = {"MLFLOW_TRACKING_URI": f"sqlite:///{cwd / 'mlflow.db'}", "PATH": "/usr/bin:/bin"}
    if "PYTHONPATH" in os.environ:
        env["PYTHONPATH"] = os.environ["PYTHONPATH"]
    shutil.copy(project / "params.yaml", cwd / "params.yaml")
    return subprocess.run([sys.executable, str(ROOT / "stages" / script), "--profile", "smoke", *map(str, args)],
                          cwd=cwd, capture_output=True, text=True, env=env, timeout=300)


def first_member(shard):
    """The first member (the first sample's first JPEG) of a shard: its header and payload offsets."""
    with tarfile.open(shard) as tar:
        member = tar.next()
    assert member.name.endswith(".0000.jpg")
    return member


def test_a_flipped_jpeg_byte_stops_the_latents_stage(project, tmp_path):
    shards = copy_of(project, tmp_path, "shards")
    shard = shard_paths(shards, "train")[0]
    member = first_member(shard)
    flip(shard, member.offset_data + member.size // 2)
    assert len(list(iter_samples(shard))) == 1  # reading alone does not notice: the JPEG still decodes
    proc = run_stage(tmp_path, project, "latents.py", "--shards", shards, "--detail-tokenizer", project / "detail",
                     "--abstract-tokenizer", project / "abstract", "--out", tmp_path / "latents")
    assert proc.returncode == 2, proc.stderr
    assert f"{shard}: content does not match the manifest's hash" in proc.stderr
    assert "re-run the `shards` stage" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "latents").exists()


def test_a_flipped_tar_header_byte_stops_the_readers_of_that_shard(project, tmp_path):
    shards = copy_of(project, tmp_path, "shards")
    shard = shard_paths(shards, "val")[0]
    flip(shard, first_member(shard).offset + 3)  # inside the member's name field
    with pytest.raises(ShardError, match=f"{shard}: content does not match"):
        verify_shards(shards)
    assert len(list(FrameDataset(shards, "train", rank=0, world=1))) > 0  # the other split's readers go on
    for read in (lambda: list(FrameDataset(shards, "val", rank=0, world=1)), lambda: split_clips(shards, "val"),
                 lambda: list(frame_batches(shards, "val", 4, 2, seed=0))):
        with pytest.raises(ShardError, match=f"{shard}: content does not match the manifest's hash"):
            read()


def test_a_reader_hashes_only_the_shards_it_reads(project, monkeypatch):
    hashed = []
    real = shards_module._stream_digest
    monkeypatch.setattr(shards_module, "_stream_digest", lambda url, bar=None: hashed.append(url) or real(url, bar))
    train = shard_paths(project / "shards", "train")
    assert len(train) == 2
    first = list(FrameDataset(project / "shards", "train", rank=0, world=2))  # rank 0 of 2 takes the first shard
    assert first and hashed == [str(train[0])]
    hashed.clear()
    assert list(iter_clips(project / "shards", "val")) and hashed == [str(shard_paths(project / "shards", "val")[0])]
    hashed.clear()  # an evaluation part: only the shards that hold its clips, named as the latent cache names them
    second = list(iter_clips(project / "shards", "train", sources=[f"train/{train[1].name}"]))
    assert second and hashed == [str(train[1])]
    first_keys = {c.key for c in iter_clips(project / "shards", "train", [f"train/{train[0].name}"])}
    assert first_keys and not first_keys & {c.key for c in second}


def test_truncated_or_missing_shard_is_named(project, tmp_path):
    shards = copy_of(project, tmp_path, "shards")
    assert verify_shards(shards, ["val"]) == shard_paths(shards, "val")[0].stat().st_size
    shard = shard_paths(shards, "train")[0]
    shard.write_bytes(shard.read_bytes()[:-1024])
    with pytest.raises(ShardError, match=f"{shard}: .* bytes, the manifest says .*truncated"):
        verify_shards(shards)
    verify_shards(shards, ["val"])  # a stage may check only the splits it reads
    shard.unlink()
    with pytest.raises(ShardError, match=f"{shard}: listed in the manifest but missing"):
        verify_shards(shards)


def test_shards_read_from_a_url_are_verified_as_streamed(project, tmp_path):
    shards = copy_of(project, tmp_path, "shards")
    base = f"pipe:cat {shards}/{{}}"
    assert verify_shards(shards, base=base) == sum(p.stat().st_size for p in shards.rglob("*.tar"))
    shard = shard_paths(shards, "val")[0]
    flip(shard, first_member(shard).offset_data)
    with pytest.raises(ShardError, match=f"pipe:cat {shards}/val/val-000000.tar: content does not match"):
        verify_shards(shards, base=base)

def detail_array(cache, split="train", chunk=0):
    """A chunk's detail.npy and the offset of the first byte after its .npy header."""
    path = cache / split / str(open_cache(cache).index(split).chunks["name"][chunk]) / "detail.npy"
    return path, np.load(path, mmap_mode="r").offset


def test_a_flipped_latent_byte_stops_the_predictor_stage(project, tmp_path):
    cache = copy_of(project, tmp_path, "latents")
    path, data_start = detail_array(cache)
    flip(path, data_start + 101)
    proc = run_stage(tmp_path, project, "predictor.py", "abstract_df", "--latents", cache,
                     "--detail-tokenizer", project / "detail", "--abstract-tokenizer", project / "abstract",
                     "--out", tmp_path / "predictor", "--report", tmp_path / "report.json")
    assert proc.returncode == 2, proc.stderr
    assert f"{path}: content does not match the SHA-256 recorded in train/chunks.npy" in proc.stderr
    assert "re-run the `latents` stage" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "predictor").exists() and not (tmp_path / "report.json").exists()


def test_cache_rows_are_checked_by_block_when_first_read(project, tmp_path, smoke_cfg):
    """A flipped byte stops the readers of the block of rows that holds it (naming the file) and no other: a reader
    of the chunk's other rows, another chunk's, another split's, or a reader of the split's tables goes on; the
    check by hand (``verify``) hashes whole files and finds it."""
    cache = copy_of(project, tmp_path, "latents")
    index = open_cache(cache).index("train")
    assert len(index.chunks) == 2 and int(index.chunks["frames"][1]) > BLOCK_ROWS
    path, data_start = detail_array(cache, "train", 1)
    row_bytes = np.load(path, mmap_mode="r")[0].nbytes
    flip(path, data_start + BLOCK_ROWS * row_bytes + 5)  # the chunk's second block
    opened = open_cache(cache)
    train = LatentWindowDataset(opened, "train", smoke_cfg.data)  # the tables are intact
    train[0]  # the first chunk's windows: intact
    first = int(index.chunks["first_row"][1])
    detail = opened.arrays("train")["detail"]
    detail[first:first + BLOCK_ROWS]  # the damaged chunk's first block: intact
    opened.arrays("train")["odometry"][:]  # the damaged chunk's other arrays: intact
    opened.arrays("val")["detail"][:]  # another split's chunks: intact
    for use in (lambda: train[len(train) - 1], lambda: detail[first + BLOCK_ROWS],
                lambda: opened.arrays("train")["detail"][:], lambda: open_cache(cache).verify("train")):
        with pytest.raises(LatentCacheError, match=f"{path}: content does not match the SHA-256 recorded in "
                                                   f"train/chunks.npy"):
            use()
    flip(path, data_start + BLOCK_ROWS * row_bytes + 5)  # restored
    assert open_cache(cache).verify("train") == 2 + 5 * 2
    clips = cache / "val" / "clips.npy"
    flip(clips, clips.stat().st_size - 1)
    with pytest.raises(LatentCacheError, match=f"{clips}: content does not match the SHA-256 recorded in meta.json"):
        open_cache(cache).index("val")
    flip(cache / "normalization.npz", 100)
    with pytest.raises(LatentCacheError, match="normalization.npz: content does not match"):
        open_cache(cache)


def test_truncated_missing_or_replaced_cache_files_are_named(project, tmp_path, smoke_cfg):
    """Mapping a chunk's array checks its header and size (no hashing): a truncated, extended, missing or rewritten
    file is named when the chunk is first read; so is a damaged blocks.npy, and a cache of the former format."""
    cache = copy_of(project, tmp_path, "latents")
    path, _ = detail_array(cache, "val")
    original = path.read_bytes()
    array = np.load(path)
    for damaged, message in ((original[:-7], "unreadable"), (original + b"\0", f"{len(original) + 1} bytes, its "
                                                                                 f"header says {len(original)}")):
        path.write_bytes(damaged)
        with pytest.raises(LatentCacheError, match=f"{path}: {message}.*re-run the `latents` stage"):
            open_cache(cache).arrays("val")["detail"][0]
    np.save(path, array.astype(np.float32))  # the same values, another dtype
    with pytest.raises(LatentCacheError, match=f"{path}: a float32 array in C order, the cache's tables say float16"):
        open_cache(cache).arrays("val")["detail"][0]
    np.save(path, array[:-1])
    with pytest.raises(LatentCacheError, match=f"{path}: shape .*, the cache's tables say"):
        open_cache(cache).arrays("val")["detail"][0]
    path.unlink()
    with pytest.raises(LatentCacheError, match=f"{path}: missing from the latent cache; re-run the `latents` stage"):
        open_cache(cache).arrays("val")["detail"][0]
    path.write_bytes(original)
    blocks = path.with_name("blocks.npy")
    flip(blocks, blocks.stat().st_size - 1)
    opened = open_cache(cache)
    with pytest.raises(LatentCacheError, match=f"{blocks}: content does not match the SHA-256 recorded in "
                                               f"val/chunks.npy"):
        opened.arrays("val")["odometry"][0]
    meta = cache / "meta.json"
    meta.write_text(meta.read_text().replace('"format": 5', '"format": 4'))
    with pytest.raises(LatentCacheError, match="cache format 4, this code reads 5; re-run the `latents` stage"):
        open_cache(cache)


def test_every_reader_of_shards_or_a_cache_takes_their_files_as_inputs():
    """Snakemake sees a file changed in place only if it is an input: each reader lists the folder's files."""
    rules = {rule.name: rule for rule in dag.snakemake_rules(ROOT)}
    folders = {"shards": "shard_files", "latents": "latent_files"}
    readers = {key: [r for r in rules.values() if key in r.input.keys()] for key in folders}
    assert len(readers["shards"]) >= 7 and len(readers["latents"]) >= 5
    for key, files in folders.items():
        for rule in readers[key]:
            assert callable(getattr(rule.input, files, None)), f"rule {rule.name}: no {files} input"
    assert all(rules[name].is_checkpoint for name in ("shards", "latents", "latents_full"))
