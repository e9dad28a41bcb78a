"""FVD of a system's rollouts on one evaluation split, with reference rows, chunked FVD and FVD-slope.

One split's figures (the ``eval_fvd_<system>`` stage collects them into
``reports/eval/fvd_<system>.json``): FVD over ``evaluation.seconds`` with a
clip-bootstrap interval, the reference rows of :mod:`orbis2.eval.protocols.references` on
the same clips and frames, and on ``long_split`` chunked FVD and the FVD-slope over
``long_seconds``. The long split's FVD uses the first ``seconds`` of its long
rollouts (same contexts, same distribution as separate short rollouts).
Randomness comes from ``evaluation.seed`` only: each generation batch draws its own noise from it and its index.

The rollouts' side (generate, decode, featurise: :func:`part_outcome`) runs in parts over blocks of batches,
each batch alone, so that any number of parts gives the same numbers as one (the stage's ``--parts``); the
gather (:func:`split_fvd`) adds the real side and the intervals.

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
import functools
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from orbis2.config.sections import DataConfig, EvaluationConfig
from orbis2.data.parts import part_slice
from orbis2.data.shards import Clip, split_clips, split_digest
from orbis2.data.video import write_gif, write_video
from orbis2.errors import OrbisError
from orbis2.eval.metrics.fvd import CLIP_FRAMES, cached_features, i3d_code, i3d_features
from orbis2.eval.metrics.pixels import psnr
from orbis2.eval.metrics.stats import mean_interval, paired_difference
from orbis2.eval.protocols.evaluate import i3d_picks, protocol, score_rollouts
from orbis2.eval.protocols.references import reference_rows
from orbis2.eval.protocols.systems import (
    LoadedSystem,
    Sample,
    batch_count,
    cache_latents,
    eval_samples,
    generate,
    generated_indices,
    rollout_steps,
    sample_clusters,
)
from orbis2.io import atomic_file
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


@dataclass(frozen=True)
class SplitPlan:
    """What every part of one split's FVD pass and its gather agree on: the samples in order, the native indices
    of the frames each rollout generates, the clips a bootstrap resamples, the rollout steps, the FVD windows and
    the generation batches."""

    split: str
    long: bool
    steps: int
    samples: list[Sample]
    indices: list[np.ndarray]
    clusters: list[str]
    short: slice
    chunks: list[slice]
    whole: slice | None
    batch_size: int

    @property
    def windows(self) -> list[slice]:
        return [self.short, *self.chunks, *([self.whole] if self.whole else [])]

    @property
    def batches(self) -> int:
        return batch_count(len(self.samples), self.batch_size)

    def part_batches(self, part: int, parts: int) -> range:
        """The contiguous block of batches part ``part`` of ``parts`` generates (empty when parts > batches)."""
        block = part_slice(self.batches, part, parts)
        return range(block.start, block.stop)

    def rows(self, batch: int) -> slice:
        return slice(batch * self.batch_size, min((batch + 1) * self.batch_size, len(self.samples)))


def split_plan(split: str, cache: LatentCache, data: DataConfig, ev: EvaluationConfig) -> SplitPlan:
    long = split == ev.long_split
    proto = protocol("orbis2", ev)
    steps = rollout_steps(data, ev.long_seconds if long else ev.seconds)
    samples = eval_samples(cache, split, data, steps, ev.starts_per_clip)
    chunks, whole = proto.chunks(data.detail_hz) if long else ([], None)
    return SplitPlan(split, long, steps, samples, [generated_indices(data, s.context_end, steps) for s in samples],
                     sample_clusters(cache, split, samples), proto.short(data.detail_hz), chunks, whole,
                     ev.batch_size)


def window_key(window: slice) -> str:
    return f"{window.start}-{window.stop}"


def batch_outcome(plan: SplitPlan, batch: int, system: LoadedSystem, cache: LatentCache, i3d, data: DataConfig,
                  ev: EvaluationConfig, device: torch.device, clips: dict[str, Clip],
                  rollouts: Path | None) -> dict[str, np.ndarray]:
    """One generation batch of a split, everything per rollout the FVD records need: its I3D features in every
    window (``fake/<start>-<stop>``), the PSNR of its first generated frame and of the tokenizer's
    reconstruction of the same real frame (``generated_psnr``, ``reconstruction_psnr``), the decoded frame size;
    batch 0 also every frame of its first rollout (``sample``, for :func:`write_media`).

    Each batch is generated (its own noise, :func:`generate`), decoded and featurised alone, so a part made of
    any blocks of batches gives the same numbers as one pass over the split, to the bit. With ``rollouts``, every
    frame is decoded and each rollout written losslessly (:func:`write_rollouts`)."""
    rows = plan.rows(batch)
    samples, indices = plan.samples[rows], plan.indices[rows]
    latents = generate(system, cache, plan.split, plan.samples, plan.steps, data, ev, device,
                       batches=range(batch, batch + 1))
    every = system.decode(latents) if rollouts is not None else None
    generated = PickedFrames(system, latents, plan.windows, every)
    out = {f"fake/{window_key(w)}": i3d_features(generated.clip(w), i3d) for w in plan.windows}
    first = [idx[:1] for idx in indices]
    real = real_videos(clips, samples, first)
    recon = system.decode(cache_latents(cache, plan.split, system.output_level, samples, first))
    out["generated_psnr"] = psnr(system.decode(latents[:, :1]), real)[:, 0]
    out["reconstruction_psnr"] = psnr(recon, real)[:, 0]
    out["source_resolution"] = np.array(generated.frames.shape[2:4])
    if batch == 0:
        out["sample"] = every[:1] if every is not None else system.decode(latents[:1])
    if rollouts is not None:
        write_rollouts(rollouts / plan.split, every, clips, samples, indices, rows.start, data)
    return out


def part_outcome(plan: SplitPlan, batches: range, system: LoadedSystem, cache: LatentCache, i3d, data: DataConfig,
                 ev: EvaluationConfig, device: torch.device, shards: Path, work: Path,
                 rollouts: Path | None = None) -> dict[str, np.ndarray]:
    """:func:`batch_outcome` of each of ``batches`` (a part of the split), concatenated in order.

    Each batch's outcome is kept in ``work`` (a folder keyed by everything it depends on), written atomically:
    a batch already there is read back, so a killed part resumes at the batch it was on, and a gather reads
    what its part jobs left. The part reads only the clips of the rollouts it still has to make, from their
    shards (:func:`clips_of`). With ``rollouts`` every batch is made again: its videos are written as it goes."""
    saved = {b: work / plan.split / f"{b:06d}.npz" for b in batches}
    todo = [b for b in batches if rollouts is not None or not saved[b].is_file()]
    clips = clips_of(cache, shards, plan.split, [s for b in todo for s in plan.samples[plan.rows(b)]]) if todo else {}
    outcomes = []
    for batch in batches:
        if batch in todo:
            outcome = batch_outcome(plan, batch, system, cache, i3d, data, ev, device, clips, rollouts)
            with atomic_file(saved[batch]) as tmp, open(tmp, "wb") as f:
                np.savez(f, **outcome)
        else:
            outcome = read_outcome(saved[batch])
        outcomes.append(outcome)
    return concat_outcomes(outcomes)


def read_outcome(path: Path) -> dict[str, np.ndarray]:
    """A batch's outcome as :func:`part_outcome` kept it; a damaged file fails the zip's CRC check of each array
    as it is read, and is named with the fix."""
    try:
        with np.load(path) as arrays:
            return {key: arrays[key] for key in arrays.files}
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise OrbisError(f"{path}: unreadable ({err}); delete it and run the stage again") from err


def clips_of(cache: LatentCache, shards: Path, split: str, samples: list[Sample]) -> dict[str, Clip]:
    """The clips of ``samples``, read from the shards that hold them alone (the latent cache's chunk table names
    each clip's source shard): a part reads its own shards, not its split's."""
    index, keys = cache.index(split), {s.key for s in samples}
    sources = set(index.chunks["source"][index.clips["chunk"][index.find(sorted(keys))]].tolist())
    return split_clips(shards, split, keys, sources)


def concat_outcomes(outcomes: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Parts' (or batches') outcomes in order, as one: the per-rollout arrays concatenated (an empty part adds
    nothing)."""
    outcomes = [o for o in outcomes if o]
    if not outcomes:
        return {}
    out = {k: np.concatenate([o[k] for o in outcomes]) for k in outcomes[0] if k not in ("source_resolution", "sample")}
    out["source_resolution"] = outcomes[0]["source_resolution"]
    if "sample" in outcomes[0]:  # batch 0's, in the first part that has batches
        out["sample"] = outcomes[0]["sample"]
    return out


def write_media(plan: SplitPlan, outcome: dict[str, np.ndarray], system: LoadedSystem, cache: LatentCache,
                media: Path, data: DataConfig, shards: Path) -> None:
    """The split's sample video from its first rollout, real | tokenizer | model from the context on, at least
    256 px tall (:func:`sample_video`; ``media/<split>.mp4``, VP9, and the same as ``media/<split>.gif``) and, on
    the long split, the frames of the qualitative grid (``media/grid.npz``)."""
    video, sample = outcome["sample"][0], plan.samples[0]
    if plan.long:
        save_grid_frames(media / "grid.npz", video, data.detail_hz)
    clips = clips_of(cache, shards, plan.split, [sample])
    frames = sample_video(system, cache, plan.split, clips, sample, plan.indices[0], video, data)
    write_video(media / f"{plan.split}.mp4", frames, data.detail_hz, playable=True)
    write_gif(media / f"{plan.split}.gif", frames, data.detail_hz)


def split_fvd(plan: SplitPlan, outcome: dict[str, np.ndarray], system: LoadedSystem, cache: LatentCache, i3d,
              data: DataConfig, ev: EvaluationConfig, shards: Path, stats_cache: Path, i3d_sha256: str = "",
              ) -> dict[str, Any]:
    """One split's figures from its rollouts' outcome (every part's, :func:`part_outcome`): ``{"fvd": ...,
    "references": ..., "first_frame": ..., "protocol": ...}``, plus ``"chunked"`` on the long split, scored by
    :func:`orbis2.eval.protocols.evaluate.score_rollouts` (the code ``orbis2 evaluate`` runs).

    The real side is the whole split's: the I3D features of the real frames of every window and the reference
    rows are cached in ``stats_cache`` (keyed by the split's shard digest, the I3D weights and code, and a
    description of the videos), so the split's clips are read only when a window's real features are not cached
    yet. ``shards`` is the shard folder the cache was encoded from.
    """
    split, samples, indices, clusters = plan.split, plan.samples, plan.indices, plan.clusters
    if len(outcome.get("generated_psnr", ())) != len(samples):
        raise OrbisError(f"{split}: the parts hold {len(outcome.get('generated_psnr', ()))} rollouts, the split has "
                         f"{len(samples)}; re-run the parts with the same settings and --parts")
    proto = protocol("orbis2", ev)
    resolution = outcome["source_resolution"].tolist()
    what = f"{len(samples)}x{ev.starts_per_clip}starts|{plan.steps}steps|{data.width}x{data.height}"
    clips = functools.cache(lambda: split_clips(shards, split))  # read only if a window's features are not cached

    def cached(description: str, compute: Callable[[], np.ndarray]) -> np.ndarray:
        network = f"i3d {i3d_sha256[:16]} code {i3d_code()[:16]}"
        return cached_features(stats_cache, f"{split}|{split_digest(shards, split)}|{network}|{description}", compute)

    def real(window: slice) -> np.ndarray:
        return cached(f"{what}|frames{window.start}-{window.stop}",
                      lambda: i3d_features(real_videos(clips(), samples, [i[i3d_picks(window)] for i in indices]),
                                           i3d))

    def fake(window: slice) -> np.ndarray:
        return outcome[f"fake/{window_key(window)}"]

    out = score_rollouts(split, real, fake, clusters, data.detail_hz, proto, plan.short, plan.chunks, plan.whole)
    out["fvd"]["source_resolution"] = resolution
    out["references"] = references(split, system, cache, samples, indices, plan.short, real(plan.short), clusters,
                                   what, i3d, ev, cached)
    ours, tokenizer = outcome["generated_psnr"], outcome["reconstruction_psnr"]
    out["first_frame"] = {"generated_psnr": mean_interval(ours, clusters, seed=ev.seed).to_dict(),
                          "reconstruction_psnr": mean_interval(tokenizer, clusters, seed=ev.seed).to_dict(),
                          "gap_db": paired_difference(tokenizer, ours, clusters, seed=ev.seed).to_dict()}
    out["protocol"] = proto.card(data.detail_hz, data.detail_context, len(set(clusters)), len(samples), i3d_sha256,
                                 resolution)
    return out


def context_indices(data: DataConfig, context_end: int) -> np.ndarray:
    """Native indices of a rollout's detail context frames (the last one is ``context_end``)."""
    return context_end - data.detail_stride * np.arange(data.detail_context - 1, -1, -1)


def write_rollouts(folder: Path, frames: np.ndarray, clips: dict[str, Clip], samples: list[Sample],
                   indices: list[np.ndarray], first: int, data: DataConfig) -> None:
    """Rollouts ``first``, ``first + 1``, ... as ``generated/<n>.mkv`` and the real ``detail_context`` frames plus
    their true continuation as ``real/<n>.mkv`` (lossless FFV1 at ``detail_hz``); :func:`write_manifest` names
    them all."""
    for n, (sample, idx, video) in enumerate(zip(samples, indices, frames), start=first):
        write_video(folder / "generated" / f"{n:04d}.mkv", video, data.detail_hz, lossless=True)
        truth = clips[sample.key].frames(np.concatenate([context_indices(data, sample.context_end), idx]))
        write_video(folder / "real" / f"{n:04d}.mkv", truth, data.detail_hz, lossless=True)


def write_manifest(folder: Path, plan: SplitPlan, data: DataConfig) -> None:
    """``manifest.csv`` of a split's rollouts (:func:`write_rollouts`): each one's videos and episode."""
    with (folder / "manifest.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["name", "generated", "real", "clip", "context_frames"])
        writer.writeheader()
        writer.writerows({"name": f"{n:04d}", "generated": f"generated/{n:04d}.mkv", "real": f"real/{n:04d}.mkv",
                          "clip": clip, "context_frames": data.detail_context} for n, clip in enumerate(plan.clusters))


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
