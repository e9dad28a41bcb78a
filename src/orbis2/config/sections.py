"""The typed sections of params.yaml that every profile has once: data, world, shards, assets, evaluation.

One frozen dataclass per section, with ``validate`` for what types cannot say.
No field has a default: params.yaml is the single source of every value
(``orbis2.config.params`` reads and checks it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from orbis2.errors import ConfigError

SPLITS = ("train", "val", "turns", "heldout", "probe")


@dataclass(frozen=True)
class DataConfig:
    """Frame geometry and the two temporal rates of the hierarchy.

    ``fps`` is the native rate of every episode on disk; detail windows sample it
    every ``fps // detail_hz`` frames and abstract windows every ``fps // abstract_hz``.
    """

    width: int
    height: int
    fps: int
    source: str
    detail_hz: int
    abstract_hz: int
    detail_window: int
    detail_context: int
    abstract_window: int
    abstract_context: int

    def validate(self, where: str) -> None:
        positive(self, where, "width", "height", "fps", "detail_hz", "abstract_hz")
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
    hfov_deg: float
    mount_height_m: float
    turns_candidates: int
    label_splits: list[str]
    label_stride: int
    workers: int
    preview_seconds: float

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
        positive(self, where, "label_stride", "mount_height_m", "preview_seconds")
        if self.workers < 0:
            raise ConfigError(f"{where}.workers must be >= 0 (0 = one per CPU core)")


@dataclass(frozen=True)
class ImportConfig:
    """User videos: a folder of OpenCV-readable files with optional odometry CSVs."""

    videos: str
    skip_bad: bool
    fps_tolerance: float

    def validate(self, where: str) -> None:
        if not 0 <= self.fps_tolerance < 0.1:
            raise ConfigError(f"{where}.fps_tolerance must lie in [0, 0.1)")


@dataclass(frozen=True)
class ShardsConfig:
    """WebDataset shards: clip length per split, JPEG quality, shard size."""

    clip_seconds: dict[str, float]
    max_shard_mb: float
    jpeg_quality: int

    def validate(self, where: str) -> None:
        if set(self.clip_seconds) != set(SPLITS):
            raise ConfigError(f"{where}.clip_seconds must name exactly the splits {list(SPLITS)}")
        if not 50 <= self.jpeg_quality <= 100:
            raise ConfigError(f"{where}.jpeg_quality must lie in [50, 100]")
        positive(self, where, "max_shard_mb")


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

    dir: str
    download: bool
    local: dict[str, str | None]

    def validate(self, where: str) -> None:
        if Path(self.dir) != Path(ASSETS_DIR):
            raise ConfigError(f"{where}.dir = {self.dir!r} differs from the assets stage's output in the Snakefile and "
                              f"dvc.yaml ({ASSETS_DIR}); set it back to {ASSETS_DIR} and, to keep the files "
                              f"elsewhere, make {ASSETS_DIR} a symlink to that folder")
        unknown = set(self.local) - set(ASSET_NAMES)
        if unknown:
            raise ConfigError(f"{where}.local names unknown assets {sorted(unknown)}; known: {list(ASSET_NAMES)}")



@dataclass(frozen=True)
class LatentsConfig:
    """The latent cache: how many frames are encoded per forward pass."""

    batch_size: int

    def validate(self, where: str) -> None:
        positive(self, where, "batch_size")



@dataclass(frozen=True)
class ProbeSettings:
    """Linear probes (paper appendix "Linear probing details"): AdamW 1e-3 / 1e-4 on a 1x1 conv head.

    Training lengths are epochs over the probe's train frames (segmentation, depth).
    ``block_main`` is the k-th block from the end probed for the main models (4th in
    the paper), ``block_ablation`` the one for ablation models (2nd); both are clamped
    to the network's depth. ``test_fraction`` of the probe episodes are held out for
    the metrics. ``standardize`` fixes per-channel feature statistics from the train
    frames before the head (still a linear probe; see ``orbis2.eval.metrics.probe_heads``).

    Default data: the town's labelled ``probe`` split for both tasks. The paper's:
    ``cityscapes`` (root of leftImg8bit/ and gtFine/; train -> val) for segmentation
    and ``kitti`` (raw-data root) with the Eigen split files ``kitti_train_split`` /
    ``kitti_test_split`` (and ``kitti_depth`` if the annotated depth is a separate
    tree) for depth; ``max_frames`` caps each side (evenly spread). See
    ``orbis2.data.probes`` for the layouts.
    """

    seg_epochs: int
    depth_epochs: int
    batch_size: int
    lr: float
    weight_decay: float
    block_main: int
    block_ablation: int
    test_fraction: float
    standardize: bool
    seed: int
    cityscapes: str | None
    kitti: str | None
    kitti_depth: str | None
    kitti_train_split: str | None
    kitti_test_split: str | None
    max_frames: int | None

    def validate(self, where: str) -> None:
        if self.kitti is not None and (self.kitti_train_split is None or self.kitti_test_split is None):
            raise ConfigError(f"{where}.kitti needs kitti_train_split and kitti_test_split (Eigen split files)")
        positive(self, where, "seg_epochs", "depth_epochs", "batch_size", "lr", "block_main", "block_ablation")
        if not 0 < self.test_fraction < 1:
            raise ConfigError(f"{where}.test_fraction must lie in (0, 1)")


@dataclass(frozen=True)
class ConditioningSettings:
    """The ``eval_conditioning`` stage (``orbis2.eval.protocols.conditioning``): does each predictor use its inputs?

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

    draws: int
    anchor_stride: int
    max_windows: int
    batch_size: int
    threshold: float
    bootstrap_reps: int
    probe_stride: int
    ridge: list[float]
    probe_folds: int
    strips: int  # 0: the probe reads the whole latent grid; > 0: channel means over vertical strips
    response_material: float

    def validate(self, where: str) -> None:
        positive(self, where, "draws", "anchor_stride", "max_windows", "batch_size", "bootstrap_reps",
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
    seconds: float
    long_seconds: float
    chunk_seconds: float
    fvd_splits: list[str]
    long_split: str
    starts_per_clip: int
    top_nfe: int
    bottom_nfe: int
    batch_size: int
    steering_split: str
    steering_seconds: float
    steering_starts_per_clip: int
    # Material steering responses: recovered turn under yaw rate x1.5 minus x0.5 (degrees), and path length
    # under speed x1.5 over x0.5 (commanded: 3).
    steering_turn_material_deg: float
    steering_path_ratio_material: float
    steering_modes: dict[str, list[float]]  # mode: [speed scale, yaw-rate scale]
    inverse_dynamics: str
    # OpenCV odometry as a second column on the generated videos too (always on the real ones: the check of
    # both instruments); it is a third of eval_steering's time on a CPU.
    opencv_rollouts: bool
    speed_seconds: float
    speed_repeats: int
    precision: str
    compile: bool
    kv_cache: bool
    # Classifier-free guidance on the steered top predictor's steering in rollouts (1 = none, the paper's
    # sampler): the steered velocity extrapolated away from the unsteered one (steering dropout's).
    steering_guidance: float
    conditioning: ConditioningSettings
    # FVD intervals: clip-bootstrap resamples, random clip half-splits for the real-vs-real floor, and the
    # smallest FVD(-slope) difference a claim counts as material (FVD units).
    fvd_bootstrap_reps: int
    floor_splits: int
    fvd_material: float
    # Seeds (noise draws, rollout noise) over which the claim-bearing evaluation is repeated.
    seeds: list[int]
    # Scoring against the town's true counterfactuals (the truth stage): the horizons (s after the last context
    # frame) of the per-frame errors, and the smallest relative margin by which a rollout must be closer to the
    # truth under its own command than to the truths under the others for the claim (0.1 = 10 %).
    truth_horizons_s: list[float]
    truth_margin: float

    def validate(self, where: str) -> None:
        self.conditioning.validate(f"{where}.conditioning")
        positive(self, where, "fvd_bootstrap_reps", "floor_splits")
        if self.fvd_material < 0:
            raise ConfigError(f"{where}.fvd_material must be >= 0 (FVD units)")
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise ConfigError(f"{where}.seeds must be a non-empty list of distinct integers")
        positive(self, where, "seconds", "long_seconds", "chunk_seconds", "starts_per_clip",
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
        if not self.truth_horizons_s or min(self.truth_horizons_s) <= 0:
            raise ConfigError(f"{where}.truth_horizons_s must be a non-empty list of positive seconds")
        if self.truth_margin < 0:
            raise ConfigError(f"{where}.truth_margin must be >= 0 (a fraction)")


@dataclass(frozen=True)
class TruthConfig:
    """The ``truth`` stage: the town re-renders the steering evaluation's starts under each steering mode (what
    it renders follows ``evaluation``'s steering settings; this section says how)."""

    workers: int  # processes rendering clips side by side; 0 = one per CPU core

    def validate(self, where: str) -> None:
        if self.workers < 0:
            raise ConfigError(f"{where}.workers must be >= 0 (0 = one per CPU core)")



def positive(obj: Any, where: str, *names: str) -> None:
    """Each of ``obj``'s fields ``names`` must be > 0."""
    for name in names:
        if getattr(obj, name) <= 0:
            raise ConfigError(f"{where}.{name} = {getattr(obj, name)} must be positive")
