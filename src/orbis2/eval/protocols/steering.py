"""Counterfactual steering, scored (paper Table 2, appendix "Counterfactual steering"; the ``eval_steering`` stage).

Rollouts of the hierarchical model with the steered top predictor run under each
mode's scaling of the clip's own speed and yaw rate (:func:`steering_inputs`).
Each video's trajectory is recovered by an inverse-dynamics instrument
(:mod:`orbis2.eval.metrics.odometry`) and compared with the commanded one: ADE in metres
after least-squares scale alignment (:func:`score_videos`). Scale-free responses,
paired per start (:func:`steering_responses`): the recovered turn (end-point
angle, the clip's own turn direction positive) under yaw rate x1.5 minus under
x0.5, and the path-length ratio (before alignment) under speed x1.5 over x0.5 (3
if the video follows). Every figure has a clip-bootstrap interval. Sanity
(:func:`odometry_sanity`): each instrument on the real videos of those spans, in
order and with shuffled frames.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from orbis2.config.sections import DataConfig
from orbis2.data.shards import Clip
from orbis2.eval.figures import save_frame_columns, save_steering_strip
from orbis2.eval.metrics.odometry import endpoint_angle, path_length, trajectory_ade
from orbis2.eval.metrics.stats import mean_interval, paired_difference
from orbis2.eval.protocols.conditioning import sideways_shift
from orbis2.eval.protocols.systems import Sample
from orbis2.eval.records import GuidanceSelection, SteeringRecord
from orbis2.rollout import rollout_schedule, steering_sequences

# Times (s) of the frames shown in the steering strip (those the rollout reaches).
STRIP_TIMES = (0.0, 2.0, 4.0, 6.0)
# Times (s after the last context frame) of the headline figure's columns.
HEADLINE_TIMES = (0.0, 1.0, 3.0)


def steering_inputs(samples: list[Sample], odometry: np.ndarray, data: DataConfig, steps: int, speed_scale: float,
                    yaw_scale: float, scale: Sequence[float]) -> tuple[list[tuple[np.ndarray, np.ndarray]],
                                                                      torch.Tensor]:
    """One mode's commands: per sample the scaled (speed, yaw rate) from its last context frame on, and the
    steering input [N, steps, ...] of the steered predictor (``scale``: its speed and yaw-rate normalisers)."""
    controls, steering = [], []
    for s in samples:
        rows = odometry[s.offset: s.offset + s.context_end + steps * 5 + 1].astype(np.float64)
        speed, yaw = rows[:, 0] * speed_scale, rows[:, 1] * yaw_scale
        schedule = rollout_schedule(data, s.context_end, steps)
        steering.append(steering_sequences(schedule, speed, yaw, scale))
        controls.append((speed[s.context_end:], yaw[s.context_end:]))
    return controls, torch.stack(steering)


def trajectories(videos, controls: list, inverse, K: np.ndarray, fps: float) -> list[dict]:
    """:func:`trajectory_ade` of each video under its (speed, yaw rate) controls, in order; an instrument that
    releases the GIL (OpenCV's odometry) reads the videos on one thread per torch thread."""
    workers = torch.get_num_threads() if getattr(inverse, "releases_gil", False) else 1
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(lambda vc: trajectory_ade(vc[0], *vc[1], fps, K, inverse), zip(videos, controls)))


def score_videos(videos: np.ndarray, controls: list, inverse, K: np.ndarray, fps: float) -> dict[str, np.ndarray]:
    """Per video: aligned ADE, signed turn (clip's own direction positive, degrees) and unaligned path length."""
    scored = trajectories(videos, controls, inverse, K, fps)
    sign = np.array([np.sign(endpoint_angle(r["reference"])) or 1.0 for r in scored])
    return {"ade": np.array([r["ade"] for r in scored]),
            "turn_deg": sign * np.array([endpoint_angle(r["estimated"]) for r in scored]),
            "commanded_turn_deg": sign * np.array([endpoint_angle(r["reference"]) for r in scored]),
            "path_length": np.array([path_length(r["estimated"]) for r in scored])}


def shift_degrees(shifts: np.ndarray, columns: int, hfov_deg: float) -> np.ndarray:
    """Sideways shifts of a grid ``columns`` wide -> heading changes in degrees, through the camera's
    horizontal field of view (a pinhole: a shift of the half width is hfov / 2)."""
    return np.degrees(np.arctan(np.asarray(shifts) / (columns / 2) * np.tan(np.radians(hfov_deg) / 2)))


def own_direction(turn: np.ndarray, commanded: np.ndarray) -> dict[str, np.ndarray]:
    """A reading and the commanded heading change per video, signed so the commanded direction is positive."""
    sign = np.where(np.asarray(commanded) < 0, -1.0, 1.0)
    return {"turn_deg": sign * np.asarray(turn), "commanded_turn_deg": sign * np.asarray(commanded)}


# The latent reading: shifts between consecutive detail latents searched up to 3 columns either way in
# steps of 1/16 column. Over one frame at 10 Hz the ego's steering limit (1.8 rad/s) times the largest
# counterfactual factor (1.5) turns 15.5 degrees, 2.2 columns of a 16-column grid: the reach covers every
# real and commanded step, which a 0.5-s step (47 degrees at the world's fastest turns) could not.
LATENT_SEARCH = (3.0, 1 / 16)


def latent_turns(first: torch.Tensor, latents: torch.Tensor, controls: list, fps: float,
                 hfov_deg: float) -> dict[str, np.ndarray]:
    """Per video, the heading change read from the detail latents themselves, with no decoding (degrees,
    the clip's own commanded direction positive), and the commanded one.

    A turn moves the latent grid sideways: ``sideways_shift`` between consecutive latents (from the
    last context latent ``first`` [N, 1, ...] on; ``controls`` per video (speed, yaw rate) at ``fps``
    from that frame), searched over ``LATENT_SEARCH``, each converted to an angle
    (:func:`shift_degrees`), summed. Blind to speed; a check on the decoded-video instruments, which
    can miss a turn the latents make when the decoded frames are too blurred for their flow.
    """
    sequence = torch.cat([first, latents], dim=1)
    shifts = np.stack([sideways_shift(sequence[:, i], sequence[:, i + 1], LATENT_SEARCH)
                       for i in range(sequence.shape[1] - 1)], 1)
    commanded = np.degrees([np.sum(yaw[:shifts.shape[1]]) / fps for _, yaw in controls])
    return own_direction(shift_degrees(shifts, sequence.shape[-1], hfov_deg).sum(axis=1), commanded)


# The image reading: grey frames shrunk to this many columns, shifts searched up to 4 columns either way
# in steps of 1/16 column (a quarter pixel at 256 pixels wide).
IMAGE_COLUMNS, IMAGE_SEARCH = 64, (4.0, 1 / 16)


def image_turns(videos: np.ndarray | list[np.ndarray], controls: list, fps: float,
                hfov_deg: float) -> dict[str, np.ndarray]:
    """Per video [T, H, W, 3] uint8, the heading change read from the frames' sideways motion (degrees, the
    clip's own commanded direction positive), and the commanded one over the same T - 1 steps.

    A camera that turns moves the whole image sideways (content moves right in a left turn):
    ``sideways_shift`` between consecutive grey frames (shrunk to ``IMAGE_COLUMNS``), turned
    into an angle (:func:`shift_degrees`), summed.
    Model-free and blind to speed; on rollouts it tells whether a turn the latents make
    survives decoding as image motion, where the learned instrument's flow sees none.
    """
    turns, commanded = [], []
    for video, (_, yaw) in zip(videos, controls):
        grey = torch.from_numpy(np.asarray(video)).float().mean(dim=-1)[:, None]  # [T, 1, H, W]
        height, width = grey.shape[-2:]
        small = F.interpolate(grey, size=(max(1, round(height * IMAGE_COLUMNS / width)), IMAGE_COLUMNS),
                              mode="area")
        turns.append(shift_degrees(sideways_shift(small[:-1], small[1:], IMAGE_SEARCH), IMAGE_COLUMNS,
                                   hfov_deg).sum())
        commanded.append(np.degrees(np.sum(yaw[:len(video) - 1]) / fps))
    return own_direction(np.array(turns), np.array(commanded))


YAW_ORDER = ("yaw_rate_x0.5", "original", "yaw_rate_x1.5")  # the turn each should show, least to most


def ordering_steps(by_mode: dict[str, dict[str, np.ndarray]], clusters: list[str], seed: int) -> dict[str, Any]:
    """The turn ordering yaw rate x0.5 < original < x1.5, paired per start: each step's turn difference
    (degrees, the clip's own direction positive) with a clip-bootstrap interval and its commanded difference;
    empty without the three modes."""
    if not all(m in by_mode for m in YAW_ORDER):
        return {}
    steps = {}
    for lower, upper in zip(YAW_ORDER, YAW_ORDER[1:]):
        lo, hi = by_mode[lower], by_mode[upper]
        steps[f"{upper} - {lower}"] = {
            **paired_difference(hi["turn_deg"], lo["turn_deg"], clusters, seed=seed).to_dict(),
            "commanded": float((hi["commanded_turn_deg"] - lo["commanded_turn_deg"]).mean())}
    return steps


def turn_record(turns: dict[str, dict[str, np.ndarray]], clusters: list[str], seed: int) -> dict[str, Any]:
    """Per mode (and "real", the real continuation) the mean turn of one reading (:func:`latent_turns`,
    :func:`image_turns`) with a clip-bootstrap interval, the paired response turn(yaw rate x1.5) -
    turn(x0.5) against the commanded one, and the ordering's two steps (:func:`ordering_steps`)."""
    out: dict[str, Any] = {"modes": {}}
    for mode, t in turns.items():
        iv = mean_interval(t["turn_deg"], clusters, seed=seed)
        out["modes"][mode] = {"turn_deg": iv.estimate, "low": iv.low, "high": iv.high,
                              "commanded_turn_deg": float(t["commanded_turn_deg"].mean())}
    if "yaw_rate_x0.5" in turns and "yaw_rate_x1.5" in turns:
        lo, hi = turns["yaw_rate_x0.5"], turns["yaw_rate_x1.5"]
        out["turn_response_deg"] = paired_difference(hi["turn_deg"], lo["turn_deg"], clusters, seed=seed).to_dict()
        out["commanded_turn_response_deg"] = float((hi["commanded_turn_deg"] - lo["commanded_turn_deg"]).mean())
    out["turn_steps_deg"] = ordering_steps(turns, clusters, seed)
    return out


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
    """Scale-free, paired per start: turn(x1.5) - turn(x0.5) in degrees with the ordering's two steps
    (:func:`ordering_steps`), and path length(x1.5) / (x0.5)."""
    out: dict[str, Any] = {}
    yaw = ("yaw_rate_x0.5", "yaw_rate_x1.5")
    if all(m in per_sample for m in yaw):
        lo, hi = (per_sample[m][name] for m in yaw)
        iv = paired_difference(hi["turn_deg"], lo["turn_deg"], clusters, seed=seed)
        out["turn_response_deg"] = iv.to_dict()
        cmd = float((hi["commanded_turn_deg"] - lo["commanded_turn_deg"]).mean())
        out["commanded_turn_response_deg"] = cmd
        out["turn_by_mode_deg"] = {m: float(per_sample[m][name]["turn_deg"].mean())
                                   for m in YAW_ORDER if m in per_sample}
        out["turn_steps_deg"] = ordering_steps({m: per_sample[m][name] for m in YAW_ORDER if m in per_sample},
                                               clusters, seed)
    speed = ("speed_x0.5", "speed_x1.5")
    if all(m in per_sample for m in speed):
        lo, hi = (per_sample[m][name]["path_length"] for m in speed)
        ratio = np.log(np.maximum(hi, 1e-9) / np.maximum(lo, 1e-9))
        iv = mean_interval(ratio, clusters, seed=seed)
        out["path_ratio"] = {"estimate": float(np.exp(iv.estimate)), "low": float(np.exp(iv.low)),
                             "high": float(np.exp(iv.high)), "commanded": 3.0, "clusters": iv.clusters,
                             "note": "geometric mean of path length under speed x1.5 over x0.5, before alignment"}
    return out


def choose_guidance(records: dict[float, SteeringRecord], instrument: str, material: float,
                    split: str) -> GuidanceSelection:
    """The steering-guidance scale a selection split (``split``) supports, from ``eval_steering`` records keyed by
    scale.

    The smallest scale whose two ordering steps (original - yaw x0.5, yaw x1.5 - original) read by
    ``instrument`` both have an interval lower bound above ``material`` degrees; if none does, the scale
    whose smaller lower bound is largest. Smallest, because a larger scale moves the subgoals further
    sideways than real ones (over-steer) once the ordering is already resolved.
    """
    if not records:
        raise ValueError("choose_guidance needs at least one record")
    lows = {}
    for scale, record in records.items():
        responses = record.responses.get(instrument)
        steps = (responses.turn_steps_deg if responses is not None else None) or {}
        if len(steps) != 2:
            raise ValueError(f"the record of guidance {scale:g} lacks the yaw-rate modes {YAW_ORDER}")
        lows[float(scale)] = min(step.low for step in steps.values())
    passing = sorted(scale for scale, low in lows.items() if low > material)
    chosen = passing[0] if passing else max(lows, key=lows.get)
    return GuidanceSelection(chosen=chosen, resolved=bool(passing), instrument=instrument, material_deg=material,
                             smaller_step_low_deg={str(scale): low for scale, low in lows.items()}, split=split)


def real_videos(clips: dict[str, Clip], samples: list[Sample], indices: list[np.ndarray]) -> list[np.ndarray]:
    """The real frames of each evaluated span: the last context frame, then the generated frames' indices."""
    return [clips[s.key].frames(np.concatenate([[s.context_end], idx])) for s, idx in zip(samples, indices)]


def odometry_sanity(videos: list[np.ndarray], samples: list[Sample], indices: list[np.ndarray],
                    odometry: np.ndarray, K, inverse, data: DataConfig, clusters: list[str],
                    seed: int) -> dict[str, Any]:
    """An instrument on the real videos of the evaluated spans (:func:`real_videos`), in order and with a
    fixed frame shuffle."""
    rng = np.random.default_rng(0)
    controls = []
    for s, idx in zip(samples, indices):
        rows = odometry[s.offset + s.context_end: s.offset + idx[-1]].astype(np.float64)
        controls.append((rows[:, 0], rows[:, 1]))
    shuffled_videos = [video[rng.permutation(len(video))] for video in videos]
    real = [r["ade"] for r in trajectories(videos, controls, inverse, K, data.detail_hz)]
    shuffled = [r["ade"] for r in trajectories(shuffled_videos, controls, inverse, K, data.detail_hz)]
    real_iv, shuffled_iv = mean_interval(real, clusters, seed=seed), mean_interval(shuffled, clusters, seed=seed)
    return {"real_ade": real_iv.estimate, "real_low": real_iv.low, "real_high": real_iv.high,
            "shuffled_ade": shuffled_iv.estimate, "shuffled_low": shuffled_iv.low,
            "shuffled_high": shuffled_iv.high, "videos": len(samples)}


def save_headline(rows: dict[str, np.ndarray], fps: float, path: Path) -> None:
    """The README's figure: one clip's videos (columns, titled by the keys; each starts at the last context frame)
    at ``HEADLINE_TIMES`` (rows)."""
    length = min(len(video) for video in rows.values())
    times = [t for t in HEADLINE_TIMES if round(t * fps) < length]
    picks = [round(t * fps) for t in times]
    save_frame_columns([video[picks] for video in rows.values()], list(rows), times, path)


def save_strip(strip: dict[str, tuple[np.ndarray, np.ndarray]], fps: float, path: Path) -> None:
    """The steering strip: per mode (rows) the first video's frames at ``STRIP_TIMES`` and its commanded path."""
    frames = next(iter(strip.values()))[0]
    times = [t for t in STRIP_TIMES if round(t * fps) < len(frames)]
    picks = [round(t * fps) for t in times]
    save_steering_strip([v[picks] for v, _ in strip.values()], list(strip), times,
                        [path_ for _, path_ in strip.values()], path)
