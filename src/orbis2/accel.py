"""Precision and compilation policies for GPU inference and training, inert on the CPU.

* **TF32** (:func:`set_tf32`): fp32 matmuls and convolutions on tensor cores
  (10-bit mantissa products, fp32 accumulation). Set explicitly by every stage
  and benchmark so results do not depend on a library default.
* **bf16 autocast** (:func:`inference_autocast`): rollouts and decoding run
  under ``torch.autocast(bfloat16)`` on CUDA only; on the CPU everything stays
  fp32 so the laptop numbers and the tests are unchanged. The FVD network (I3D)
  and the Frechet distance are never wrapped: they run after decoding, in fp32.
* **Channels-last convolutions** (:func:`conv_layout`): every convolutional
  network (tokenizers, discriminator, teacher, I3D, the inverse-dynamics CNN)
  keeps its weights, and so its activations, in channels-last memory, the fast
  layout of oneDNN on the CPU and of cuDNN: the same math up to float round-off;
  on a 2-core CPU decoding runs 2.4x and I3D 1.6x faster, tokenizer training
  steps 1.0-1.1x (``benchmarks/bench_layout.py``).
* **torch.compile** (:func:`compile_predictor`, :func:`compile_for_training`,
  :func:`compile_decoder`): ``dynamic=False``, because a rollout calls each
  network with one shape per rollout (fixed batch, window and grid), so each
  compiles once and re-uses the graph for every Euler step. Predictors are
  compiled by region: the repeated ST-DiT block is compiled once per kind of
  call (a KV-cache build, a cached step, a whole window) and its graph serves
  every block at any depth (the weights are graph inputs, the block keeps no
  Python state that dynamo would guard on), which is what keeps the warm-up
  short. On CUDA the blocks of a rollout run as CUDA graphs
  (``mode="reduce-overhead"``), each whole-network call one graph generation
  (:meth:`~orbis2.models.stdit.STDiT.begin_graph_generation`). A recompile
  beyond what the design needs (:data:`RECOMPILE_LIMIT`) falls back to eager
  with one warning from dynamo; the tests compile with ``fullgraph=True``,
  where it fails. :func:`compile_cache` keeps the compiled artifacts between runs.
* **Weights cast once** (:func:`cast_for_inference`): under bf16 autocast every
  linear layer's weight is cast at every call (autocast caches casts only of
  weights that require grad, and inference weights do not); casting them to
  bf16 once gives the same arithmetic without the per-call casts.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

from orbis2.io import atomic_file

PRECISIONS = ("bf16", "fp32")


@dataclass(frozen=True)
class Inference:
    """How rollouts run: ``precision`` (bf16 autocast on CUDA, else fp32), ``compile``, ``kv_cache``, and
    ``steering_guidance`` (classifier-free guidance on a steered top predictor's steering; 1 = none)."""

    precision: str = "bf16"
    compile: bool = False
    kv_cache: bool = True
    tf32: bool = True
    steering_guidance: float = 1.0

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision = {self.precision!r} must be one of {list(PRECISIONS)}")


def default_device() -> torch.device:
    """CUDA when available, else the CPU."""
    return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")


def set_tf32(enabled: bool = True) -> None:
    """The process-wide fp32 policy on CUDA: TF32 tensor cores for matmuls and cuDNN convolutions, or exact fp32."""
    torch.set_float32_matmul_precision("high" if enabled else "highest")
    torch.backends.cudnn.allow_tf32 = enabled


def inference_autocast(device: torch.device | str, precision: str = "bf16") -> contextlib.AbstractContextManager:
    """bf16 autocast on CUDA when ``precision`` is ``bf16``; a no-op elsewhere (CPU runs stay fp32)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision = {precision!r} must be one of {list(PRECISIONS)}")
    if torch.device(device).type == "cuda" and precision == "bf16":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()


def conv_layout(module: nn.Module) -> nn.Module:
    """``module`` (in place) with its convolution weights in channels-last memory (3-D for a network of
    3-D convolutions); inputs in either layout work, outputs follow the weights."""
    three_d = any(isinstance(m, nn.Conv3d) for m in module.modules())
    return module.to(memory_format=torch.channels_last_3d if three_d else torch.channels_last)


# Compiled entries of the ST-DiT block's code one process may hold: one per kind of call (KV-cache build,
# cached step, whole window; with or without abstract conditioning; training forward) and input shape
# (batch, window, grid). A hierarchical rollout needs 3 (abstract KV build, abstract cached step, detail
# step) whatever the depth; an evaluation process compiling every system of the registry at two batch sizes
# stays under 32. Dynamo's default (8) counts all of them together, across blocks and predictors.
RECOMPILE_LIMIT = 32


def _compile_blocks(model: nn.Module, backend: str, fullgraph: bool, mode: str | None) -> None:
    torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, RECOMPILE_LIMIT)
    for block in model.blocks:
        block.compile(dynamic=False, fullgraph=fullgraph, backend=backend, mode=mode)


def compile_predictor(model: nn.Module, cuda_graphs: bool | None = None, backend: str = "inductor",
                      fullgraph: bool = False) -> nn.Module:
    """Compile an ST-DiT by region for inference, in place: each block through one shared graph per kind of
    call (same code, the block's weights as inputs), so the network compiles in the time of one block at any
    depth; the sampling plan and the glue between blocks stay eager. ``cuda_graphs`` (default: when the model
    is on CUDA, with inductor): the blocks run as CUDA graphs (``mode="reduce-overhead"``) and every
    whole-network call starts a graph generation. ``fullgraph``: a graph break or a recompile past
    :data:`RECOMPILE_LIMIT` raises (the tests) instead of falling back to eager. Returns the same module."""
    if cuda_graphs is None:
        cuda_graphs = next(model.parameters()).device.type == "cuda"
    cuda_graphs = cuda_graphs and backend == "inductor"
    _compile_blocks(model, backend, fullgraph, "reduce-overhead" if cuda_graphs else None)
    model.cuda_graphs = cuda_graphs
    return model


def compile_for_training(model: nn.Module, backend: str = "inductor", fullgraph: bool = False) -> nn.Module:
    """``train.compile``, in place: an ST-DiT by region (its forward and backward compile once for all blocks,
    activation checkpointing included), any other network whole. No CUDA graphs: a training step's optimizer
    and loss run eagerly between the blocks' calls, and each step's batch is new memory."""
    if hasattr(model, "begin_graph_generation"):  # an ST-DiT
        _compile_blocks(model, backend, fullgraph, None)
    else:
        model.compile()
    return model


class HostSyncs(TorchDispatchMode):
    """Records the ops that read a tensor back to the host or make a shape depend on its values: each one stops
    a CUDA-graph capture and breaks a compiled graph. ``with HostSyncs() as syncs: ...``, then ``syncs.seen``."""

    OPS = {"aten._local_scalar_dense", "aten.item", "aten.is_nonzero", "aten.equal", "aten.nonzero",
           "aten.nonzero_static", "aten.masked_select", "aten.unique", "aten._unique2", "aten.unique_consecutive",
           "aten.unique_dim", "aten.repeat_interleave.Tensor", "aten.bincount", "aten.histc"}

    def __init__(self):
        super().__init__()
        self.seen: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func.overloadpacket)
        if name in self.OPS or str(func.name()).replace("::", ".") in self.OPS:
            self.seen.append(str(func))
        if name == "aten.index" and any(isinstance(i, torch.Tensor) and i.dtype == torch.bool
                                        for i in tree_flatten(args[1:])[0]):
            self.seen.append("aten.index (boolean mask)")
        return func(*args, **(kwargs or {}))


def cast_for_inference(model: nn.Module, device: torch.device | str, precision: str = "bf16") -> nn.Module:
    """On CUDA with ``precision`` bf16, every linear layer's weight and bias cast to bf16 once, in place (the
    casts bf16 autocast would make at every call), and the weights of the normalisations that have them (the
    attention's q/k norms), so that no norm meets mixed dtypes (autocast still runs LayerNorm in fp32; the
    attention casts its output back). The other parameters (embeddings, gates) stay fp32 and are cast to the
    activations' dtype where they are added. Run the model under :func:`inference_autocast` still. A no-op
    elsewhere (CPU runs stay fp32)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision = {precision!r} must be one of {list(PRECISIONS)}")
    if torch.device(device).type == "cuda" and precision == "bf16":
        for module in model.modules():
            if isinstance(module, (nn.Linear, nn.RMSNorm, nn.LayerNorm)):
                module.to(torch.bfloat16)
    return model


@contextlib.contextmanager
def compile_cache(path: Path | str | None) -> Iterator[dict]:
    """Load torch.compile's artifacts (``torch.compiler`` mega-cache) from ``path`` before the block and save
    them after it, so a later run skips most of the compilation; yields a dict that receives
    ``load_s`` and ``save_s`` (seconds) and ``loaded`` (whether artifacts were found). None: nothing cached."""
    record: dict = {"loaded": False}
    if path is None:
        yield record
        return
    path = Path(path)
    start = time.perf_counter()
    if path.is_file():
        torch.compiler.load_cache_artifacts(path.read_bytes())
        record["loaded"] = True
    record["load_s"] = time.perf_counter() - start
    yield record
    start = time.perf_counter()
    artifacts = torch.compiler.save_cache_artifacts()
    if artifacts is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(path) as tmp:
            tmp.write_bytes(artifacts[0])
    record["save_s"] = time.perf_counter() - start


def compile_decoder(tokenizer: nn.Module, backend: str = "inductor") -> nn.Module:
    """Compile a tokenizer's ``decode`` in place (decoding is part of the measured generation)."""
    tokenizer.decode = torch.compile(tokenizer.decode, dynamic=False, backend=backend)
    return tokenizer
