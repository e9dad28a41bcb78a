"""Bodies of the evaluation stages: FVD per system, steering ADE, speed and memory, probes, reports.

Every stage reads the trained artifacts, measures, and writes one JSON file under
``reports/eval/`` (the contract :mod:`orbis2.eval.report` reads), plus figures and
videos that it logs to the stage's MLflow run. Randomness comes from
``evaluation.seed`` only, and every figure records its sample count and seed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from orbis2.accel import Inference, set_tf32
from orbis2.assets import ensure_asset
from orbis2.config import PipelineConfig
from orbis2.data.probes import cityscapes_frames, kitti_eigen_frames, split_by_episode, town_probe_frames
from orbis2.data.shards import Clip, iter_samples, load_manifest, shard_paths
from orbis2.data.video import write_video
from orbis2.errors import OrbisError
from orbis2.eval.fvd import cached_features, chunk_windows, clip_features
from orbis2.eval.odometry import (
    camera_intrinsics,
    endpoint_angle,
    get_inverse_dynamics,
    integrate_controls,
    path_length,
    trajectory_ade,
)
from orbis2.eval.probe import ProbeConfig, predictor_features, run_probe, teacher_features, tokenizer_features
from orbis2.eval.references import fvd_with_interval, reference_rows
from orbis2.eval.report import (
    compression_from_evals,
    load_eval,
    save_rollout_grid,
    save_steering_strip,
    write_full_report,
    write_main_report,
)
from orbis2.eval.speed import measure
from orbis2.eval.stats import fvd_slope_interval, mean_interval, paired_difference
from orbis2.eval.systems import (
    SYSTEMS,
    LoadedSystem,
    Sample,
    cache_latents,
    contexts_for,
    eval_samples,
    generated_indices,
    load_system,
    predictor_file,
    rollout_steps,
)
from orbis2.io import atomic_dir, write_json
from orbis2.latents import LATENT_SETS, LatentCache, open_cache
from orbis2.models.i3d import load_i3d
from orbis2.models.stdit import load_predictor
from orbis2.models.teachers import build_teacher
from orbis2.models.tokenizer import load_tokenizer
from orbis2.registry import layout_path, registry
from orbis2.rollout import rollout_schedule, steering_sequences
from orbis2.tasks.predictors import STAGES
from orbis2.tasks.tokenizers import TEACHER_ASSETS, asset_path
from orbis2.tracking import StageRun

LATENTS = LATENT_SETS["compressed"].root
SHARDS = layout_path("shards")
EVAL = layout_path("eval")
# Real-data I3D statistics, keyed by the shards' hashes; outside every stage's outputs so they survive re-runs.
STATS_CACHE = layout_path("eval_cache")
# Times (s) of the frames shown in the qualitative rollout grid and the steering strip.
GRID_TIMES = (0.5, 4.0, 8.0, 12.0, 16.0)


def device() -> torch.device:
    return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")


def inference_settings(cfg: PipelineConfig) -> Inference:
    """Rollout precision, KV cache and compilation from ``evaluation``; sets the TF32 policy on CUDA."""
    ev = cfg.evaluation
    if torch.cuda.is_available():
        set_tf32(True)
    return Inference(precision=ev.precision, compile=ev.compile, kv_cache=ev.kv_cache)


def generator(seed: int, dev: torch.device) -> torch.Generator:
    return torch.Generator(dev).manual_seed(seed)


# --------------------------------------------------------------------------- real data


def split_clips(split: str) -> dict[str, Clip]:
    """Every clip of a split's shards by key (JPEGs stay compressed until frames are asked for)."""
    return {clip.key: clip for path in shard_paths(SHARDS, split)
            for clip in (Clip.from_sample(s, str(path)) for s in iter_samples(path))}


def split_hash(split: str) -> str:
    """A digest of a split's shards (their SHA-256 from the manifest): the key of cached real statistics."""
    shards = load_manifest(SHARDS)["splits"][split]["shards"]
    return hashlib.sha256("".join(s["sha256"] for s in shards).encode()).hexdigest()[:16]


def real_videos(clips: dict[str, Clip], samples: list[Sample], indices: list[np.ndarray]) -> np.ndarray:
    """Ground-truth RGB frames [N, T, H, W, 3] of each sample at the given native indices."""
    return np.stack([clips[s.key].frames(idx) for s, idx in zip(samples, indices)])


# --------------------------------------------------------------------------- rollouts


def generate(system: LoadedSystem, cache: LatentCache, split: str, samples: list[Sample], steps: int,
             cfg: PipelineConfig, dev: torch.device, steering: torch.Tensor | None = None,
             desc: str = "") -> torch.Tensor:
    """Rollout latents [N, 5 * steps, ...] of ``samples``, in batches of ``evaluation.batch_size``."""
    ev = cfg.evaluation
    gen = generator(ev.seed, dev)
    out = []
    batches = range(0, len(samples), ev.batch_size)
    for start in tqdm(batches, desc=desc or f"{system.name} {split}", unit="batch"):
        part = samples[start:start + ev.batch_size]
        contexts = contexts_for(system, cache, split, cfg.data, part, dev)
        steer = None if steering is None else steering[start:start + ev.batch_size].to(dev)
        out.append(system.rollout(contexts, steps, gen, ev.top_nfe, ev.bottom_nfe, steer).cpu())
    return torch.cat(out)


def load_fvd_network(cfg: PipelineConfig, dev: torch.device):
    path = ensure_asset("i3d_kinetics400", Path(cfg.assets.dir), cfg.assets.local.get("i3d_kinetics400"),
                        download=False)
    return load_i3d(path).to(dev).eval()


def sample_clusters(cache: LatentCache, split: str, samples: list[Sample]) -> list[str]:
    """What a bootstrap resamples: each sample's episode (clips and starts of one episode are not independent)."""
    index = cache.index(split)
    return [str(index[s.key].get("episode", s.key)) for s in samples]


def run_fvd(name: str, cfg: PipelineConfig, run: StageRun) -> str:
    """FVD over ``seconds`` on each split, chunked FVD and FVD-slope over ``long_seconds`` on ``long_split``,
    each with a clip-bootstrap interval, beside the reference rows of :mod:`orbis2.eval.references`.

    The long split's FVD uses the first ``seconds`` of its long rollouts (same
    contexts, same distribution as separate short rollouts). Whether a rollout
    beats repeating the last frame in latent space is the ``eval_conditioning``
    stage's unbiased one-step comparison, not a sample's MSE (which pays twice the
    conditional variance).
    """
    ev, dev = cfg.evaluation, device()
    system = load_system(name, dev, inference=inference_settings(cfg))
    cache = open_cache(LATENT_SETS[system.system.latents].root)
    i3d = load_fvd_network(cfg, dev)
    record: dict[str, Any] = {"model": name, "label": SYSTEMS[name].label, "parameters": system.parameters,
                              "latent_channels": system.bottom.model.latent_channels,
                              "predictors": SYSTEMS[name].stages, "nfe": {"top": ev.top_nfe, "bottom": ev.bottom_nfe},
                              "starts_per_clip": ev.starts_per_clip, "fvd_material": ev.fvd_material, "fvd": {},
                              "references": {}}
    media = EVAL / "media" / name
    with atomic_dir(media) as tmp:
        for split in ev.fvd_splits:
            fvd_split(split, system, cache, i3d, record, tmp, cfg, dev)
    for video in sorted(media.glob("*.mp4")):
        run.log_artifact(video, "videos")
    write_json(EVAL / f"fvd_{name}.json", record)
    run.log_artifact(EVAL / f"fvd_{name}.json")
    run.log_metrics({f"fvd_{split}": v["fvd"] for split, v in record["fvd"].items()})
    run.log_metrics({f"fvd_{split}_{ref}": v["fvd"] for split, refs in record["references"].items()
                     for ref, v in refs.items() if v["fvd"] is not None})
    if "chunked" in record:
        run.log_metrics({"fvd_slope": record["chunked"]["fvd_slope"]})
    splits = ", ".join(f"{s} {v['fvd']:.1f} [{v['low']:.1f}, {v['high']:.1f}] (n={v['videos']}, {v['clips']} clips)"
                       for s, v in record["fvd"].items())
    slope = f"; FVD-slope {record['chunked']['fvd_slope']:.1f}" if "chunked" in record else ""
    return f"{name}: FVD {splits}{slope}"


def fvd_split(split: str, system: LoadedSystem, cache: LatentCache, i3d, record: dict[str, Any], media: Path,
              cfg: PipelineConfig, dev: torch.device) -> None:
    """Roll out one split, add its FVD, reference rows and (long split) chunked FVD to ``record``; save a video."""
    ev, data = cfg.evaluation, cfg.data
    long = split == ev.long_split
    steps = rollout_steps(data, ev.long_seconds if long else ev.seconds)
    n_short, n_long = round(ev.seconds * data.detail_hz), round(ev.long_seconds * data.detail_hz)
    samples = eval_samples(cache, split, data, steps, ev.starts_per_clip)
    indices = [generated_indices(data, s.context_end, steps) for s in samples]
    clusters = sample_clusters(cache, split, samples)
    latents = generate(system, cache, split, samples, steps, cfg, dev)
    fake = system.decode(latents)
    clips = split_clips(split)
    what = f"{len(samples)}x{ev.starts_per_clip}starts|{steps}steps|{data.width}x{data.height}"

    def real(window: slice) -> np.ndarray:
        return real_features(split, f"{what}|frames{window.start}-{window.stop}",
                             lambda: clip_features(real_videos(clips, samples, [i[window] for i in indices]), i3d))

    short = slice(0, n_short)
    real_short = real(short)
    record["fvd"][split] = {**fvd_with_interval(real_short, clip_features(fake[:, short], i3d), clusters,
                                                ev.fvd_bootstrap_reps, ev.seed),
                            "frames": 16, "seconds": ev.seconds, "resolution": [224, 224],
                            "source_resolution": list(fake.shape[2:4]), "seed": ev.seed}
    record["references"][split] = references(split, system, cache, samples, indices, short, real_short, clusters,
                                             what, i3d, cfg)
    if long:
        record["chunked"] = chunked_record(split, fake[:, :n_long], real, clusters, i3d, cfg)
        save_grid_frames(media / "grid.npz", fake[0], data.detail_hz)
    write_video(media / f"{split}.mp4", fake[0], data.detail_hz)


def real_features(split: str, what: str, compute) -> np.ndarray:
    """Per-video I3D features of real videos, cached under the split's shard hash and a description of the videos."""
    return cached_features(STATS_CACHE, f"{split}|{split_hash(split)}|{what}", compute)


def references(split: str, system: LoadedSystem, cache: LatentCache, samples: list[Sample],
               indices: list[np.ndarray], window: slice, real: np.ndarray, clusters: list[str], what: str, i3d,
               cfg: PipelineConfig) -> dict[str, Any]:
    """Reference rows on the same clips and frames: real-vs-real floor, tokenizer reconstruction, repeat-last.

    Cached by the decoding tokenizer's checksum: systems that decode with the same
    tokenizer (all detail-level ones) share them.
    """
    ev, level = cfg.evaluation, system.output_level
    key = f"{what}|frames{window.start}-{window.stop}|{level}|{system.tokenizers[level].checksum[:16]}"

    def reconstruction() -> np.ndarray:
        truth = cache_latents(cache, split, level, samples, [i[window] for i in indices])
        return clip_features(system.decode(truth), i3d)

    def repeat_last() -> np.ndarray:
        last = cache_latents(cache, split, level, samples, [np.array([s.context_end]) for s in samples])
        frames = system.decode(last)
        return clip_features(np.broadcast_to(frames, (len(frames), window.stop - window.start, *frames.shape[2:])),
                             i3d)

    recon = real_features(split, f"{key}|reconstruction", reconstruction)
    still = real_features(split, f"{key}|repeat_last", repeat_last)
    return reference_rows(real, recon, still, clusters, ev.fvd_bootstrap_reps, ev.seed, ev.floor_splits)


def chunked_record(split: str, fake: np.ndarray, real, clusters: list[str], i3d,
                   cfg: PipelineConfig) -> dict[str, Any]:
    """Chunked FVD over consecutive ``chunk_seconds`` windows, FVD over the whole span, and the FVD-slope,
    each with a clip-bootstrap interval (all chunks on the same resamples)."""
    ev, data = cfg.evaluation, cfg.data
    windows = chunk_windows(fake.shape[1], data.detail_hz, ev.chunk_seconds)
    reals = [real(w) for w in windows]
    fakes = [clip_features(fake[:, w], i3d) for w in windows]
    chunks, slope, slope_draws = fvd_slope_interval(reals, fakes, clusters, ev.fvd_bootstrap_reps, seed=ev.seed)
    whole = slice(0, windows[-1].stop)
    full = fvd_with_interval(real(whole), clip_features(fake[:, whole], i3d), clusters,
                             ev.fvd_bootstrap_reps, ev.seed)
    return {"split": split, "seconds": len(windows) * ev.chunk_seconds, "chunk_seconds": ev.chunk_seconds,
            "videos": len(clusters), "clips": slope.clusters, "seed": ev.seed,
            "chunks": [{"start_s": w.start / data.detail_hz, "end_s": w.stop / data.detail_hz, "fvd": c.estimate,
                        "low": c.low, "high": c.high} for w, c in zip(windows, chunks)],
            "fvd_16s": full["fvd"], "fvd_16s_low": full["low"], "fvd_16s_high": full["high"],
            "fvd_slope": slope.estimate, "fvd_slope_low": slope.low, "fvd_slope_high": slope.high,
            "bootstrap_reps": ev.fvd_bootstrap_reps, "bootstrap_seed": ev.seed,
            "fvd_slope_draws": [float(d) for d in slope_draws]}


def save_grid_frames(path: Path, frames: np.ndarray, fps: float) -> None:
    """The frames of one long rollout at ``GRID_TIMES`` (those it reaches), for the report's qualitative grid."""
    times = [t for t in GRID_TIMES if round(t * fps) <= len(frames)]
    picks = [max(0, round(t * fps) - 1) for t in times]
    np.savez_compressed(path, frames=frames[picks], times=np.array(times))


# --------------------------------------------------------------------------- steering


def run_steering(cfg: PipelineConfig, run: StageRun) -> str:
    """Counterfactual steering (paper Table 2, appendix "Counterfactual steering"), read by two instruments.

    Rollouts of the hierarchical model with the steered top predictor (``action``)
    on ``steering_split`` starts, under each mode's scaling of the clip's own speed
    and yaw rate. Each video's trajectory is recovered by ``evaluation.inverse_dynamics``
    (the learned instrument by default) and by OpenCV visual odometry (second column);
    ADE in metres after least-squares scale alignment to the commanded trajectory.
    Scale-free responses, paired per start: the recovered turn (end-point angle, the
    clip's own turn direction positive) under yaw rate x1.5 minus under x0.5, and the
    path-length ratio (before alignment) under speed x1.5 over x0.5 (3 if the video
    follows). Every figure has a clip-bootstrap interval. Sanity: each instrument on
    the real videos of those spans, in order and with shuffled frames.
    """
    ev, data = cfg.evaluation, cfg.data
    if data.detail_stride != 1:
        raise OrbisError(f"data.{cfg.profile}: the steering evaluation compares odometry at the video rate and needs "
                         f"fps == detail_hz (got {data.fps} and {data.detail_hz})")
    dev = device()
    system = load_system("hierarchical", dev, top_override="action", inference=inference_settings(cfg))
    steer_meta = system.top.meta.get("steering")
    if steer_meta is None:
        raise OrbisError(f"{predictor_file('action')} is not steered; re-run the `action` stage")
    cache = open_cache(LATENTS)
    steps = rollout_steps(data, ev.steering_seconds)
    split = ev.steering_split
    samples = eval_samples(cache, split, data, steps, ev.steering_starts_per_clip)
    clusters = sample_clusters(cache, split, samples)
    indices = [generated_indices(data, s.context_end, steps) for s in samples]
    odometry = cache.arrays(split)["odometry"]
    K = camera_intrinsics(data.width, data.height, cfg.town.hfov_deg)
    instruments = {name: get_inverse_dynamics(name) for name in dict.fromkeys([ev.inverse_dynamics, "opencv"])}
    first = cache_latents(cache, split, "detail", samples, [np.array([s.context_end]) for s in samples])
    first_frames = system.decode(first)  # [N, 1, H, W, 3]
    speed_norm, yaw_norm = steer_meta["scale"]
    modes: dict[str, Any] = {}
    per_sample: dict[str, dict[str, dict[str, np.ndarray]]] = {}
    strip = {}
    for mode, (speed_scale, yaw_scale) in ev.steering_modes.items():
        controls, steering = [], []
        for s in samples:
            rows = odometry[s.offset: s.offset + s.context_end + steps * 5 + 1].astype(np.float64)
            speed, yaw = rows[:, 0] * speed_scale, rows[:, 1] * yaw_scale
            schedule = rollout_schedule(data, s.context_end, steps)
            steering.append(steering_sequences(schedule, speed, yaw, speed_norm, yaw_norm))
            controls.append((speed[s.context_end:], yaw[s.context_end:]))
        latents = generate(system, cache, split, samples, steps, cfg, dev, torch.stack(steering), desc=mode)
        videos = np.concatenate([first_frames, system.decode(latents)], axis=1)
        per_sample[mode] = {name: score_videos(videos, controls, inverse, K, data.detail_hz)
                            for name, inverse in instruments.items()}
        modes[mode] = mode_record(per_sample[mode], clusters, speed_scale, yaw_scale, ev.seed)
        sp, yw = controls[0]
        strip[mode] = (videos[0], integrate_controls(sp[:videos.shape[1] - 1], yw[:videos.shape[1] - 1],
                                                     1.0 / data.detail_hz))
    sanity = {name: odometry_sanity(split, samples, indices, odometry, K, inverse, data, clusters, ev.seed)
              for name, inverse in instruments.items()}
    record = {"split": split, "seconds": ev.steering_seconds, "samples": len(samples), "clips": len(set(clusters)),
              "seed": ev.seed, "inverse_dynamics": ev.inverse_dynamics, "instruments": list(instruments),
              "nfe": {"top": ev.top_nfe, "bottom": ev.bottom_nfe}, "modes": modes,
              "responses": {name: steering_responses(per_sample, name, clusters, ev.seed) for name in instruments},
              "material": {"turn_deg": ev.steering_turn_material_deg, "path_ratio": ev.steering_path_ratio_material},
              "odometry_sanity": sanity[ev.inverse_dynamics], "sanity": sanity}
    write_json(EVAL / "steering.json", record)
    run.log_artifact(EVAL / "steering.json")
    save_strip(strip, data.detail_hz, run)
    run.log_metrics({f"ade_{m}": v["ade"] for m, v in modes.items()})
    response, floor = record["responses"][ev.inverse_dynamics], sanity[ev.inverse_dynamics]
    return ("ADE (turn) " + ", ".join(f"{m} {v['ade']:.2f} m ({v['turn_deg']:.0f} deg)" for m, v in modes.items())
            + f" (n={len(samples)}, {ev.inverse_dynamics}); turn response "
              f"{response['turn_response_deg']['estimate']:.1f} deg, path ratio x1.5/x0.5 "
              f"{response['path_ratio']['estimate']:.2f}; real video ADE {floor['real_ade']:.2f} m, shuffled "
              f"{floor['shuffled_ade']:.2f} m")


def score_videos(videos: np.ndarray, controls: list, inverse, K: np.ndarray, fps: float) -> dict[str, np.ndarray]:
    """Per video: aligned ADE, signed turn (clip's own direction positive, degrees) and unaligned path length."""
    scored = [trajectory_ade(v, sp, yw, fps, K, inverse) for v, (sp, yw) in zip(videos, controls)]
    sign = np.array([np.sign(endpoint_angle(r["reference"])) or 1.0 for r in scored])
    return {"ade": np.array([r["ade"] for r in scored]),
            "turn_deg": sign * np.array([endpoint_angle(r["estimated"]) for r in scored]),
            "commanded_turn_deg": sign * np.array([endpoint_angle(r["reference"]) for r in scored]),
            "path_length": np.array([path_length(r["estimated"]) for r in scored])}


def mode_record(scores: dict[str, dict[str, np.ndarray]], clusters: list[str], speed_scale: float, yaw_scale: float,
                seed: int) -> dict[str, Any]:
    """One mode's figures per instrument with clip-bootstrap intervals; the first instrument's on top."""
    per = {}
    for name, sc in scores.items():
        ade_iv, turn_iv = mean_interval(sc["ade"], clusters, seed=seed), mean_interval(sc["turn_deg"], clusters,
                                                                                       seed=seed)
        per[name] = {"ade": ade_iv.estimate, "ade_low": ade_iv.low, "ade_high": ade_iv.high,
                     "turn_deg": turn_iv.estimate, "turn_low": turn_iv.low, "turn_high": turn_iv.high,
                     "path_length": float(sc["path_length"].mean())}
    main = next(iter(scores))
    return {**per[main], "samples": len(clusters), "speed_scale": speed_scale, "yaw_rate_scale": yaw_scale,
            "commanded_turn_deg": float(scores[main]["commanded_turn_deg"].mean()), "instruments": per}


def steering_responses(per_sample: dict, name: str, clusters: list[str], seed: int) -> dict[str, Any]:
    """Scale-free, paired per start: turn(x1.5) - turn(x0.5) in degrees, and path length(x1.5) / (x0.5)."""
    out: dict[str, Any] = {}
    yaw = ("yaw_rate_x0.5", "yaw_rate_x1.5")
    if all(m in per_sample for m in yaw):
        lo, hi = (per_sample[m][name] for m in yaw)
        iv = paired_difference(hi["turn_deg"], lo["turn_deg"], clusters, seed=seed)
        out["turn_response_deg"] = iv.to_dict()
        cmd = float((hi["commanded_turn_deg"] - lo["commanded_turn_deg"]).mean())
        out["commanded_turn_response_deg"] = cmd
        out["turn_by_mode_deg"] = {m: float(per_sample[m][name]["turn_deg"].mean())
                                   for m in ("yaw_rate_x0.5", "original", "yaw_rate_x1.5") if m in per_sample}
    speed = ("speed_x0.5", "speed_x1.5")
    if all(m in per_sample for m in speed):
        lo, hi = (per_sample[m][name]["path_length"] for m in speed)
        ratio = np.log(np.maximum(hi, 1e-9) / np.maximum(lo, 1e-9))
        iv = mean_interval(ratio, clusters, seed=seed)
        out["path_ratio"] = {"estimate": float(np.exp(iv.estimate)), "low": float(np.exp(iv.low)),
                             "high": float(np.exp(iv.high)), "commanded": 3.0, "clusters": iv.clusters,
                             "note": "geometric mean of path length under speed x1.5 over x0.5, before alignment"}
    return out


def odometry_sanity(split: str, samples: list[Sample], indices: list[np.ndarray], odometry: np.ndarray, K,
                    inverse, data, clusters: list[str], seed: int) -> dict[str, Any]:
    """An instrument on the real videos of the evaluated spans, in order and with a fixed frame shuffle."""
    clips = split_clips(split)
    rng = np.random.default_rng(0)
    real, shuffled = [], []
    for s, idx in zip(samples, indices):
        span = np.concatenate([[s.context_end], idx])
        video = clips[s.key].frames(span)
        rows = odometry[s.offset + s.context_end: s.offset + span[-1]].astype(np.float64)
        real.append(trajectory_ade(video, rows[:, 0], rows[:, 1], data.detail_hz, K, inverse)["ade"])
        order = rng.permutation(len(video))
        shuffled.append(trajectory_ade(video[order], rows[:, 0], rows[:, 1], data.detail_hz, K, inverse)["ade"])
    real_iv, shuffled_iv = mean_interval(real, clusters, seed=seed), mean_interval(shuffled, clusters, seed=seed)
    return {"real_ade": real_iv.estimate, "real_low": real_iv.low, "real_high": real_iv.high,
            "shuffled_ade": shuffled_iv.estimate, "shuffled_low": shuffled_iv.low,
            "shuffled_high": shuffled_iv.high, "videos": len(samples)}


def save_strip(strip: dict[str, tuple[np.ndarray, np.ndarray]], fps: float, run: StageRun) -> None:
    frames = next(iter(strip.values()))[0]
    times = [t for t in (0.0, 2.0, 4.0, 6.0) if round(t * fps) < len(frames)]
    picks = [round(t * fps) for t in times]
    path = EVAL / "steering_strip.png"
    save_steering_strip([v[picks] for v, _ in strip.values()], list(strip), times,
                        [path_ for _, path_ in strip.values()], path)
    run.log_artifact(path)


# --------------------------------------------------------------------------- speed


# Speed rows: name -> (system, frames per step; None = the system's own). ``v1_style`` runs the flat detail
# network like Orbis v1, one frame per step at 10 Hz with the full NFE (same parameters, 5x the calls).
SPEED_RUNS = {
    "hierarchical": ("hierarchical", None),
    "hierarchical_distilled": ("hierarchical_distilled", None),
    "flat_detail": ("flat_detail", None),
    "flat_abstract": ("flat_abstract", None),
    "v1_style": ("flat_detail", 1),
}


def run_speed(cfg: PipelineConfig, run: StageRun) -> str:
    """Frames per second and peak memory of ``SPEED_RUNS``, one after another in one process (paper Table 5).

    Batch 1, ``speed_seconds`` of rollout from a val context with the evaluation's
    NFE (the distilled detail predictor with its own), the last-decoded frames
    included (generation as a user sees it); bf16 / compile / KV cache per
    ``evaluation``.
    """
    ev, data = cfg.evaluation, cfg.data
    dev = device()
    cache = open_cache(LATENTS)
    steps = rollout_steps(data, ev.speed_seconds)
    settings = inference_settings(cfg)
    models = {}
    for name, (system_name, frames_per_step) in SPEED_RUNS.items():
        system = load_system(system_name, dev, inference=settings)
        sample = eval_samples(cache, "val", data, steps, 1)[:1]
        contexts = contexts_for(system, cache, "val", data, sample, dev)
        bottom_nfe = system.bottom_nfe(ev.bottom_nfe)

        def one_rollout(system=system, contexts=contexts, nfe=bottom_nfe, per_step=frames_per_step) -> int:
            latents = system.rollout(contexts, steps, generator(ev.seed, dev), ev.top_nfe, nfe,
                                     frames_per_step=per_step)
            return system.decode(latents).shape[1]

        result = measure(one_rollout, warmup=1, repeats=ev.speed_repeats, device=dev)
        models[name] = {"fps": result["fps"], "peak_memory_mb": result["peak_memory_mb"],
                        "parameters": system.parameters, "frames": result["frames"],
                        "memory_kind": result["memory_kind"], "bottom_nfe": bottom_nfe,
                        "top_nfe": ev.top_nfe if system.top is not None else None,
                        "frames_per_step": frames_per_step or 5}
        del system, contexts
    record = {"device": torch.cuda.get_device_name() if dev.type == "cuda" else f"cpu ({torch.get_num_threads()} "
              f"threads)", "memory_kind": next(iter(models.values()))["memory_kind"], "batch": 1,
              "seconds": steps * 0.5, "nfe": {"top": ev.top_nfe, "bottom": ev.bottom_nfe}, "models": models,
              "precision": settings.precision if dev.type == "cuda" else "fp32", "compile": settings.compile,
              "kv_cache": settings.kv_cache}
    write_json(EVAL / "speed.json", record)
    run.log_artifact(EVAL / "speed.json")
    run.log_metrics({f"fps_{m}": v["fps"] for m, v in models.items()})
    return ", ".join(f"{m} {v['fps']:.2f} frames/s, {v['peak_memory_mb']:.0f} MB" for m, v in models.items())


# --------------------------------------------------------------------------- linear probes

# Probe targets beyond the predictors: the abstract tokenizers' latents and the frozen teacher.
# The main model's predictors are probed at ``block_main`` (the paper's 4th from the end), ablations at
# ``block_ablation``. Per-block curves (paper Fig. 5: diffusion forcing vs teacher forcing at every block)
# for the DF-only and TF-only predictors; both are ablation targets, so the main report does not wait for them.
MAIN_PROBES = ("abstract_tf", "detail")
PER_BLOCK = ("abstract_df", "abstract_tf_only")


def probe_targets() -> list[str]:
    """Representations and predictors that are linearly probed (registry.yaml)."""
    return registry().probe_targets


def probe_sets(cfg: PipelineConfig) -> list[tuple[str, list, list]]:
    """(name, train frames, test frames) per probe data source.

    The town's labelled ``probe`` split (divided by episode) serves both tasks unless
    Cityscapes and/or KITTI are configured, which then take over segmentation and/or
    depth (paper appendix "Linear probing details").
    """
    ps, size = cfg.evaluation.probe, (cfg.data.width, cfg.data.height)
    sets = []
    if ps.cityscapes is not None:
        sets.append(("cityscapes", cityscapes_frames(ps.cityscapes, "train", size, ps.max_frames),
                     cityscapes_frames(ps.cityscapes, "val", size, ps.max_frames)))
    if ps.kitti is not None:
        sets.append(("kitti eigen", kitti_eigen_frames(ps.kitti, ps.kitti_train_split, size, ps.kitti_depth,
                                                       ps.max_frames),
                     kitti_eigen_frames(ps.kitti, ps.kitti_test_split, size, ps.kitti_depth, ps.max_frames)))
    if len(sets) < 2:
        train, test = split_by_episode(town_probe_frames(SHARDS, "probe", size), ps.test_fraction, ps.seed)
        sets.append(("town probe split", train, test))
    return sets


def probe_all(feature_fn, sets: list[tuple[str, list, list]], cfg) -> dict[str, Any]:
    """Segmentation from the first source with semantics, depth from the first with depth."""
    out: dict[str, Any] = {"segmentation": None, "depth": None, "data": {}}
    for name, train, test in sets:
        result = run_probe(feature_fn, train, test, cfg)
        for task in ("segmentation", "depth"):
            if out[task] is None and result[task] is not None:
                out[task] = result[task]
                out["data"][task] = name
    return out


def run_probe_stage(target: str, cfg: PipelineConfig, run: StageRun) -> str:
    """Linear probes of one representation (paper appendix "Linear probing details").

    Predictors follow the null-context protocol of :func:`orbis2.eval.probe.predictor_features`;
    the k-th block from the end is clamped to the network's depth.
    """
    if target not in probe_targets():
        raise OrbisError(f"unknown probe target {target!r}; choose from {probe_targets()}")
    ps, dev = cfg.evaluation.probe, device()
    # The params section carries every training setting of the probe module's config (plus data and blocks).
    shared = {f.name for f in dataclasses.fields(ProbeConfig)} & {f.name for f in dataclasses.fields(ps)}
    probe_cfg = ProbeConfig(**{name: getattr(ps, name) for name in shared}, device=str(dev))
    sets = probe_sets(cfg)
    record: dict[str, Any] = {"target": target, "block": None}
    representation = registry().representations.get(target)
    if representation is not None and not representation.teacher:
        latents = representation.latents
        record["label"] = f"Abstract tokenizer ({latents})"
        tokenizer = load_tokenizer(LATENT_SETS[latents].tokenizers["abstract"], dev)
        result = probe_all(tokenizer_features(tokenizer), sets, probe_cfg)
    elif representation is not None:
        tc = cfg.tokenizer_abstract
        teacher = build_teacher(tc.teacher, asset_path(Path(cfg.assets.dir), TEACHER_ASSETS[tc.teacher]),
                                tc.teacher_layer).to(dev)
        record["label"] = f"Teacher ({tc.teacher})"
        result = probe_all(teacher_features(teacher), sets, probe_cfg)
    else:
        predictor = load_predictor(predictor_file(target), dev)
        tokenizer = load_tokenizer(LATENT_SETS[STAGES[target].latents].tokenizers[predictor.meta["level"]], dev)
        depth = len(predictor.model.blocks)
        wanted = ps.block_main if target in MAIN_PROBES else ps.block_ablation
        block = min(wanted, depth)
        record.update(label=target, block=block, depth=depth)
        result = probe_all(predictor_features(predictor, tokenizer, block), sets, probe_cfg)
        if target in PER_BLOCK:
            record["per_block"] = []
            for k in range(1, depth + 1):
                r = result if k == block else probe_all(predictor_features(predictor, tokenizer, k), sets, probe_cfg)
                record["per_block"].append({"block": k, "miou": r["segmentation"]["miou"],
                                            "rmse": r["depth"]["rmse"]})
    record.update(segmentation=result["segmentation"], depth=result["depth"], data=result["data"])
    write_json(EVAL / f"probe_{target}.json", record)
    run.log_artifact(EVAL / f"probe_{target}.json")
    run.log_metrics({"miou": result["segmentation"]["miou"], "depth_rmse": result["depth"]["rmse"]})
    return (f"{target}: mIoU {result['segmentation']['miou']:.3f} ({result['data']['segmentation']}), depth RMSE "
            f"{result['depth']['rmse']:.2f} m ({result['data']['depth']})")


# --------------------------------------------------------------------------- reports


def report_setup(cfg: PipelineConfig) -> dict[str, Any]:
    """What the summary states about how the numbers were made."""
    ev = cfg.evaluation
    return {"profile": cfg.profile, "resolution": f"{cfg.data.width}x{cfg.data.height}",
            "evaluation seed": ev.seed, "NFE (top / bottom)": f"{ev.top_nfe} / {ev.bottom_nfe}",
            "FVD rollouts": f"{ev.seconds} s on {', '.join(ev.fvd_splits)}; chunked {ev.long_seconds} s on "
                            f"{ev.long_split} in {ev.chunk_seconds} s chunks",
            "starts per clip": ev.starts_per_clip, "steering": f"{ev.steering_seconds} s on {ev.steering_split}",
            "probe": f"town probe split, {ev.probe.seg_epochs} / {ev.probe.depth_epochs} epochs, "
                     f"seed {ev.probe.seed}",
            "training seeds": {s: cfg.section(s).train.seed for s in ("abstract_df", "abstract_tf", "detail",
                                                                       "action", "flat_detail", "flat_abstract")}}


def run_report(scope: str, cfg: PipelineConfig, run: StageRun) -> str:
    """``main``: main_table/steering/speed CSVs and summary.md in reports/; ``all``: every table and figure in
    reports/all/, with the qualitative rollout grid (from the FVD stages' saved frames) and the steering strip."""

    evals = load_eval(EVAL)
    setup, rates = report_setup(cfg), {"detail_hz": cfg.data.detail_hz, "abstract_hz": cfg.data.abstract_hz}
    if scope == "main":
        written = write_main_report(evals, layout_path("reports"), setup, **rates)
    else:
        evals["compression"] = compression_from_evals(evals)
        with atomic_dir(layout_path("report_all")) as tmp:
            write_full_report(evals, tmp, setup, **rates)
            shutil.copy2(EVAL / "steering_strip.png", tmp / "figures" / "steering_strip.png")
            grids = [(n, np.load(EVAL / "media" / n / "grid.npz")) for n in SYSTEMS
                     if (EVAL / "media" / n / "grid.npz").is_file()]
            if grids:
                times = min((g["times"] for _, g in grids), key=len)
                save_rollout_grid([g["frames"][:len(times)] for _, g in grids], [SYSTEMS[n].label for n, _ in grids],
                                  list(times), tmp / "figures" / "rollout_grid.png")
        written = sorted(p for p in layout_path("report_all").rglob("*") if p.is_file())
    for path in written:
        run.log_artifact(path, None if scope == "main" else "all")
    return f"{len(written)} files: " + ", ".join(p.name for p in written)
