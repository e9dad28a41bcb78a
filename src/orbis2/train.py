"""One training loop for every stage: DDP, EMA, bf16 on GPU, resumable checkpoints.

A stage supplies a :class:`Task` (model, data, loss, optional evaluation, optional
extra optimisers such as a GAN discriminator); :func:`train` owns the rest, so
resuming, logging and multi-process behaviour are written and tested once.

``out_dir/checkpoints/last.pt`` (every ``checkpoint_every`` steps and at the end)
holds model, EMA, optimisers, step, data position and every rank's RNG state,
behind a checksum (:func:`load_checkpoint`); a re-run resumes from it,
bit-identically on CPU. The schedule is a pure function
of the step (:func:`lr_at`), so the step is the whole scheduler state.

SIGUSR1 or SIGURG (a scheduler's warning before a time limit) and SIGTERM (preemption, a cancel) stop the run
at the next step boundary: every rank agrees on the signal, rank 0 writes the checkpoint while the others wait, and
:func:`train` raises :class:`~orbis2.errors.TrainingStopped` (a stage then exits with ``REQUEUE_EXIT``, 75);
the next run resumes there, bit-identically. A run may resume with another number of processes when its task
draws every batch from the global sample order (``Task.global_order``); see :meth:`_Run.resume` for what is
then not bit-identical.

A process whose share of the global batch exceeds ``micro_batch_size`` runs it as several micro-batches,
accumulating their gradients (synchronised across processes on the last one only, DDP's ``no_sync``), and
steps the optimiser once (:func:`batch_split`); signals, checkpoints and the data position count optimiser
steps, never micro-batches.

``out_dir/model.pt`` holds ``{"model": EMA weights if EMA is on else raw, "raw",
"ema", "step", "config"}``; read it with :func:`load_weights`. Beside it,
``out_dir/curves/train.csv`` and ``curves/eval.csv`` hold every logged row (``step`` +
metrics; kept through resumes, where the first row after a resume averages only the steps
since it), the files ``dvc plots`` draws. Under ``torchrun``
every rank calls :func:`train`; rank 0 alone logs, evaluates and writes files.
"""

from __future__ import annotations

import atexit
import contextlib
import contextvars
import copy
import dataclasses
import functools
import hashlib
import io
import math
import os
import pickle
import random
import signal
import socket
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Protocol, Sequence

import numpy as np
import pandas as pd
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.checkpoint import CheckpointPolicy, checkpoint, create_selective_checkpoint_contexts
from tqdm import tqdm

from orbis2.accel import compile_for_training, set_tf32
from orbis2.config.training import CHECKPOINT_POLICIES, TrainConfig
from orbis2.errors import ConfigError, OrbisError, TrainingStopped
from orbis2.io import atomic_file

# The loss and its metrics (0-dim tensors or numbers; tensors are read only when the metrics are logged).
LossOutput = tuple[torch.Tensor, dict[str, Any]]


def lr_at(step: int, cfg: TrainConfig) -> float:
    """Learning rate of the update at 0-based ``step``: linear warm-up, then cosine.

    Warm-up reaches ``lr`` at step ``warmup_steps - 1``; the cosine then falls to
    ``min_lr_ratio * lr`` at ``step == steps`` and stays there.
    """
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    progress = min(1.0, (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps))
    floor = cfg.min_lr_ratio
    return cfg.lr * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress)))


def batch_split(cfg: TrainConfig, world_size: int) -> tuple[int, int, int]:
    """``(share, micro, accumulation)``: each of ``world_size`` processes takes ``share`` samples of the global
    ``batch_size`` a step and runs them as ``accumulation`` micro-batches of ``micro`` samples.

    ``micro`` is ``micro_batch_size`` when the share exceeds it, else the whole share (one micro-batch): the
    same setting serves 8 GPUs (share 8, one micro-batch) and 4 (share 16, two of 8). A split that does not come
    out whole raises :class:`ConfigError` naming the numbers and what would divide.
    """
    if cfg.batch_size % world_size:
        raise ConfigError(f"train config: batch_size = {cfg.batch_size} is not divisible by the "
                          f"{world_size} processes; use a multiple of {world_size}")
    share = cfg.batch_size // world_size
    micro = cfg.micro_batch_size
    if micro is None or share <= micro:
        return share, share, 1
    if share % micro:
        fits = [d for d in range(micro, 0, -1) if share % d == 0][:3]
        raise ConfigError(f"train config: batch_size = {cfg.batch_size} over {world_size} processes is {share} "
                          f"samples a process, which micro_batch_size = {micro} does not divide; set "
                          f"micro_batch_size to a divisor of {share} (e.g. {', '.join(map(str, fits))}) or "
                          f"run on a number of processes that leaves a multiple of {micro}")
    return share, micro, share // micro


# Which micro-batch of the current optimiser step a task's loss is computing (:func:`micro_step`).
_MICRO_STEP: contextvars.ContextVar[int] = contextvars.ContextVar("micro_step", default=0)


def micro_step() -> int:
    """The index of the micro-batch that the task's ``loss`` is computing within this optimiser step: 0 without
    gradient accumulation. A task that seeds its noise per ``(rank, step)`` adds it (when not 0) so that the
    micro-batches of one step draw independent noise."""
    return _MICRO_STEP.get()


def rank_seed(seed: int, rank: int) -> int:
    """An independent seed per rank, so ranks draw different noise from one params.yaml seed."""
    return int(np.random.SeedSequence([seed, rank]).generate_state(1)[0])


@dataclass(frozen=True)
class DataSpec:
    """What a task needs to produce this rank's batches.

    ``seed`` is the config seed, shared by all ranks, so a task can draw one global
    stream and keep its ``rank``-th slice (or use ``rank_seed(seed, rank)``). ``start``
    is how many batches this rank has already consumed: the iterator must begin there
    (a resume after a kill), and must not draw from the global RNGs. Every step consumes
    one batch on every rank, so ``start`` also counts the global batches, whatever the
    number of processes that consumed them.
    """

    rank: int
    world_size: int
    batch_size: int  # per rank: its share of the global batch, all its micro-batches together
    seed: int
    start: int
    num_workers: int
    pin_memory: bool = False  # CUDA: collate into page-locked memory, so that the copy to the device is asynchronous


@dataclass(frozen=True)
class Update:
    """An extra optimiser, stepped after the main one on the same batch (e.g. a discriminator).

    ``loss(model, batch, step)`` returns ``(loss, metrics)``, or ``None`` to skip this
    step (e.g. before the discriminator starts); decide before running the model.
    Its ``params`` are left out of the main optimiser; ``lr_scale`` scales the schedule.
    """

    name: str
    params: Sequence[nn.Parameter]
    loss: Callable[[nn.Module, Any, int], LossOutput | None]
    lr_scale: float = 1.0


class Task(Protocol):
    """The stage-specific part of training.

    ``loss`` receives the model as wrapped for training (``DistributedDataParallel``
    under DDP): run it by calling it, so gradients are synchronised; reach its
    attributes through :func:`unwrap`. Two optional methods are used when present:

    - ``evaluate(model, step) -> dict[str, float]``: rank 0 only, on the EMA model when
      EMA is on, in eval mode; the training RNG streams are restored afterwards.
    - ``extra_updates(model) -> list[Update]``: more optimisers over parts of the
      unwrapped model, stepped in order after the main loss each step.

    An optional attribute ``global_order = True`` says that global batch ``b`` (the
    ranks' ``b``-th batches together) is the same samples for any ``world_size`` dividing
    the batch size: the task's checkpoints may then resume with another number of processes.
    """

    def build_model(self) -> nn.Module: ...

    def batches(self, spec: DataSpec) -> Iterable[Any]: ...

    def loss(self, model: nn.Module, batch: Any, step: int) -> LossOutput: ...


@dataclass(frozen=True)
class TrainResult:
    """How a call to :func:`train` went and where its outputs are."""

    step: int
    start_step: int
    seconds: float
    model_path: Path
    checkpoint_path: Path
    metrics: dict[str, float]
    history: list[tuple[int, dict[str, float]]]


class ResumeError(OrbisError):
    """A checkpoint in the output folder cannot continue this run."""


# The ops whose outputs selective checkpointing keeps: matmuls and attention (the compute); everything else in a
# block (norms, modulation, activations, residual adds) is recomputed in the backward pass.
SAVED_OPS = frozenset(
    getattr(torch.ops.aten, name).default
    for name in ("mm", "addmm", "bmm", "baddbmm", "_scaled_dot_product_flash_attention",
                 "_scaled_dot_product_efficient_attention", "_scaled_dot_product_cudnn_attention",
                 "_scaled_dot_product_flash_attention_for_cpu", "_scaled_mm")
    if hasattr(torch.ops.aten, name))


def _selective_policy(ctx: Any, op: Any, *args: Any, **kwargs: Any) -> CheckpointPolicy:
    return CheckpointPolicy.MUST_SAVE if op in SAVED_OPS else CheckpointPolicy.PREFER_RECOMPUTE


class _SelectiveCheckpoint:
    """A block's ``forward`` run under selective activation checkpointing while it trains.

    Set as the block's instance attribute ``forward``, so the state dict keeps its names
    and a deep copy (the EMA model) checkpoints its own block.
    """

    def __init__(self, forward: Callable[..., Any]):
        self.forward = forward

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        module = self.forward.__self__
        if not (module.training and torch.is_grad_enabled()):
            return self.forward(*args, **kwargs)
        context = functools.partial(create_selective_checkpoint_contexts, _selective_policy)
        return checkpoint(self.forward, *args, use_reentrant=False, context_fn=context, **kwargs)


def set_checkpointing(model: nn.Module, blocks: int, policy: str = "full") -> None:
    """Activation checkpointing of the model's first ``blocks`` blocks, ``full`` or ``selective`` (``SAVED_OPS``).

    ``full`` is the model's own (``checkpoint_blocks``); ``selective`` wraps each block's forward in
    :func:`torch.utils.checkpoint.checkpoint` with a policy from
    :func:`torch.utils.checkpoint.create_selective_checkpoint_contexts`. Both recompute exactly what they
    dropped: losses and gradients equal the plain run's bit for bit.
    """
    if not (hasattr(model, "checkpoint_blocks") and isinstance(getattr(model, "blocks", None), nn.ModuleList)):
        raise ConfigError(f"activation_checkpointing = {blocks}: {type(model).__name__} does not support it; "
                          f"set it to 0")
    if policy not in CHECKPOINT_POLICIES:
        raise ConfigError(f"checkpoint_policy = {policy!r} must be one of {CHECKPOINT_POLICIES}")
    for block in model.blocks:
        if isinstance(block.__dict__.get("forward"), _SelectiveCheckpoint):
            del block.forward
    model.checkpoint_blocks = blocks if policy == "full" else 0
    if policy == "selective":
        for block in model.blocks[:blocks]:
            block.forward = _SelectiveCheckpoint(block.forward)


def unwrap(model: nn.Module) -> nn.Module:
    """The plain module inside a ``DistributedDataParallel`` wrapper."""
    return model.module if isinstance(model, DistributedDataParallel) else model


CHECKPOINT_MAGIC = b"ORBIS2-CHECKPOINT-1 sha256="
# The logged rows, by source: the running training metrics and the task's evaluations.
CURVES = ("train", "eval")


def load_checkpoint(path: Path) -> dict[str, Any]:
    """A training checkpoint (``checkpoints/last.pt``), verified against the checksum it carries.

    The file is a header naming the SHA-256 of the payload, then the payload
    (``torch.save`` bytes). A file without the header (foreign, or from an older
    version), a truncated one or one with a flipped bit raises :class:`ResumeError`
    naming the file and the fix, before anything is unpickled.
    """
    path = Path(path)
    fix = f"delete {path} (or the whole {path.parent.parent}) to start this stage over"
    try:
        blob = path.read_bytes()
    except OSError as err:
        raise ResumeError(f"{path}: cannot be read ({err}); {fix}") from err
    header, newline, payload = blob.partition(b"\n")
    if not header.startswith(CHECKPOINT_MAGIC) or not newline:
        raise ResumeError(f"{path}: not an orbis2 training checkpoint (no checksum header); {fix}")
    if hashlib.sha256(payload).hexdigest().encode() != header[len(CHECKPOINT_MAGIC):]:
        raise ResumeError(f"{path}: checksum mismatch, the file is corrupt (truncated or altered on disk); {fix}")
    try:
        return torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except (OSError, EOFError, RuntimeError, pickle.UnpicklingError) as err:
        raise ResumeError(f"{path}: cannot be read ({err}); {fix}") from err


def load_weights(path: Path, raw: bool = False) -> dict[str, torch.Tensor]:
    """The state dict saved in ``model.pt``: EMA weights when EMA was on, unless ``raw``."""
    saved = torch.load(path, map_location="cpu", weights_only=True)
    return saved["raw" if raw else "model"]


def train(task: Task, cfg: TrainConfig, out_dir: Path, logger: Any = None) -> TrainResult:
    """Train ``task`` to ``cfg.steps``, resuming from ``out_dir/checkpoints/last.pt`` if present.

    ``logger`` is anything with ``log_metrics(metrics, step)`` (e.g. the stage's
    MLflow run); only rank 0 calls it.
    """
    return _Run(task, cfg, Path(out_dir), logger, _start_distributed()).run()


def spawn_cpu_processes(fn: Callable[..., Any], world_size: int, *args: Any, timeout_s: float = 600) -> list[Any]:
    """Run ``fn(*args)`` in ``world_size`` fresh CPU processes set up the way torchrun does.

    Lets tests and laptops exercise the DDP path over gloo. ``fn`` and ``args`` must
    be picklable (module level); returns each rank's result, rank 0 first. A hang
    (e.g. one rank skipping a collective) is killed after ``timeout_s``.
    """
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with tempfile.TemporaryDirectory() as results:
        context = mp.spawn(_cpu_process, args=(fn, args, world_size, port, results), nprocs=world_size, join=False)
        deadline = time.monotonic() + timeout_s
        while not context.join(max(0.0, deadline - time.monotonic())):
            if time.monotonic() >= deadline:
                for process in context.processes:
                    process.kill()
                raise TimeoutError(f"{world_size} processes running {fn.__name__} still busy after {timeout_s} s")
        return [pickle.loads(Path(results, f"{rank}.pkl").read_bytes()) for rank in range(world_size)]


def _cpu_process(rank: int, fn: Callable[..., Any], args: tuple, world_size: int, port: int, results: str) -> None:
    os.environ.update(RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE=str(world_size),
                      MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), CUDA_VISIBLE_DEVICES="")
    Path(results, f"{rank}.pkl").write_bytes(pickle.dumps(fn(*args)))


@dataclass(frozen=True)
class _Env:
    rank: int
    world_size: int
    device: torch.device
    control: Any = None  # the host-side group (_host_group) when there are several processes


def _start_distributed() -> _Env:
    """Join the process group described by torchrun's environment variables, if any.

    The group is destroyed when the process exits, not when :func:`train` returns: a
    second rendezvous on the same port can hang, and a stage may train twice.
    """
    cuda = torch.cuda.is_available()
    device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0"))) if cuda else torch.device("cpu")
    if cuda:
        torch.cuda.set_device(device)
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if cuda else "gloo", device_id=device if cuda else None)
        atexit.register(_destroy_group)
    if dist.is_initialized():
        return _Env(dist.get_rank(), dist.get_world_size(), device, _host_group())
    return _Env(0, 1, device)


@functools.cache
def _host_group() -> Any:
    """A gloo group beside the default one, for the per-step stop flag and the waits while rank 0 writes: a
    host tensor reduced on the host, so asking whether any rank was signalled does not wait for the GPU (an
    NCCL reduction read on the host would), and a long write is not an NCCL timeout. Made under gloo too
    (the CPU runs and tests), so that they take the same path as NCCL runs."""
    return dist.new_group(backend="gloo")


def _destroy_group() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


def _updates(task: Task, model: nn.Module) -> list[Update]:
    """The task's main update (every trainable parameter no extra update claims) and its extra ones."""
    extras = list(task.extra_updates(model)) if hasattr(task, "extra_updates") else []
    claimed = {id(p) for update in extras for p in update.params}
    if len(claimed) != sum(len(update.params) for update in extras):
        raise ValueError("extra_updates must not share parameters")
    main = [p for p in model.parameters() if p.requires_grad and id(p) not in claimed]
    updates = [Update("main", main, task.loss), *extras]
    names = [update.name for update in updates]
    if len(set(names)) != len(names):
        raise ValueError(f"update names must be unique and not 'main', got {names}")
    return updates


class _Run:
    """One call to :func:`train` on one rank: built (model, updates, optimizers, DDP, EMA) in ``__init__``, then
    :meth:`run` resumes if a checkpoint is there and loops :meth:`train_step` and :meth:`after_step` (logging,
    evaluation, periodic checkpoints) to ``cfg.steps``; the checkpoint and weight files are written last."""

    def __init__(self, task: Task, cfg: TrainConfig, out_dir: Path, logger: Any, env: _Env):
        self.share, _, self.accumulation = batch_split(cfg, env.world_size)
        self.task, self.cfg, self.logger, self.env = task, cfg, logger, env
        self.out_dir = out_dir
        self.checkpoint_path = out_dir / "checkpoints" / "last.pt"
        torch.manual_seed(cfg.seed)  # the same initial weights on every rank
        self.raw = task.build_model().to(env.device)
        if env.device.type == "cuda":
            set_tf32(cfg.tf32)
        if cfg.activation_checkpointing:
            set_checkpointing(self.raw, cfg.activation_checkpointing, cfg.checkpoint_policy)
        self.updates = _updates(task, self.raw)
        if self.accumulation > 1 and len(self.updates) > 1:
            # An extra update (a discriminator) scores the main update's outputs of the same batch: it would
            # need every micro-batch's, kept across the main update's optimiser step.
            raise ConfigError(f"train config: micro_batch_size = {cfg.micro_batch_size} accumulates "
                              f"{self.accumulation} micro-batches a step, and this stage also trains "
                              f"{', '.join(u.name for u in self.updates[1:])} on the same batch, which gradient "
                              f"accumulation does not support; set micro_batch_size: null or use more processes")
        self.optimizers = {u.name: _optimizer(u.params, cfg, env.device) for u in self.updates}
        self.model: nn.Module = self.raw
        if env.world_size > 1:
            # Alternating updates leave the other part without gradients on each backward.
            cuda = env.device.type == "cuda"
            self.model = DistributedDataParallel(self.raw, device_ids=[env.device] if cuda else None,
                                                 find_unused_parameters=len(self.updates) > 1)
        self.ema = None if cfg.ema_decay is None else copy.deepcopy(self.raw).requires_grad_(False).eval()
        if cfg.compile:
            compile_for_training(self.raw)  # in place: the state dict keeps its names; the EMA copy stays eager
        self.step = self.start_step = self.position = 0
        self.checkpointed: int | None = None  # the step of the checkpoint this run last read or wrote
        self.resumed_from: int | None = None  # how many processes wrote the checkpoint this run resumed
        self.metrics: dict[str, float] = {}
        self.history: list[tuple[int, dict[str, float]]] = []
        self.curves: dict[str, list[dict[str, float]]] = {name: [] for name in CURVES}
        _seed_global_streams(rank_seed(cfg.seed, env.rank))  # a resume replaces these streams with the saved ones

    def run(self) -> TrainResult:
        self.resume()
        cfg, env = self.cfg, self.env
        spec = DataSpec(env.rank, env.world_size, self.share, cfg.seed, self.position, cfg.num_workers,
                        pin_memory=env.device.type == "cuda")
        batches: Iterator[Any] = iter(self.task.batches(spec))
        meter = _Meter()
        started = time.perf_counter()
        bar = tqdm(total=cfg.steps, initial=self.step, unit="step", desc=self.out_dir.name, dynamic_ncols=True,
                   disable=env.rank != 0, mininterval=0.5 if sys.stderr.isatty() else 30.0)
        with bar, _StopSignals() as stop:
            while self.step < cfg.steps:
                batch = next(batches, _EXHAUSTED)
                if batch is _EXHAUSTED:
                    raise RuntimeError(f"task.batches ran out after {self.position} batches; "
                                       f"it must keep yielding until step {cfg.steps}")
                self.train_step(batch, meter)
                bar.update()
                self.after_step(meter, bar)
                if self.step < cfg.steps:
                    self.stop_if_signalled(stop.received)
        if self.step > self.start_step:
            self.save_checkpoint()
        if env.rank == 0 and (self.step > self.start_step or not (self.out_dir / "model.pt").exists()):
            self.save_weights()
        _barrier(env, env.control)
        seconds = time.perf_counter() - started
        if env.rank == 0:
            print(self.summary(seconds), flush=True)
        return TrainResult(self.step, self.start_step, seconds, self.out_dir / "model.pt", self.checkpoint_path,
                           self.metrics, self.history)

    def train_step(self, batch: Any, meter: _Meter) -> None:
        lr = lr_at(self.step, self.cfg)
        batch = _to_device(batch, self.env.device)
        self.position += 1
        for update in self.updates:
            if self.accumulation == 1:
                with self.autocast():
                    out = update.loss(self.model, batch, self.step)
                if out is None:
                    continue
                loss, metrics = out
                self.model.zero_grad(set_to_none=True)
                loss.backward()
            else:
                out = self.accumulate(update, batch)
                if out is None:
                    continue
                loss, metrics = out
            norm = nn.utils.clip_grad_norm_(update.params, self.cfg.grad_clip or math.inf)
            optimizer = self.optimizers[update.name]
            for group in optimizer.param_groups:
                group["lr"] = lr * update.lr_scale
            optimizer.step()
            suffix = "" if update.name == "main" else f"_{update.name}"
            meter.add({**metrics, f"loss{suffix}": loss.detach(), f"grad_norm{suffix}": norm})
        if self.ema is not None:
            _ema_update(self.ema, self.raw, ema_decay_at(self.step, self.cfg.ema_decay))
        self.step += 1

    def accumulate(self, update: Update, batch: Any) -> LossOutput | None:
        """Gradients of ``update``'s loss over this rank's batch, as ``self.accumulation`` micro-batches: each
        micro-batch's loss divided by their number and back-propagated, DDP's gradient averaging left to the
        last. Returns the micro-batches' mean loss and metrics, or ``None`` when the update skips this step."""
        micro_batches = _split_batch(batch, self.accumulation)
        losses, sums = [], {}
        for index, micro in enumerate(micro_batches):
            last = index == len(micro_batches) - 1
            sync = contextlib.nullcontext() if last or self.env.world_size == 1 else self.model.no_sync()
            token = _MICRO_STEP.set(index)
            try:
                with sync:
                    with self.autocast():
                        out = update.loss(self.model, micro, self.step)
                    if out is None:
                        return None
                    loss, metrics = out
                    if index == 0:
                        self.model.zero_grad(set_to_none=True)
                    (loss / self.accumulation).backward()
            finally:
                _MICRO_STEP.reset(token)
            losses.append(loss.detach())
            for key, value in metrics.items():
                sums[key] = sums.get(key, 0.0) + (value.detach() if torch.is_tensor(value) else value)
        return sum(losses) / len(losses), {key: value / len(losses) for key, value in sums.items()}

    def after_step(self, meter: _Meter, bar: tqdm) -> None:
        step, cfg = self.step, self.cfg
        last = step == cfg.steps
        if step % cfg.log_every == 0 or last:
            self.metrics = {**meter.reduce(self.env), "lr": lr_at(step - 1, cfg)}
            bad = {k: v for k, v in self.metrics.items() if k.startswith("loss") and not math.isfinite(v)}
            if bad:
                raise OrbisError(f"training diverged at step {step} ({bad}) in {self.out_dir}: lower lr or set "
                                 f"grad_clip, then delete {self.checkpoint_path} and run again")
            self.log(self.metrics, "train")
            bar.set_postfix_str(f"loss {self.metrics.get('loss', math.nan):.4g}", refresh=False)
        if cfg.eval_every and (step % cfg.eval_every == 0 or last) and hasattr(self.task, "evaluate"):
            if self.env.rank == 0:
                model = self.ema if self.ema is not None else self.raw
                with _eval_mode(model), _preserved_rng(self.env.device):
                    self.log(dict(self.task.evaluate(model, step)), "eval")
        if step % cfg.checkpoint_every == 0 and not last:
            self.save_checkpoint()

    def stop_if_signalled(self, received: int) -> None:
        """At a step boundary: if any rank has received a stop signal (``received`` is this rank's, 0 if none),
        every rank stops here, after rank 0 has written the checkpoint of this step.

        The ranks agree through a reduction of the signals' ranks in :data:`STOP_SIGNALS` (SIGTERM, a cancel,
        outranks a warning), so they stop at the same step: a rank that stopped alone would leave the others
        waiting in the next collective.
        """
        signum = received
        if self.env.world_size > 1:
            flag = torch.tensor([STOP_SIGNALS.index(received) + 1 if received else 0], dtype=torch.int32)
            dist.all_reduce(flag, op=dist.ReduceOp.MAX, group=self.env.control)
            signum = STOP_SIGNALS[int(flag.item()) - 1] if flag.item() else 0
        if not signum:
            return
        if self.checkpointed != self.step:
            self.save_checkpoint()
        name = signal.Signals(signum).name
        raise TrainingStopped(f"stopped by {name} at step {self.step} of {self.cfg.steps}, checkpoint "
                              f"{self.checkpoint_path} written; run the stage again to resume", name, self.step,
                              together=functools.partial(_barrier, self.env, self.env.control))

    def autocast(self) -> contextlib.AbstractContextManager:
        if self.cfg.mixed_precision == "bf16" and self.env.device.type == "cuda":
            return torch.autocast("cuda", dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def log(self, metrics: dict[str, float], curve: str) -> None:
        self.history.append((self.step, metrics))
        self.curves[curve].append({"step": self.step, **metrics})
        if self.env.rank == 0 and self.logger is not None:
            self.logger.log_metrics(metrics, self.step)

    def resume(self) -> None:
        """Continue from ``checkpoints/last.pt`` if there is one.

        With the number of processes that wrote it, each rank gets its RNG streams back and the run continues
        bit for bit (on CPU). With another number (tasks with ``global_order`` only) the run consumes the same
        global batches in the same order, with the same weights, optimiser state and schedule, but is not
        bit-identical to an uninterrupted run: the gradient is averaged over another split of the batch (another
        reduction order), and noise drawn per rank (a task's ``(seed, rank, step)`` generators, the global
        streams here) is drawn for other samples.
        """
        path = self.checkpoint_path
        if not path.exists():
            return
        saved = load_checkpoint(path)
        if saved["fingerprint"] != self.cfg.fingerprint():
            old = saved["config"]
            changed = ", ".join(f"{k}: {old.get(k)!r} -> {v!r}"
                                for k, v in self.cfg.trajectory_fields().items() if old.get(k) != v)
            raise ResumeError(f"{path} was written with a different training config ({changed}); resuming it "
                              f"would mix two runs. Delete {path} to start this stage over, or restore the old "
                              f"config to resume")
        written_by = saved["world_size"]
        if written_by != self.env.world_size and not getattr(self.task, "global_order", False):
            raise ResumeError(f"{path} was written by {written_by} processes, this run has {self.env.world_size}, "
                              f"and this task's batches depend on the number of processes; resume with "
                              f"{written_by} or delete {path}")
        try:
            self.raw.load_state_dict(saved["model"])
            if self.ema is not None:
                self.ema.load_state_dict(saved["ema"])
            for name, optimizer in self.optimizers.items():
                optimizer.load_state_dict(saved["optimizers"][name])
        except (KeyError, RuntimeError, ValueError) as err:
            raise ResumeError(f"{path} does not fit this model ({err}); delete it to start this stage over") from err
        self.step = self.start_step = self.checkpointed = saved["step"]
        self.position = saved["data_position"]
        self.curves = saved["curves"]
        self.resumed_from = written_by
        if written_by == self.env.world_size:
            _set_rng_state(saved["rng"][self.env.rank], self.env.device)
        else:
            # Rank r's streams of the old run have no counterpart in the new one: each rank starts its own,
            # a pure function of (seed, rank, step), so a resume at this size is repeatable.
            _seed_global_streams(int(np.random.SeedSequence([self.cfg.seed, self.env.rank, self.step])
                                     .generate_state(1)[0]))

    def save_checkpoint(self) -> None:
        rng = _all_gather(_rng_state(self.env.device), self.env)
        if self.env.rank == 0:
            _save_checkpoint({
                "fingerprint": self.cfg.fingerprint(), "config": dataclasses.asdict(self.cfg),
                "world_size": self.env.world_size, "step": self.step, "data_position": self.position,
                "model": self.raw.state_dict(), "ema": None if self.ema is None else self.ema.state_dict(),
                "optimizers": {name: opt.state_dict() for name, opt in self.optimizers.items()}, "rng": rng,
                "curves": self.curves,
            }, self.checkpoint_path)
        self.checkpointed = self.step
        _barrier(self.env, self.env.control)  # on the host: the others wait out a long write without a GPU timeout

    def save_weights(self) -> None:
        final = self.ema if self.ema is not None else self.raw
        _atomic_save({"model": final.state_dict(), "raw": self.raw.state_dict(), "ema": self.ema is not None,
                      "step": self.step, "config": dataclasses.asdict(self.cfg)}, self.out_dir / "model.pt")
        for name, rows in self.curves.items():
            with atomic_file(self.out_dir / "curves" / f"{name}.csv") as tmp:
                pd.DataFrame(rows, columns=["step", *dict.fromkeys(k for row in rows for k in row if k != "step")]
                             ).to_csv(tmp, index=False, lineterminator="\n")

    def summary(self, seconds: float) -> str:
        ran, weights = self.step - self.start_step, self.out_dir / "model.pt"
        if ran == 0:
            return f"train {self.out_dir}: already complete at step {self.step}; weights {weights}"
        resumed = ""
        if self.start_step:
            other = f", written by {self.resumed_from} processes" if self.resumed_from != self.env.world_size else ""
            resumed = f" (resumed at {self.start_step}{other})"
        return (f"train {self.out_dir}: {ran} steps to {self.step}{resumed} in {seconds:.1f} s ({ran / seconds:.2f}"
                f" steps/s), loss {self.metrics.get('loss', math.nan):.4g}; weights {weights}")


_EXHAUSTED = object()


class _Meter:
    """Averages metrics over the steps since the last log and over ranks."""

    def __init__(self) -> None:
        self.sums: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def add(self, metrics: dict[str, Any]) -> None:
        for key, value in metrics.items():
            value = value.detach().double() if torch.is_tensor(value) else float(value)  # no GPU sync per step
            self.sums[key] = self.sums.get(key, 0.0) + value
            self.counts[key] = self.counts.get(key, 0) + 1

    def reduce(self, env: _Env) -> dict[str, float]:
        keys = sorted(self.sums)
        totals = torch.tensor([[float(self.sums[k]), self.counts[k]] for k in keys], dtype=torch.float64,
                              device=env.device).reshape(-1, 2)
        if env.world_size > 1:
            dist.all_reduce(totals)
        self.sums, self.counts = {}, {}
        return {key: (total / count).item() for key, (total, count) in zip(keys, totals)}


def _optimizer(params: Sequence[nn.Parameter], cfg: TrainConfig, device: torch.device) -> torch.optim.Optimizer:
    """Adam(W) with no weight decay on biases and norm scales (tensors with fewer than 2 dims), unless
    ``cfg.decay_biases_and_norms``; each parameter's update is independent of its group, so one group
    with the same settings gives the same numbers."""
    vector_decay = cfg.weight_decay if cfg.decay_biases_and_norms else 0.0
    groups = [{"params": [p for p in params if p.ndim >= 2], "weight_decay": cfg.weight_decay},
              {"params": [p for p in params if p.ndim < 2], "weight_decay": vector_decay}]
    kind = torch.optim.AdamW if cfg.optimizer == "adamw" else torch.optim.Adam
    return kind([g for g in groups if g["params"]], lr=cfg.lr, betas=cfg.betas, fused=device.type == "cuda")


def ema_decay_at(step: int, decay: float) -> float:
    """EMA decay after ``step`` optimiser steps, warmed up as min(decay, (1 + step) / (10 + step)).

    A fixed decay keeps decay ** steps of the initialisation: 13% after 200 steps at 0.99, which
    dominates a short run's published weights. The warm-up lets early averages follow training
    and reaches the configured decay once (1 + step) / (10 + step) exceeds it (step ~ 890 at
    0.99, ~90k at 0.9999), so long runs average as before.
    """
    return min(decay, (1.0 + step) / (10.0 + step))


@torch.no_grad()
def _ema_update(ema: nn.Module, raw: nn.Module, decay: float) -> None:
    """Parameters move towards the trained ones; buffers (e.g. norm statistics) are copied."""
    torch._foreach_lerp_(list(ema.parameters()), list(raw.parameters()), 1.0 - decay)
    for ema_buffer, buffer in zip(ema.buffers(), raw.buffers()):
        ema_buffer.copy_(buffer)


def _split_batch(batch: Any, parts: int) -> list[Any]:
    """``batch`` (tensors, or dicts, lists and tuples of them, with the samples along the first dimension) as
    ``parts`` consecutive micro-batches of equal size."""
    if torch.is_tensor(batch):
        if batch.ndim == 0 or batch.shape[0] % parts:
            raise ConfigError(f"micro_batch_size: a batch tensor of shape {tuple(batch.shape)} does not split into "
                              f"{parts} micro-batches along its first dimension; set micro_batch_size: null")
        return list(batch.tensor_split(parts))
    if isinstance(batch, dict):
        columns = {key: _split_batch(value, parts) for key, value in batch.items()}
        return [{key: column[i] for key, column in columns.items()} for i in range(parts)]
    if isinstance(batch, (list, tuple)):
        columns = [_split_batch(value, parts) for value in batch]
        return [type(batch)(column[i] for column in columns) for i in range(parts)]
    raise ConfigError(f"micro_batch_size: a batch of {type(batch).__name__} does not split into micro-batches; "
                      f"set micro_batch_size: null")


def _to_device(batch: Any, device: torch.device) -> Any:
    if device.type == "cpu":
        return batch
    if torch.is_tensor(batch):
        return batch.to(device, non_blocking=True)
    if isinstance(batch, dict):
        return {key: _to_device(value, device) for key, value in batch.items()}
    if isinstance(batch, (list, tuple)):
        return type(batch)(_to_device(value, device) for value in batch)
    return batch


@contextlib.contextmanager
def _eval_mode(model: nn.Module) -> Iterator[None]:
    """Eval mode for evaluation, then every submodule's own mode back (frozen parts stay frozen)."""
    modes = [(module, module.training) for module in model.modules()]
    model.eval()
    try:
        yield
    finally:
        for module, training in modes:
            module.training = training


def _rng_state(device: torch.device) -> dict[str, Any]:
    """Every global RNG stream, in types that ``torch.load(weights_only=True)`` accepts."""
    numpy_state = np.random.get_state(legacy=False)
    return {
        "python": random.getstate(),
        "numpy": {"key": torch.from_numpy(numpy_state["state"]["key"].astype(np.int64)),
                  "pos": numpy_state["state"]["pos"], "has_gauss": numpy_state["has_gauss"],
                  "gauss": numpy_state["gauss"]},
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state(device) if device.type == "cuda" else None,
    }


def _set_rng_state(state: dict[str, Any], device: torch.device) -> None:
    random.setstate(state["python"])
    numpy_state = state["numpy"]
    np.random.set_state({"bit_generator": "MT19937",
                         "state": {"key": numpy_state["key"].numpy().astype(np.uint32), "pos": numpy_state["pos"]},
                         "has_gauss": numpy_state["has_gauss"], "gauss": numpy_state["gauss"]})
    torch.set_rng_state(state["torch"])
    if state["cuda"] is not None and device.type == "cuda":
        torch.cuda.set_rng_state(state["cuda"], device)


@contextlib.contextmanager
def _preserved_rng(device: torch.device) -> Iterator[None]:
    """Evaluation may draw random numbers without shifting training's streams."""
    state = _rng_state(device)
    try:
        yield
    finally:
        _set_rng_state(state, device)


def _all_gather(obj: Any, env: _Env) -> list[Any]:
    gathered: list[Any] = [obj] * env.world_size
    if env.world_size > 1:
        dist.all_gather_object(gathered, obj)
    return gathered


def _barrier(env: _Env, group: Any = None) -> None:
    if env.world_size > 1:
        dist.barrier(group=group)


def _save_checkpoint(obj: Any, path: Path) -> None:
    """``obj`` with its checksum header (see :func:`load_checkpoint`), atomically."""
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    payload = buffer.getvalue()
    with atomic_file(path) as tmp:
        tmp.write_bytes(CHECKPOINT_MAGIC + hashlib.sha256(payload).hexdigest().encode() + b"\n" + payload)


def _atomic_save(obj: Any, path: Path) -> None:
    with atomic_file(path) as tmp, open(tmp, "wb") as handle:
        torch.save(obj, handle)  # through a handle: the bytes must not depend on the temp file's name


def _seed_global_streams(seed: int) -> None:
    """Python's, NumPy's and torch's global RNGs, all from ``seed``."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


# The signals that stop training at the next step boundary, weakest first: a scheduler's warning ahead of a time
# limit (Slurm's `--signal=USR1@<seconds>` to a job over nodes; `URG@<seconds>` to a one-task job, whose Snakemake
# and shell share the stage's job step and ignore SIGURG, where SIGUSR1 would kill them: orbis2.dag) and
# termination (preemption, a cancel, the time limit itself).
STOP_SIGNALS = (signal.SIGUSR1, signal.SIGURG, signal.SIGTERM)


class _StopSignals:
    """While training runs, :data:`STOP_SIGNALS` are noted (``received``: the first one's number, 0 for none)
    instead of acted on; the loop stops at the next step boundary (:meth:`_Run.stop_if_signalled`).

    Python runs handlers in the main thread only, so elsewhere (a test's worker thread) nothing is installed.
    The handlers in place before come back on exit.
    """

    def __init__(self) -> None:
        self.received = 0
        self.previous: dict[int, Any] = {}

    def __enter__(self) -> _StopSignals:
        if threading.current_thread() is threading.main_thread():
            self.previous = {sig: signal.signal(sig, self.note) for sig in STOP_SIGNALS}
        return self

    def note(self, signum: int, frame: Any) -> None:
        self.received = self.received or signum

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)


def ignore_stop_signals(worker_id: int) -> None:
    """A DataLoader's ``worker_init_fn``: its workers ignore :data:`STOP_SIGNALS`.

    Slurm signals every process of a job step, the loader's workers included; one that died of SIGUSR1 would
    fail the next batch before the training process reaches its step boundary and checkpoint. The training
    process alone decides when to stop; its loader shuts the workers down when it exits.
    """
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
