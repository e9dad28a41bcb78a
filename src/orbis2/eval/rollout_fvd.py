"""FVD of a system's rollouts on one evaluation split, with reference rows, chunked FVD and FVD-slope.

One split's figures (the ``eval_fvd_<system>`` stage collects them into
``reports/eval/fvd_<system>.json``): FVD over ``evaluation.seconds`` with a
clip-bootstrap interval, the reference rows of :mod:`orbis2.eval.references` on
the same clips and frames, and on ``long_split`` chunked FVD and the FVD-slope over
``long_seconds``. The long split's FVD uses the first ``seconds`` of its long
rollouts (same contexts, same distribution as separate short rollouts).
Randomness comes from ``evaluation.seed`` only.

I3D features of real videos (and of the references, which only depend on the
decoding tokenizer) are cached in a folder keyed by the split's shard digest and a
description of the videos, so that systems evaluated on the same clips share them.

I3D sees 16 evenly spaced frames of each window (``even_frame_indices``), and the
tokenizers decode frame by frame, so only those frames are decoded (and read from
the shards): the frames of decoding every frame (up to float round-off, at most a
grey level), at a fraction of the decoding that dominates this stage on a CPU
(``benchmarks/bench_fvd.py``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from orbis2.config import DataConfig, EvaluationConfig
from orbis2.data.shards import Clip, split_clips, split_digest
from orbis2.data.video import write_gif, write_video
from orbis2.eval.fvd import CLIP_FRAMES, cached_features, chunk_windows, even_frame_indices, i3d_features
from orbis2.eval.references import fvd_with_interval, reference_rows
from orbis2.eval.stats import fvd_slope_interval
from orbis2.eval.systems import (
    LoadedSystem,
    Sample,
    cache_latents,
    eval_samples,
    generate,
    generated_indices,
    rollout_steps,
    sample_clusters,
)
from orbis2.latents import LatentCache

# Times (s) of the frames shown in the qualitative rollout grid.
GRID_TIMES = (0.5, 4.0, 8.0, 12.0, 16.0)
Features = Callable[[slice], np.ndarray]  # I3D features [N, 400] of a frame window


def real_videos(clips: dict[str, Clip], samples: list[Sample], indices: list[np.ndarray]) -> np.ndarray:
    """Ground-truth RGB frames [N, T, H, W, 3] of each sample at the given native indices."""
    return np.stack([clips[s.key].frames(idx) for s, idx in zip(samples, indices)])


def i3d_picks(window: slice) -> np.ndarray:
    """Positions of the CLIP_FRAMES (16) frames of ``window`` that I3D sees (evenly spaced, both ends included)."""
    return window.start + np.asarray(even_frame_indices(window.stop - window.start))


class PickedFrames:
    """Generated videos decoded only at the frames some FVD window's I3D clip reads."""

    def __init__(self, system: LoadedSystem, latents: torch.Tensor, windows: list[slice]):
        picks = np.unique(np.concatenate([i3d_picks(w) for w in windows]))
        self.position = {int(p): i for i, p in enumerate(picks)}
        self.frames = system.decode(latents[:, picks])

    def clip(self, window: slice) -> np.ndarray:
        """[N, 16, H, W, 3]: each video's I3D clip of ``window``."""
        return self.frames[:, [self.position[int(p)] for p in i3d_picks(window)]]


def long_windows(data: DataConfig, ev: EvaluationConfig) -> tuple[list[slice], slice]:
    """The long split's consecutive ``chunk_seconds`` windows and the span they cover."""
    chunks = chunk_windows(round(ev.long_seconds * data.detail_hz), data.detail_hz, ev.chunk_seconds)
    return chunks, slice(0, chunks[-1].stop)


GIF_WIDTH = 320  # pixels: the rollout thumbnails on the runs' pages


def split_fvd(split: str, system: LoadedSystem, cache: LatentCache, i3d, media: Path, data: DataConfig,
              ev: EvaluationConfig, device: torch.device, shards: Path, stats_cache: Path) -> dict[str, Any]:
    """Roll out one split: ``{"fvd": ..., "references": ...}``, plus ``"chunked"`` on the long split.

    Writes a sample video (``media/<split>.mp4``, VP9, and a GIF thumbnail ``media/<split>.gif``)
    and, on the long split, the frames of
    the qualitative grid (``media/grid.npz``). ``shards`` is the shard folder the cache
    was encoded from; ``stats_cache`` the folder of cached real-video features.
    """
    long = split == ev.long_split
    steps = rollout_steps(data, ev.long_seconds if long else ev.seconds)
    samples = eval_samples(cache, split, data, steps, ev.starts_per_clip)
    indices = [generated_indices(data, s.context_end, steps) for s in samples]
    clusters = sample_clusters(cache, split, samples)
    latents = generate(system, cache, split, samples, steps, data, ev, device)
    short = slice(0, round(ev.seconds * data.detail_hz))
    chunks, whole = long_windows(data, ev) if long else ([], short)
    generated = PickedFrames(system, latents, [short, *chunks, whole])
    clips = split_clips(shards, split)
    what = f"{len(samples)}x{ev.starts_per_clip}starts|{steps}steps|{data.width}x{data.height}"

    def cached(description: str, compute: Callable[[], np.ndarray]) -> np.ndarray:
        return cached_features(stats_cache, f"{split}|{split_digest(shards, split)}|{description}", compute)

    def real(window: slice) -> np.ndarray:
        return cached(f"{what}|frames{window.start}-{window.stop}",
                      lambda: i3d_features(real_videos(clips, samples, [i[i3d_picks(window)] for i in indices]), i3d))

    def fake(window: slice) -> np.ndarray:
        return i3d_features(generated.clip(window), i3d)

    real_short = real(short)
    out: dict[str, Any] = {}
    out["fvd"] = {**fvd_with_interval(real_short, fake(short), clusters, ev.fvd_bootstrap_reps, ev.seed),
                  "frames": CLIP_FRAMES, "seconds": ev.seconds, "resolution": [224, 224],
                  "source_resolution": list(generated.frames.shape[2:4]), "seed": ev.seed}
    out["references"] = references(split, system, cache, samples, indices, short, real_short, clusters, what, i3d,
                                   ev, cached)
    first = system.decode(latents[:1])[0]  # the sample video, every frame
    if long:
        out["chunked"] = chunked_record(split, chunks, whole, real, fake, clusters, data, ev)
        save_grid_frames(media / "grid.npz", first, data.detail_hz)
    write_video(media / f"{split}.mp4", first, data.detail_hz, playable=True)
    write_gif(media / f"{split}.gif", first, data.detail_hz, width=GIF_WIDTH)
    return out


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


def chunked_record(split: str, windows: list[slice], whole: slice, real: Features, fake: Features,
                   clusters: list[str], data: DataConfig, ev: EvaluationConfig) -> dict[str, Any]:
    """Chunked FVD over consecutive ``chunk_seconds`` windows, FVD over ``whole`` (their span), and the FVD-slope,
    each with a clip-bootstrap interval (all chunks on the same resamples)."""
    reals, fakes = [real(w) for w in windows], [fake(w) for w in windows]
    chunks, slope, slope_draws = fvd_slope_interval(reals, fakes, clusters, ev.fvd_bootstrap_reps, seed=ev.seed)
    full = fvd_with_interval(real(whole), fake(whole), clusters, ev.fvd_bootstrap_reps, ev.seed)
    return {"split": split, "seconds": len(windows) * ev.chunk_seconds, "chunk_seconds": ev.chunk_seconds,
            "videos": len(clusters), "clips": slope.clusters, "seed": ev.seed,
            "chunks": [{"start_s": w.start / data.detail_hz, "end_s": w.stop / data.detail_hz, "fvd": c.estimate,
                        "low": c.low, "high": c.high} for w, c in zip(windows, chunks)],
            "fvd_long": full["fvd"], "fvd_long_low": full["low"], "fvd_long_high": full["high"],
            "fvd_slope": slope.estimate, "fvd_slope_low": slope.low, "fvd_slope_high": slope.high,
            "bootstrap_reps": ev.fvd_bootstrap_reps, "bootstrap_seed": ev.seed,
            "fvd_slope_draws": [float(d) for d in slope_draws]}


def save_grid_frames(path: Path, frames: np.ndarray, fps: float) -> None:
    """The frames of one long rollout at ``GRID_TIMES`` (those it reaches), for the report's qualitative grid."""
    times = [t for t in GRID_TIMES if round(t * fps) <= len(frames)]
    picks = [max(0, round(t * fps) - 1) for t in times]
    np.savez_compressed(path, frames=frames[picks], times=np.array(times))
