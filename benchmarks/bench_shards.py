"""Shard writing at the paper's resolution: frames/s of one part, two parts side by side, and each part's peak
memory as the corpus grows.

    python benchmarks/bench_shards.py [--scale 4] [--size 512x288] [--json out.json]

A raw town corpus is rendered once at 512x288 (the paper's resolution; the smoke profile's episode plan),
then grown to ``--scale`` times its episodes by linking its files under new names (the writer's work per
frame does not depend on which episode it is). Each measurement runs ``write_part`` in a fresh process, on
the shards' settings of the paper profile (JPEG quality, clip lengths, shard size), and reports its wall
time and peak resident memory (``ru_maxrss``):

- one part, alone: frames/s per core (decode, JPEG encode, tar, hash);
- two parts of the same corpus at once, one process each: the speed-up over one part (2 cores);
- one part of the 1x corpus against one part of the ``--scale`` x corpus: peak memory (flat when the
  writer streams: it holds one clip, whatever the corpus).

Run it alone on the machine: anything else running changes the wall times.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from corpus import cpu_model, grown

PAPER = "512x288"

WORKER = """
import dataclasses, json, resource, sys, time
from pathlib import Path
from orbis2.config.params import load_config
from orbis2.data.shards import write_part
raw, work, part, parts, width, height = sys.argv[1:]
shards = load_config("params.yaml", "paper").shards
data = dataclasses.replace(load_config("params.yaml", "smoke").data, width=int(width), height=int(height))
start, before = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
written = write_part(Path(raw), Path(work), data, shards, int(part), int(parts))
seconds, after = time.perf_counter() - start, resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"seconds": seconds, "peak_mb": after.ru_maxrss / 1024,
                  "frames": sum(s["frames"] for split in written["splits"].values() for s in split),
                  "cpu_s": after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime}))
"""


def render(root: Path, size: tuple[int, int]) -> None:
    """The smoke profile's town plan at ``size`` (W, H)."""
    from orbis2.config.params import load_config
    from orbis2.data.town_dataset import build_town_dataset

    smoke = load_config("params.yaml", "smoke")
    build_town_dataset(root, dataclasses.replace(smoke.data, width=size[0], height=size[1]), smoke.town)


def run_parts(raw: Path, work: Path, parts: list[int], of: int, size: tuple[int, int]) -> list[dict]:
    """``write_part`` for each of ``parts`` (of ``of``), one process each, all at once."""
    shutil.rmtree(work, ignore_errors=True)
    procs = [subprocess.Popen([sys.executable, "-c", WORKER, str(raw), str(work), str(p), str(of), *map(str, size)],
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                              env={**os.environ, "OMP_NUM_THREADS": "1"}) for p in parts]
    out = []
    for proc in procs:
        stdout, _ = proc.communicate()
        if proc.returncode:
            raise SystemExit(f"write_part failed ({proc.returncode})")
        out.append(json.loads(stdout.strip().splitlines()[-1]))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scale", type=int, default=4, help="the grown corpus, in copies of the rendered one")
    p.add_argument("--size", default=PAPER, help=f"frame size WxH (default: the paper's, {PAPER})")
    p.add_argument("--json", type=Path, default=None, help="also write the figures here")
    a = p.parse_args()
    size = tuple(int(v) for v in a.size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        render(tmp / "base", size)
        print(f"rendered the corpus at {a.size} in {time.perf_counter() - t:.0f} s")
        one = grown(tmp / "base", tmp / "x1", 2)  # two copies: two parts of equal work
        big = grown(tmp / "base", tmp / f"x{a.scale}", 2 * a.scale)
        raw_bytes = sum(f.stat().st_size for f in (tmp / "base").rglob("*.mp4"))
        raw_frames = sum(e["frames"] for e in json.loads((tmp / "base/index.json").read_text())["episodes"])
        alone = run_parts(big, tmp / "work", [0], 1, size)[0]  # the rates on the grown corpus: seconds, not one
        shard_bytes = sum(f.stat().st_size for f in (tmp / "work").rglob("*.tar"))
        pair = run_parts(big, tmp / "work", [0, 1], 2, size)  # file's start-up (imports on first use)
        small, large = run_parts(one, tmp / "work", [0], 1, size)[0], run_parts(big, tmp / "work", [0], 1, size)[0]
    rate = alone["frames"] / alone["seconds"]
    both = sum(r["frames"] for r in pair) / max(r["seconds"] for r in pair)
    figures = {"resolution": a.size, "frames": alone["frames"], "one_part_frames_per_s": rate,
               "shard_bytes_per_frame": shard_bytes / alone["frames"],
               "raw_video_bytes_per_frame": raw_bytes / raw_frames, "scale": a.scale,
               "one_part_cores": alone["cpu_s"] / alone["seconds"], "two_parts_frames_per_s": both,
               "two_parts_speedup": both / rate,
               "peak_mb_1x": small["peak_mb"], "peak_mb_scaled": large["peak_mb"],
               "peak_ratio": large["peak_mb"] / small["peak_mb"], "frames_1x": small["frames"],
               "frames_scaled": large["frames"], "cpus": os.cpu_count(), "cpu": cpu_model()}
    print(f"one part         : {rate:7.1f} frames/s ({alone['frames']} frames at {figures['resolution']}, "
          f"{alone['cpu_s'] / alone['seconds']:.2f} cores busy)")
    print(f"two parts at once: {both:7.1f} frames/s, {both / rate:.2f}x one part")
    print(f"peak memory      : {small['peak_mb']:.0f} MB at 1x ({small['frames']} frames), "
          f"{large['peak_mb']:.0f} MB at {a.scale}x ({large['frames']} frames): ratio {figures['peak_ratio']:.3f}")
    if a.json:
        a.json.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
