"""What verifying shards and latent caches costs: SHA-256 throughput next to a plain read, in one run.

    python benchmarks/bench_integrity.py [--shards data/shards] [--latents data/latents] [--synthetic-mb 512]

(a) a synthetic file of ``--synthetic-mb`` random bytes (a default-profile shard is at most 64 MiB, its
latent cache about 260 MiB) read in 1 MiB blocks, plainly and through SHA-256, warm in the page cache;
(b) ``verify_shards`` over every split of ``--shards`` and (c) the check of every split of
``--latents`` that a reader makes before first use, when those exist. Every figure is warm-cache
throughput: a cold disk adds its own read time, which the stage would pay when reading anyway.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import tempfile
import time
from pathlib import Path
from typing import Callable

from orbis2.data.shards import MANIFEST, verify_shards
from orbis2.latents import META, open_cache

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


def line(label: str, size: int, seconds: float) -> str:
    return f"{label:<22}: {size / 2**20:9.1f} MiB in {seconds:7.2f} s = {size / 2**20 / seconds:7.0f} MiB/s"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--shards", type=Path, default=Path("data/shards"))
    p.add_argument("--latents", type=Path, default=Path("data/latents"))
    p.add_argument("--synthetic-mb", type=int, default=512)
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


if __name__ == "__main__":
    main()
