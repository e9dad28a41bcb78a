"""A drive: the hierarchical world model stepped live, one 0.5 s chunk per command (``orbis2 play``).

A :class:`Drive` starts from a scene's real context (a held-out town clip or an imported video with odometry),
exactly as ``orbis2 rollout`` does, and runs :func:`~orbis2.rollout.cascaded_steps`: each step takes a
commanded speed and yaw rate (held over the step's native frames) or, in replay, the clip's recorded ones.
The commanded odometry is kept at the native rate from the clip's first frame, so a recording is a CSV that
``orbis2 rollout --trajectory`` reads back to the same steering, and with the same seed to the same frames.

For a town clip the drive also renders the true view: the recorded episode re-rendered along the commanded
path (:class:`~orbis2.sim.counterfactual.PathRenderer`), the frames a camera on that path would have seen.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import pyarrow.parquet as pq
import torch

from orbis2.accel import cast_for_inference, inference_autocast, set_tf32
from orbis2.config.params import PipelineConfig
from orbis2.data.importer import find_videos
from orbis2.errors import OrbisError
from orbis2.inference import (
    abstract_predictor_path,
    compile_models,
    compose,
    decode_latents,
    load_checkpoints,
    load_steering,
    read_context,
    sampler_settings,
    write_outputs,
)
from orbis2.io import atomic_file
from orbis2.kinematics import integrate_odometry
from orbis2.latents import encode_frames
from orbis2.models.files import PredictorFile, TokenizerFile
from orbis2.registry import layout_path
from orbis2.rollout import cascaded_steps, first_context_end, rollout_schedule, steering_offsets, steering_sequences
from orbis2.run_profile import resolve_profile
from orbis2.sim import Camera, EgoTrack, Town
from orbis2.sim.counterfactual import PathFrames, PathRenderer
from orbis2.tasks.official import unconverted_steering

TRUTH_WORKER = ThreadPoolExecutor(1, thread_name_prefix="true-view")  # the town's kernels release the GIL
TOWN_SPLIT = "heldout"  # the town clips offered as scenes: none of them was trained on
TOWN_ORIGIN = re.compile(r"town style=(\S+) town_seed=(\d+) ego_seed=(\d+)")  # a raw town episode's index entry


@dataclass(frozen=True)
class Scene:
    """A video to start from and its recorded odometry (timestamp, speed, yaw_rate from its first frame)."""

    name: str
    video: Path
    odometry: dict[str, np.ndarray]
    odometry_path: Path


def scene_of(video: Path) -> Scene:
    """A scene from a video with odometry beside it (``<stem>.csv`` or the town's ``<stem>.parquet``)."""
    if not video.is_file():
        raise OrbisError(f"{video}: video not found; pass an existing video")
    odometry, path = load_steering(None, video)
    if odometry is None:
        raise OrbisError(f"{video}: no odometry beside it; add {video.with_suffix('.csv')} with columns timestamp, "
                         f"speed, yaw_rate (the import layout) to drive from it")
    return Scene(video.stem, video, odometry, path)


def find_scenes(extra: list[Path]) -> list[Scene]:
    """The held-out town clips, the imported videos that have odometry (any split sub-folder), then ``extra``
    (refused without)."""
    videos = sorted(layout_path("raw", "town").glob(f"{TOWN_SPLIT}/*.mp4"))
    if layout_path("videos").is_dir():
        videos += [v for _, v in find_videos(layout_path("videos")) if v.with_suffix(".csv").is_file()]
    scenes = [scene_of(v) for v in videos] + [scene_of(v) for v in extra]
    if not scenes:
        raise OrbisError(f"no scenes: neither {layout_path('raw', 'town') / TOWN_SPLIT} nor {layout_path('videos')} "
                         f"holds a video with odometry; run the main job first or pass --video")
    return scenes


@lru_cache(maxsize=2)
def town_of(style: str, seed: int) -> Town:
    return Town.generate(style, seed)


def town_episode(scene: Scene) -> tuple[Town, EgoTrack] | None:
    """The town and the recorded track of a raw town episode (its split folder's ``../index.json`` names the
    town; its parquet holds the poses and controls as driven); None for any other video."""
    index = scene.video.parent.parent / "index.json"
    if scene.odometry_path.suffix != ".parquet" or not index.is_file():
        return None
    entries = {e["stem"]: e for e in json.loads(index.read_text())["episodes"]}
    found = TOWN_ORIGIN.fullmatch(str(entries.get(scene.video.stem, {}).get("origin", "")))
    if found is None:
        return None
    table = pq.read_table(scene.odometry_path)
    columns = [table.column(c).to_numpy().astype(np.float64) for c in ("t", "x", "y", "yaw", "speed", "yaw_rate")]
    fps = round(1 / float(columns[0][1] - columns[0][0]))
    return town_of(found.group(1), int(found.group(2))), EgoTrack(*columns, fps=fps)


@dataclass
class StepFrames:
    """One step's generated frames and, for a town clip, the true view at the same native frames with how far
    the two differ (mean PSNR, dB); on request the abstract forecast the step was conditioned on."""

    generated: np.ndarray
    true: PathFrames | None = None
    psnr: float | None = None
    forecast: np.ndarray | None = None  # the top level's new frame, decoded by the abstract tokenizer [H, W, 3]


@dataclass
class Models:
    """Both tokenizers and predictors, checked as ``orbis2 rollout`` checks them, on their device."""

    args: argparse.Namespace  # the command's options: model paths, sampler and precision (a replay repeats them)
    cfg: PipelineConfig
    detail_tok: TokenizerFile
    abstract_tok: TokenizerFile
    abstract_pred: PredictorFile
    detail_pred: PredictorFile
    device: torch.device
    abstract_nfe: int  # the sampler (orbis2.inference.sampler_settings)
    detail_nfe: int
    guidance: float
    summary: str  # which profile and sampler, and why
    steering_offsets: list[int] | None  # an imported predictor's steering frames (orbis2.rollout.steering_offsets)


def load_models(args: argparse.Namespace) -> Models:
    """The models of ``orbis2 rollout``'s options, its profile (from the files, unless ``--profile``) and its
    sampler; the abstract predictor must be steered."""
    cfg, which = resolve_profile(args.params, args.profile, [
        args.detail_tokenizer, args.abstract_tokenizer, abstract_predictor_path(args.abstract_predictor),
        args.detail_predictor])
    detail_tok, abstract_tok, abstract_path, abstract_pred, detail_pred = load_checkpoints(
        args.detail_tokenizer, args.abstract_tokenizer, args.abstract_predictor, args.detail_predictor, args.device,
        cfg, args.params)
    if unconverted_steering(abstract_pred.meta, abstract_path):
        raise OrbisError(unconverted_steering(abstract_pred.meta, abstract_path))
    if abstract_pred.model.steering is None or "steering" not in abstract_pred.meta:
        raise OrbisError(f"{abstract_path}: not a steered predictor, so it cannot be driven; pass the action "
                         f"stage's predictor (--abstract-predictor) or train it (python stages/predictor.py action)")
    device = next(detail_pred.model.parameters()).device
    if device.type == "cuda":
        set_tf32(True)
    for predictor in (abstract_pred, detail_pred):
        cast_for_inference(predictor.model, device, args.precision)
    if args.compile:
        compile_models(abstract_pred, detail_pred, detail_tok)
    abstract_nfe, detail_nfe, guidance, sampler = sampler_settings(args.abstract_nfe, args.detail_nfe,
                                                                   args.steering_guidance, cfg, detail_pred,
                                                                   steered=True)
    offsets = steering_offsets(abstract_pred.meta["steering"], cfg.data.fps, abstract_path)
    return Models(args, cfg, detail_tok, abstract_tok, abstract_pred, detail_pred, device, abstract_nfe, detail_nfe,
                  guidance, f"{which}; {sampler}", offsets)


class Drive:
    """One drive from a scene's context: :meth:`step` advances 0.5 s, :meth:`save` writes it as a recording."""

    def __init__(self, models: Models, scene: Scene, seed: int):
        self.models, self.scene, self.seed = models, scene, seed
        data = models.cfg.data
        self.fps = data.fps
        self.context_end = first_context_end(data)
        self.frames = read_context(scene.video, models.cfg, self.context_end + 1)
        first = rollout_schedule(data, self.context_end, 1)[0]
        self.first = first
        self.context_frames = self.frames[list(first.detail_context)]
        self.speed = self.recorded("speed", self.context_end + 1)
        self.yaw_rate = self.recorded("yaw_rate", self.context_end + 1)
        m = models
        detail_ctx = m.detail_tok.normalize(encode_frames(m.detail_tok, self.frames[list(first.detail_context)]))
        abstract_ctx = m.abstract_tok.normalize(encode_frames(m.abstract_tok,
                                                              self.frames[list(first.abstract_context)]))
        generator = torch.Generator(device=m.device).manual_seed(seed)
        self.latents: list[torch.Tensor] = []
        self.stepper = cascaded_steps(m.abstract_pred.model, m.detail_pred.model, detail_ctx[None].to(m.device),
                                      abstract_ctx[None].to(m.device), generator, m.abstract_nfe, m.detail_nfe,
                                      abstract_hz=data.abstract_hz, detail_hz=data.detail_hz, steered=True,
                                      steering_guidance=m.guidance)
        with inference_autocast(m.device, m.args.precision):  # the set-up runs here, as in orbis2 rollout's autocast
            next(self.stepper)
        episode = town_episode(scene)
        self.truth = None
        if episode is not None:
            data, town = models.cfg.data, models.cfg.town
            camera = Camera(data.width, data.height, town.hfov_deg, town.mount_height_m)
            self.truth = PathRenderer(episode[0], camera, episode[1], self.context_end)

    def recorded(self, column: str, n: int, start: int = 0) -> np.ndarray:
        """The clip's recorded ``column`` at native frames ``start``..``n - 1`` (its last value past its end)."""
        t = np.arange(n) / self.fps
        return np.interp(t, self.scene.odometry["timestamp"], self.scene.odometry[column])[start:]

    @property
    def steps(self) -> int:
        return len(self.latents)

    def step(self, speed: float, yaw_rate: float, replay: bool = False, forecast: bool = False,
             true_view: bool = True) -> StepFrames:
        """One 0.5 s step steered by ``speed`` (m/s) and ``yaw_rate`` (rad/s, left positive), or by the clip's
        recorded odometry when ``replay``; returns its decoded frames [frames_per_step, H, W, 3], the true
        view (a town clip, unless ``true_view`` is off: the path is kept, nothing rendered) and, with
        ``forecast``, the abstract level's prediction decoded (:class:`StepFrames`)."""
        m = self.models
        step = rollout_schedule(m.cfg.data, self.context_end, self.steps + 1)[-1]
        end = step.detail_target[-1] + 1
        if replay:
            new_speed, new_yaw = self.recorded("speed", end, len(self.speed)), self.recorded("yaw_rate", end,
                                                                                             len(self.speed))
        else:
            new_speed = np.full(end - len(self.speed), float(speed))
            new_yaw = np.full(end - len(self.speed), float(yaw_rate))
        self.speed, self.yaw_rate = np.concatenate([self.speed, new_speed]), np.concatenate([self.yaw_rate, new_yaw])
        steering = steering_sequences([step], self.speed, self.yaw_rate, m.abstract_pred.meta["steering"]["scale"],
                                      m.steering_offsets)
        rendering = None
        if self.truth is not None:  # the true view renders in another thread while the model samples
            # Control k drives pose k to k + 1 (the convention of the bird's-eye path, integrate_odometry).
            k0 = self.truth.frame
            controls = self.speed[k0:end - 1], self.yaw_rate[k0:end - 1]
            if true_view:
                rendering = TRUTH_WORKER.submit(self.truth.step, *controls)
            else:
                self.truth.advance(*controls)
        with inference_autocast(m.device, m.args.precision):
            new, top = self.stepper.send(steering.to(m.device))
        self.latents.append(new)
        frames = StepFrames(decode_latents(m.detail_tok, new[0], m.device, m.args.precision))
        if forecast:
            frames.forecast = decode_latents(m.abstract_tok, top[0, -1:], m.device, m.args.precision)[0]
        if rendering is None:
            return frames
        true = rendering.result()
        keep = np.isin(true.frames, step.detail_target)
        true = PathFrames(*(getattr(true, f)[keep] for f in PathFrames.__dataclass_fields__))
        frames.true = true
        frames.psnr = float(np.mean([cv2.PSNR(g, t) for g, t in zip(frames.generated, true.rgb, strict=True)]))
        return frames

    def path(self) -> tuple[np.ndarray, np.ndarray]:
        """The commanded path so far in metres from the last context frame (x forward, y left)."""
        x, y, _ = integrate_odometry(self.speed[self.context_end:], self.yaw_rate[self.context_end:], self.fps)
        return x, y

    def trajectory_csv(self) -> str:
        """The commanded odometry from the clip's first frame, in the columns ``orbis2 rollout --trajectory``
        reads, every number written so it reads back exactly."""
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(["timestamp", "speed", "yaw_rate"])
        t = np.arange(len(self.speed)) / self.fps
        for row in zip(t, self.speed, self.yaw_rate, strict=True):
            writer.writerow([repr(float(v)) for v in row])
        return out.getvalue()

    def save(self, out: Path) -> tuple[Path, Path, Path]:
        """The drive so far as ``out`` (VP9 mp4), a GIF and a CSV with its stem: the frames ``orbis2 rollout``
        writes for this video, trajectory and seed (decoded as it decodes them), with the commanded path inset."""
        if not self.latents:
            raise OrbisError("nothing to record yet: drive at least one step")
        m = self.models
        details = torch.cat(self.latents, dim=1)[0]
        video = np.concatenate([self.context_frames, decode_latents(m.detail_tok, details, m.device,
                                                                     m.args.precision)])
        schedule = rollout_schedule(m.cfg.data, self.context_end, self.steps)
        indices = np.array(list(self.first.detail_context) + [i for s in schedule for i in s.detail_target])
        frames = compose(video, None, self.path(), np.clip(indices - self.context_end, 0, None))
        gif = write_outputs(out, frames, m.cfg.data.detail_hz)
        trajectory = out.with_suffix(".csv")
        with atomic_file(trajectory) as tmp:
            tmp.write_text(self.trajectory_csv())
        return out, gif, trajectory

    def replay_command(self, out: Path, trajectory: Path) -> list[str]:
        """The ``orbis2 rollout`` arguments that reproduce a recording's frames."""
        a = self.models.args
        command = ["orbis2", "rollout", "--video", str(self.scene.video), "--trajectory", str(trajectory),
                   "--seconds", repr(self.steps / self.models.cfg.data.abstract_hz), "--seed", str(self.seed),
                   "--out", str(out), "--params", str(a.params), "--abstract-nfe", str(self.models.abstract_nfe),
                   "--detail-nfe", str(self.models.detail_nfe), "--steering-guidance", repr(self.models.guidance),
                   "--precision", a.precision, "--profile", self.models.cfg.profile]
        for flag in ("detail_tokenizer", "abstract_tokenizer", "abstract_predictor", "detail_predictor", "device"):
            if getattr(a, flag) is not None:
                command += [f"--{flag.replace('_', '-')}", str(getattr(a, flag))]
        if a.compile:  # compiled kernels may round differently from eager ones
            command.append("--compile")
        return command
