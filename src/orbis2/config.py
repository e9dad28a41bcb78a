"""Typed, validated configuration read from ``params.yaml``.

Over 600 lines on purpose: one typed class per params.yaml section, so the whole
schema of the settings reads in one file.

``params.yaml`` is the single source of every hyper-parameter and seed. Each
stage has a section; inside a section, ``all`` holds the values shared by every
profile and ``smoke`` / ``default`` / ``gpu`` / ``paper`` hold what differs. The
top-level ``profile`` key picks one; the resolved section is ``all`` updated by
the profile's mapping (nested mappings are merged key by key), on top of the
section named by ``extends`` if any (shared bases are named ``_...``). Which
tokenizer and predictor sections exist, and their types, follows registry.yaml;
``preset`` (model size) defaults to the profile.

Resolution is strict: an unknown key, a value of the wrong type or an
impossible value stops with a :class:`ConfigError` naming the key, e.g.
``data.default.fps``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from orbis2.errors import OrbisError

PROFILES = ("smoke", "default", "gpu", "paper")
SPLITS = ("train", "val", "turns", "heldout", "probe")


class ConfigError(OrbisError):
    """A params.yaml value is missing, unknown, mistyped or impossible."""


# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class DataConfig:
    """Frame geometry and the two temporal rates of the hierarchy.

    ``fps`` is the native rate of every episode on disk; detail windows sample it
    every ``fps // detail_hz`` frames and abstract windows every ``fps // abstract_hz``.
    """

    width: int
    height: int
    fps: int
    source: str = "town"
    detail_hz: int = 10
    abstract_hz: int = 2
    detail_window: int = 10
    detail_context: int = 5
    abstract_window: int = 6
    abstract_context: int = 5

    def validate(self, where: str) -> None:
        _positive(self, where, "width", "height", "fps", "detail_hz", "abstract_hz")
        for rate in ("detail_hz", "abstract_hz"):
            if self.fps % getattr(self, rate):
                raise ConfigError(
                    f"{where}.fps = {self.fps} must be an integer multiple of "
                    f"{rate} = {getattr(self, rate)} (the hierarchy samples the native "
                    f"rate every fps/{rate} frames)"
                )
        if self.width % 2 or self.height % 2:
            raise ConfigError(f"{where}.width/height must be even (video codecs need it)")
        if self.source not in ("town", "import"):
            raise ConfigError(f"{where}.source = {self.source!r} must be 'town' or 'import'")
        for win, ctx in (("detail_window", "detail_context"), ("abstract_window", "abstract_context")):
            if not 0 < getattr(self, ctx) < getattr(self, win):
                raise ConfigError(f"{where}.{ctx} must lie in [1, {win} - 1]")

    @property
    def window_span_frames(self) -> int:
        """Native frames covered by one training sample (abstract context start to last prediction)."""
        before = (self.abstract_context - 1) * self.abstract_stride
        after = max((self.abstract_window - self.abstract_context) * self.abstract_stride,
                    (self.detail_window - self.detail_context) * self.detail_stride)
        return before + after + 1

    @property
    def detail_stride(self) -> int:
        return self.fps // self.detail_hz

    @property
    def abstract_stride(self) -> int:
        return self.fps // self.abstract_hz


@dataclass(frozen=True)
class TownConfig:
    """The procedural driving world: how many episodes per split and how long."""

    seed: int
    episodes: dict[str, int]
    episode_seconds: dict[str, float]
    hfov_deg: float = 90.0
    mount_height_m: float = 1.5
    turns_candidates: int = 32
    label_splits: list[str] = field(default_factory=lambda: ["probe"])
    label_stride: int = 5
    workers: int = 0
    preview_seconds: float = 6.0

    def validate(self, where: str) -> None:
        for name in ("episodes", "episode_seconds"):
            mapping = getattr(self, name)
            if set(mapping) != set(SPLITS):
                raise ConfigError(f"{where}.{name} must name exactly the splits {list(SPLITS)}, got {sorted(mapping)}")
            if any(v <= 0 for v in mapping.values()):
                raise ConfigError(f"{where}.{name} values must be positive")
        unknown = set(self.label_splits) - set(SPLITS)
        if unknown:
            raise ConfigError(f"{where}.label_splits names unknown splits {sorted(unknown)}")
        if not 10.0 <= self.hfov_deg <= 170.0:
            raise ConfigError(f"{where}.hfov_deg = {self.hfov_deg} must lie in [10, 170]")
        if self.turns_candidates < self.episodes["turns"]:
            raise ConfigError(f"{where}.turns_candidates must be >= episodes.turns")
        _positive(self, where, "label_stride", "mount_height_m", "preview_seconds")
        if self.workers < 0:
            raise ConfigError(f"{where}.workers must be >= 0 (0 = one per CPU core)")


@dataclass(frozen=True)
class ImportConfig:
    """User videos: a folder of OpenCV-readable files with optional odometry CSVs."""

    videos: str = "data/videos"
    skip_bad: bool = False
    fps_tolerance: float = 0.002

    def validate(self, where: str) -> None:
        if not 0 <= self.fps_tolerance < 0.1:
            raise ConfigError(f"{where}.fps_tolerance must lie in [0, 0.1)")


@dataclass(frozen=True)
class ShardsConfig:
    """WebDataset shards: clip length per split, JPEG quality, shard size."""

    clip_seconds: dict[str, float]
    max_shard_mb: float = 256.0
    jpeg_quality: int = 95

    def validate(self, where: str) -> None:
        if set(self.clip_seconds) != set(SPLITS):
            raise ConfigError(f"{where}.clip_seconds must name exactly the splits {list(SPLITS)}")
        if not 50 <= self.jpeg_quality <= 100:
            raise ConfigError(f"{where}.jpeg_quality must lie in [50, 100]")
        _positive(self, where, "max_shard_mb")


ASSET_NAMES = ("i3d_kinetics400", "inception_v3", "dinov2_vitb14")


# The assets stage's output as the DAG (Snakefile, dvc.yaml) declares it; a test keeps them equal.
ASSETS_DIR = "data/assets"


@dataclass(frozen=True)
class AssetsConfig:
    """Pretrained networks: where converted files go, and files the user provides by hand.

    ``dir`` must be the DAG's declared output (``ASSETS_DIR``): anywhere else, the
    stage would write where Snakemake and DVC do not look. To keep the files on
    another disk, make ``data/assets`` a symlink (outputs follow symlinks).
    """

    dir: str = ASSETS_DIR
    download: bool = True
    local: dict[str, str | None] = field(default_factory=dict)

    def validate(self, where: str) -> None:
        if Path(self.dir) != Path(ASSETS_DIR):
            raise ConfigError(f"{where}.dir = {self.dir!r} differs from the assets stage's output in the Snakefile and "
                              f"dvc.yaml ({ASSETS_DIR}); set it back to {ASSETS_DIR} and, to keep the files "
                              f"elsewhere, make {ASSETS_DIR} a symlink to that folder")
        unknown = set(self.local) - set(ASSET_NAMES)
        if unknown:
            raise ConfigError(f"{where}.local names unknown assets {sorted(unknown)}; known: {list(ASSET_NAMES)}")


@dataclass(frozen=True)
class DetailTokenizerConfig:
    """The detail (VQ) tokenizer: preset sizes, loss weights and schedules (paper appendix, reference code)."""

    preset: str
    train: TrainConfig
    frames_per_clip: int = 4
    l1_weight: float = 1.0
    entropy_start: float = 0.01
    entropy_end: float = 0.001
    entropy_decay_steps: int = 10000
    disc_start: int = 10000
    gan_scale: float = 0.1
    disc_lr_scale: float = 1.0
    mae_checkpoint: str | None = None
    eval_images: int = 64
    fid_images: int = 256
    scale_images: int = 256
    latent_norm: str = "per_position"  # or "global": the paper's single scale factor

    def validate(self, where: str) -> None:
        _tokenizer_common(self, where)
        if self.disc_start < 0:
            raise ConfigError(f"{where}.disc_start must be >= 0")
        _positive(self, where, "fid_images")


@dataclass(frozen=True)
class AbstractTokenizerConfig:
    """The abstract tokenizer: encoder aligned to a frozen teacher (paper eq. 3) plus a weak decoder."""

    preset: str
    train: TrainConfig
    teacher: str = "inception"
    teacher_layer: str = "mixed_7"  # inception only: which 768-channel map the encoder aligns to
    alignment: str = "l2"
    rec_weight: float = 0.1
    compress: bool = True
    frames_per_clip: int = 4
    eval_images: int = 64
    scale_images: int = 256
    latent_norm: str = "per_position"  # or "global": the paper's single scale factor

    def validate(self, where: str) -> None:
        _tokenizer_common(self, where)
        if self.teacher not in ("inception", "dinov2"):
            raise ConfigError(f"{where}.teacher = {self.teacher!r} must be 'inception' or 'dinov2'")
        if self.teacher_layer not in ("mixed_3", "mixed_4", "mixed_5", "mixed_6", "mixed_7"):
            raise ConfigError(f"{where}.teacher_layer = {self.teacher_layer!r} must be one of mixed_3 .. mixed_7")
        if self.alignment not in ("l2", "cosine"):
            raise ConfigError(f"{where}.alignment = {self.alignment!r} must be 'l2' or 'cosine'")
        if self.rec_weight < 0:
            raise ConfigError(f"{where}.rec_weight must be >= 0")


@dataclass(frozen=True)
class LatentsConfig:
    """The latent cache: how many frames are encoded per forward pass."""

    batch_size: int = 32

    def validate(self, where: str) -> None:
        _positive(self, where, "batch_size")


@dataclass(frozen=True)
class PredictorConfig:
    """A predictor training stage (paper Sec. 3.3-3.4): network size, optimisation, data and validation.

    ``model`` overrides fields of the ST-DiT preset (a typed ``STDiTConfig``, e.g. a
    narrower ``hidden_size`` for a CPU budget). ``init_from`` names the predictor
    stage whose weights start this one, or null for a fresh network: the
    training-strategy ablation (TF only, DF only, DF+TF; paper Table "df_tf") is
    this parameter, not another script. ``val_batches`` batches of the val split,
    with fixed noise, give the validation loss. EMA is ``train.ema_decay``. Train
    windows where the ego turns (mean |yaw rate| above the town statistics' turning
    threshold) enter each epoch ``turn_repeat`` times (above 1, a deviation from the
    paper's uniform sampling).
    """

    preset: str
    train: TrainConfig
    model: dict[str, bool | int | float] = field(default_factory=dict)
    init_from: str | None = None
    anchor_stride: int = 1
    val_batches: int = 4
    turn_repeat: int = 1

    INIT_SOURCES: typing.ClassVar[tuple[str, ...]] = ()

    def validate(self, where: str) -> None:
        from orbis2.models.stdit import STDIT_PRESETS

        _model_size(STDIT_PRESETS, self.preset, self.model, where)
        if self.init_from is not None and self.init_from not in self.INIT_SOURCES:
            allowed = [*self.INIT_SOURCES, None]
            raise ConfigError(f"{where}.init_from = {self.init_from!r} must be one of {allowed}")
        _positive(self, where, "anchor_stride", "val_batches", "turn_repeat")


@dataclass(frozen=True)
class TeacherForcingConfig(PredictorConfig):
    """Teacher forcing (paper eq. 1) with the reference code's context augmentation.

    Per sample, with ``context_noise_prob`` the clean context gets
    ``context_noise_std`` Gaussian noise, and with ``context_drop_prob`` it is
    replaced by the null context (the authors' code, "Predictor": 0.5 / 0.1 / 0.2).
    """

    context_noise_prob: float = 0.5
    context_noise_std: float = 0.1
    context_drop_prob: float = 0.2

    INIT_SOURCES: typing.ClassVar[tuple[str, ...]] = ("abstract_df",)

    def validate(self, where: str) -> None:
        super().validate(where)
        for name in ("context_noise_prob", "context_drop_prob"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"{where}.{name} must lie in [0, 1]")
        if self.context_noise_std < 0:
            raise ConfigError(f"{where}.context_noise_std must be >= 0")


@dataclass(frozen=True)
class DetailPredictorConfig(TeacherForcingConfig):
    """The detail predictor F_L: teacher forcing from scratch, conditioned on abstract latents."""

    INIT_SOURCES: typing.ClassVar[tuple[str, ...]] = ()


@dataclass(frozen=True)
class DistillConfig(PredictorConfig):
    """The few-step detail predictor, distilled from ``init_from`` (the teacher) by rectified-flow reflow.

    Each step the teacher samples the targets from fresh noise with
    ``teacher_nfe`` Euler steps (use the NFE the evaluation samples the teacher
    with); the student, initialised from the teacher, learns the straight path
    of each (noise, sample) pair and is sampled with ``student_nfe`` steps.
    """

    teacher_nfe: int = 30
    student_nfe: int = 4

    INIT_SOURCES: typing.ClassVar[tuple[str, ...]] = ("detail",)

    def validate(self, where: str) -> None:
        super().validate(where)
        if self.init_from is None:
            raise ConfigError(f"{where}.init_from must name the teacher stage (detail)")
        _positive(self, where, "teacher_nfe", "student_nfe")
        if self.student_nfe >= self.teacher_nfe:
            raise ConfigError(f"{where}.student_nfe = {self.student_nfe} must be below teacher_nfe = "
                              f"{self.teacher_nfe}: the point of distillation is fewer steps")


@dataclass(frozen=True)
class ActionConfig(TeacherForcingConfig):
    """The steering fine-tune of the abstract predictor (paper "Action-conditioning").

    Steering features are speed and yaw rate divided by ``speed_scale`` (m/s) and
    ``yaw_rate_scale`` (rad/s), so the embedder sees roughly unit-scale values;
    ``steering_dropout`` of the samples train the unconditional path. With
    ``yaw_offset_prob`` a steered sample gets a counterfactual yaw-rate offset up
    to ``yaw_offset_max`` rad/s and its target moves sideways as far as the data's
    turns move the grid (``orbis2.tasks.predictors.offset_yaw``; above 0, a
    deviation from the paper).
    """

    steering_dropout: float = 0.1
    speed_scale: float = 10.0
    yaw_rate_scale: float = 0.5
    yaw_offset_prob: float = 0.0
    yaw_offset_max: float = 0.5

    INIT_SOURCES: typing.ClassVar[tuple[str, ...]] = ("abstract_tf", "abstract_df")

    def validate(self, where: str) -> None:
        super().validate(where)
        if not 0 <= self.steering_dropout < 1:
            raise ConfigError(f"{where}.steering_dropout must lie in [0, 1)")
        _positive(self, where, "speed_scale", "yaw_rate_scale", "yaw_offset_max")
        if not 0 <= self.yaw_offset_prob <= 1:
            raise ConfigError(f"{where}.yaw_offset_prob must lie in [0, 1]")


@dataclass(frozen=True)
class ProbeSettings:
    """Linear probes (paper appendix "Linear probing details"): AdamW 1e-3 / 1e-4 on a 1x1 conv head.

    Training lengths are epochs over the probe's train frames (segmentation, depth).
    ``block_main`` is the k-th block from the end probed for the main models (4th in
    the paper), ``block_ablation`` the one for ablation models (2nd); both are clamped
    to the network's depth. ``test_fraction`` of the probe episodes are held out for
    the metrics. ``standardize`` fixes per-channel feature statistics from the train
    frames before the head (still a linear probe; see ``orbis2.eval.probe``).

    Default data: the town's labelled ``probe`` split for both tasks. The paper's:
    ``cityscapes`` (root of leftImg8bit/ and gtFine/; train -> val) for segmentation
    and ``kitti`` (raw-data root) with the Eigen split files ``kitti_train_split`` /
    ``kitti_test_split`` (and ``kitti_depth`` if the annotated depth is a separate
    tree) for depth; ``max_frames`` caps each side (evenly spread). See
    ``orbis2.data.probes`` for the layouts.
    """

    seg_epochs: int = 100
    depth_epochs: int = 10
    batch_size: int = 8
    lr: float = 1e-3
    weight_decay: float = 1e-4
    block_main: int = 4
    block_ablation: int = 2
    test_fraction: float = 0.25
    standardize: bool = True
    seed: int = 0
    cityscapes: str | None = None
    kitti: str | None = None
    kitti_depth: str | None = None
    kitti_train_split: str | None = None
    kitti_test_split: str | None = None
    max_frames: int | None = None

    def validate(self, where: str) -> None:
        if self.kitti is not None and (self.kitti_train_split is None or self.kitti_test_split is None):
            raise ConfigError(f"{where}.kitti needs kitti_train_split and kitti_test_split (Eigen split files)")
        _positive(self, where, "seg_epochs", "depth_epochs", "batch_size", "lr", "block_main", "block_ablation")
        if not 0 < self.test_fraction < 1:
            raise ConfigError(f"{where}.test_fraction must lie in (0, 1)")


@dataclass(frozen=True)
class InverseDynamicsConfig:
    """The learned inverse-dynamics instrument (``orbis2.eval.inverse_dynamics``): a CNN of base ``width``
    trained for ``steps`` AdamW steps on pairs of consecutive train frames (resized by ``scale``, at most
    ``max_train_clips`` clips) to regress speed and yaw rate; scored on ``eval_pairs`` val pairs."""

    steps: int = 600
    batch_size: int = 32
    lr: float = 2e-3
    weight_decay: float = 1e-4
    width: int = 16
    scale: float = 0.5
    max_train_clips: int | None = None
    eval_pairs: int = 512
    seed: int = 0

    def validate(self, where: str) -> None:
        _positive(self, where, "steps", "batch_size", "lr", "width", "scale", "eval_pairs")
        if self.scale > 1:
            raise ConfigError(f"{where}.scale must be in (0, 1] (frames are only ever shrunk)")


@dataclass(frozen=True)
class ConditioningSettings:
    """The ``eval_conditioning`` stage (``orbis2.eval.conditioning``): does each predictor use its inputs?

    Val windows every ``anchor_stride`` native frames (at most ``max_windows``, evenly
    spread), ``draws`` noise draws per window shared by every variant. An input is
    "used" when the clip-bootstrap lower bound of the error increase without it
    exceeds ``threshold`` (a fraction of the error with it). The ego-motion probe
    fits ridge regression on standardised features of train frames every
    ``probe_stride`` frames, with the penalty of ``ridge`` that predicts best across
    ``probe_folds`` folds of the train clips (val never chooses it). The steered predictor's latents "answer" a
    steering input when the lower bound of their response (relative to real latents'
    response to the same motion difference) clears ``response_material``.
    """

    draws: int = 3
    anchor_stride: int = 5
    max_windows: int = 512
    batch_size: int = 32
    threshold: float = 0.03
    bootstrap_reps: int = 1000
    probe_stride: int = 2
    ridge: list[float] = field(default_factory=lambda: [1.0, 10.0, 100.0, 1000.0, 10000.0, 100000.0])
    probe_folds: int = 4
    strips: int = 0  # 0: the probe reads the whole latent grid; > 0: channel means over vertical strips
    response_material: float = 0.25

    def validate(self, where: str) -> None:
        _positive(self, where, "draws", "anchor_stride", "max_windows", "batch_size", "bootstrap_reps",
                  "probe_stride", "probe_folds", "response_material")
        if not self.ridge or min(self.ridge) <= 0:
            raise ConfigError(f"{where}.ridge must be a non-empty list of positive penalties")
        if self.probe_folds < 2:
            raise ConfigError(f"{where}.probe_folds must be >= 2 (the penalty is chosen across train folds)")
        if self.strips < 0:
            raise ConfigError(f"{where}.strips must be >= 0 (0: the whole latent grid)")
        if self.threshold < 0:
            raise ConfigError(f"{where}.threshold must be >= 0 (a fraction of the reference error)")


@dataclass(frozen=True)
class EvaluationConfig:
    """The ``eval_*`` stages (paper Sec. 4.3 and 5).

    FVD over ``seconds`` of rollout on each split in ``fvd_splits``; chunked FVD
    over ``chunk_seconds`` windows of ``long_seconds`` rollouts on ``long_split``
    (whose first ``seconds`` also give that split's FVD). ``starts_per_clip``
    context positions per evaluation clip, evenly spread (FVD needs many videos: its
    covariance has rank videos - 1). ``top_nfe`` and
    ``bottom_nfe`` are the Euler steps of the top (abstract, 2 Hz) and bottom
    (detail, 10 Hz; also flat) predictors. Steering: ``steering_seconds`` rollouts
    of ``steering_split`` clips under each mode of ``steering_modes``.
    """

    seed: int
    probe: ProbeSettings
    seconds: float = 6.0
    long_seconds: float = 16.0
    chunk_seconds: float = 4.0
    fvd_splits: list[str] = field(default_factory=lambda: ["val", "heldout", "turns"])
    long_split: str = "turns"
    starts_per_clip: int = 1
    top_nfe: int = 15
    bottom_nfe: int = 30
    batch_size: int = 8
    steering_split: str = "turns"
    steering_seconds: float = 6.0
    steering_starts_per_clip: int = 1
    # Material steering responses: recovered turn under yaw rate x1.5 minus x0.5 (degrees), and path length
    # under speed x1.5 over x0.5 (commanded: 3).
    steering_turn_material_deg: float = 2.0
    steering_path_ratio_material: float = 1.1
    steering_modes: dict[str, list[float]] = field(default_factory=lambda: {
        "original": [1.0, 1.0], "speed_x0.5": [0.5, 1.0], "speed_x1.5": [1.5, 1.0],
        "yaw_rate_x0.5": [1.0, 0.5], "yaw_rate_x1.5": [1.0, 1.5]})
    inverse_dynamics: str = "opencv"
    # OpenCV odometry as a second column on the generated videos too (always on the real ones: the check of
    # both instruments); it is a third of eval_steering's time on a CPU.
    opencv_rollouts: bool = True
    speed_seconds: float = 2.0
    speed_repeats: int = 2
    precision: str = "bf16"
    compile: bool = False
    kv_cache: bool = True
    # Classifier-free guidance on the steered top predictor's steering in rollouts (1 = none, the paper's
    # sampler): the steered velocity extrapolated away from the unsteered one (steering dropout's).
    steering_guidance: float = 1.0
    conditioning: ConditioningSettings = field(default_factory=ConditioningSettings)
    # FVD intervals: clip-bootstrap resamples, random clip half-splits for the real-vs-real floor, and the
    # smallest FVD(-slope) difference a claim counts as material (FVD units).
    fvd_bootstrap_reps: int = 200
    floor_splits: int = 50
    fvd_material: float = 10.0
    # Seeds (noise draws, rollout noise) over which the claim-bearing evaluation is repeated.
    seeds: list[int] = field(default_factory=lambda: [0])

    def validate(self, where: str) -> None:
        self.conditioning.validate(f"{where}.conditioning")
        _positive(self, where, "fvd_bootstrap_reps", "floor_splits")
        if self.fvd_material < 0:
            raise ConfigError(f"{where}.fvd_material must be >= 0 (FVD units)")
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise ConfigError(f"{where}.seeds must be a non-empty list of distinct integers")
        _positive(self, where, "seconds", "long_seconds", "chunk_seconds", "starts_per_clip",
                  "steering_starts_per_clip", "top_nfe", "bottom_nfe", "batch_size", "steering_seconds",
                  "speed_seconds", "speed_repeats")
        self.probe.validate(f"{where}.probe")
        if self.precision not in ("bf16", "fp32"):
            raise ConfigError(f"{where}.precision = {self.precision!r} must be 'bf16' (autocast on CUDA) or 'fp32'")
        if self.long_seconds < 2 * self.chunk_seconds:
            raise ConfigError(f"{where}.long_seconds must hold at least two chunks of chunk_seconds for FVD-slope")
        if self.steering_guidance < 0:
            raise ConfigError(f"{where}.steering_guidance = {self.steering_guidance} must be >= 0 (1: no guidance)")
        for mode, scales in self.steering_modes.items():
            if len(scales) != 2 or min(scales) <= 0:
                raise ConfigError(f"{where}.steering_modes.{mode} must be [speed scale, yaw-rate scale], both > 0")


def _tokenizer_common(cfg: Any, where: str) -> None:
    from orbis2.models.tokenizer import TOKENIZER_PRESETS

    _model_size(TOKENIZER_PRESETS, cfg.preset, {}, where)
    _positive(cfg, where, "frames_per_clip", "eval_images", "scale_images")
    if cfg.latent_norm not in ("per_position", "global"):
        raise ConfigError(f"{where}.latent_norm = {cfg.latent_norm!r} must be 'per_position' or 'global'")


@dataclass(frozen=True)
class PipelineConfig:
    """Every stage's resolved section for one profile."""

    profile: str
    data: DataConfig
    town: TownConfig
    import_: ImportConfig
    shards: ShardsConfig
    assets: AssetsConfig
    latents: LatentsConfig
    evaluation: EvaluationConfig
    inverse_dynamics: InverseDynamicsConfig
    # The tokenizer and predictor sections, one per registry.yaml entry (also reachable as attributes).
    stages: dict[str, Any] = field(default_factory=dict)

    def section(self, name: str) -> Any:
        if name in self.stages:
            return self.stages[name]
        return getattr(self, SECTION_ATTRS.get(name, name))

    def with_section(self, name: str, value: Any) -> PipelineConfig:
        """A copy with one section replaced (``dataclasses.replace`` for registry sections too)."""
        if name in self.stages:
            return dataclasses.replace(self, stages={**self.stages, name: value})
        return dataclasses.replace(self, **{SECTION_ATTRS.get(name, name): value})

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name == "stages":
            raise AttributeError(name)
        try:
            return self.stages[name]
        except KeyError:
            raise AttributeError(f"PipelineConfig has no section {name!r}") from None

    def validate(self) -> None:
        d = self.data
        abstract_ahead = (d.abstract_window - d.abstract_context) * d.abstract_stride
        if abstract_ahead != (d.detail_window - d.detail_context) * d.detail_stride:
            raise ConfigError(
                f"data.{self.profile}: the abstract prediction ({d.abstract_window - d.abstract_context} frames at "
                f"{d.abstract_hz} Hz) must end on the last detail prediction ({d.detail_window - d.detail_context} "
                f"frames at {d.detail_hz} Hz): the detail predictor is conditioned on that abstract subgoal"
            )
        min_clip = self.data.window_span_frames / self.data.fps
        for split, seconds in self.shards.clip_seconds.items():
            if seconds < min_clip:
                raise ConfigError(
                    f"shards.{self.profile}.clip_seconds.{split} = {seconds} is shorter than one "
                    f"training window ({min_clip:.2f} s)"
                )
            if seconds > self.town.episode_seconds[split]:
                raise ConfigError(
                    f"shards.{self.profile}.clip_seconds.{split} = {seconds} exceeds "
                    f"town.episode_seconds.{split} = {self.town.episode_seconds[split]}"
                )


# Fields that change only bookkeeping, never the trajectory: a resume may change them.
# Activation checkpointing recomputes the same activations: it changes memory and time, not the numbers;
# compilation changes only the order of floating-point operations (on GPU), not the method.
BOOKKEEPING_FIELDS = frozenset({"log_every", "eval_every", "checkpoint_every", "activation_checkpointing",
                                "checkpoint_policy", "compile"})
CHECKPOINT_POLICIES = ("full", "selective")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings of one stage; ``batch_size`` is global (summed over ranks).

    GPU only: ``mixed_precision`` bf16 autocast, ``tf32`` for the remaining fp32
    matmuls, ``activation_checkpointing`` = how many of the model's first blocks
    recompute their activations in the backward pass (0 off; >= depth all), with
    ``checkpoint_policy`` ``full`` (keep only each block's input) or ``selective``
    (keep the matmul and attention outputs, recompute the cheap elementwise and
    norm ops). ``compile``: ``torch.compile`` the network for training (off by
    default: on the CPU the compile time exceeds a short run's gain).
    """

    steps: int
    batch_size: int
    lr: float
    weight_decay: float = 0.0
    betas: tuple[float, float] = (0.9, 0.999)
    optimizer: str = "adamw"
    warmup_steps: int = 0
    min_lr_ratio: float = 0.1
    grad_clip: float | None = None
    ema_decay: float | None = None
    mixed_precision: str = "bf16"
    tf32: bool = True
    activation_checkpointing: int = 0
    checkpoint_policy: str = "full"
    compile: bool = False
    log_every: int = 10
    eval_every: int = 0
    checkpoint_every: int = 500
    seed: int = 0
    num_workers: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "betas", tuple(self.betas))  # YAML gives a list
        rules = {  # field: (valid, what it must be)
            "lr": (self.lr > 0, "> 0"),
            "betas": (len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas), "two numbers in [0, 1)"),
            "optimizer": (self.optimizer in ("adamw", "adam"), "'adamw' or 'adam'"),
            "min_lr_ratio": (0 <= self.min_lr_ratio <= 1, "in [0, 1]"),
            "grad_clip": (self.grad_clip is None or self.grad_clip > 0, "> 0, or null for off"),
            "ema_decay": (self.ema_decay is None or 0 <= self.ema_decay < 1, "in [0, 1), or null for off"),
            "mixed_precision": (self.mixed_precision in ("bf16", "none"), "'bf16' or 'none'"),
            "checkpoint_policy": (self.checkpoint_policy in CHECKPOINT_POLICIES, "'full' or 'selective'"),
            "compile": (isinstance(self.compile, bool), "true or false"),
            **{name: (getattr(self, name) >= 1, ">= 1") for name in ("steps", "batch_size", "log_every",
                                                                     "checkpoint_every")},
            **{name: (getattr(self, name) >= 0, ">= 0") for name in ("weight_decay", "warmup_steps", "eval_every",
                                                                     "seed", "num_workers",
                                                                     "activation_checkpointing")},
        }
        for name, (valid, rule) in rules.items():
            if not valid:
                raise ConfigError(f"{name} = {getattr(self, name)!r} must be {rule}")

    def trajectory_fields(self) -> dict[str, Any]:
        """The fields a resumed run must share with the run that wrote the checkpoint."""
        return {k: v for k, v in dataclasses.asdict(self).items() if k not in BOOKKEEPING_FIELDS}

    def fingerprint(self) -> str:
        blob = json.dumps(self.trajectory_fields(), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


# Section names in params.yaml whose Python attribute differs (``import`` is a keyword).
SECTION_ATTRS = {"import": "import_"}
FIXED_SECTIONS: dict[str, type] = {
    "data": DataConfig,
    "town": TownConfig,
    "import": ImportConfig,
    "shards": ShardsConfig,
    "assets": AssetsConfig,
    "latents": LatentsConfig,
    "evaluation": EvaluationConfig,
    "inverse_dynamics": InverseDynamicsConfig,
}


def predictor_config_type(spec: Any) -> type:
    """The typed section of a registry predictor: steering, distillation, diffusion forcing, conditioned,
    or teacher forcing."""
    if spec.objective == "reflow":
        return DistillConfig
    if spec.steering:
        return ActionConfig
    if spec.objective == "diffusion_forcing":
        return PredictorConfig
    return DetailPredictorConfig if spec.condition else TeacherForcingConfig


def section_types() -> dict[str, type]:
    """Every params.yaml stage section and its type: the fixed ones plus one per registry.yaml tokenizer/predictor."""
    from orbis2.registry import registry

    reg = registry()
    kinds = {"detail": DetailTokenizerConfig, "abstract": AbstractTokenizerConfig}
    stages = {f"tokenizer_{name}": kinds[kind] for name, kind in reg.tokenizers.items()}
    stages |= {name: predictor_config_type(spec) for name, spec in reg.predictors.items()}
    return {**FIXED_SECTIONS, **stages}


# --------------------------------------------------------------------------- loading


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, except that a key given twice in one mapping is an error (not "last one wins")."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, Any] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue  # "<<: *anchor" entries may be overridden, that is their purpose
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    "while reading a mapping", node.start_mark,
                    f"key {key!r} is given twice (first {seen[key]}); keep one", key_node.start_mark)
            seen[key] = f"line {key_node.start_mark.line + 1}"
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str) -> Any:
    """Parse YAML safely, rejecting duplicate keys; how the project reads params.yaml everywhere."""
    return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass


def load_params(path: str | Path = "params.yaml") -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: not found; run from the project root or pass --params")
    try:
        raw = load_yaml(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}") from err
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: the top level must be a mapping")
    return raw


def resolve_section(raw: dict[str, Any], name: str, profile: str, _seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """``<name>.all`` updated by ``<name>.<profile>``, on top of the section it ``extends`` (resolved the same way).

    A plain mapping, validated later; nested mappings are merged key by key.
    """
    if name not in raw:
        where = f"{_seen[-1]}.extends" if _seen else "params.yaml"
        raise ConfigError(f"{where}: no section '{name}' in params.yaml")
    if name in _seen:
        raise ConfigError(f"params.yaml: sections extend each other in a loop: {' -> '.join([*_seen, name])}")
    section = raw[name]
    if not isinstance(section, dict):
        raise ConfigError(f"{name} must be a mapping with keys 'all' and the profiles {list(PROFILES)}")
    unknown = set(section) - {"all", "extends", *PROFILES}
    if unknown:
        raise ConfigError(f"{name}: unknown key(s) {sorted(unknown)}; allowed: 'all', 'extends', {list(PROFILES)}")
    merged: dict[str, Any] = {}
    if section.get("extends") is not None:
        merged = resolve_section(raw, section["extends"], profile, (*_seen, name))
    for part in ("all", profile):
        value = section.get(part) or {}
        if not isinstance(value, dict):
            raise ConfigError(f"{name}.{part} must be a mapping")
        merged = _deep_merge(merged, value)
    return merged


def section_chain(raw: dict[str, Any], name: str) -> list[str]:
    """``name`` and the sections it extends, nearest first (what a stage's params depend on)."""
    chain = [name]
    while isinstance(raw.get(chain[-1]), dict) and raw[chain[-1]].get("extends") and len(chain) <= len(raw):
        chain.append(raw[chain[-1]]["extends"])
    return chain


def load_config(path: str | Path = "params.yaml", profile: str | None = None) -> PipelineConfig:
    """Read params.yaml and return the validated config of ``profile`` (default: its ``profile`` key)."""
    return parse_config(load_params(path), profile)


def parse_config(raw: dict[str, Any], profile: str | None = None) -> PipelineConfig:
    """The validated config of ``profile`` (default: ``raw["profile"]``) from params.yaml's mapping."""
    profile = profile or raw.get("profile")
    if profile not in PROFILES:
        raise ConfigError(f"profile = {profile!r} must be one of {list(PROFILES)}")
    types_ = section_types()
    unknown = {key for key in raw if not key.startswith("_")} - {"profile", "train_launcher", *types_}
    if unknown:
        raise ConfigError(f"params.yaml: unknown top-level key(s) {sorted(unknown)}; a stage section needs a "
                          f"registry.yaml entry, a shared base a name starting with '_'")
    sections: dict[str, Any] = {"stages": {}}
    for name, cls in types_.items():
        values = resolve_section(raw, name, profile)
        if "preset" in {f.name for f in dataclasses.fields(cls)}:
            values.setdefault("preset", profile)  # model size follows the profile unless the section says otherwise
        obj = build(cls, values, f"{name}.{profile}")
        obj.validate(f"{name}.{profile}")
        if name in FIXED_SECTIONS:
            sections[SECTION_ATTRS.get(name, name)] = obj
        else:
            sections["stages"][name] = obj
    cfg = PipelineConfig(profile=profile, **sections)
    cfg.validate()
    return cfg


def build(cls: type, values: dict[str, Any], where: str) -> Any:
    """Instantiate dataclass ``cls`` from ``values`` checking keys and types."""
    if not isinstance(values, dict):
        raise ConfigError(f"{where} must be a mapping")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(values) - set(fields)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(fields)}")
    kwargs = {}
    for name, f in fields.items():
        if name not in values:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{where}.{name} is required")
            continue
        kwargs[name] = _check(hints[name], values[name], f"{where}.{name}")
    try:
        return cls(**kwargs)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from err


def as_dict(obj: Any) -> dict[str, Any]:
    return dataclasses.asdict(obj)


def flatten(mapping: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (for MLflow params)."""
    out: dict[str, Any] = {}
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = value
    return out


# --------------------------------------------------------------------------- helpers


def _check(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _check(arg, value, where)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError(errors[0] if errors else f"{where} must not be null")
    if origin is list:
        if not isinstance(value, list):
            raise ConfigError(f"{where} must be a list, got {type(value).__name__}")
        return [_check(args[0], v, f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is tuple:
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise ConfigError(f"{where} must be a list of {len(args)} values, got {value!r}")
        return tuple(_check(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where} must be a mapping, got {type(value).__name__}")
        return {_check(args[0], k, where): _check(args[1], v, f"{where}.{k}") for k, v in value.items()}
    if dataclasses.is_dataclass(tp):
        return build(tp, value, where)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where} must be a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    raise TypeError(f"unsupported config type {tp} at {where}")


def _deep_merge(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _model_size(presets: dict[str, Any], preset: str, model: dict[str, Any], where: str) -> None:
    """``preset`` must name one of the model family's ``presets``; ``model`` overrides its typed fields."""
    if preset not in presets:
        raise ConfigError(f"{where}.preset = {preset!r} must be one of {list(presets)}")
    try:
        presets[preset].with_overrides(**model)
    except ValueError as err:
        raise ConfigError(f"{where}.model: {err}") from err


def _positive(obj: Any, where: str, *names: str) -> None:
    for name in names:
        if getattr(obj, name) <= 0:
            raise ConfigError(f"{where}.{name} = {getattr(obj, name)} must be positive")
