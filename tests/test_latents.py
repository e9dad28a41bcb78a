"""Latent cache: equal to fresh encoding, keys and offsets, stale-tokenizer refusal, sampler partitioning, atomicity."""

import pickle
import re

import numpy as np
import pytest
import torch
from test_shards import make_raw
from torch.utils.data import DataLoader, DistributedSampler

from orbis2.data.shards import MANIFEST, Clip, anchor_range, clip_window, iter_samples, shard_paths, write_shards
from orbis2.latents import (
    LatentCacheError,
    LatentWindowDataset,
    build_latent_cache,
    encode_window,
    open_cache,
    sha256_file,
)
from orbis2.models.files import load_tokenizer, save_tokenizer
from orbis2.models.tokenizer import build_abstract_tokenizer, build_detail_tokenizer

DETAIL_SCALE, ABSTRACT_SCALE = 0.8, 1.7


def save_detail(path, seed):
    torch.manual_seed(seed)
    save_tokenizer(path, "detail", build_detail_tokenizer("smoke"), DETAIL_SCALE, {"preset": "smoke"})
    return path


@pytest.fixture(scope="module")
def setup(tmp_path_factory, smoke_cfg):
    """Shards of 6 train clips (30 frames) and 1 val clip (40 frames), two smoke tokenizers, the cache."""
    tmp = tmp_path_factory.mktemp("latents")
    make_raw(tmp / "raw", smoke_cfg, episodes=(("train", 3, 64), ("val", 1, 40)))
    write_shards(tmp / "raw", tmp / "shards", smoke_cfg.data, smoke_cfg.shards)
    detail_path = save_detail(tmp / "detail.pt", seed=0)
    torch.manual_seed(1)
    save_tokenizer(tmp / "abstract.pt", "abstract", build_abstract_tokenizer("smoke", teacher_dim=32),
                   ABSTRACT_SCALE, {"preset": "smoke", "teacher_dim": 32, "compress": True})
    meta = build_latent_cache(tmp / "shards", tmp / "cache", detail_path, tmp / "abstract.pt", batch_size=7,
                              device="cpu")
    return tmp, meta, load_tokenizer(detail_path), load_tokenizer(tmp / "abstract.pt")


def clips(root, split):
    return [Clip.from_sample(s) for path in shard_paths(root, split) for s in iter_samples(path)]


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


def test_keys_offsets_and_meta_round_trip(setup):
    tmp, meta, detail, abstract = setup
    cache = open_cache(tmp / "cache", detail.checksum, abstract.checksum)
    for split in ("train", "val"):
        index, arrays = cache.index(split), cache.arrays(split)
        expected = clips(tmp / "shards", split)
        assert sorted(index, key=lambda k: index[k]["offset"]) == [c.key for c in expected]
        offset = 0
        for clip in expected:
            entry = index[clip.key]
            assert entry == {"offset": offset, "length": len(clip), "has_odometry": True,
                             "episode": clip.meta["episode"], "start_frame": clip.meta["start_frame"]}
            np.testing.assert_array_equal(arrays["odometry"][offset:offset + len(clip)], clip.odometry)
            offset += len(clip)
        assert arrays["detail"].shape[0] == arrays["abstract"].shape[0] == offset == meta["splits"][split]["frames"]
        assert arrays["detail"].dtype == np.float16 and isinstance(arrays["detail"], np.memmap)
    assert cache.splits == ["train", "val"]
    assert meta["shards"]["manifest_sha256"] == sha256_file(tmp / "shards" / MANIFEST)
    assert meta["tokenizers"]["detail"]["checksum"] == sha256_file(tmp / "detail.pt") == detail.checksum
    z = torch.from_numpy(cache.arrays("val")["abstract"][:3].astype(np.float32))
    torch.testing.assert_close(cache.normalize("abstract", z), abstract.normalize(z))
    torch.testing.assert_close(cache.normalize("detail", z), z * DETAIL_SCALE)
    assert meta["data"]["fps"] == 10 and meta["data"]["width"] == 128


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
    assert len(LatentWindowDataset(tmp / "cache", "train", smoke_cfg.data, anchor_stride=2)) == 6 * 3
    seen = []
    for rank in range(2):
        sampler = DistributedSampler(ds, num_replicas=2, rank=rank, shuffle=True, seed=3)
        loader = DataLoader(ds, batch_size=4, sampler=sampler, num_workers=2 if rank else 0)
        for batch in loader:
            assert batch["detail"].shape[:2] == (len(batch["key"]), 10)
            seen += list(zip(batch["key"], batch["anchor"].tolist()))
    assert len(seen) == len(set(seen)) == len(ds)
    assert set(seen) == {(ds.keys[c], a) for c, a in ds.items.tolist()}


def test_pickled_dataset_maps_instead_of_copying(setup, smoke_cfg):
    tmp, _, _, _ = setup
    ds = LatentWindowDataset(tmp / "cache", "train", smoke_cfg.data)
    item = ds[7]
    blob = pickle.dumps(ds)  # what spawn-started DataLoader workers receive
    norm_bytes = sum(t.numel() * t.element_size() for t in ds.cache.norm.values())  # fixed size, not data
    assert len(blob) < 20_000 + norm_bytes
    torch.testing.assert_close(pickle.loads(blob)[7]["detail"], item["detail"])


def test_failure_mid_way_leaves_nothing(setup, tmp_path):
    tmp, _, _, abstract = setup
    detail = load_tokenizer(tmp / "detail.pt")
    calls = {"n": 0}
    encode = detail.model.encode

    def failing(images):
        calls["n"] += 1
        if calls["n"] == 4:
            raise RuntimeError("tokenizer failed mid-way")
        return encode(images)

    detail.model.encode = failing
    with pytest.raises(RuntimeError, match="mid-way"):
        build_latent_cache(tmp / "shards", tmp_path / "out" / "latents", detail, abstract, batch_size=8)
    assert calls["n"] == 4
    assert list((tmp_path / "out").iterdir()) == []


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


def test_decoding_in_worker_processes_gives_the_same_latents(setup, tmp_path):
    tmp, meta, detail, abstract = setup
    again = build_latent_cache(tmp / "shards", tmp_path / "cache", tmp / "detail.pt", tmp / "abstract.pt",
                               batch_size=7, device="cpu", decode_workers=2)
    assert again["splits"] == meta["splits"]
    first = open_cache(tmp / "cache", detail.checksum, abstract.checksum)
    second = open_cache(tmp_path / "cache", detail.checksum, abstract.checksum)
    for split in ("train", "val"):
        a, b = first.index(split), second.index(split)
        assert sorted(a) == sorted(b)
        for key in a:
            rows = [slice(i[key]["offset"], i[key]["offset"] + i[key]["length"]) for i in (a, b)]
            for kind in ("detail", "abstract"):
                np.testing.assert_allclose(first.arrays(split)[kind][rows[0]], second.arrays(split)[kind][rows[1]],
                                           rtol=0, atol=1e-3)
