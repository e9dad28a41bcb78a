"""Linear probes of a model's frozen features: the probe sets, the feature extractors, and both heads
(:mod:`orbis2.eval.metrics.probe_heads`) trained on the features extracted once.

The backbone is frozen, so features are extracted once (:func:`extract_features`) and only the head
trains, on the cached features: fast, and deterministic given the seed (paper appendix "Linear probing
details"; the heads, losses and measures are in :mod:`orbis2.eval.metrics.probe_heads`).

Feature extractors map images ``[B, 3, H, W]`` in [-1, 1] to features ``[B, D, h, w]``:
the tokenizer latent, a frozen teacher, or an intermediate block of a predictor.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from tqdm import tqdm

from orbis2.config.sections import ProbeSettings
from orbis2.data.probes import (
    IGNORE,
    ProbeFrame,
    cityscapes_frames,
    kitti_eigen_frames,
    split_by_episode,
    town_probe_frames,
)
from orbis2.errors import OrbisError
from orbis2.eval.metrics.probe_heads import (
    ProbeConfig,
    downsample_depth,
    probe_depth,
    probe_segmentation,
    valid_depth,
)
from orbis2.latents import to_model_input
from orbis2.models.files import PredictorFile, TokenizerFile
from orbis2.models.teachers import DinoV2Teacher

FeatureFn = Callable[[torch.Tensor], torch.Tensor]


def frame_labels(frames: Sequence[ProbeFrame]) -> tuple[torch.Tensor, torch.Tensor]:
    """Semantic train ids uint8 [N, H, W] and depth float32 [N, H, W] of a frame list."""
    semantic = torch.from_numpy(np.stack([f.semantic for f in frames]).astype(np.uint8))
    depth = torch.from_numpy(np.stack([f.depth for f in frames]).astype(np.float32))
    return semantic, depth


def probe_on_features(train_features: torch.Tensor, train_frames: Sequence[ProbeFrame],
                      test_features: torch.Tensor, test_frames: Sequence[ProbeFrame],
                      cfg: ProbeConfig) -> dict[str, Any]:
    """Both probes on cached features; a task without labels on either side is reported as ``None``."""
    train_sem, train_depth = frame_labels(train_frames)
    test_sem, test_depth = frame_labels(test_frames)
    has_sem = bool((train_sem != IGNORE).any() and (test_sem != IGNORE).any())
    if has_sem and int(train_sem[train_sem != IGNORE].max()) >= cfg.num_classes:
        raise OrbisError(f"semantic labels reach id {int(train_sem[train_sem != IGNORE].max())} but the probe "
                         f"has {cfg.num_classes} classes; labels must be train ids 0..{cfg.num_classes - 1} or 255")
    grid = (train_features.shape[-2] * cfg.upsample, train_features.shape[-1] * cfg.upsample)
    has_depth = bool(valid_depth(downsample_depth(train_depth, grid), cfg.max_depth).any()
                     and valid_depth(test_depth, cfg.max_depth).any())
    return {
        "features": {"channels": train_features.shape[1], "height": train_features.shape[2],
                     "width": train_features.shape[3]},
        "segmentation": probe_segmentation(train_features, train_sem, test_features, test_sem, cfg)
        if has_sem else None,
        "depth": probe_depth(train_features, train_depth, test_features, test_depth, cfg) if has_depth else None,
    }


def extract_features(feature_fn: FeatureFn, frames: Sequence[ProbeFrame], batch_size: int,
                     desc: str = "probe: features") -> torch.Tensor:
    """Features of every frame once, float32 ``[N, D, h, w]`` on the CPU (the frozen backbone's only pass)."""
    if not frames:
        raise OrbisError("no frames to extract probe features from")
    out = []
    for start in tqdm(range(0, len(frames), batch_size), desc=desc, unit="batch", leave=False):
        images = to_model_input(np.stack([f.image for f in frames[start:start + batch_size]]))
        with torch.inference_mode():
            out.append(feature_fn(images).float().cpu())
    return torch.cat(out)


def run_probe(feature_fn: FeatureFn, train_frames: Sequence[ProbeFrame], test_frames: Sequence[ProbeFrame],
              cfg: ProbeConfig) -> dict[str, Any]:
    """Extract features once, then train and score both probes (see :func:`probe_on_features`)."""
    train_features = extract_features(feature_fn, train_frames, cfg.batch_size, "probe: train features")
    test_features = extract_features(feature_fn, test_frames, cfg.batch_size, "probe: test features")
    return probe_on_features(train_features, train_frames, test_features, test_frames, cfg)


def probe_config(settings: ProbeSettings, device: str) -> ProbeConfig:
    """The probe training settings of ``evaluation.probe`` (which also holds data sources and blocks)."""
    shared = {f.name for f in dataclasses.fields(ProbeConfig)} & {f.name for f in dataclasses.fields(settings)}
    return ProbeConfig(**{name: getattr(settings, name) for name in shared}, device=device)


ProbeSet = tuple[str, list[ProbeFrame], list[ProbeFrame]]


def probe_sets(settings: ProbeSettings, size: tuple[int, int], shards: Path) -> list[ProbeSet]:
    """(name, train frames, test frames) per probe data source, frames at ``size`` (width, height).

    The town's labelled ``probe`` split of ``shards`` (divided by episode) serves both
    tasks unless Cityscapes and/or KITTI are configured, which then take over
    segmentation and/or depth (paper appendix "Linear probing details").
    """
    ps, sets = settings, []
    if ps.cityscapes is not None:
        sets.append(("cityscapes", cityscapes_frames(ps.cityscapes, "train", size, ps.max_frames),
                     cityscapes_frames(ps.cityscapes, "val", size, ps.max_frames)))
    if ps.kitti is not None:
        sets.append(("kitti eigen", kitti_eigen_frames(ps.kitti, ps.kitti_train_split, size, ps.kitti_depth,
                                                       ps.max_frames),
                     kitti_eigen_frames(ps.kitti, ps.kitti_test_split, size, ps.kitti_depth, ps.max_frames)))
    if len(sets) < 2:
        train, test = split_by_episode(town_probe_frames(shards, "probe", size), ps.test_fraction, ps.seed)
        sets.append(("town probe split", train, test))
    return sets


def probe_all(feature_fn: FeatureFn, sets: list[ProbeSet], cfg: ProbeConfig) -> dict[str, Any]:
    """Segmentation from the first source with semantics, depth from the first with depth."""
    out: dict[str, Any] = {"segmentation": None, "depth": None, "data": {}}
    for name, train, test in sets:
        result = run_probe(feature_fn, train, test, cfg)
        for task in ("segmentation", "depth"):
            if out[task] is None and result[task] is not None:
                out[task] = result[task]
                out["data"][task] = name
    return out


# --------------------------------------------------------------------------- feature extractors


def _device(module: nn.Module) -> torch.device:
    return next(module.parameters()).device


def tokenizer_features(tokenizer: TokenizerFile, normalized: bool = False) -> FeatureFn:
    """The tokenizer's latent; ``normalized``: after its normalisation, exactly what the predictors see.

    The tokenizer's own probe reads the raw latent: removing the per-position mean would take
    away the position cue a 1x1 probe has no other way to get.
    """
    model = tokenizer.model.eval()
    device = _device(model)

    def features(images: torch.Tensor) -> torch.Tensor:
        with torch.inference_mode():
            z = model.encode(images.to(device))
            return tokenizer.normalize(z) if normalized else z

    return features


def teacher_features(teacher: nn.Module, size: tuple[int, int] | None = None) -> FeatureFn:
    """A frozen teacher's patch features; images resized to ``size=(H, W)`` first when given.

    DINOv2 needs sides that are multiples of its patch: without ``size`` they are rounded
    to the nearest multiple (the Inception teacher takes any size).
    """
    device = _device(teacher)
    patch = teacher.vit.patch_size if isinstance(teacher, DinoV2Teacher) else None

    def features(images: torch.Tensor) -> torch.Tensor:
        h, w = images.shape[-2:]
        target = size
        if target is None and patch is not None:
            target = (max(patch, round(h / patch) * patch), max(patch, round(w / patch) * patch))
        if target is not None and tuple(target) != (h, w):
            images = F.interpolate(images, size=tuple(target), mode="bilinear", align_corners=False, antialias=True)
        with torch.inference_mode():
            return teacher(images.to(device))

    return features


def predictor_features(predictor: PredictorFile, tokenizer: TokenizerFile, block: int,
                       slots: int | None = None) -> FeatureFn:
    """Token features after block ``block`` from the end, under the appendix's null-context protocol.

    No context frames: the scaled latent of the image fills ``slots`` predicted-frame
    slots (default: all of them, window - context of the predictor's level; 1 gives the
    depth protocol's "sole target frame"), every slot at tau = 0, the clean end of the
    flow (the image is given, nothing is left to denoise), at the predictor's frame rate.
    A detail predictor gets zero abstract latents and an all-False mask, i.e. no
    conditioning. The last slot's features are returned, ``[B, D, h, w]``.
    """
    meta, model = predictor.meta, predictor.model.eval()
    level = meta.get("level")
    if level not in ("detail", "abstract"):
        raise OrbisError(f"predictor meta has level {level!r}; expected 'detail' or 'abstract' "
                         f"(a file written by a predictor training stage)")
    if tokenizer.kind != level:
        raise OrbisError(f"a {level} predictor reads {level} latents but the tokenizer given is the {tokenizer.kind} "
                         f"one; pass the {level} tokenizer")
    expected = meta.get("tokenizers", {}).get(level, {}).get("checksum")
    if expected is not None and expected != tokenizer.checksum:
        raise OrbisError(f"the predictor was trained on latents of the {level} tokenizer with sha256 {expected[:12]}, "
                         f"the one given has {tokenizer.checksum[:12]}; pass the tokenizer it was trained with")
    window = meta["window"]
    predicted = window["window"] - window["context"]
    slots = predicted if slots is None else slots
    if not 1 <= slots <= predicted:
        raise OrbisError(f"slots = {slots}; the {level} predictor has {predicted} predicted-frame slots")
    frame_rate, device = float(meta["frame_rate"]), _device(model)
    abstract_channels = predictor.build.get("abstract_channels")
    encode = tokenizer_features(tokenizer, normalized=True)

    def features(images: torch.Tensor) -> torch.Tensor:
        z = encode(images).to(device)
        b = z.shape[0]
        x = z[:, None].expand(b, slots, *z.shape[1:])
        tau = torch.zeros(b, slots, device=device)
        cond_frames = cond_mask = None
        if abstract_channels is not None:
            cond_frames = torch.zeros(b, slots, abstract_channels, *z.shape[-2:], device=device)
            cond_mask = torch.zeros(b, slots, dtype=torch.bool, device=device)
        with torch.inference_mode():
            out = model(x, tau, frame_rate=frame_rate, cond_frames=cond_frames, cond_mask=cond_mask,
                        features_from_block=block)
        return out[:, -1]

    return features
