"""Training the learned inverse-dynamics instrument (:mod:`orbis2.eval.metrics.inverse_dynamics`) with the shared loop.

The flow front end is fixed, so every train pair's Farneback flow, and its mirror
image (horizontal flow negated), is computed once. Each step draws ``batch_size``
random pairs and flips about half of them (yaw rate negated), from one numpy
Generator seeded with ``train.seed``; the targets are standardised with the train
pairs' mean and std, which the instrument keeps. With the instrument's params
(fp32 AdamW on every parameter, ``decay_biases_and_norms``; cosine from ``lr`` to 0,
no warm-up, clipping or EMA) the weights equal, bit for bit on the CPU, those of
``AdamW(net.parameters())`` stepped by ``CosineAnnealingLR(opt, steps)`` over the
same batches (tests/test_inverse_dynamics.py keeps that loop as the reference). On
CUDA the shared loop steps torch's fused AdamW, so GPU weights differ from that
loop's in round-off only.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from orbis2.accel import conv_layout
from orbis2.config.training import InverseDynamicsConfig
from orbis2.errors import OrbisError
from orbis2.eval.metrics.inverse_dynamics import ClipFrames, Instrument, pair_flow, pair_index
from orbis2.models.inverse_dynamics import InverseDynamicsNet
from orbis2.train import DataSpec, LossOutput, load_weights, train

# A horizontal flip keeps the speed and negates the yaw rate.
FLIP_SIGN = np.array([1.0, -1.0])


class InstrumentTask:
    """Flow fields of random train pairs -> standardised (speed, yaw rate), mean squared error."""

    def __init__(self, data: ClipFrames, cfg: InverseDynamicsConfig):
        self.cfg = cfg
        self.index = pair_index(data)
        if len(self.index) < cfg.train.batch_size:
            raise OrbisError(f"only {len(self.index)} frame pairs with odometry in the train split; need at least "
                             f"a batch ({cfg.train.batch_size}); lower inverse_dynamics.train.batch_size or add "
                             f"train clips")
        self.targets = np.stack([data.odometry[c][t] for c, t in self.index])
        self.mean, self.std = self.targets.mean(axis=0), self.targets.std(axis=0) + 1e-6
        self.flows = pair_flow(np.stack([data.frames[c][t] for c, t in self.index]),
                               np.stack([data.frames[c][t + 1] for c, t in self.index]))
        self.mirrored = np.ascontiguousarray(self.flows[..., ::-1] * np.array([-1.0, 1.0], np.float32)[:, None, None])

    def build_model(self) -> nn.Module:
        return conv_layout(InverseDynamicsNet(self.cfg.width))

    def batches(self, spec: DataSpec) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """Endless (flow, target) batches of this rank from batch ``spec.start`` on.

        Each global batch's picks and flips are drawn in full from the one seeded
        Generator and each rank keeps its slice, so ranks together see the
        single-process batches; a resume re-draws (without building) the batches before ``start``.
        """
        rng = np.random.default_rng(spec.seed)
        size = spec.batch_size * spec.world_size
        mine = slice(spec.rank * spec.batch_size, (spec.rank + 1) * spec.batch_size)
        for position in itertools.count():
            pick = rng.integers(0, len(self.index), size)
            flip = rng.random(size) < 0.5
            if position < spec.start:
                continue
            pick, flip = pick[mine], flip[mine]
            flow = np.where(flip[:, None, None, None], self.mirrored[pick], self.flows[pick])
            target = np.where(flip[:, None], self.targets[pick] * FLIP_SIGN, self.targets[pick])
            yield torch.from_numpy(flow), torch.from_numpy((target - self.mean) / self.std).float()

    def loss(self, model: nn.Module, batch: tuple[torch.Tensor, torch.Tensor], step: int) -> LossOutput:
        flow, target = batch
        return F.mse_loss(model(flow), target), {}

    def instrument(self, weights: dict[str, torch.Tensor], fps: float, device: torch.device) -> Instrument:
        """The trained network with this data's standardisation, ready to read ``fps`` video."""
        net = self.build_model()
        net.load_state_dict(weights)
        return Instrument(net.to(device).eval(), self.mean, self.std, fps, self.cfg.scale)


def train_instrument(data: ClipFrames, cfg: InverseDynamicsConfig, fps: float, out_dir: Path,
                     device: torch.device, logger: Any = None) -> Instrument:
    """Train on ``data`` (the train clips) in ``out_dir`` (resuming its checkpoint), return the instrument."""
    task = InstrumentTask(data, cfg)
    result = train(task, cfg.train, out_dir, logger)
    return task.instrument(load_weights(result.model_path), fps, device)
