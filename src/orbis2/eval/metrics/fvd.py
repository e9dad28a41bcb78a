"""Frechet Video Distance (FVD), chunked FVD and FVD-slope (paper section 4.3).

Features are the Kinetics-400 logits of Inception-I3D (``orbis2.models.i3d``),
as in the reference TF implementation (google-research
``frechet_video_distance``) and in StyleGAN-V's PyTorch one. Preprocessing
follows them too: every frame is resized to 224x224 with plain bilinear
interpolation (no crop, no antialiasing, aspect ratio not kept), then scaled
to [-1, 1]. The one difference left is the one StyleGAN-V also has: TF1's
``resize_bilinear`` samples without the half-pixel offset that PyTorch's
``interpolate(align_corners=False)`` uses.

Clips have 16 frames, the length StyleGAN-V evaluates. A longer video or
chunk window is reduced to 16 evenly spaced frames (``even_frame_indices``),
so a clip spans its whole window at any frame rate: degradation late in a
window counts in that window. The paper does not say how its chunks are fed
to I3D; real and generated videos always go through the same selection.
"""

from __future__ import annotations

import hashlib
import os
import re
import tempfile
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from threadpoolctl import ThreadpoolController
from torch import nn

from orbis2.models import i3d as i3d_network
from orbis2.sources import source_digest

CLIP_FRAMES = 16
I3D_SIZE = 224

# [N, T, H, W, 3] RGB, numpy or torch: uint8 in 0..255, or float in [-1, 1] (the project's image range).
Videos = np.ndarray | torch.Tensor


@cache
def _threadpools() -> ThreadpoolController:
    """The process's thread pools, found once: finding them walks every loaded library (a few ms in a stage
    process), and a clip bootstrap computes hundreds of distances."""
    return ThreadpoolController()


def _one_blas_thread() -> AbstractContextManager:
    """BLAS on one thread: the distances' float sums then do not depend on the machine's core count."""
    return _threadpools().limit(limits=1, user_api="blas")


def _check_covariance(name: str, sigma: np.ndarray, dim: int) -> None:
    if sigma.shape != (dim, dim):
        raise ValueError(f"{name} has shape {sigma.shape}, expected {(dim, dim)}")
    if not np.all(np.isfinite(sigma)):
        raise ValueError(f"{name} has non-finite entries")
    if np.abs(sigma - sigma.T).max() > 1e-8 * max(np.abs(sigma).max(), 1e-300):
        raise ValueError(f"{name} is not symmetric, so it is not a covariance matrix")


def _drop_round_off(eigval: np.ndarray) -> np.ndarray:
    """Zero the eigenvalues of a PSD matrix that are round-off, not signal: below size * eps * largest.

    That is numpy's ``matrix_rank`` tolerance. Without it the square roots of the
    ~eps-sized eigenvalues of a rank-deficient covariance add up to a visible error
    (about 1e-3 on an FVD of 100 from 12 videos).
    """
    floor = eigval.size * np.finfo(np.float64).eps * max(float(eigval.max()), 0.0)
    return np.where(eigval > floor, eigval, 0.0)


def frechet_distance(mu1, sigma1, mu2, sigma2) -> float:
    """Frechet distance between N(mu1, sigma1) and N(mu2, sigma2), computed in float64.

    d = |mu1 - mu2|^2 + tr(sigma1) + tr(sigma2) - 2 tr((sigma1 sigma2)^(1/2)). The last
    trace is taken in its symmetric form tr((A sigma2 A)^(1/2)) with A = sigma1^(1/2):
    A sigma2 A is symmetric positive semi-definite, so ``eigh`` gives real eigenvalues
    and no complex matrix square root is needed (unlike ``scipy.linalg.sqrtm`` on the
    non-symmetric product, with its eps-offset retry and imaginary-part check).
    Eigenvalues at round-off level are set to zero, which keeps rank-deficient
    covariances (fewer videos than feature dimensions) exact.

    BLAS runs single-threaded here: next to PyTorch's OpenMP threads a multi-threaded
    OpenBLAS stalls (seconds instead of milliseconds per 400x400 decomposition).
    """
    mu1 = np.asarray(mu1, dtype=np.float64).reshape(-1)
    mu2 = np.asarray(mu2, dtype=np.float64).reshape(-1)
    sigma1 = np.atleast_2d(np.asarray(sigma1, dtype=np.float64))
    sigma2 = np.atleast_2d(np.asarray(sigma2, dtype=np.float64))
    dim = mu1.shape[0]
    if mu2.shape != (dim,):
        raise ValueError(f"mu1 and mu2 differ in length: {dim} vs {mu2.shape[0]}")
    if not (np.all(np.isfinite(mu1)) and np.all(np.isfinite(mu2))):
        raise ValueError("the means have non-finite entries")
    _check_covariance("sigma1", sigma1, dim)
    _check_covariance("sigma2", sigma2, dim)

    with _one_blas_thread():
        eigval, eigvec = np.linalg.eigh(sigma1)
        root1 = (eigvec * np.sqrt(_drop_round_off(eigval))) @ eigvec.T
        inner = root1 @ sigma2 @ root1
        trace_sqrt = np.sqrt(_drop_round_off(np.linalg.eigvalsh((inner + inner.T) / 2.0))).sum()
    diff = mu1 - mu2
    return float(diff @ diff + np.trace(sigma1) + np.trace(sigma2) - 2.0 * trace_sqrt)


def frechet_distance_of_rows(mu1, rows1, mu2, rows2) -> float:
    """The Frechet distance with each covariance given by rows: sigma = rows.T @ rows.

    The same number as :func:`frechet_distance` (float64), in O(n^2 d) instead of
    O(d^3) when each set has n < d rows: the non-zero eigenvalues of
    sigma1 sigma2 = R1^T R1 R2^T R2 are those of M M^T with M = R1 R2^T [n1, n2],
    so tr((sigma1^(1/2) sigma2 sigma1^(1/2))^(1/2)) is the sum of M's singular
    values (its nuclear norm), and tr(sigma) = |rows|^2. At 64 videos and 400
    I3D features that is a 64 x 64 SVD instead of two 400 x 400 eigendecompositions,
    which makes a clip bootstrap of a few hundred resamples cheap.
    """
    mu1 = np.asarray(mu1, dtype=np.float64).reshape(-1)
    mu2 = np.asarray(mu2, dtype=np.float64).reshape(-1)
    rows1, rows2 = np.atleast_2d(np.asarray(rows1, np.float64)), np.atleast_2d(np.asarray(rows2, np.float64))
    dim = mu1.shape[0]
    if mu2.shape != (dim,) or rows1.shape[1] != dim or rows2.shape[1] != dim:
        raise ValueError(f"means and rows differ in dimension: {mu1.shape}, {mu2.shape}, {rows1.shape}, "
                         f"{rows2.shape}")
    if not all(np.all(np.isfinite(x)) for x in (mu1, mu2, rows1, rows2)):
        raise ValueError("the means or covariance rows have non-finite entries")
    with _one_blas_thread():
        trace_sqrt = np.linalg.svd(rows1 @ rows2.T, compute_uv=False).sum()
    diff = mu1 - mu2
    return float(diff @ diff + np.sum(rows1 * rows1) + np.sum(rows2 * rows2) - 2.0 * trace_sqrt)


@contextmanager
def _full_fp32() -> Iterator[None]:
    """Keep cuDNN convolutions in IEEE float32 (PyTorch allows TF32 by default) so GPU features match CPU ones."""
    conv = torch.backends.cudnn.conv
    previous = conv.fp32_precision
    conv.fp32_precision = "ieee"
    try:
        yield
    finally:
        conv.fp32_precision = previous


def _to_i3d_input(clips: torch.Tensor) -> torch.Tensor:
    """[B, T, H, W, 3] uint8 or float in [-1, 1] -> [B, 3, T, 224, 224] float in [-1, 1]: resize, then scale."""
    b, t, h, w, _ = clips.shape
    if clips.is_floating_point():
        low, high = clips.min().item(), clips.max().item()
        if low < -1.001 or high > 1.001:  # the reference asserts the same slack
            raise ValueError(
                f"float videos must lie in [-1, 1], got values in [{low:.3g}, {high:.3g}]; pass uint8 for 0..255"
            )
    elif clips.dtype != torch.uint8:
        raise TypeError(f"videos must be uint8 (0..255) or float ([-1, 1]), got {clips.dtype}")
    x = clips.float().reshape(b * t, h, w, 3).permute(0, 3, 1, 2)
    if (h, w) != (I3D_SIZE, I3D_SIZE):
        x = F.interpolate(x, size=(I3D_SIZE, I3D_SIZE), mode="bilinear", align_corners=False)
    if not clips.is_floating_point():
        x = x / 127.5 - 1.0
    x = x.reshape(b, t, 3, I3D_SIZE, I3D_SIZE).permute(0, 2, 1, 3, 4)
    return x.contiguous(memory_format=torch.channels_last_3d)


def i3d_features(videos: Videos, model: nn.Module, batch_size: int = 8, device=None) -> np.ndarray:
    """I3D logits [N, 400] (float64) of N clips [N, 16, H, W, 3] (uint8 0..255, or float in [-1, 1]).

    Clips must have exactly 16 frames: which frames stand for a longer video is the
    caller's choice (``even_frame_indices``), never a silent cut. ``model`` is moved to
    ``device`` (default: where it already is) in channels-last layout, which runs its
    Conv3d layers about 1.5x faster on CPU.
    """
    if videos.ndim != 5 or videos.shape[-1] != 3 or videos.shape[0] == 0:
        raise ValueError(f"videos must be a non-empty [N, T, H, W, 3] array, got shape {tuple(videos.shape)}")
    if videos.shape[1] != CLIP_FRAMES:
        raise ValueError(
            f"I3D features take clips of {CLIP_FRAMES} frames, got {videos.shape[1]}; "
            "select frames first (even_frame_indices) or use clip_stats"
        )
    device = torch.device(device) if device is not None else next(model.parameters()).device
    model.to(device=device, memory_format=torch.channels_last_3d)
    features = []
    with torch.inference_mode(), _full_fp32():
        for start in range(0, videos.shape[0], batch_size):
            batch = videos[start : start + batch_size]
            batch = batch.detach() if isinstance(batch, torch.Tensor) else torch.from_numpy(np.array(batch))
            features.append(model(_to_i3d_input(batch.to(device))).double().cpu())
    return torch.cat(features).numpy()


@dataclass(frozen=True)
class FeatureStats:
    """Mean and covariance of a set's features: all FVD needs of a set, and what is cached for real data."""

    mean: np.ndarray  # [D], float64
    cov: np.ndarray  # [D, D], float64, unbiased (divides by n - 1) as in the reference implementations
    n: int

    @classmethod
    def from_features(cls, features) -> FeatureStats:
        features = np.asarray(features, dtype=np.float64)
        if features.ndim != 2 or features.shape[0] < 2:
            raise ValueError(f"need features [N >= 2, D] for a covariance, got shape {features.shape}")
        if not np.all(np.isfinite(features)):
            raise ValueError("features have non-finite entries")
        return cls(features.mean(axis=0), np.cov(features, rowvar=False), features.shape[0])

    def save(self, path: str | Path, key: str = "") -> None:
        """Write an npz atomically (nothing half-written on failure), recording ``key`` for cache checks."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}-", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, mean=self.mean, cov=self.cov, n=np.int64(self.n), key=np.array(key))
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    @classmethod
    def load(cls, path: str | Path, key: str | None = None) -> FeatureStats:
        """Read a file written by :meth:`save`; given ``key``, refuse a file saved under another key."""
        with np.load(path, allow_pickle=False) as data:
            stored = str(data["key"])
            if key is not None and stored != key:
                raise ValueError(f"{path} holds statistics for key {stored!r}, not {key!r}")
            return cls(data["mean"], data["cov"], int(data["n"]))


def cached_stats(folder: str | Path, key: str, compute: Callable[[], FeatureStats]) -> FeatureStats:
    """The statistics saved under ``key`` in ``folder``, or ``compute()`` saved there first.

    The pipeline keys real-data statistics by the hashes of the shards they come from,
    so they are recomputed exactly when the data changes. The file name is a readable
    prefix of the key plus a hash of all of it; the key is stored and checked on load.
    """
    readable = re.sub(r"[^A-Za-z0-9_-]+", "_", key)[:48]
    path = Path(folder) / f"i3d-{readable}-{hashlib.sha256(key.encode()).hexdigest()[:16]}.npz"
    if path.is_file():
        return FeatureStats.load(path, key)
    stats = compute()
    stats.save(path, key)
    return stats


def even_frame_indices(n_frames: int, k: int = CLIP_FRAMES) -> list[int]:
    """``k`` indices spread evenly over ``n_frames``, both ends included: round(i (n - 1) / (k - 1)), half up.

    A 4-s window at 10 Hz (40 frames) gives 0, 3, 5, 8, 10, 13, 16, 18, 21, 23, 26, 29, 31, 34, 36, 39.
    """
    if k < 2 or n_frames < k:
        raise ValueError(f"cannot pick {k} distinct frames out of {n_frames}")
    return [(2 * i * (n_frames - 1) + k - 1) // (2 * (k - 1)) for i in range(k)]


def clip_features(videos: Videos, model: nn.Module, batch_size: int = 8, device=None) -> np.ndarray:
    """I3D features [N, 400] of videos [N, T >= 16, H, W, 3], each reduced to its 16 evenly spaced frames.

    Per-video rows (not only their statistics) are what a clip-level bootstrap resamples.
    """
    frames = even_frame_indices(videos.shape[1])
    return np.concatenate([
        i3d_features(videos[start : start + batch_size][:, frames], model, batch_size, device)
        for start in range(0, videos.shape[0], batch_size)
    ])  # frame selection per batch, so a large uint8 set is never copied whole


def clip_stats(videos: Videos, model: nn.Module, batch_size: int = 8, device=None) -> FeatureStats:
    """Feature statistics of videos [N, T >= 16, H, W, 3], each reduced to its 16 evenly spaced frames."""
    return FeatureStats.from_features(clip_features(videos, model, batch_size, device))


@cache
def i3d_code() -> str:
    """Digest of the code I3D features come from (the network's module and this one, which prepares its input),
    as :func:`orbis2.sources.source_digest` reads it: what a feature cache is keyed by besides the weights, so
    that features computed by other arithmetic are never reused."""
    return source_digest([Path(i3d_network.__file__), Path(__file__)])


def cached_features(folder: str | Path, key: str, compute: Callable[[], np.ndarray]) -> np.ndarray:
    """Per-video features saved under ``key`` in ``folder`` (checked on load), or ``compute()`` saved first."""
    readable = re.sub(r"[^A-Za-z0-9_-]+", "_", key)[:48]
    path = Path(folder) / f"i3d-rows-{readable}-{hashlib.sha256(key.encode()).hexdigest()[:16]}.npz"
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) == key:
                return data["features"]
    features = np.asarray(compute(), np.float64)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}-", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, features=features, key=np.array(key))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return features


def fvd(real, fake) -> float:
    """FVD between two sets, each given as I3D features [N, 400] or as their FeatureStats."""
    real, fake = (x if isinstance(x, FeatureStats) else FeatureStats.from_features(x) for x in (real, fake))
    return frechet_distance(real.mean, real.cov, fake.mean, fake.cov)


@dataclass(frozen=True)
class FVDResult:
    """One FVD figure with what it was measured on, so a reported number can be reproduced."""

    value: float
    n_videos: int  # generated videos (the real side's count is its FeatureStats.n)
    frames: int  # frames per clip given to I3D
    resolution: tuple[int, int]  # (H, W) of the generated videos, before the resize to 224x224
    seed: int | None  # seed of the run that generated them


def video_fvd(
    real: Videos | FeatureStats,
    fake: Videos,
    model: nn.Module,
    *,
    seed: int | None = None,
    batch_size: int = 8,
    device=None,
) -> FVDResult:
    """FVD of generated videos [N, T, H, W, 3] against real ones (videos, or their cached ``clip_stats``)."""
    real_stats = real if isinstance(real, FeatureStats) else clip_stats(real, model, batch_size, device)
    value = fvd(real_stats, clip_stats(fake, model, batch_size, device))
    return FVDResult(value, int(fake.shape[0]), CLIP_FRAMES, (int(fake.shape[2]), int(fake.shape[3])), seed)


def chunk_windows(n_frames: int, fps: float, chunk_seconds: float = 4.0) -> list[slice]:
    """Consecutive non-overlapping windows of ``chunk_seconds``: frames [0, w), [w, 2w), ... with w = seconds * fps.

    w must be a whole number of frames, and at least 16 so a window yields 16 distinct
    frames. A trailing partial window is dropped: its FVD would cover a shorter span.
    """
    exact = chunk_seconds * fps
    width = round(exact)
    if abs(exact - width) > 1e-6 * max(exact, 1.0):
        raise ValueError(f"{chunk_seconds} s at {fps} fps is {exact:g} frames; chunks need a whole number of frames")
    if width < CLIP_FRAMES:
        raise ValueError(
            f"a {chunk_seconds} s chunk at {fps} fps has {width} frames, fewer than the {CLIP_FRAMES} I3D needs"
        )
    if n_frames < width:
        raise ValueError(f"videos of {n_frames} frames are shorter than one {chunk_seconds} s chunk ({width} frames)")
    return [slice(i * width, (i + 1) * width) for i in range(n_frames // width)]


def chunked_fvd(
    real: Videos | Sequence[FeatureStats],
    fake: Videos,
    fps: float,
    model: nn.Module,
    chunk_seconds: float = 4.0,
    *,
    seed: int | None = None,
    batch_size: int = 8,
    device=None,
) -> list[FVDResult]:
    """FVD of each consecutive ``chunk_seconds`` window of the rollouts (chunked FVD), first window first.

    ``fake`` holds generated frames only (no context frames), [N, T, H, W, 3]; window t
    covers seconds [t, t + 1) * chunk_seconds of it. ``real`` is the ground truth of the
    same length, or the cached ``clip_stats`` of its windows, one per window.
    """
    windows = chunk_windows(fake.shape[1], fps, chunk_seconds)
    if isinstance(real, (np.ndarray, torch.Tensor)):
        if real.shape[1] != fake.shape[1]:
            raise ValueError(f"real videos have {real.shape[1]} frames, generated ones {fake.shape[1]}")
        real = [real[:, window] for window in windows]
    elif len(real) != len(windows):
        raise ValueError(f"got real statistics for {len(real)} chunks, but the videos have {len(windows)}")
    return [
        video_fvd(reference, fake[:, window], model, seed=seed, batch_size=batch_size, device=device)
        for reference, window in zip(real, windows)
    ]


def fvd_slope(values: Sequence[float]) -> float:
    """FVD-slope = (FVD_T - FVD_1) / (T - 1) over the T >= 2 chunk values: the mean rise of FVD per chunk."""
    if len(values) < 2:
        raise ValueError(f"FVD-slope needs at least 2 chunks, got {len(values)}")
    return (float(values[-1]) - float(values[0])) / (len(values) - 1)
