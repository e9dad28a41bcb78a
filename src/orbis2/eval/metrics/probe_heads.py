"""Linear probe heads and their measures: semantic segmentation (mIoU) and binned depth (RMSE).

The heads and training of the paper's appendix "Linear probing details" (applied to a model's
features by :mod:`orbis2.eval.protocols.probe`):

- the head is one 1x1 convolution followed by bilinear upsampling. Both are linear
  and bilinear weights sum to one, so "upsample, then conv" (the paper's depth head)
  and "conv, then upsample" are the same map; the cheaper order is used. With
  ``standardize`` the features are first shifted and scaled per channel by fixed
  statistics of the training features: an affine map folded in front of the conv,
  so the probe stays linear, but AdamW no longer sees channels of wildly different scale;
- segmentation: logits upsampled bilinearly to the label resolution (paper), cross-entropy
  with ignore index 255, mIoU from a confusion matrix accumulated over the held-out frames,
  averaged over the classes whose union is non-empty (present in the labels or predicted);
- depth (DINOv2 "Lin-1"): 256 uniform bins over [0, 80] m; logits upsampled ``upsample``
  times (4, paper); the depth is the softmax-weighted sum of the bin centres. Training compares
  these logits with the depth downsampled (nearest) to the same grid: cross-entropy against the
  bin holding the true depth. Valid pixels are finite with 0 < d <= 80 m; farther ones (and
  the town's sky, +inf) are out of range and excluded, as the paper excludes missing and
  out-of-range pixels, rather than clamped into the last bin. RMSE: the predicted depth map
  upsampled bilinearly to the label resolution, RMSE over each held-out frame's valid pixels,
  averaged over frames (the KITTI convention);
- AdamW (lr 1e-3, weight decay 1e-4); 100 epochs for segmentation and 10 for depth (paper).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from tqdm import tqdm

from orbis2.data.probes import IGNORE, NUM_CLASSES
from orbis2.errors import OrbisError


@dataclass(frozen=True)
class ProbeConfig:
    """Probe training settings; defaults are the paper's."""

    seg_epochs: int = 100
    depth_epochs: int = 10
    batch_size: int = 8
    lr: float = 1e-3
    weight_decay: float = 1e-4
    seed: int = 0
    num_classes: int = NUM_CLASSES
    depth_bins: int = 256
    max_depth: float = 80.0
    upsample: int = 4
    standardize: bool = True
    device: str = "cpu"

    def __post_init__(self) -> None:
        for name in ("seg_epochs", "depth_epochs", "batch_size", "num_classes", "depth_bins", "upsample"):
            if getattr(self, name) < 1:
                raise OrbisError(f"probe.{name} must be >= 1, got {getattr(self, name)}")
        if not self.max_depth > 0:
            raise OrbisError(f"probe.max_depth must be > 0, got {self.max_depth}")


# --------------------------------------------------------------------------- depth bins


def bin_centres(bins: int, max_depth: float) -> torch.Tensor:
    """Centres of ``bins`` uniform bins over [0, max_depth] metres."""
    return (torch.arange(bins, dtype=torch.float32) + 0.5) * (max_depth / bins)


def valid_depth(depth: torch.Tensor, max_depth: float) -> torch.Tensor:
    """Pixels with a usable ground truth: finite and 0 < d <= max_depth (0 and NaN mark missing values)."""
    return torch.isfinite(depth) & (depth > 0) & (depth <= max_depth)


def depth_to_bin(depth: torch.Tensor, bins: int, max_depth: float) -> torch.Tensor:
    """Index of the bin holding each depth (invalid pixels map to bin 0; mask them with :func:`valid_depth`)."""
    scaled = torch.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0) * (bins / max_depth)
    return scaled.floor().long().clamp(0, bins - 1)


def decode_depth(logits: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    """Bin logits ``[B, K, h, w]`` -> depth ``[B, h, w]``: the softmax-weighted sum of the bin centres."""
    return torch.einsum("bkhw,k->bhw", logits.float().softmax(dim=1), centres.to(logits.device))


def binned_depth_loss(logits: torch.Tensor, depth: torch.Tensor, max_depth: float,
                      reduction: str = "mean") -> torch.Tensor:
    """Cross-entropy of bin logits ``[B, K, h, w]`` against the true depth's bin, on valid pixels only."""
    valid = valid_depth(depth, max_depth)
    target = depth_to_bin(depth, logits.shape[1], max_depth).masked_fill(~valid, -100)
    if reduction == "mean" and not valid.any():
        return logits.sum() * 0.0  # nothing to learn from in this batch; keeps the graph intact
    return F.cross_entropy(logits.float(), target, ignore_index=-100, reduction=reduction)


def depth_rmse(predicted: torch.Tensor, depth: torch.Tensor, max_depth: float) -> torch.Tensor:
    """RMSE per frame ``[B]`` over its valid pixels (NaN for a frame without any)."""
    valid = valid_depth(depth, max_depth)
    error = (predicted.float() - torch.nan_to_num(depth.float())).masked_fill(~valid, 0.0)
    return (error.square().sum(dim=(1, 2)) / valid.sum(dim=(1, 2))).sqrt()


# --------------------------------------------------------------------------- segmentation


def segmentation_loss(logits: torch.Tensor, labels: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """Cross-entropy of class logits ``[B, K, H, W]`` against train ids, 255 ignored."""
    labels = labels.long()
    if reduction == "mean" and not (labels != IGNORE).any():
        return logits.sum() * 0.0
    return F.cross_entropy(logits.float(), labels, ignore_index=IGNORE, reduction=reduction)


def confusion_matrix(predicted: torch.Tensor, labels: torch.Tensor, num_classes: int) -> torch.Tensor:
    """Counts ``[K, K]`` (row: true class, column: predicted), ignored pixels left out."""
    labels = labels.long().flatten()
    keep = labels != IGNORE
    index = labels[keep] * num_classes + predicted.long().flatten()[keep]
    return torch.bincount(index.cpu(), minlength=num_classes**2).reshape(num_classes, num_classes)


def iou_per_class(confusion: torch.Tensor) -> dict[int, float]:
    """IoU of every class whose union is non-empty; classes neither labelled nor predicted are left out."""
    confusion = confusion.double()
    hits = confusion.diag()
    union = confusion.sum(dim=0) + confusion.sum(dim=1) - hits
    return {int(c): float(hits[c] / union[c]) for c in torch.nonzero(union > 0).flatten()}


def mean_iou(confusion: torch.Tensor) -> float:
    """Mean of :func:`iou_per_class` (NaN if no class occurs at all)."""
    ious = iou_per_class(confusion)
    return float(np.mean(list(ious.values()))) if ious else float("nan")


# --------------------------------------------------------------------------- head and training


class LinearProbeHead(nn.Module):
    """Fixed per-channel standardisation, a 1x1 conv, bilinear upsampling to the requested size."""

    def __init__(self, channels: int, outputs: int, mean: torch.Tensor, std: torch.Tensor):
        super().__init__()
        self.register_buffer("mean", mean.reshape(1, channels, 1, 1).float())
        self.register_buffer("std", std.reshape(1, channels, 1, 1).float())
        self.conv = nn.Conv2d(channels, outputs, 1)

    def forward(self, features: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        logits = self.conv((features.float() - self.mean) / self.std)
        if tuple(logits.shape[-2:]) == tuple(size):
            return logits
        return F.interpolate(logits, size=size, mode="bilinear", align_corners=False)


def _new_head(features: torch.Tensor, outputs: int, cfg: ProbeConfig) -> LinearProbeHead:
    channels = features.shape[1]
    if cfg.standardize:
        mean = features.mean(dim=(0, 2, 3))
        std = features.std(dim=(0, 2, 3)).clamp_min(1e-6)
    else:
        mean, std = torch.zeros(channels), torch.ones(channels)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        head = LinearProbeHead(channels, outputs, mean, std)
    return head.to(cfg.device)


def train_head(features: torch.Tensor, targets: torch.Tensor, outputs: int, size: tuple[int, int],
               loss_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], epochs: int, cfg: ProbeConfig,
               desc: str = "probe") -> LinearProbeHead:
    """Fit a head on cached ``features`` [N, D, h, w] to ``targets`` [N, *size]; batches drawn with ``cfg.seed``."""
    head = _new_head(features, outputs, cfg)
    optimizer = torch.optim.AdamW(head.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    generator = torch.Generator().manual_seed(cfg.seed)
    n = len(features)
    for _ in tqdm(range(epochs), desc=desc, unit="epoch", leave=False):
        for batch in torch.randperm(n, generator=generator).split(cfg.batch_size):
            logits = head(features[batch].to(cfg.device), size)
            loss = loss_fn(logits, targets[batch].to(cfg.device))
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
    return head.eval()


def _batches(n: int, batch_size: int) -> list[torch.Tensor]:
    return list(torch.arange(n).split(batch_size))


def downsample_depth(depth: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Nearest-neighbour resampling of depth maps [N, H, W] (never blends a near and a far pixel)."""
    return F.interpolate(depth[:, None].float(), size=size, mode="nearest")[:, 0]


def probe_segmentation(train_features: torch.Tensor, train_labels: torch.Tensor, test_features: torch.Tensor,
                       test_labels: torch.Tensor, cfg: ProbeConfig) -> dict[str, Any]:
    """Train the segmentation head and score it: mIoU, per-class IoU, held-out loss."""
    size = tuple(train_labels.shape[-2:])
    head = train_head(train_features, train_labels, cfg.num_classes, size, segmentation_loss, cfg.seg_epochs, cfg,
                      "probe: segmentation")
    confusion = torch.zeros(cfg.num_classes, cfg.num_classes, dtype=torch.long)
    loss_sum, count = 0.0, 0
    with torch.inference_mode():
        for batch in _batches(len(test_features), cfg.batch_size):
            labels = test_labels[batch].to(cfg.device)
            logits = head(test_features[batch].to(cfg.device), tuple(labels.shape[-2:]))
            loss_sum += float(segmentation_loss(logits, labels, reduction="sum"))
            count += int((labels != IGNORE).sum())
            confusion += confusion_matrix(logits.argmax(dim=1), labels, cfg.num_classes)
    ious = iou_per_class(confusion)
    return {"miou": mean_iou(confusion), "iou": {str(c): v for c, v in ious.items()}, "classes": sorted(ious),
            "val_loss": loss_sum / count, "train_frames": len(train_features), "test_frames": len(test_features),
            "epochs": cfg.seg_epochs}


def probe_depth(train_features: torch.Tensor, train_depth: torch.Tensor, test_features: torch.Tensor,
                test_depth: torch.Tensor, cfg: ProbeConfig) -> dict[str, Any]:
    """Train the binned depth head and score it: RMSE (m) at the label resolution, held-out binned loss."""
    h, w = train_features.shape[-2:]
    grid = (h * cfg.upsample, w * cfg.upsample)
    centres = bin_centres(cfg.depth_bins, cfg.max_depth).to(cfg.device)

    def loss_fn(logits: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        return binned_depth_loss(logits, depth, cfg.max_depth)

    head = train_head(train_features, downsample_depth(train_depth, grid), cfg.depth_bins, grid, loss_fn,
                      cfg.depth_epochs, cfg, "probe: depth")
    rmse, loss_sum, count = [], 0.0, 0
    with torch.inference_mode():
        for batch in _batches(len(test_features), cfg.batch_size):
            depth = test_depth[batch].to(cfg.device)
            logits = head(test_features[batch].to(cfg.device), grid)
            coarse = downsample_depth(depth, grid)
            loss_sum += float(binned_depth_loss(logits, coarse, cfg.max_depth, reduction="sum"))
            count += int(valid_depth(coarse, cfg.max_depth).sum())
            predicted = F.interpolate(decode_depth(logits, centres)[:, None], size=tuple(depth.shape[-2:]),
                                      mode="bilinear", align_corners=False)[:, 0]
            rmse.append(depth_rmse(predicted, depth, cfg.max_depth).cpu())
    per_frame = torch.cat(rmse)
    scored = per_frame[torch.isfinite(per_frame)]
    return {"rmse": float(scored.mean()), "val_loss": loss_sum / count if count else float("nan"),
            "train_frames": len(train_features), "test_frames": len(test_features),
            "scored_frames": len(scored), "epochs": cfg.depth_epochs}
