"""FVD of a system's rollouts on one evaluation split, with reference rows, chunked FVD and FVD-slope.

One split's figures (the ``eval_fvd_<system>`` stage collects them into
``reports/eval/fvd_<system>.json``): FVD over ``evaluation.seconds`` with a
clip-bootstrap interval, the reference rows of :mod:`orbis2.eval.protocols.references` on
the same clips and frames, and on ``long_split`` chunked FVD and the FVD-slope over
``long_seconds``. The long split's FVD uses the first ``seconds`` of its long
rollouts (same contexts, same distribution as separate short rollouts).
Randomness comes from ``evaluation.seed`` only.

I3D features of real videos (and of the references, which only depend on the
decoding tokenizer) are cached in a folder keyed by the split's shard digest and a
description of the videos, so that systems evaluated on the same clips share them.

I3D sees 16 evenly spaced frames of each window (``orbis2.eval.metrics.fvd.even_frame_indices``), and the
tokenizers decode frame by frame, so only those frames are decoded (and read from
the shards): the frames of decoding every frame (up to float round-off, at most a
grey level), at a fraction of the decoding that dominates this stage on a CPU
(``benchmarks/bench_fvd.py``).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from orbis2.config.sections import DataConfig, EvaluationConfig
from orbis2.data.shards import Clip, split_clips, split_digest
from orbis2.data.video import write_gif, write_video
from orbis2.eval.metrics.fvd import CLIP_FRAMES, cached_features, i3d_features
from orbis2.eval.metrics.stats import mean_interval, paired_difference
from orbis2.eval.protocols.evaluate import i3d_picks, protocol, score_rollouts
from orbis2.eval.protocols.references import reference_rows
from orbis2.eval.protocols.systems import (
    LoadedSystem,
    Sample,
    cache_latents,
    eval_samples,
    generate,
    generated_indices,
    rollout_steps,
    sample_clusters,
)
from orbis2.eval.protocols.truth import psnr
from orbis2.latents import LatentCache

# Times (s) of the frames shown in the qualitative rollout grid.
GRID_TIMES = (0.5, 4.0, 8.0, 12.0, 16.0)


def real_videos(clips: dict[str, Clip], samples: list[Sample], indices: list[np.ndarray]) -> np.ndarray:
    """Ground-truth RGB frames [N, T, H, W, 3] of each sample at the given native indices."""
    return np.stack([clips[s.key].frames(idx) for s, idx in zip(samples, indices)])


class PickedFrames:
    """Generated videos decoded only at the frames some FVD window's I3D clip reads (``frames``: every frame,
    already decoded, to pick from instead)."""

    def __init__(self, system: LoadedSystem, latents: torch.Tensor, windows: list[slice],
                 frames: np.ndarray | None = None):
        picks = np.unique(np.concatenate([i3d_picks(w) for w in windows]))
        self.position = {int(p): i for i, p in enumerate(picks)}
        self.frames = system.decode(latents[:, picks]) if frames is None else frames[:, picks]

    def clip(self, window: slice) -> np.ndarray:
        """[N, 16, H, W, 3]: each video's I3D clip of ``window``."""
        return self.frames[:, [self.position[int(p)] for p in i3d_picks(window)]]


GALLERY_HEIGHT = 256  # pixels, at least: the sample videos on the runs' pages, watchable at every profile


def gallery_frames(*panels: np.ndarray, min_height: int = GALLERY_HEIGHT) -> np.ndarray:
    """The sample video as a reviewer watches it: equal-length videos side by side (left to right as given),
    enlarged by a whole factor to at least ``min_height`` pixels (nearest neighbour: no detail made up)."""
    frames = np.concatenate(panels, axis=2)
    factor = max(1, -(-min_height // frames.shape[1]))
    return frames.repeat(factor, axis=1).repeat(factor, axis=2)


def sample_video(system: LoadedSystem, cache: LatentCache, split: str, clips: dict[str, Clip], sample: Sample,
                 indices: np.ndarray, generated: np.ndarray, data: DataConfig) -> np.ndarray:
    """One rollout from its context on, in three panels: the real frames | the tokenizer's reconstruction of
    them | the model (the context as the tokenizer reconstructs it, which is what the model sees, then its
    prediction). Side by side, a reader tells the tokenizer's blur from the predictor's. ``indices``: the
    generated frames' native indices."""
    span = np.concatenate([context_indices(data, sample.context_end), indices])
    real = clips[sample.key].frames(span)
    recon = system.decode(cache_latents(cache, split, system.output_level, [sample], [span]))[0]
    model = np.concatenate([recon[:data.detail_context], generated])
    return gallery_frames(real, recon, model)


def first_frame(system: LoadedSystem, cache: LatentCache, split: str, clips: dict[str, Clip],
                samples: list[Sample], indices: list[np.ndarray], latents: torch.Tensor, clusters: list[str],
                seed: int) -> dict[str, Any]:
    """PSNR of each rollout's first generated frame and of the tokenizer's reconstruction of the same real frame,
    against the real frame, and their paired gap, with clip-bootstrap intervals (a :class:`FirstFrame`)."""
    first = [idx[:1] for idx in indices]
    real = real_videos(clips, samples, first)
    recon = system.decode(cache_latents(cache, split, system.output_level, samples, first))
    generated = system.decode(latents[:, :1])
    ours, tokenizer = psnr(generated, real)[:, 0], psnr(recon, real)[:, 0]
    return {"generated_psnr": mean_interval(ours, clusters, seed=seed).to_dict(),
            "reconstruction_psnr": mean_interval(tokenizer, clusters, seed=seed).to_dict(),
            "gap_db": paired_difference(tokenizer, ours, clusters, seed=seed).to_dict()}


def split_fvd(split: str, system: LoadedSystem, cache: LatentCache, i3d, media: Path, data: DataConfig,
              ev: EvaluationConfig, device: torch.device, shards: Path, stats_cache: Path, i3d_sha256: str = "",
              rollouts: Path | None = None) -> dict[str, Any]:
    """Roll out one split: ``{"fvd": ..., "references": ..., "first_frame": ..., "protocol": ...}``, plus
    ``"chunked"`` on the long
    split, scored by :func:`orbis2.eval.protocols.evaluate.score_rollouts` (the code ``orbis2 evaluate`` runs).

    Writes a sample video, real | tokenizer | model from the context on, at least 256 px tall
    (:func:`sample_video`; ``media/<split>.mp4``, VP9, and the same as ``media/<split>.gif``) and, on the long
    split, the frames of
    the qualitative grid (``media/grid.npz``). ``shards`` is the shard folder the cache
    was encoded from; ``stats_cache`` the folder of cached real-video features. Given
    ``rollouts``, every frame is decoded and each rollout is written losslessly with the
    real video it continues and a manifest (:func:`write_rollouts`); the FVDs are then
    computed from exactly the frames written.
    """
    long = split == ev.long_split
    proto = protocol("orbis2", ev)
    steps = rollout_steps(data, ev.long_seconds if long else ev.seconds)
    samples = eval_samples(cache, split, data, steps, ev.starts_per_clip)
    indices = [generated_indices(data, s.context_end, steps) for s in samples]
    clusters = sample_clusters(cache, split, samples)
    latents = generate(system, cache, split, samples, steps, data, ev, device)
    short = proto.short(data.detail_hz)
    chunks, whole = proto.chunks(data.detail_hz) if long else ([], None)
    every = system.decode(latents) if rollouts is not None else None
    generated = PickedFrames(system, latents, [short, *chunks, *([whole] if whole else [])], every)
    clips = split_clips(shards, split)
    what = f"{len(samples)}x{ev.starts_per_clip}starts|{steps}steps|{data.width}x{data.height}"

    def cached(description: str, compute: Callable[[], np.ndarray]) -> np.ndarray:
        return cached_features(stats_cache, f"{split}|{split_digest(shards, split)}|{description}", compute)

    def real(window: slice) -> np.ndarray:
        return cached(f"{what}|frames{window.start}-{window.stop}",
                      lambda: i3d_features(real_videos(clips, samples, [i[i3d_picks(window)] for i in indices]), i3d))

    def fake(window: slice) -> np.ndarray:
        return i3d_features(generated.clip(window), i3d)

    out = score_rollouts(split, real, fake, clusters, data.detail_hz, proto, short, chunks, whole)
    out["fvd"]["source_resolution"] = list(generated.frames.shape[2:4])
    out["references"] = references(split, system, cache, samples, indices, short, real(short), clusters, what, i3d,
                                   ev, cached)
    out["first_frame"] = first_frame(system, cache, split, clips, samples, indices, latents, clusters, ev.seed)
    out["protocol"] = proto.card(data.detail_hz, data.detail_context, len(set(clusters)), len(samples), i3d_sha256,
                                 generated.frames.shape[2:4])
    first = every[0] if every is not None else system.decode(latents[:1])[0]  # the sample video, every frame
    if long:
        save_grid_frames(media / "grid.npz", first, data.detail_hz)
    sample = sample_video(system, cache, split, clips, samples[0], indices[0], first, data)
    write_video(media / f"{split}.mp4", sample, data.detail_hz, playable=True)
    write_gif(media / f"{split}.gif", sample, data.detail_hz)
    if rollouts is not None:
        write_rollouts(rollouts / split, every, clips, samples, indices, clusters, data)
    return out


def context_indices(data: DataConfig, context_end: int) -> np.ndarray:
    """Native indices of a rollout's detail context frames (the last one is ``context_end``)."""
    return context_end - data.detail_stride * np.arange(data.detail_context - 1, -1, -1)


def write_rollouts(folder: Path, frames: np.ndarray, clips: dict[str, Clip], samples: list[Sample],
                   indices: list[np.ndarray], clusters: list[str], data: DataConfig) -> None:
    """Each rollout as ``generated/<n>.mkv`` and the real ``detail_context`` frames plus its true continuation as
    ``real/<n>.mkv`` (lossless FFV1 at ``detail_hz``), and ``manifest.csv`` naming both and the episode."""
    rows = []
    for n, (sample, idx, clip, video) in enumerate(zip(samples, indices, clusters, frames)):
        name = f"{n:04d}"
        write_video(folder / "generated" / f"{name}.mkv", video, data.detail_hz, lossless=True)
        truth = clips[sample.key].frames(np.concatenate([context_indices(data, sample.context_end), idx]))
        write_video(folder / "real" / f"{name}.mkv", truth, data.detail_hz, lossless=True)
        rows.append({"name": name, "generated": f"generated/{name}.mkv", "real": f"real/{name}.mkv", "clip": clip,
                     "context_frames": data.detail_context})
    with (folder / "manifest.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["name", "generated", "real", "clip", "context_frames"])
        writer.writeheader()
        writer.writerows(rows)


def references(split: str, system: LoadedSystem, cache: LatentCache, samples: list[Sample],
               indices: list[np.ndarray], window: slice, real: np.ndarray, clusters: list[str], what: str, i3d,
               ev: EvaluationConfig, cached: Callable[[str, Callable[[], np.ndarray]], np.ndarray]
               ) -> dict[str, Any]:
    """Reference rows on the same clips and frames: real-vs-real floor, tokenizer reconstruction, repeat-last.

    Cached (through ``cached``) by the decoding tokenizer's checksum: systems that decode
    with the same tokenizer (all detail-level ones) share them.
    """
    level = system.output_level
    key = f"{what}|frames{window.start}-{window.stop}|{level}|{system.tokenizers[level].checksum[:16]}"

    def reconstruction() -> np.ndarray:
        truth = cache_latents(cache, split, level, samples, [i[i3d_picks(window)] for i in indices])
        return i3d_features(system.decode(truth), i3d)

    def repeat_last() -> np.ndarray:
        last = cache_latents(cache, split, level, samples, [np.array([s.context_end]) for s in samples])
        frames = system.decode(last)
        return i3d_features(np.broadcast_to(frames, (len(frames), CLIP_FRAMES, *frames.shape[2:])), i3d)

    recon = cached(f"{key}|reconstruction", reconstruction)
    still = cached(f"{key}|repeat_last", repeat_last)
    return reference_rows(real, recon, still, clusters, ev.fvd_bootstrap_reps, ev.seed, ev.floor_splits)


def save_grid_frames(path: Path, frames: np.ndarray, fps: float) -> None:
    """The frames of one long rollout at ``GRID_TIMES`` (those it reaches), for the report's qualitative grid."""
    times = [t for t in GRID_TIMES if round(t * fps) <= len(frames)]
    picks = [max(0, round(t * fps) - 1) for t in times]
    np.savez_compressed(path, frames=frames[picks], times=np.array(times))
