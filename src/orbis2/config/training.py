"""The typed sections of the trained stages: optimisation (``train``), tokenizers, predictors, the instrument.

Which tokenizer and predictor sections params.yaml has follows registry.yaml
(``orbis2.config.params.section_types``). No field has a default: params.yaml is
the single source of every value.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import typing
from dataclasses import dataclass
from typing import Any

from orbis2.config.sections import positive
from orbis2.errors import ConfigError
from orbis2.models.sizes import STDIT_PRESETS, TOKENIZER_PRESETS, TokenizerConfig, tokenizer_config

# Fields that change only bookkeeping, never the trajectory: a resume may change them.
# Activation checkpointing recomputes the same activations: it changes memory and time, not the numbers;
# compilation changes only the order of floating-point operations (on GPU), not the method. The micro-batch
# (gradient accumulation) changes how a process splits its share of the same global batch: the order of the
# gradient's sums, as another number of processes does (orbis2.train.batch_split).
BOOKKEEPING_FIELDS = frozenset({"log_every", "eval_every", "checkpoint_every", "activation_checkpointing",
                                "checkpoint_policy", "compile", "micro_batch_size"})
CHECKPOINT_POLICIES = ("full", "selective")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings of one stage; ``batch_size`` is global (summed over ranks).

    ``micro_batch_size`` caps the samples one process runs forward and backward at once (what its memory
    holds): a process whose share of the global batch (``batch_size / processes``) is larger splits it into
    micro-batches of this size and accumulates their gradients before the optimiser step, so that
    ``batch_size = micro-batch x processes x accumulation steps`` (``orbis2.train.batch_split``); null: no
    cap, one micro-batch of the whole share.

    ``weight_decay`` applies to weight matrices and kernels; ``decay_biases_and_norms``
    extends it to biases and norm scales (tensors under 2 dims), as a plain
    ``AdamW(model.parameters())`` does.

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
    micro_batch_size: int | None
    lr: float
    weight_decay: float
    decay_biases_and_norms: bool
    betas: tuple[float, float]
    optimizer: str
    warmup_steps: int
    min_lr_ratio: float
    grad_clip: float | None
    ema_decay: float | None
    mixed_precision: str
    tf32: bool
    activation_checkpointing: int
    checkpoint_policy: str
    compile: bool
    log_every: int
    eval_every: int
    checkpoint_every: int
    seed: int
    num_workers: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "betas", tuple(self.betas))  # YAML gives a list
        rules = {  # field: (valid, what it must be)
            "lr": (self.lr > 0, "> 0"),
            "betas": (len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas), "two numbers in [0, 1)"),
            "optimizer": (self.optimizer in ("adamw", "adam"), "'adamw' or 'adam'"),
            "min_lr_ratio": (0 <= self.min_lr_ratio <= 1, "in [0, 1]"),
            "grad_clip": (self.grad_clip is None or self.grad_clip > 0, "> 0, or null for off"),
            "micro_batch_size": (self.micro_batch_size is None or self.micro_batch_size >= 1,
                                 ">= 1, or null for no cap"),
            "ema_decay": (self.ema_decay is None or 0 <= self.ema_decay < 1, "in [0, 1), or null for off"),
            "mixed_precision": (self.mixed_precision in ("bf16", "none"), "'bf16' or 'none'"),
            "checkpoint_policy": (self.checkpoint_policy in CHECKPOINT_POLICIES, "'full' or 'selective'"),
            "compile": (isinstance(self.compile, bool), "true or false"),
            "decay_biases_and_norms": (isinstance(self.decay_biases_and_norms, bool), "true or false"),
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


@dataclass(frozen=True)
class TokenizerSection:
    """What both tokenizer sections share: the size, a preset of ``TOKENIZER_PRESETS`` with ``model`` overriding
    its typed fields (``TokenizerConfig``, e.g. ``patch_size`` and the decoders' levels for another latent grid).
    Every tokenizer section of a profile has the same latent grid (:meth:`PipelineConfig.validate`)."""

    preset: str
    model: dict[str, bool | int | float | str | tuple[int, ...]]

    def sizes(self) -> TokenizerConfig:
        return tokenizer_config(self.preset, **self.model)


@dataclass(frozen=True)
class DetailTokenizerConfig(TokenizerSection):
    """The detail (VQ) tokenizer: preset sizes, loss weights and schedules (paper appendix, reference code)."""

    train: TrainConfig
    frames_per_clip: int
    interleave_shards: int | None  # train shards read side by side (orbis2.data.shards.interleave); None: 1
    l1_weight: float
    mse_weight: float  # 0 in the paper's objective (docs/differences.md, "Detail tokenizer objective")
    entropy_start: float
    entropy_end: float
    entropy_decay_steps: int
    disc_start: int
    gan_scale: float
    disc_lr_scale: float
    mae_checkpoint: str | None
    eval_images: int
    fid_images: int
    scale_images: int
    latent_norm: str  # or "global": the paper's single scale factor

    def validate(self, where: str) -> None:
        _tokenizer_common(self, where)
        if self.disc_start < 0:
            raise ConfigError(f"{where}.disc_start must be >= 0")
        positive(self, where, "fid_images")


@dataclass(frozen=True)
class AbstractTokenizerConfig(TokenizerSection):
    """The abstract tokenizer: encoder aligned to a frozen teacher (paper eq. 3) plus a weak decoder."""

    train: TrainConfig
    teacher: str
    teacher_layer: str  # inception only: which 768-channel map the encoder aligns to
    alignment: str
    rec_weight: float
    compress: bool
    frames_per_clip: int
    interleave_shards: int | None  # train shards read side by side (orbis2.data.shards.interleave); None: 1
    eval_images: int
    scale_images: int
    latent_norm: str  # or "global": the paper's single scale factor

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



def _tokenizer_common(cfg: Any, where: str) -> None:
    _model_size(TOKENIZER_PRESETS, cfg.preset, cfg.model, where)
    positive(cfg, where, "frames_per_clip", "eval_images", "scale_images")
    if cfg.interleave_shards is not None and cfg.interleave_shards < 1:
        raise ConfigError(f"{where}.interleave_shards = {cfg.interleave_shards} must be >= 1 or null")
    if cfg.latent_norm not in ("per_position", "global"):
        raise ConfigError(f"{where}.latent_norm = {cfg.latent_norm!r} must be 'per_position' or 'global'")



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
    model: dict[str, bool | int | float]
    init_from: str | None
    anchor_stride: int
    val_batches: int
    turn_repeat: int

    INIT_SOURCES: typing.ClassVar[tuple[str, ...]] = ()

    def validate(self, where: str) -> None:
        _model_size(STDIT_PRESETS, self.preset, self.model, where)
        if self.init_from is not None and self.init_from not in self.INIT_SOURCES:
            allowed = [*self.INIT_SOURCES, None]
            raise ConfigError(f"{where}.init_from = {self.init_from!r} must be one of {allowed}")
        positive(self, where, "anchor_stride", "val_batches", "turn_repeat")


@dataclass(frozen=True)
class TeacherForcingConfig(PredictorConfig):
    """Teacher forcing (paper eq. 1) with the reference code's context augmentation.

    Per sample, with ``context_noise_prob`` the clean context gets
    ``context_noise_std`` Gaussian noise, and with ``context_drop_prob`` it is
    replaced by the null context (the authors' code, "Predictor": 0.5 / 0.1 / 0.2).
    """

    context_noise_prob: float
    context_noise_std: float
    context_drop_prob: float

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

    teacher_nfe: int
    student_nfe: int

    INIT_SOURCES: typing.ClassVar[tuple[str, ...]] = ("detail",)

    def validate(self, where: str) -> None:
        super().validate(where)
        if self.init_from is None:
            raise ConfigError(f"{where}.init_from must name the teacher stage (detail)")
        positive(self, where, "teacher_nfe", "student_nfe")
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

    steering_dropout: float
    speed_scale: float
    yaw_rate_scale: float
    yaw_offset_prob: float
    yaw_offset_max: float

    INIT_SOURCES: typing.ClassVar[tuple[str, ...]] = ("abstract_tf", "abstract_df")

    def validate(self, where: str) -> None:
        super().validate(where)
        if not 0 <= self.steering_dropout < 1:
            raise ConfigError(f"{where}.steering_dropout must lie in [0, 1)")
        positive(self, where, "speed_scale", "yaw_rate_scale", "yaw_offset_max")
        if not 0 <= self.yaw_offset_prob <= 1:
            raise ConfigError(f"{where}.yaw_offset_prob must lie in [0, 1]")



@dataclass(frozen=True)
class InverseDynamicsConfig:
    """The learned inverse-dynamics instrument (``orbis2.eval.metrics.inverse_dynamics``): a CNN of base ``width``
    trained (``train``) on pairs of consecutive train frames (resized by ``scale``, at most ``max_train_clips``
    clips) to regress speed and yaw rate; scored on ``eval_pairs`` val pairs drawn with ``train.seed``.

    ``counterfactual_clips`` town clips of the train split (evenly spread; 0: none) are also driven again by the
    town with their recorded controls scaled by each (speed, yaw rate) pair of ``counterfactual_scales``, and
    their pairs join the real ones: the recorded drives stay on the road and turn only as the roads do, so an
    instrument trained on them alone under-reads the counterfactual commands the steering evaluation gives."""

    train: TrainConfig
    width: int
    scale: float
    max_train_clips: int | None
    eval_pairs: int
    counterfactual_clips: int
    counterfactual_scales: list[list[float]]

    def validate(self, where: str) -> None:
        positive(self, where, "width", "scale", "eval_pairs")
        if self.scale > 1:
            raise ConfigError(f"{where}.scale must be in (0, 1] (frames are only ever shrunk)")
        if self.counterfactual_clips < 0:
            raise ConfigError(f"{where}.counterfactual_clips must be >= 0 (0: the recorded drives only)")
        for pair in self.counterfactual_scales:
            if len(pair) != 2 or not all(math.isfinite(v) for v in pair) or pair[0] < 0:
                raise ConfigError(f"{where}.counterfactual_scales: {pair} is not a (speed >= 0, yaw rate) pair of "
                                  f"finite scales")


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



def _model_size(presets: dict[str, Any], preset: str, model: dict[str, Any], where: str) -> None:
    """``preset`` must name one of the model family's ``presets``; ``model`` overrides its typed fields."""
    if preset not in presets:
        raise ConfigError(f"{where}.preset = {preset!r} must be one of {list(presets)}")
    try:
        presets[preset].with_overrides(**model)
    except ValueError as err:
        raise ConfigError(f"{where}.model: {err}") from err
