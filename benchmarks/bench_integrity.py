"""What verifying shards and latent caches costs: SHA-256 throughput next to a plain read, in one run.

    python benchmarks/bench_integrity.py [--shards data/shards] [--latents data/latents] [--synthetic-mb 512]
        [--windows 500] [--profile default] [--chunks 8 --chunk-frames 600]

(a) a synthetic file of ``--synthetic-mb`` random bytes (a default-profile shard is at most 64 MiB, its
latent cache about 260 MiB) read in 1 MiB blocks, plainly and through SHA-256, warm in the page cache;
(b) ``verify_shards`` over every split of ``--shards`` and (c) ``verify`` (every file hashed whole) of
every split of ``--latents``, when those exist. Every figure is warm-cache throughput: a cold disk adds
its own read time, which the stage would pay when reading anyway.
(d) a predictor-like reader: ``--windows`` random windows (the profile's geometry) of the train split of
``--latents`` (or, without one, of a synthetic cache of ``--chunks`` chunks of ``--chunk-frames`` frames
of random latents, the profile's latent shape) read through ``LatentWindowDataset`` in one process: the
bytes its windows read, the bytes it hashes (the blocks holding them and each chunk's ``blocks.npy``),
and what hashing the whole chunk files it touched would have been (cache format 4).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

from orbis2 import latents
from orbis2.config.params import load_config
from orbis2.config.sections import DataConfig
from orbis2.data.shards import MANIFEST, verify_shards
from orbis2.latents import (
    ARRAYS,
    META,
    LatentCacheError,
    LatentWindowDataset,
    clip_table,
    open_cache,
    write_chunk,
    write_meta,
    write_split,
)

BLOCK = 1 << 20


def timed(work: Callable[[], int]) -> tuple[int, float]:
    """Bytes processed and the best wall time of two runs (the first also warms the page cache)."""
    best, size = float("inf"), 0
    for _ in range(2):
        start = time.perf_counter()
        size = work()
        best = min(best, time.perf_counter() - start)
    return size, best


def read_plain(path: Path) -> int:
    size = 0
    with open(path, "rb") as handle:
        while block := handle.read(BLOCK):
            size += len(block)
    return size


def read_hashed(path: Path) -> int:
    digest, size = hashlib.sha256(), 0
    with open(path, "rb") as handle:
        while block := handle.read(BLOCK):
            digest.update(block)
            size += len(block)
    return size


def verify_cache(root: Path) -> int:
    cache = open_cache(root)
    for split in cache.splits:
        cache.verify(split)
    return sum(f.stat().st_size for f in root.rglob("*") if f.is_file() and f.name != META)


def synthetic_cache(root: Path, data: DataConfig, shape: tuple[int, ...], chunks: int, frames: int) -> Path:
    """A train split of ``chunks`` chunks of ``frames`` frames of random latents, 4 clips a chunk."""
    rng, written = np.random.default_rng(0), []
    for c in range(chunks):
        arrays = {kind: rng.standard_normal((frames, *shape)).astype(np.float16) for kind in ("detail", "abstract")}
        arrays["odometry"] = rng.standard_normal((frames, 2)).astype(np.float32)
        lengths = [frames // 4] * 3 + [frames - 3 * (frames // 4)]
        name = f"train-{c:06d}"
        table = clip_table([(f"{name}-{i}", n, True, f"{name}-{i}", 0) for i, n in enumerate(lengths)])
        written.append({"chunk": name, "source": f"train/{name}.tar", "frames": frames, "clips": len(lengths),
                        "sha256": write_chunk(root / "train" / name, arrays, table)})
    meta = {"format": latents.FORMAT, "dtype": "float16", "encoder": "cpu float32",
            "data": {"source": data.source, "fps": data.fps, "width": data.width, "height": data.height},
            "tokenizers": {kind: {"checksum": "0" * 64, "file": None, "shape": list(shape)}
                           for kind in ("detail", "abstract")},
            "splits": {"train": write_split(root / "train", written)}}
    write_meta(root, meta, normalization={f"{kind}_{part}": value for kind in ("detail", "abstract")
                                          for part, value in (("shift", np.zeros(shape, np.float32)),
                                                              ("scale", np.ones((shape[0], 1, 1), np.float32)))})
    return root


def window_reads(root: Path, data: DataConfig, windows: int) -> list[str]:
    """Read ``windows`` random windows of the train split in one process; the bytes read and hashed, as lines."""
    counts = {"read": 0, "blocks": 0, "files": 0}
    rows_read: dict[Path, np.ndarray] = {}  # per file, the rows some window read
    real_get, real_block, real_file = latents.ChunkArray.__getitem__, latents.block_digest, latents.sha256_file

    def get(self: latents.ChunkArray, key: object) -> np.ndarray:
        out = real_get(self, key)
        counts["read"] += out.nbytes
        rows_read.setdefault(self.path, np.zeros(len(self), bool))[key[0] if isinstance(key, tuple) else key] = True
        return out

    def block(rows: np.ndarray) -> bytes:
        counts["blocks"] += rows.nbytes
        return real_block(rows)

    def file(path: Path) -> str:
        counts["files"] += Path(path).stat().st_size
        return real_file(path)

    latents.ChunkArray.__getitem__, latents.block_digest, latents.sha256_file = get, block, file
    try:
        ds = LatentWindowDataset(root, "train", data)
        tables = counts["files"]
        picks = np.random.default_rng(1).integers(0, len(ds), windows)
        start = time.perf_counter()
        for i in picks:
            ds[int(i)]
        seconds = time.perf_counter() - start
    finally:
        latents.ChunkArray.__getitem__, latents.block_digest, latents.sha256_file = real_get, real_block, real_file
    index = ds.cache.index("train")
    touched = np.unique(ds.clips["chunk"][ds.windows()[0][picks]])
    whole = sum((root / "train" / str(index.chunks["name"][c]) / f"{name}.npy").stat().st_size
                for c in touched for name in ARRAYS)
    now = counts["blocks"] + counts["files"] - tables
    distinct = sum(int(rows.sum()) * np.load(path, mmap_mode="r")[0].nbytes for path, rows in rows_read.items())
    mib = lambda n: n / 2**20  # noqa: E731
    return [f"(d) {windows} windows of {root}/train ({len(touched)} of {len(index.chunks)} chunks touched, "
            f"{seconds:.2f} s)",
            f"    read by the windows : {mib(counts['read']):9.2f} MiB ({mib(distinct):.2f} MiB of distinct rows)",
            f"    hashed, by blocks   : {mib(now):9.2f} MiB = {now / distinct:6.2f}x the distinct rows read "
            f"({mib(counts['blocks']):.2f} MiB of rows, {mib(counts['files'] - tables):.2f} MiB of blocks.npy)",
            f"    hashed, whole chunks: {mib(whole):9.2f} MiB = {whole / distinct:6.2f}x the distinct rows read "
            f"(format 4)"]


def line(label: str, size: int, seconds: float) -> str:
    return f"{label:<22}: {size / 2**20:9.1f} MiB in {seconds:7.2f} s = {size / 2**20 / seconds:7.0f} MiB/s"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--shards", type=Path, default=Path("data/shards"))
    p.add_argument("--latents", type=Path, default=Path("data/latents"))
    p.add_argument("--synthetic-mb", type=int, default=512)
    p.add_argument("--windows", type=int, default=500, help="random windows read in (d)")
    p.add_argument("--profile", default=None, help="the windows' geometry and latent shape (params.yaml's default)")
    p.add_argument("--chunks", type=int, default=8, help="chunks of (d)'s synthetic cache")
    p.add_argument("--chunk-frames", type=int, default=600, help="frames a chunk of (d)'s synthetic cache")
    a = p.parse_args()
    print(f"machine               : load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    with tempfile.TemporaryDirectory(prefix="bench_integrity_") as tmp:
        path = Path(tmp) / "synthetic.bin"
        with open(path, "wb") as handle:
            for _ in range(a.synthetic_mb):
                handle.write(os.urandom(BLOCK))
        plain = timed(lambda: read_plain(path))
        hashed = timed(lambda: read_hashed(path))
    print(line("(a) synthetic, read", *plain))
    print(line("(a) synthetic, SHA-256", *hashed))
    print(f"SHA-256 / plain read  : {hashed[1] / plain[1]:9.1f}x the time")
    if (a.shards / MANIFEST).is_file():
        print(line(f"(b) {a.shards}", *timed(lambda: verify_shards(a.shards))))
    if (a.latents / META).is_file():
        print(line(f"(c) {a.latents}", *timed(lambda: verify_cache(a.latents))))
    cfg = load_config("params.yaml", a.profile)
    if a.windows:
        if (a.latents / META).is_file() and "train" in open_cache(a.latents).splits:
            try:
                print("\n".join(window_reads(a.latents, cfg.data, a.windows)))
            except LatentCacheError as err:  # another profile's cache: its windows do not fit this geometry
                print(f"(d) skipped: {err}")
        else:
            shape = (16, cfg.data.height // 16, cfg.data.width // 16)  # the detail tokenizer's, 16x downsampled
            with tempfile.TemporaryDirectory(prefix="bench_integrity_") as tmp:
                root = synthetic_cache(Path(tmp) / "latents", cfg.data, shape, a.chunks, a.chunk_frames)
                print("\n".join(window_reads(root, cfg.data, a.windows)))


if __name__ == "__main__":
    main()
