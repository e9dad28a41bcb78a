"""Training the learned inverse-dynamics instrument (:mod:`orbis2.eval.metrics.inverse_dynamics`) with the shared loop.

The flow front end is fixed, so every train pair's Farneback flow is computed once
(its mirror image, horizontal flow negated, per batch). Each step draws ``batch_size``
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
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from orbis2.accel import conv_layout
from orbis2.config.params import PipelineConfig
from orbis2.config.training import InverseDynamicsConfig
from orbis2.data.shards import split_clips
from orbis2.data.truth import counterfactual_clip, single_thread_renderer
from orbis2.errors import OrbisError
from orbis2.eval.metrics.inverse_dynamics import ClipFrames, Instrument, pair_flow, pair_index, resize
from orbis2.models.inverse_dynamics import InverseDynamicsNet
from orbis2.train import DataSpec, LossOutput, load_weights, train

# A horizontal flip keeps the speed and negates the yaw rate, and negates the flow's horizontal component.
FLIP_SIGN = np.array([1.0, -1.0])
MIRROR_FLOW = np.array([-1.0, 1.0], np.float32)[:, None, None]
FLOW_CHUNK = 1024  # pairs whose frames are stacked at once to compute their flow


class InstrumentTask:
    """Flow fields of random train pairs -> standardised (speed, yaw rate), mean squared error."""

    global_order = True  # each global batch is drawn whole and sliced per rank (batches)

    def __init__(self, data: ClipFrames, cfg: InverseDynamicsConfig):
        self.cfg = cfg
        self.index = pair_index(data)
        if len(self.index) < cfg.train.batch_size:
            raise OrbisError(f"only {len(self.index)} frame pairs with odometry in the train split; need at least "
                             f"a batch ({cfg.train.batch_size}); lower inverse_dynamics.train.batch_size or add "
                             f"train clips")
        self.targets = np.stack([data.odometry[c][t] for c, t in self.index])
        self.mean, self.std = self.targets.mean(axis=0), self.targets.std(axis=0) + 1e-6
        h, w = data.frames[0].shape[1:3]
        self.flows = np.empty((len(self.index), 2, h, w), np.float32)
        for start in range(0, len(self.index), FLOW_CHUNK):  # frame stacks of one chunk at a time, not of all pairs
            rows = self.index[start:start + FLOW_CHUNK]
            self.flows[start:start + len(rows)] = pair_flow(np.stack([data.frames[c][t] for c, t in rows]),
                                                            np.stack([data.frames[c][t + 1] for c, t in rows]))

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
            flows = self.flows[pick]  # mirrored per batch: a stored copy of every mirror image doubled the memory
            flow = np.where(flip[:, None, None, None], flows[..., ::-1] * MIRROR_FLOW, flows)
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


def _render_counterfactuals(job) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """One clip under each scale pair: (key, frames at the instrument's scale, odometry)."""
    clip, scales, data, town, jpeg_quality, scale = job
    out = []
    for speed_scale, yaw_rate_scale in scales:
        frames, odometry = counterfactual_clip(clip, speed_scale, yaw_rate_scale, data, town, jpeg_quality)
        out.append((f"{clip.key}_speed{speed_scale:g}_yaw{yaw_rate_scale:g}", resize(frames, scale), odometry))
    return out


def counterfactual_train_clips(shards: Path, cfg: PipelineConfig, workers: int) -> tuple[ClipFrames, dict[str, Any]]:
    """``inverse_dynamics.counterfactual_clips`` town clips of the train split (evenly spread), each driven again
    by the town under every ``counterfactual_scales`` pair (:func:`orbis2.data.truth.counterfactual_clip`), at
    the instrument's scale, rendered on ``workers`` processes; and what was rendered (a record's part)."""
    ic = cfg.inverse_dynamics
    clips = [c for c in split_clips(shards, "train").values() if c.meta.get("source") == "town"
             and c.meta["has_odometry"]]
    clips.sort(key=lambda c: c.key)
    wanted = min(ic.counterfactual_clips, len(clips))
    summary: dict[str, Any] = {"clips": wanted, "scales": ic.counterfactual_scales, "videos": 0, "pairs": 0}
    if not wanted or not ic.counterfactual_scales:
        return ClipFrames([], [], []), {**summary, "clips": 0, "reason": "none asked for, or no town clip in train"}
    picked = [clips[int(i)] for i in np.linspace(0, len(clips) - 1, wanted).round()]
    jobs = [(c, ic.counterfactual_scales, cfg.data, cfg.town, cfg.shards.jpeg_quality, ic.scale) for c in picked]
    began = time.perf_counter()
    with ProcessPoolExecutor(max(1, min(workers, len(jobs))), initializer=single_thread_renderer) as pool:
        rendered = [item for items in pool.map(_render_counterfactuals, jobs) for item in items]
    data = ClipFrames([f for _, f, _ in rendered], [o for _, _, o in rendered], [k for k, _, _ in rendered])
    return data, {**summary, "videos": len(rendered), "pairs": len(pair_index(data)),
                  "render_seconds": time.perf_counter() - began}


def train_instrument(data: ClipFrames, cfg: InverseDynamicsConfig, fps: float, out_dir: Path,
                     device: torch.device, logger: Any = None) -> Instrument:
    """Train on ``data`` (the train clips) in ``out_dir`` (resuming its checkpoint), return the instrument."""
    task = InstrumentTask(data, cfg)
    result = train(task, cfg.train, out_dir, logger)
    return task.instrument(load_weights(result.model_path), fps, device)
