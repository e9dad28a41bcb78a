"""Training batches from the latent cache vs decoding shard JPEGs and encoding them on the fly.

    python benchmarks/bench_latent_cache.py [--profile smoke|default|paper] [--batches 20 --batch-size 8]
        [--shards data/shards --detail data/tokenizers/detail/tokenizer.pt
         --abstract data/tokenizers/abstract/tokenizer.pt --latents data/latents] [--synthetic]

Both paths produce the same collated batches (detail + abstract latent windows and odometry) in the
main process with the same torch threads, timed side by side in one run after one warm-up batch:
(a) ``LatentWindowDataset`` over the memory-mapped cache, shuffled; (b) ``WindowDataset`` over the
shards (tar read, JPEG decode) with both tokenizers encoding each window (``encode_window``).
Uses the profile's shards and trained tokenizers when they exist (and ``--latents`` when it was
built from them); otherwise builds a small synthetic setup of the profile's geometry with
random-weight tokenizers of the profile's presets in a temporary folder, so it always runs.
"""

from __future__ import annotations

import argparse
import itertools
import os
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
from corpus import random_tokenizers
from torch.utils.data import DataLoader, default_collate

from orbis2.config.params import PipelineConfig, load_config
from orbis2.data.episodes import EpisodeRecord, RawIndex, write_odometry
from orbis2.data.shards import MANIFEST, WindowDataset, write_shards
from orbis2.data.video import write_video
from orbis2.errors import OrbisError
from orbis2.latents import LatentCache, LatentWindowDataset, build_latent_cache, encode_window, open_cache, sha256_file
from orbis2.models.files import load_tokenizer


def synthetic_setup(cfg: PipelineConfig, root: Path, episodes: int = 4) -> tuple[Path, Path, Path]:
    """Train-split shards of drifting textures (two clips per episode) and random-weight tokenizers."""
    data, rng = cfg.data, np.random.default_rng(0)
    n = 2 * round(cfg.shards.clip_seconds["train"] * data.fps)
    records = []
    (root / "raw/train").mkdir(parents=True)
    for e in range(episodes):
        texture = rng.integers(0, 255, (data.height // 8 + 1, data.width // 8 + n // 8 + 2, 3), dtype=np.uint8)
        texture = np.repeat(np.repeat(texture, 8, 0), 8, 1)[:data.height]
        write_video(root / "raw/train" / f"ep_train_{e:05d}.mp4",
                    (texture[:, k:k + data.width] for k in range(n)), data.fps)
        k, zeros = np.arange(n, dtype=float), np.zeros(n)
        write_odometry(root / "raw/train" / f"ep_train_{e:05d}.parquet", data.fps, np.full(n, 5.0),
                       0.1 * np.sin(k / 9), (0.5 * k, zeros, zeros))
        records.append(EpisodeRecord("train", f"ep_train_{e:05d}", n, True, True, origin="synthetic"))
    RawIndex("synthetic", data.fps, data.width, data.height, None, records).write(root / "raw")
    write_shards(root / "raw", root / "shards", data, cfg.shards)
    return root / "shards", *random_tokenizers(root, cfg)


def reusable_cache(root: Path, shards: Path, split: str, detail: Any, abstract: Any) -> LatentCache | None:
    """The existing cache if it was built from these shards and tokenizers and holds ``split``."""
    try:
        cache = open_cache(root, detail.checksum, abstract.checksum)
        cache.arrays(split)
    except OrbisError:
        return None
    return cache if cache.meta["shards"]["manifest_sha256"] == sha256_file(shards / MANIFEST) else None


def on_the_fly(shards: Path, split: str, cfg: PipelineConfig, detail: Any, abstract: Any,
               batch_size: int) -> Iterator[dict[str, Any]]:
    """Batches the way training would make them without a cache: one random window per clip per epoch."""
    def windows() -> Iterator[dict[str, Any]]:
        for epoch in itertools.count():
            for window in WindowDataset(shards, split, cfg.data, seed=0, epoch=epoch, rank=0, world=1):
                yield encode_window(window, detail, abstract)

    stream = windows()
    while True:
        yield default_collate([next(stream) for _ in range(batch_size)])


def from_cache(cache: LatentCache, split: str, cfg: PipelineConfig, batch_size: int) -> Iterator[dict[str, Any]]:
    dataset = LatentWindowDataset(cache, split, cfg.data)
    for epoch in itertools.count():
        loader = DataLoader(dataset, batch_size=batch_size, shuffle=True, drop_last=True,
                            generator=torch.Generator().manual_seed(epoch))
        yield from loader


def seconds_per_batch(batches: Iterator[dict[str, Any]], n: int) -> float:
    next(batches)  # warm-up: first shard open, first page faults, allocator
    start = time.perf_counter()
    for _ in range(n):
        next(batches)
    return (time.perf_counter() - start) / n


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--params", default="params.yaml")
    p.add_argument("--profile", default=None, help="smoke | default | paper (default: params.yaml's profile)")
    p.add_argument("--shards", type=Path, default=Path("data/shards"))
    p.add_argument("--detail", type=Path, default=Path("data/tokenizers/detail/tokenizer.pt"))
    p.add_argument("--abstract", type=Path, default=Path("data/tokenizers/abstract/tokenizer.pt"))
    p.add_argument("--latents", type=Path, default=Path("data/latents"), help="an existing cache to reuse")
    p.add_argument("--split", default="train")
    p.add_argument("--batches", type=int, default=20)
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--synthetic", action="store_true", help="use the synthetic setup even if real data exists")
    a = p.parse_args()
    cfg = load_config(a.params, a.profile)
    real = not a.synthetic and all(path.is_file() for path in (a.shards / "manifest.json", a.detail, a.abstract))
    with tempfile.TemporaryDirectory(prefix="bench_latents_") as tmp:
        tmp = Path(tmp)
        shards, detail_path, abstract_path = (a.shards, a.detail, a.abstract) if real else synthetic_setup(cfg, tmp)
        detail, abstract = load_tokenizer(detail_path), load_tokenizer(abstract_path)
        print(f"profile        : {cfg.profile}, {cfg.data.width}x{cfg.data.height}, "
              f"{'shards ' + str(shards) if real else 'synthetic shards + random-weight tokenizers'} "
              f"(presets {detail.build['preset']}/{abstract.build['preset']}), split {a.split}")
        print(f"machine        : {torch.get_num_threads()} torch threads, load average "
              f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
        cache = reusable_cache(a.latents, shards, a.split, detail, abstract) if real else None
        if cache is not None:
            print(f"cache          : reusing {a.latents}")
        else:
            start = time.perf_counter()
            meta = build_latent_cache(shards, tmp / "latents", detail, abstract, cfg.latents.batch_size,
                                      splits=[a.split])
            took, frames = time.perf_counter() - start, meta["splits"][a.split]["frames"]
            print(f"cache build    : {took:.1f} s for {frames} frames ({frames / took:.0f} frames/s, one-off)")
            cache = open_cache(tmp / "latents")
        windows = len(LatentWindowDataset(cache, a.split, cfg.data))
        print(f"batches        : {a.batches} x {a.batch_size} windows "
              f"({cfg.data.detail_window} detail + {cfg.data.abstract_window} abstract frames) "
              f"from {windows} cached windows")
        t_cache = seconds_per_batch(from_cache(cache, a.split, cfg, a.batch_size), a.batches)
        t_fly = seconds_per_batch(on_the_fly(shards, a.split, cfg, detail, abstract, a.batch_size), a.batches)
    print(f"(a) from cache : {1 / t_cache:9.1f} batches/s ({1000 * t_cache:8.2f} ms/batch)")
    print(f"(b) on the fly : {1 / t_fly:9.1f} batches/s ({1000 * t_fly:8.2f} ms/batch)")
    print(f"ratio (a)/(b)  : {t_fly / t_cache:9.1f}x  (target >= 20x)")


if __name__ == "__main__":
    main()
