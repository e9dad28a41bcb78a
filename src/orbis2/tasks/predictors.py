"""Training the predictors of the hierarchy (paper Sec. 3.3-3.4) and of its ablations with the shared loop.

One task class; what distinguishes the stages is their spec in registry.yaml (``STAGES``)
and their params.yaml section (same name):

- ``abstract_df``: the abstract predictor F_H (causal, 6 frames at 2 Hz) pre-trained
  with diffusion forcing (eq. 2): an independent tau per frame, loss on every frame.
- ``abstract_tf``: F_H fine-tuned with teacher forcing (eq. 1): 5 clean context
  frames, 1 target; starts from ``init_from`` (``abstract_df``).
- ``detail``: the detail predictor F_L (bidirectional, 10 frames at 10 Hz, 5 + 5)
  with teacher forcing, conditioned on the ground-truth abstract latents of its
  last context frame and of the subgoal aligned with its last predicted frame
  (paper eq. for F_L; the authors' code, "Hierarchy wiring").
- ``action``: F_H with a steering embedder, fine-tuned with teacher forcing from
  ``abstract_tf``; only the abstract level is steered (paper "Action-conditioning").

Ablations (paper Tables 3 and 4), the same code with another spec:

- ``abstract_tf_only``: F_H trained with teacher forcing alone (``init_from: null``).
- ``flat_detail`` / ``flat_abstract``: single-branch 10 Hz predictors of detail or
  abstract latents (hierarchy Exps. 1 and 2); ``flat_abstract`` is also Exp. 5's
  10 Hz top predictor.
- ``top_detail``: a 2 Hz top predictor of detail latents, and ``detail_on_detail``
  the bottom predictor conditioned on detail-latent subgoals (Exp. 4).
- ``flat_abstract_full``: ``flat_abstract`` on the uncompressed, teacher-dimensional
  abstract latents (the compression ablation).

Faster inference: ``detail_distill`` is the few-step detail predictor, ``detail``
distilled by rectified-flow reflow (``orbis2.flow.reflow_loss``): initialised
from its teacher, trained on the teacher's own (noise, sample) pairs, sampled
with ``student_nfe`` Euler steps instead of the teacher's ``teacher_nfe``.

Batches come from :class:`~orbis2.latents.LatentWindowDataset` (already normalised
latents). All randomness of a training step comes from a generator seeded by
``(seed, rank, step)``, so a resumed run draws what an uninterrupted one would.
The validation loss uses fixed val windows and a fixed generator: it is
comparable across steps and with the network at initialisation
(``val_loss_init``), which :meth:`PredictorTask.build_model` rebuilds exactly
because it is a pure function of the config.
"""

from __future__ import annotations

import itertools
import warnings
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from torch.utils.data import DataLoader

from orbis2.config.params import PipelineConfig
from orbis2.config.sections import DataConfig
from orbis2.config.training import ActionConfig, DistillConfig, PredictorConfig, TeacherForcingConfig
from orbis2.data.motion import TURN_THRESHOLD
from orbis2.errors import OrbisError
from orbis2.flow import (
    diffusion_forcing_draws,
    diffusion_forcing_from_draws,
    euler_sample,
    reflow_draws,
    reflow_from_draws,
    teacher_forcing_draws,
    teacher_forcing_from_draws,
)
from orbis2.hierarchy import (
    STEERING_FEATURES,
    detail_condition,
    detail_condition_slots,
    rate_geometry,
    steering_features,
    steering_interval,
    window_indices,
    window_key,
    window_span,
)
from orbis2.io import sha256_file
from orbis2.latents import LatentCache, LatentWindowDataset, collate
from orbis2.models import full_build
from orbis2.models.deviations import TURN_SEARCH, best_sideways_shift, translate_columns
from orbis2.models.files import PredictorFile, load_predictor, save_predictor
from orbis2.models.sizes import STDIT_PRESETS
from orbis2.models.stdit import build_stdit_from
from orbis2.registry import PredictorSpec, registry
from orbis2.tasks import official
from orbis2.train import DataSpec, ignore_stop_signals, load_weights, micro_step, train

# Offset of the validation generator's seed from the training seed: a different stream, fixed across steps.
VAL_SEED_OFFSET = 7919


# What distinguishes the predictor stages: registry.yaml, ``predictors``.
StageSpec = PredictorSpec
STAGES: dict[str, StageSpec] = registry().predictors


# --------------------------------------------------------------------------- counterfactual turns


def turn_columns_per_yaw_rate(dataset: LatentWindowDataset, data: DataConfig, windows: int = 2048) -> float:
    """How far a turn moves the abstract grid over the steering interval: columns per rad/s of mean yaw rate.

    The least-squares slope through the origin of the best sideways shift
    (:func:`best_sideways_shift`) between the last context latent and the target
    against the mean yaw rate, over up to ``windows`` train windows spread evenly
    over the split (those with odometry). The search is the models' (``TURN_SEARCH``),
    reaching less far on grids narrower than 16 so that half the columns are still compared.
    """
    key, n_context = window_key("abstract", "slow"), rate_geometry(data, "slow")[2]
    width = dataset[0][key].shape[-1]
    reach, step = min(TURN_SEARCH[0], (width - 4) // 2), TURN_SEARCH[1]
    if reach < 1:
        raise OrbisError(f"{dataset.cache.root}: abstract grids {width} columns wide are too narrow "
                         f"to measure a turn; set yaw_offset_prob: 0 for the steered predictor")
    picks = np.unique(np.linspace(0, len(dataset) - 1, min(windows, len(dataset))).round().astype(int))
    shifts, yaws, known = [], [], []
    for start in range(0, len(picks), 256):
        batch = collate([dataset[int(i)] for i in picks[start:start + 256]])
        frames = batch[key].float()
        shifts.append(best_sideways_shift(frames[:, n_context - 1], frames[:, -1], reach, step))
        yaws.append(batch["odometry"][:, steering_interval(data), 1].float().mean(dim=1))
        known.append(batch["has_odometry"].bool())
    shift, yaw = torch.cat(shifts).double(), torch.cat(yaws).double()
    known = torch.cat(known) & torch.isfinite(yaw)
    if not known.any() or float((yaw[known] ** 2).sum()) == 0.0:
        raise OrbisError(f"{dataset.cache.root}: the {dataset.split} split has no turning windows with odometry; "
                         f"set yaw_offset_prob: 0 for the steered predictor, or add turning data")
    return float((shift[known] * yaw[known]).sum() / (yaw[known] ** 2).sum())


def offset_yaw(targets: torch.Tensor, steering: torch.Tensor, active: torch.Tensor,
               draws: torch.Generator | torch.Tensor, prob: float, max_offset: float, columns_per_yaw_rate: float,
               yaw_rate_scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Counterfactual turns for the steered fine-tune: targets [B, T, C, h, w] and unit-scale steering [B, S, 2].

    With probability ``prob`` an ``active`` sample gets a yaw-rate offset
    delta ~ U(-max_offset, max_offset) rad/s over its steering interval, and its
    target frame j moves sideways by delta x ``columns_per_yaw_rate`` x (j + 1) / T
    columns (:func:`translate_columns`): the frames a slightly sharper or gentler
    turn would have shown, approximated as a pure sideways move of the grid. The
    world turns at a few rates only; these samples show the predictor how the
    scene moves with the yaw rate in between and beyond them. ``draws`` is a
    generator, or the [2, B] uniforms it would give (:func:`offset_yaw_draws`).
    """
    b, n_target = targets.shape[:2]
    if isinstance(draws, torch.Generator):
        draws = offset_yaw_draws(b, draws, targets.device)
    delta = torch.where(active & (draws[0] < prob), (2 * draws[1] - 1) * max_offset, torch.zeros_like(draws[1]))
    moved = torch.stack([translate_columns(targets[:, j], delta * columns_per_yaw_rate * (j + 1) / n_target)
                         for j in range(n_target)], dim=1)
    moved = torch.where((delta != 0).reshape(-1, 1, 1, 1, 1), moved, targets)
    steering = steering.clone()
    steering[..., 1] += (delta / yaw_rate_scale)[:, None]
    return moved, steering


def offset_yaw_draws(b: int, generator: torch.Generator, device: torch.device) -> torch.Tensor:
    """The [2, B] uniforms of one :func:`offset_yaw` (whether to offset, and by how much)."""
    return torch.rand(2, b, generator=generator, device=generator.device).to(device)


# --------------------------------------------------------------------------- data


def turn_repeats(dataset: LatentWindowDataset, data: DataConfig, cfg: PredictorConfig,
                 block: int = 1 << 16) -> np.ndarray:
    """How often each train window enters an epoch: ``turn_repeat`` times where the ego turns (mean
    |yaw rate| above ``TURN_THRESHOLD``) over the steering interval or the interval before it, so
    turn onsets, turns and turn ends all count; once elsewhere.

    Only windows that turn show what a turn does to the scene (and, for the steering
    fine-tune, what the yaw rate does): in the rest the ongoing motion is already in the
    context, and a short run sees too few turns to learn to carry one. Vectorised over
    ``block`` windows at a time (their yaw rates are read in one gather), so memory stays
    that of the result.
    """
    steer = steering_interval(data)
    before = slice(steer.start - (steer.stop - steer.start), steer.start)
    detail, abstract = window_indices(data, 0)
    offsets = window_span(detail, abstract)
    odometry = dataset.cache.arrays(dataset.split)["odometry"]
    repeats = np.ones(len(dataset), np.int64)
    for start in range(0, len(dataset), block):
        clip, anchor = dataset.windows(start, min(start + block, len(dataset)))
        yaw = odometry[(dataset.clips["offset"][clip] + anchor)[:, None] + offsets, 1]
        with warnings.catch_warnings():  # a window without odometry (all NaN) does not turn
            warnings.simplefilter("ignore", RuntimeWarning)
            now, then = (np.abs(np.nanmean(yaw[:, part], axis=1)) for part in (steer, before))
        # the larger of the two, NaN where the steering interval's is (a window whose odometry is unknown)
        turning = np.where(then > now, then, now) > TURN_THRESHOLD
        repeats[start:start + len(clip)] = np.where(turning, cfg.turn_repeat, 1)
    return repeats


def window_index_batches(n_windows: int, spec: DataSpec, split: str,
                         repeats: np.ndarray | None = None) -> Iterator[list[int]]:
    """Endless window indices of this rank's train batches from batch ``spec.start`` on; a pure function of the spec.

    Each epoch is a permutation drawn from ``(seed, epoch)``, shared by all ranks, of
    the windows with window i listed ``repeats[i]`` times (once without ``repeats``).
    Global batch ``g`` of the epoch is its entries ``g * B`` to ``(g + 1) * B - 1``
    (``B = batch_size * world_size``, the configured global batch) and rank ``r`` keeps
    every ``world_size``-th of them from the ``r``-th: the global batches, and the
    number of them in an epoch (the whole ones, ``len(pool) // B``), do not depend on
    how many processes share them, so a run may resume with another number; within
    an epoch no window repeats or goes missing, but for the permutation's last
    ``len(pool) % B`` entries, which the epoch leaves out. Only ``len(dataset)`` is
    needed, and skipping to ``start`` reads no windows.
    """
    pool = np.arange(n_windows) if repeats is None else np.repeat(np.arange(n_windows), repeats)
    n, size = len(pool), spec.batch_size * spec.world_size
    per_epoch = n // size
    if per_epoch == 0:
        raise OrbisError(f"the {split} split gives {n} windows, fewer than one global batch of {size}; "
                         f"lower the batch size or anchor_stride, or add data")
    first_epoch, offset = divmod(spec.start, per_epoch)
    for epoch in itertools.count(first_epoch):
        order = pool[np.random.default_rng([spec.seed, epoch]).permutation(n)]
        for g in range(offset, per_epoch):
            yield [int(i) for i in order[g * size:(g + 1) * size][spec.rank::spec.world_size]]
        offset = 0


class _IndexBatches:
    """The ``batch_sampler`` of a :class:`~torch.utils.data.DataLoader`: one pass is the endless index stream."""

    def __init__(self, batches: Iterator[list[int]]):
        self.batches = batches

    def __iter__(self) -> Iterator[list[int]]:
        return self.batches


def window_batches(dataset: LatentWindowDataset, spec: DataSpec,
                   repeats: np.ndarray | None = None) -> Iterator[dict[str, torch.Tensor]]:
    """Endless train batches of this rank (:func:`window_index_batches`), read and collated by a DataLoader.

    ``spec.num_workers`` worker processes read and collate the next batches while the
    network trains (0: in this process, what the CPU profiles use); ``spec.pin_memory``
    collates into page-locked memory, so the training loop's ``non_blocking`` copy
    overlaps with compute. The batches are the same either way, in the same order.
    """
    indices = window_index_batches(len(dataset), spec, dataset.split, repeats)
    if spec.num_workers == 0 and not spec.pin_memory:
        return (collate([dataset[i] for i in batch]) for batch in indices)
    loader = DataLoader(dataset, batch_sampler=_IndexBatches(indices), collate_fn=collate,
                        num_workers=spec.num_workers, pin_memory=spec.pin_memory,
                        prefetch_factor=2 if spec.num_workers else None, worker_init_fn=ignore_stop_signals)
    return iter(loader)


def step_generator(seed: int, rank: int, step: int, device: torch.device, micro: int = 0) -> torch.Generator:
    """The noise source of one training step: independent of the global RNG, so resuming replays it.

    ``micro``: the micro-batch within the step under gradient accumulation (:func:`orbis2.train.micro_step`);
    each draws its own noise, and the first (the only one without accumulation) the step's of old."""
    key = [seed, rank, step] if micro == 0 else [seed, rank, step, micro]
    generator = torch.Generator(device)
    generator.manual_seed(int(np.random.SeedSequence(key).generate_state(1)[0]))
    return generator


# --------------------------------------------------------------------------- task


class PredictorTask:
    """One predictor stage: model (optionally initialised from another stage), batches, loss, validation."""

    global_order = True  # window_index_batches: the same global batches for any number of processes

    def __init__(self, stage: str, cfg: PredictorConfig, data: DataConfig, cache: LatentCache,
                 init_state: dict[str, torch.Tensor] | None = None, architecture: dict[str, Any] | None = None):
        if stage not in STAGES:
            raise ValueError(f"unknown predictor stage {stage!r}; choose from {sorted(STAGES)}")
        self.stage, self.spec, self.cfg, self.data, self.cache = stage, STAGES[stage], cfg, data, cache
        self.init_state = init_state
        self.architecture = architecture  # an imported predictor's build (orbis2.tasks.official), else None
        self.batch_key = window_key(self.spec.level, self.spec.rate)
        self.train_set = LatentWindowDataset(cache, "train", data, cfg.anchor_stride)
        self.val_set = LatentWindowDataset(cache, "val", data, cfg.anchor_stride)
        self.frame_rate = float(rate_geometry(data, self.spec.rate)[0])
        self._val: list[dict[str, torch.Tensor]] | None = None
        self._val_init: float | None = None
        self._teacher: nn.Module | None = None
        self._turn_columns: float | None = None
        # Window arithmetic done once, not inside the (compilable) loss.
        self.slots = detail_condition_slots(data) if self.spec.condition is not None else None
        self.steer = steering_interval(data) if self.spec.steering else None

    @property
    def rank(self) -> int:
        """This process's rank; read when used, since :func:`train` joins the process group after construction."""
        return dist.get_rank() if dist.is_initialized() else 0

    @property
    def build(self) -> dict[str, Any]:
        """The :func:`build_stdit_from` dict (preset, the whole size with ``model`` applied, wiring) that
        :func:`save_predictor` records;
        the imported architecture where the stage starts from the authors' networks."""
        if self.architecture is not None:
            return self.architecture
        shapes, condition = self.cache.meta["tokenizers"], self.spec.condition
        return {**full_build(STDIT_PRESETS, self.cfg.preset, self.cfg.model),
                "latent_channels": shapes[self.spec.level]["shape"][0], "causal": self.spec.causal,
                "abstract_channels": shapes[condition]["shape"][0] if condition else None,
                "steering": self.spec.steering}

    def build_model(self) -> nn.Module:
        """A pure function of the config: seeded from ``train.seed``, then ``init_state`` loaded if given.

        A steered model loads an unsteered state with only the steering embedder
        (and shift) left at their initialisation, whose outputs start at zero: the fine-tune
        starts from exactly the pre-trained predictor.
        """
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.cfg.train.seed)
            model = build_stdit_from(self.build)
        if self.init_state is not None:
            missing, unexpected = model.load_state_dict(self.init_state, strict=False)
            stray = [k for k in missing if not (self.spec.steering and k.startswith(("steering.", "steering_shift.")))]
            if stray or unexpected:
                source = self.cfg.init_from or "imported"
                fix = (f"re-run {source} with the same preset and model overrides" if self.cfg.init_from else
                       "re-import the release (orbis2 import-weights)")
                raise OrbisError(f"{self.stage}: the {source} weights do not fit this predictor (missing "
                                 f"{stray[:5]}, unexpected {unexpected[:5]}); {fix}")
        return model

    def turn_columns(self) -> float:
        """:func:`turn_columns_per_yaw_rate` of the train split, measured once per process."""
        if self._turn_columns is None:
            self._turn_columns = turn_columns_per_yaw_rate(self.train_set, self.data)
        return self._turn_columns

    def batches(self, spec: DataSpec) -> Iterator[dict[str, torch.Tensor]]:
        repeats = turn_repeats(self.train_set, self.data, self.cfg) if self.cfg.turn_repeat > 1 else None
        return window_batches(self.train_set, spec, repeats)

    def teacher(self, device: torch.device) -> nn.Module:
        """The frozen ``init_from`` network a ``reflow`` stage distills (built once per process)."""
        if self.init_state is None:
            raise OrbisError(f"{self.stage}: distillation needs init_from (the teacher)")
        if self._teacher is None:
            teacher = build_stdit_from(self.build)
            teacher.load_state_dict(self.init_state)
            self._teacher = teacher.eval().requires_grad_(False)
        return self._teacher.to(device)

    def objective(self, model: nn.Module, batch: dict[str, torch.Tensor], generator: torch.Generator,
                  augment: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The flow-matching loss of this stage; ``augment`` switches on context noise/drop and steering dropout."""
        return self.objective_from_draws(model, batch, self.draws(batch, generator, augment), augment)

    def draws(self, batch: dict[str, torch.Tensor], generator: torch.Generator,
              augment: bool) -> dict[str, torch.Tensor]:
        """Every random number of one :meth:`objective`, in its order of drawing (and the teacher's pairs).

        Apart from the loss, so that :meth:`objective_from_draws` holds no generator: it runs without a host
        sync and compiles with the network.
        """
        frames = batch[self.batch_key]
        n_context = rate_geometry(self.data, self.spec.rate)[2]
        if self.spec.objective == "diffusion_forcing":
            return diffusion_forcing_draws(frames, generator)
        if self.spec.objective == "reflow":
            assert isinstance(self.cfg, DistillConfig)
            return reflow_draws(frames[:, :n_context], frames.shape[1] - n_context, generator,
                                self.teacher(frames.device), self.cfg.teacher_nfe, **self.condition(batch))
        cfg, out = self.cfg, {}
        if self.spec.steering:
            assert isinstance(cfg, ActionConfig)
            out["steering_drop"] = torch.rand(len(frames), generator=generator, device=generator.device
                                              ).to(frames.device)
            if augment and cfg.yaw_offset_prob > 0:
                out["yaw"] = offset_yaw_draws(len(frames), generator, frames.device)
        return {**out, **teacher_forcing_draws(frames[:, :n_context], frames[:, n_context:], generator)}

    def condition(self, batch: dict[str, torch.Tensor]) -> dict[str, Any]:
        """The network's conditioning of this batch: frame rate, and the subgoal slots where the stage has them."""
        cond: dict[str, Any] = {"frame_rate": self.frame_rate}
        if self.spec.condition is not None:
            subgoals = batch[window_key(self.spec.condition, "slow")]
            cond["cond_frames"], _ = detail_condition(subgoals, self.data, self.slots)
            cond["cond_mask"] = tuple(sorted(self.slots))  # static slots: the forward reads no mask (no sync)
        return cond

    def objective_from_draws(self, model: nn.Module, batch: dict[str, torch.Tensor], draws: dict[str, torch.Tensor],
                             augment: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """:meth:`objective` given its :meth:`draws`: no generator, no host sync; metrics are 0-dim tensors."""
        frames = batch[self.batch_key]
        cond = self.condition(batch)
        if self.spec.objective == "diffusion_forcing":
            return diffusion_forcing_from_draws(model, frames, draws, **cond)
        n_context = rate_geometry(self.data, self.spec.rate)[2]
        if self.spec.objective == "reflow":
            return reflow_from_draws(model, frames[:, :n_context], draws, **cond)
        cfg = self.cfg
        assert isinstance(cfg, TeacherForcingConfig)
        metrics: dict[str, torch.Tensor] = {}
        targets = frames[:, n_context:]
        if self.spec.steering:
            assert isinstance(cfg, ActionConfig)
            cond["steering"], unknown = steering_features(batch["odometry"], batch["has_odometry"], self.data,
                                                          (cfg.speed_scale, cfg.yaw_rate_scale), self.steer)
            cond["steering_drop"] = unknown | (draws["steering_drop"] < (cfg.steering_dropout if augment else 0.0))
            metrics = {"steering_unknown": unknown.float().mean(),
                       "steering_dropped": cond["steering_drop"].float().mean()}
            if "yaw" in draws:
                targets, cond["steering"] = offset_yaw(
                    targets, cond["steering"], ~cond["steering_drop"], draws["yaw"], cfg.yaw_offset_prob,
                    cfg.yaw_offset_max, self.turn_columns(), cfg.yaw_rate_scale)
        loss, tf_metrics = teacher_forcing_from_draws(
            model, frames[:, :n_context], targets, draws,
            context_noise_prob=cfg.context_noise_prob if augment else 0.0, context_noise_std=cfg.context_noise_std,
            context_drop_prob=cfg.context_drop_prob if augment else 0.0, **cond)
        return loss, {**tf_metrics, **metrics}

    def loss(self, model: nn.Module, batch: dict[str, torch.Tensor], step: int
             ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        device = batch[self.batch_key].device
        generator = step_generator(self.cfg.train.seed, self.rank, step, device, micro_step())
        return self.objective(model, batch, generator, True)

    def val_windows(self) -> list[dict[str, torch.Tensor]]:
        """``val_batches`` batches of val windows spread evenly over the split; the same every call."""
        if self._val is None:
            size = self.cfg.train.batch_size
            count = min(len(self.val_set), self.cfg.val_batches * size)
            if count == 0:
                raise OrbisError(f"{self.cache.root}: the val split gives no windows; add val data or lower "
                                 f"anchor_stride")
            picks = np.linspace(0, len(self.val_set) - 1, count).round().astype(int)
            self._val = [collate([self.val_set[int(i)] for i in picks[s:s + size]]) for s in range(0, count, size)]
        return self._val

    @torch.no_grad()
    def val_loss(self, model: nn.Module) -> float:
        """Mean un-augmented loss over :meth:`val_windows` with noise from one fixed generator."""
        device = next(model.parameters()).device
        generator = torch.Generator(device)
        generator.manual_seed(self.cfg.train.seed + VAL_SEED_OFFSET)
        losses, weights = [], []
        for batch in self.val_windows():
            batch = {k: v.to(device) for k, v in batch.items()}
            losses.append(self.objective(model, batch, generator, augment=False)[0].item())
            weights.append(len(batch["has_odometry"]))
        return float(np.average(losses, weights=weights))

    @torch.no_grad()
    def few_step_errors(self, model: nn.Module) -> dict[str, float]:
        """Reflow stages: MSE to the teacher's ``teacher_nfe``-step sample of the student's and of the teacher's
        own ``student_nfe``-step samples, from the same noise on the val windows (the student must be closer)."""
        cfg = self.cfg
        assert isinstance(cfg, DistillConfig)
        device = next(model.parameters()).device
        teacher, n_context = self.teacher(device), rate_geometry(self.data, self.spec.rate)[2]
        errors = {"student": [], "teacher": []}
        generator = torch.Generator(device).manual_seed(self.cfg.train.seed + VAL_SEED_OFFSET)
        for batch in self.val_windows():
            batch = {k: v.to(device) for k, v in batch.items()}
            frames = batch[window_key(self.spec.level, self.spec.rate)]
            context, n_target = frames[:, :n_context], frames.shape[1] - n_context
            cond: dict[str, Any] = {"frame_rate": self.frame_rate}
            cond["cond_frames"], cond["cond_mask"] = detail_condition(batch[window_key(self.spec.condition, "slow")],
                                                                      self.data)
            noise = torch.randn(frames[:, n_context:].shape, generator=generator, device=device)
            reference = euler_sample(teacher, context, n_target, cfg.teacher_nfe, generator, noise=noise, **cond)
            for name, net in (("student", model), ("teacher", teacher)):
                few = euler_sample(net, context, n_target, cfg.student_nfe, generator, noise=noise, **cond)
                errors[name].append(float((few - reference).pow(2).mean()))
        return {f"few_step_mse_{name}": float(np.mean(values)) for name, values in errors.items()}

    def evaluate(self, model: nn.Module, step: int) -> dict[str, float]:
        """``val_loss``; the first call also logs ``val_loss_init``, the same loss of the untrained network."""
        metrics = {"val_loss": self.val_loss(model)}
        if self._val_init is None:
            self._val_init = self.init_val_loss(next(model.parameters()).device)
            metrics["val_loss_init"] = self._val_init
        return metrics

    def init_val_loss(self, device: torch.device) -> float:
        return self.val_loss(self.build_model().to(device).eval())


# --------------------------------------------------------------------------- stage


def tokenizer_checksums(detail: Path, abstract: Path) -> tuple[str, str]:
    """SHA-256 of the tokenizer files (what ``load_tokenizer(...).checksum`` gives) without loading the networks."""
    for path in (detail, abstract):
        if not path.is_file():
            raise OrbisError(f"{path}: tokenizer checkpoint not found; run its training stage first")
    return sha256_file(detail), sha256_file(abstract)


def check_latents(loaded: PredictorFile, path: Path, cache: LatentCache, fix: str) -> None:
    """``loaded`` (from ``path``) predicts the latents of ``cache``'s tokenizers, or the stage stops with ``fix``."""
    for kind in ("detail", "abstract"):
        theirs = loaded.meta["tokenizers"][kind]["checksum"]
        if theirs != cache.meta["tokenizers"][kind]["checksum"]:
            raise OrbisError(f"{path} was trained on latents of another {kind} tokenizer; {fix}")


def load_init_state(stage: str, source: str, path: Path, cache: LatentCache) -> dict[str, torch.Tensor]:
    """The weights of ``path``, the published predictor of stage ``source``, refusing one trained on other latents."""
    loaded = load_predictor(path)
    check_latents(loaded, path, cache, f"re-run `{source}` before `{stage}`")
    return loaded.model.state_dict()


def imported_start(stage: str, cfg: PipelineConfig, cache: LatentCache, path: Path
                   ) -> tuple[dict[str, Any], dict[str, torch.Tensor] | None]:
    """The build of ``stage`` at the architecture of the imported predictor ``path`` and, where the stage has no
    ``init_from``, the imported weights it starts from (:mod:`orbis2.tasks.official`)."""
    pc: PredictorConfig = cfg.section(stage)
    imported = load_predictor(path)
    build = official.stage_build(imported, path, STAGES[stage], pc.model, cfg, cache.meta["tokenizers"][
        STAGES[stage].level]["shape"])
    if pc.init_from is not None:
        return build, None
    check_latents(imported, path, cache, "make the latent cache with official_weights set (its tokenizer stages "
                                         "then publish the imported tokenizers)")
    return build, official.start_state(imported)


def train_predictor(stage: str, cfg: PipelineConfig, cache: LatentCache, out_dir: Path, logger: Any = None,
                    init_file: Path | None = None, imported: Path | None = None) -> dict[str, float]:
    """A predictor stage: train (resuming), then measure the final val loss and write ``predictor.pt``.

    ``init_file`` is the published predictor of the stage's ``init_from`` (required when it
    has one); ``imported`` the imported predictor whose architecture the stage takes (and whose weights
    it starts from without an ``init_from``; :func:`orbis2.tasks.official.imported_predictor`).
    ``logger`` receives the training metrics (``log_metrics(metrics, step)``).
    Returns the final metrics on rank 0 and ``{}`` on other ranks (under torchrun).
    """
    pc: PredictorConfig = cfg.section(stage)
    if (pc.init_from is None) != (init_file is None):
        raise ValueError(f"{stage}: init_from is {pc.init_from!r} but init_file is {init_file}")
    init_state = None if init_file is None else load_init_state(stage, pc.init_from, init_file, cache)
    architecture = None
    if imported is not None:
        architecture, imported_state = imported_start(stage, cfg, cache, imported)
        init_state = init_state if imported_state is None else imported_state
    task = PredictorTask(stage, pc, cfg.data, cache, init_state, architecture)
    result = train(task, pc.train, Path(out_dir), logger)
    if task.rank != 0:
        return {}
    device = torch.device("cuda", torch.cuda.current_device()) if torch.cuda.is_available() else torch.device("cpu")
    model = task.build_model()
    model.load_state_dict(load_weights(result.model_path))
    model.to(device).eval()
    metrics = {"val_loss": task.val_loss(model), "val_loss_init": task.init_val_loss(device), "steps": result.step,
               "parameters": sum(p.numel() for p in model.parameters())}
    if task.spec.objective == "reflow":
        metrics.update(task.few_step_errors(model))
    if isinstance(pc, ActionConfig) and pc.yaw_offset_prob > 0:
        metrics["turn_columns_per_yaw_rate"] = task.turn_columns()
    meta = predictor_meta(stage, cfg, cache, metrics)
    if imported is not None:  # what it was built from, and started from where it has no init_from
        meta["imported"] = {"file": str(imported), "checksum": sha256_file(imported),
                            "started_from": pc.init_from is None}
    save_predictor(Path(out_dir) / "predictor.pt", model, task.build, meta)
    return metrics


def predictor_meta(stage: str, cfg: PipelineConfig, cache: LatentCache, metrics: dict[str, float]) -> dict:
    """What the weights mean: which latents, which rates and windows, how they were trained."""
    spec, pc, d = STAGES[stage], cfg.section(stage), cfg.data
    level_window = {"abstract": (d.abstract_window, d.abstract_context), "detail": (d.detail_window, d.detail_context)}
    rate, window, context = rate_geometry(d, spec.rate)
    meta = {
        "stage": stage, "profile": cfg.profile, "level": spec.level, "rate": spec.rate, "objective": spec.objective,
        "init_from": pc.init_from,
        "condition": spec.condition,
        "tokenizers": {kind: {"checksum": cache.meta["tokenizers"][kind]["checksum"]}
                       for kind in ("detail", "abstract")},
        "frame_rate": rate,
        "window": {"window": window, "context": context},
        "rates": {"fps": d.fps, "detail_hz": d.detail_hz, "abstract_hz": d.abstract_hz},
        "windows": {level: {"window": w, "context": c} for level, (w, c) in level_window.items()},
        "metrics": metrics,
    }
    if spec.objective == "reflow":
        meta["sampling"] = {"nfe": pc.student_nfe, "teacher_nfe": pc.teacher_nfe, "method": "reflow"}
    if spec.condition is not None:
        meta["condition_slots"] = {str(slot): index for slot, index in detail_condition_slots(d).items()}
    if spec.steering:
        interval = steering_interval(d)
        meta["steering"] = {"features": list(STEERING_FEATURES), "scale": [pc.speed_scale, pc.yaw_rate_scale],
                            "steps": interval.stop - interval.start,
                            "interval": "native odometry rows from the last context frame up to the predicted one"}
    return meta
