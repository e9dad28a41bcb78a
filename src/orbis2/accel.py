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
* **torch.compile** (:func:`compile_predictor`, :func:`compile_decoder`):
  ``dynamic=False``, because a rollout calls each network with one shape per
  rollout (fixed batch, window and grid), so each compiles once and re-uses
  the graph for every Euler step.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import torch
from torch import nn

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


def compile_predictor(model: nn.Module) -> nn.Module:
    """Compile an ST-DiT's forward (and its KV-cached forward) in place; returns the same module."""
    model.forward = torch.compile(model.forward, dynamic=False)
    if hasattr(model, "forward_cached"):
        model.forward_cached = torch.compile(model.forward_cached, dynamic=False)
    return model


def compile_decoder(tokenizer: nn.Module) -> nn.Module:
    """Compile a tokenizer's ``decode`` in place (decoding is part of the measured generation)."""
    tokenizer.decode = torch.compile(tokenizer.decode, dynamic=False)
    return tokenizer
