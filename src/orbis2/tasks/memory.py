"""GPU memory of a predictor's training step, estimated from the preset's dimensions.

Per GPU under DDP (every rank holds everything): fp32 weights, fp32 gradients, DDP's
gradient buckets, AdamW's two moments, the EMA copy and autocast's bf16 weight copies
(4 + 4 + 4 + 8 + 4 + 2 = 26 bytes per parameter), plus the activations autograd keeps
for the backward pass, plus a fixed allowance for the CUDA context and workspaces.

The activations are calibrated, not guessed: :func:`calibrate` runs the same
architecture (same options, same patch size, frame count and head width ratio) at a
small width on the CPU in fp32 and measures, per block and per sample, the bytes
autograd saves (``torch.autograd.graph.saved_tensors_hooks``) and the bytes selective
checkpointing keeps (the outputs of :data:`orbis2.train.SAVED_OPS` plus the block's
input). Both are proportional to tokens x width (flash attention keeps no attention
matrix), so they scale to the real preset by (tokens x width) / (tokens x width at
calibration). fp32 makes the estimate an upper bound of bf16 autocast, which keeps
norms and residuals in fp32 and matmul inputs in bf16.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode

from orbis2.config.params import PipelineConfig
from orbis2.models.sizes import stdit_config
from orbis2.models.stdit import build_stdit_from
from orbis2.registry import registry
from orbis2.train import SAVED_OPS

GIB = 2**30
BYTES_PER_PARAMETER = 4 + 4 + 4 + 8 + 4 + 2  # weights, grads, DDP buckets, AdamW moments, EMA, bf16 casts
CONTEXT_BYTES = 3 * GIB  # CUDA context, cuBLAS / attention workspaces, allocator slack
CALIBRATION_WIDTH = 64  # hidden size of the calibration network (head width and cond_dim scaled with it)


@dataclass(frozen=True)
class Activations:
    """Bytes per sample of one training forward, divided by tokens x hidden size (fp32)."""

    block: float  # one block without checkpointing
    selective: float  # one block under selective checkpointing
    block_input: float  # one block under full checkpointing (its input)
    outside: float  # embeddings, conditioners, final layer


@dataclass(frozen=True)
class MemoryEstimate:
    """One GPU's memory in a training step, in GiB."""

    parameters: int
    batch: int
    fixed_gb: float  # weights, grads, buckets, optimiser, EMA, casts, CUDA context
    activations_gb: float

    @property
    def total_gb(self) -> float:
        return self.fixed_gb + self.activations_gb

    def fits(self, memory_gb: float) -> bool:
        return self.total_gb <= memory_gb


class _SavedOutputs(TorchDispatchMode):
    """Bytes of the outputs of :data:`SAVED_OPS` while ``active`` (what selective checkpointing keeps)."""

    def __init__(self) -> None:
        super().__init__()
        self.active, self.storages = False, {}

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if self.active and func in SAVED_OPS:
            for t in out if isinstance(out, tuple) else (out,):
                if torch.is_tensor(t):
                    self.storages[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
        return out


def measure(model: nn.Module, x: torch.Tensor, tau: torch.Tensor, cond: dict[str, Any],
            bf16: bool = False) -> dict[str, float]:
    """Bytes per sample of one training forward of ``model``: saved per block, kept by selective, outside blocks.

    ``bf16``: under bf16 autocast (the training loop's ``mixed_precision: bf16``), on the CPU.
    """
    per_block: dict[int, dict[int, int]] = {i: {} for i in range(len(model.blocks))}
    outside: dict[int, int] = {}
    inputs: dict[int, int] = {}
    current: list[int] = []
    selective = _SavedOutputs()
    block_outputs: dict[int, dict[int, int]] = {i: {} for i in range(len(model.blocks))}

    def enter(index: int, args: tuple) -> None:
        current.append(index)
        inputs[index] = args[0].untyped_storage().nbytes()
        selective.active, selective.storages = True, block_outputs[index]

    def leave(*_: Any) -> None:
        current.pop()
        selective.active = False

    def pack(t: torch.Tensor) -> torch.Tensor:
        store = per_block[current[-1]] if current else outside
        store[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
        return t

    hooks = [h for i, block in enumerate(model.blocks) for h in (
        block.register_forward_pre_hook(lambda _m, args, i=i: enter(i, args)), block.register_forward_hook(leave))]
    try:
        autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16)
        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t), selective, autocast:
            model.train()(x, tau, **cond)
    finally:
        for hook in hooks:
            hook.remove()
    b, depth = x.shape[0], len(model.blocks)
    blocks = [sum(store.values()) for store in per_block.values()]
    kept = [sum(block_outputs[i].values()) + inputs[i] for i in range(depth)]
    return {"block": max(blocks) / b, "selective": max(kept) / b, "block_input": max(inputs.values()) / b,
            "outside": sum(outside.values()) / b}


def _inputs(build: dict[str, Any], batch: int, frames: int, grid: tuple[int, int]) -> tuple:
    channels, h, w = build["latent_channels"], *grid
    generator = torch.Generator().manual_seed(0)
    x, tau = torch.randn(batch, frames, channels, h, w, generator=generator), torch.rand(batch, frames)
    cond: dict[str, Any] = {"frame_rate": 10.0}
    if build.get("abstract_channels"):
        mask = torch.zeros(batch, frames, dtype=torch.bool)
        mask[:, [frames // 2 - 1, frames - 1]] = True
        cond.update(cond_frames=torch.randn(batch, frames, build["abstract_channels"], h, w, generator=generator),
                    cond_mask=mask)
    if build.get("steering"):
        cond["steering"] = torch.randn(batch, 5, 2, generator=generator)
    return x, tau, cond


def tokens(build: dict[str, Any], frames: int, grid: tuple[int, int]) -> int:
    """Tokens of one sample: frames x patches per frame."""
    p = stdit_config(build["preset"], **_overrides(build)).patch_size
    return frames * (grid[0] // p) * (grid[1] // p)


def _overrides(build: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in build.items()
            if k not in ("preset", "latent_channels", "causal", "abstract_channels", "steering")}


@functools.lru_cache(maxsize=32)
def _calibrate(key: str, frames: int, bf16: bool) -> Activations:
    build = eval(key)  # noqa: S307 - the repr of a dict of literals, made by calibrate()
    cfg = stdit_config(build["preset"], **_overrides(build))
    ratio = CALIBRATION_WIDTH / cfg.hidden_size
    heads = max(1, round(cfg.num_heads * ratio))
    small = {**build, "hidden_size": CALIBRATION_WIDTH, "depth": 2, "num_heads": heads,
             "cond_dim": max(heads, round((cfg.cond_dim or cfg.hidden_size) * ratio / heads) * heads)}
    grid = (3 * cfg.patch_size, 4 * cfg.patch_size)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = build_stdit_from(small)
    bytes_ = measure(model, *_inputs(small, 2, frames, grid), bf16=bf16)
    unit = tokens(small, frames, grid) * CALIBRATION_WIDTH
    return Activations(**{k: v / unit for k, v in bytes_.items()})


def calibrate(build: dict[str, Any], frames: int, bf16: bool = True) -> Activations:
    """:class:`Activations` of the architecture ``build`` (a :func:`build_stdit_from` dict), measured small."""
    return _calibrate(repr(dict(sorted(build.items()))), frames, bf16)


def estimate(build: dict[str, Any], frames: int, grid: tuple[int, int], batch: int, checkpointing: int = 0,
             policy: str = "full", bf16: bool = True, parameters: int | None = None) -> MemoryEstimate:
    """Memory of one GPU training ``batch`` samples of ``frames`` latent frames on ``grid`` with DDP and EMA.

    ``checkpointing`` blocks (the first ones) under ``policy`` keep what :func:`measure` says; a checkpointed
    block's activations are rebuilt once at a time in the backward pass, so one block's worth is added.
    """
    cfg = stdit_config(build["preset"], **_overrides(build))
    if parameters is None:
        with torch.device("meta"):
            parameters = sum(p.numel() for p in build_stdit_from(build).parameters())
    unit = tokens(build, frames, grid) * cfg.hidden_size * batch
    act = calibrate(build, frames, bf16)
    checkpointed = min(checkpointing, cfg.depth)
    kept = act.selective if policy == "selective" else act.block_input
    per_unit = act.outside + (cfg.depth - checkpointed) * act.block + checkpointed * kept
    if checkpointed:
        per_unit += act.block  # the block being recomputed
    return MemoryEstimate(parameters, batch, (BYTES_PER_PARAMETER * parameters + CONTEXT_BYTES) / GIB,
                          per_unit * unit / GIB)


def predictor_build(cfg: PipelineConfig, stage: str) -> dict[str, Any]:
    """The :func:`build_stdit_from` dict a stage of ``cfg`` trains, from the tokenizers' latent size."""
    spec, section = registry().predictors[stage], cfg.section(stage)
    channels = cfg.section("tokenizer_detail").sizes().latent_dim
    return {"preset": section.preset, "latent_channels": channels, "causal": spec.causal,
            "abstract_channels": channels if spec.condition else None, "steering": spec.steering, **section.model}


def stage_estimate(cfg: PipelineConfig, stage: str, gpus: int, **train_changes: Any) -> MemoryEstimate:
    """The estimate of a predictor stage as ``cfg`` configures it, its global batch split over ``gpus``."""
    train = dataclasses.replace(cfg.section(stage).train, **train_changes)
    spec = registry().predictors[stage]
    frames = cfg.data.abstract_window if spec.rate == "slow" else cfg.data.detail_window
    tok = cfg.section("tokenizer_detail").sizes()
    grid = (cfg.data.height // tok.patch_size, cfg.data.width // tok.patch_size)
    found = estimate(predictor_build(cfg, stage), frames, grid, train.batch_size // gpus,
                     train.activation_checkpointing, train.checkpoint_policy, train.mixed_precision == "bf16")
    if spec.objective == "reflow":  # the frozen teacher's fp32 weights; its no-grad forwards keep nothing
        found = dataclasses.replace(found, fixed_gb=found.fixed_gb + 4 * found.parameters / GIB)
    return found
