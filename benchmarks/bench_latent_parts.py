"""The latent cache in parts: one part's frames/s on this machine's device, and each job's peak memory as the corpus
grows.

    python benchmarks/bench_latent_parts.py [--profile paper] [--scale 4] [--episodes 8] [--json out.json]

A synthetic raw corpus (drifting textures, the profile's resolution, ``--episodes`` train episodes of
``--seconds``) is cut into shards of ``--shard-mb`` (smaller than the profile's, so that even the 1x corpus
spans several shards), then grown to ``--scale`` times its episodes by linking its files under new names and
cut again. Random-weight tokenizers of the profile's presets stand in for trained ones (the encoders' work does
not depend on their weights). Each measurement runs in a fresh process and reports its wall time and peak
resident memory (``ru_maxrss``; its decode workers' separately):

- one part (``encode_part``, parts=1) of the 1x and of the ``--scale`` x corpus, with the profile's
  ``latents.batch_size`` and the stage's decode workers (``orbis2.latents.decode_workers``: on CUDA every core
  this process may use but one, at most 8; on the CPU none), on CUDA when there is one (bfloat16 autocast),
  else the CPU:
  frames/s of a part (the encoding alone, the encoders already loaded), and peak memory (flat: a part holds the
  encoders and the shards in flight, whatever the corpus);
- the gather of each (``gather_parts``): its peak memory (the clip table goes to disk through a memory map).

Run it alone on the machine: anything else running changes the wall times. ``--profile smoke --episodes 2
--scale 2`` runs in seconds (what the test suite runs).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from corpus import cpu_model, grown, random_tokenizers

WORKER = """
import json, resource, sys, time
from pathlib import Path
import torch
from orbis2.latents import decode_workers, encode_part, gather_parts, latent_work, load_encoders
shards, work, out, detail, abstract, batch, workers, job = sys.argv[1:]
workers = None if workers == "auto" else int(workers)
started = time.perf_counter()
tokenizers, files = load_encoders(Path(detail), Path(abstract))
loaded = time.perf_counter()
work = latent_work(Path(work), Path(shards), tokenizers, int(batch))
if job == "part":
    workers = decode_workers(tokenizers) if workers is None else workers
    written = encode_part(Path(shards), work, tokenizers, int(batch), workers=workers)
    Path(out).write_text(json.dumps(written))
else:
    written = json.loads(Path(out).read_text())
    gather_parts(Path(shards), [written], Path(out).with_suffix(""), tokenizers, files)
done = time.perf_counter()
me, children = (resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
print(json.dumps({"seconds": done - loaded, "load_seconds": loaded - started, "peak_mb": me.ru_maxrss / 1024,
                  "workers_peak_mb": children.ru_maxrss / 1024,
                  "frames": sum(c["frames"] for split in written["splits"].values() for c in split),
                  "chunks": sum(len(split) for split in written["splits"].values()), "encoder": written["encoder"],
                  "decode_workers": workers if job == "part" else None,
                  "device": torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu"}))
"""


def corpus(root: Path, cfg, episodes: int, seconds: float) -> None:
    """``episodes`` train episodes of drifting textures at the profile's resolution, with odometry."""
    import numpy as np

    from orbis2.data.episodes import EpisodeRecord, RawIndex, write_odometry
    from orbis2.data.video import write_video

    data, rng = cfg.data, np.random.default_rng(0)
    n = round(seconds * data.fps)
    (root / "train").mkdir(parents=True)
    records = []
    for e in range(episodes):
        texture = rng.integers(0, 255, (data.height // 8 + 1, data.width // 8 + n // 8 + 2, 3), dtype=np.uint8)
        texture = np.repeat(np.repeat(texture, 8, 0), 8, 1)[:data.height]
        stem = f"ep_train_{e:05d}"
        write_video(root / "train" / f"{stem}.mp4", (texture[:, k:k + data.width] for k in range(n)), data.fps)
        k, zeros = np.arange(n, dtype=float), np.zeros(n)
        write_odometry(root / "train" / f"{stem}.parquet", data.fps, np.full(n, 5.0), 0.1 * np.sin(k / 9),
                       (0.5 * k, zeros, zeros))
        records.append(EpisodeRecord("train", stem, n, True, True, origin="synthetic"))
    RawIndex("synthetic", data.fps, data.width, data.height, None, records).write(root)


def run(job: str, shards: Path, work: Path, out: Path, models: tuple[Path, Path], batch: int,
        workers: int | None) -> dict:
    """One job (``part`` or ``gather``) in a fresh process; its figures."""
    proc = subprocess.run([sys.executable, "-c", WORKER, str(shards), str(work), str(out), *map(str, models),
                           str(batch), "auto" if workers is None else str(workers), job], capture_output=True,
                          text=True)
    if proc.returncode:
        raise SystemExit(f"the latents {job} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def measure(profile: str, scale: int, episodes: int, seconds: float, shard_mb: float, workers: int | None,
            params: Path = Path("params.yaml")) -> dict:
    from orbis2.config.params import load_config
    from orbis2.data.shards import write_shards

    cfg = load_config(params, profile)
    shards_cfg = dataclasses.replace(cfg.shards, max_shard_mb=shard_mb)
    with tempfile.TemporaryDirectory(prefix="bench_latent_parts_") as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        corpus(tmp / "raw1", cfg, episodes, seconds)
        grown(tmp / "raw1", tmp / f"raw{scale}", scale)
        for size in (1, scale):
            write_shards(tmp / f"raw{size}", tmp / f"shards{size}", cfg.data, shards_cfg)
        models = random_tokenizers(tmp, cfg)
        print(f"corpus and tokenizers made in {time.perf_counter() - t:.0f} s", file=sys.stderr)
        runs = {}
        for size in (1, scale):
            out = tmp / f"part{size}.json"
            runs[size] = {job: run(job, tmp / f"shards{size}", tmp / f"work{size}", out, models,
                                   cfg.latents.batch_size, workers) for job in ("part", "gather")}
        chunk_bytes = sum(f.stat().st_size for f in (tmp / f"part{scale}").glob("train/*/*.npy")
                          if f.name != "clips.npy")
        chunks = runs[scale]["part"]["chunks"]
    small, large = runs[1], runs[scale]
    part = large["part"]
    return {"profile": profile, "resolution": f"{cfg.data.width}x{cfg.data.height}",
            "presets": f"{cfg.tokenizer_detail.preset}/{cfg.tokenizer_abstract.preset}",
            "device": part["device"] if part["device"] != "cpu" else f"{cpu_model()}, {os.cpu_count()} cores",
            "encoder": part["encoder"], "batch_size": cfg.latents.batch_size,
            "decode_workers": part["decode_workers"], "shard_mb": shard_mb, "scale": scale,
            "frames_1x": small["part"]["frames"], "frames_scaled": part["frames"],
            "part_frames_per_s": part["frames"] / part["seconds"], "load_seconds": part["load_seconds"],
            "latent_bytes_per_frame": chunk_bytes / part["frames"], "chunk_mb": chunk_bytes / chunks / 2**20,
            "peak_mb_1x": small["part"]["peak_mb"], "peak_mb_scaled": part["peak_mb"],
            "peak_ratio": part["peak_mb"] / small["part"]["peak_mb"],
            "workers_peak_mb_1x": small["part"]["workers_peak_mb"], "workers_peak_mb_scaled": part["workers_peak_mb"],
            "gather_peak_mb_1x": small["gather"]["peak_mb"], "gather_peak_mb_scaled": large["gather"]["peak_mb"],
            "gather_peak_ratio": large["gather"]["peak_mb"] / small["gather"]["peak_mb"],
            "cpus": os.cpu_count(), "cpu": cpu_model()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--profile", default="paper", help="the geometry, presets and latents settings (default: paper)")
    p.add_argument("--scale", type=int, default=4, help="the grown corpus, in copies of the first")
    p.add_argument("--episodes", type=int, default=8, help="train episodes of the first corpus")
    p.add_argument("--seconds", type=float, default=20.0, help="each episode's length")
    p.add_argument("--shard-mb", type=float, default=4.0, help="shard size (small: several shards at 1x)")
    p.add_argument("--decode-workers", type=int, default=None,
                   help="processes decoding shards (default: the stage's, orbis2.latents.decode_workers)")
    p.add_argument("--json", type=Path, default=None, help="also write the figures here")
    a = p.parse_args()
    figures = measure(a.profile, a.scale, a.episodes, a.seconds, a.shard_mb, a.decode_workers)
    print(f"one part         : {figures['part_frames_per_s']:8.1f} frames/s ({figures['frames_scaled']} frames at "
          f"{figures['resolution']}, {figures['device']}, {figures['encoder']}, "
          f"{figures['decode_workers']} decode workers)")
    print(f"peak memory      : {figures['peak_mb_1x']:.0f} MB at 1x ({figures['frames_1x']} frames), "
          f"{figures['peak_mb_scaled']:.0f} MB at {a.scale}x ({figures['frames_scaled']} frames): "
          f"ratio {figures['peak_ratio']:.3f}")
    print(f"gather's peak    : {figures['gather_peak_mb_1x']:.0f} MB at 1x, {figures['gather_peak_mb_scaled']:.0f} MB "
          f"at {a.scale}x: ratio {figures['gather_peak_ratio']:.3f}")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
