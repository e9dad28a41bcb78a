"""Training the two tokenizers (paper Sec. 3.2, App. "Tokenizer") with the shared loop.

- :class:`DetailTokenizerTask`: the VQGAN objective. L1 reconstruction (plus pixel MSE with
  ``mse_weight``, not the paper's), codebook and commitment losses, the decaying entropy penalty,
  and from ``disc_start`` a PatchGAN hinge loss with the adaptive weight of taming. The tokenizer and its
  discriminator form one module, so one checkpoint holds both.
- :class:`AbstractTokenizerTask`: the encoder's latent, through the projection
  head P, predicts a frozen teacher's patch features (paper eq. 3), with a weak
  L1 reconstruction through the light decoder D_H (``rec_weight``).

Images are float ``[B, 3, H, W]`` in [-1, 1] everywhere. :func:`image_batches`
streams them from the train shards, deterministically and resumably;
:func:`train_detail_tokenizer` and :func:`train_abstract_tokenizer` run a whole
stage: train, then measure the latent scale (and the reconstruction FID) and
write ``tokenizer.pt`` for the later stages.
"""

from __future__ import annotations

import itertools
import math
import sys
import warnings
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import cv2
import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn
from tqdm import tqdm

from orbis2.assets import TEACHER_ASSETS, asset_path
from orbis2.config.params import PipelineConfig
from orbis2.config.training import AbstractTokenizerConfig, DetailTokenizerConfig
from orbis2.data.images import to_uint8
from orbis2.data.shards import Clip, FrameDataset, load_manifest
from orbis2.errors import OrbisError
from orbis2.eval.metrics.fvd import FeatureStats, frechet_distance
from orbis2.io import atomic_file
from orbis2.losses import (
    adaptive_gan_weight,
    entropy_weight,
    generator_gan_loss,
    hinge_d_loss,
    l1_reconstruction,
    mse_reconstruction,
    psnr,
    ssim,
    teacher_alignment_loss,
)
from orbis2.models import full_build
from orbis2.models.discriminator import build_discriminator
from orbis2.models.files import save_tokenizer
from orbis2.models.sizes import TOKENIZER_PRESETS
from orbis2.models.teachers import build_teacher
from orbis2.models.tokenizer import build_abstract_tokenizer, build_detail_tokenizer, codebook_usage, load_mae_encoder
from orbis2.train import DataSpec, Update, load_weights, train, unwrap

# Frames of one clip arrive together; a buffer spanning many clips mixes them into batches.
SHUFFLE_BUFFER = 256
# Columns of the sample grids (originals above reconstructions).
GRID_IMAGES = 6
# The FID network (TF InceptionV3 of the original FID) takes 299x299 inputs.
FID_SIZE = 299
DINOV2_PATCH = 14


# --------------------------------------------------------------------------- frames


class _LazyClip(Clip):
    """A clip whose ``frames`` hands out ``(clip, index)`` references instead of pixels.

    :class:`FrameDataset` picks the frames; through this clip its picks can be
    shuffled and skipped (on resume) without decoding a single JPEG.
    """

    def frames(self, indices: Sequence[int]) -> list[tuple[Clip, int]]:
        return [(self, int(i)) for i in indices]


class _FrameRefs(FrameDataset):
    """:class:`FrameDataset` yielding frame references (see :class:`_LazyClip`)."""

    def clips(self) -> Iterator[Clip]:
        for clip in super().clips():
            yield _LazyClip(**vars(clip))


def _decode(refs: Sequence[tuple[Clip, int]]) -> np.ndarray:
    """RGB uint8 ``[B, H, W, 3]`` of frame references."""
    return np.stack([Clip.frames(clip, [index])[0] for clip, index in refs])


def to_images(frames: np.ndarray | torch.Tensor) -> torch.Tensor:
    """RGB uint8 ``[B, H, W, 3]`` -> float ``[B, 3, H, W]`` in [-1, 1]."""
    frames = torch.as_tensor(frames)
    return frames.permute(0, 3, 1, 2).float().div(127.5).sub(1.0).contiguous()


def _shuffled(items: Iterable[Any], rng: np.random.Generator, size: int) -> Iterator[Any]:
    """A shuffle buffer: each new item replaces a random one of ``size`` held back, which is yielded."""
    held: list[Any] = []
    for item in items:
        if len(held) < size:
            held.append(item)
            continue
        j = int(rng.integers(size))
        yield held[j]
        held[j] = item
    yield from (held[j] for j in rng.permutation(len(held)))


def _train_refs(root: Path, spec: DataSpec, per_clip: int, interleave: int,
                buffer: int) -> Iterator[tuple[Clip, int]]:
    """Endless frame references of this rank, epoch after epoch, its shards read ``interleave`` at a time.

    Every epoch re-draws everything from ``(seed, epoch)``: the frames per clip
    (FrameDataset), the shard order (shared by all ranks, so they still split the
    shards between them) and the shuffle buffer (per rank).
    """
    for epoch in itertools.count():
        refs = _FrameRefs(root, "train", per_clip, seed=spec.seed, epoch=epoch, rank=spec.rank,
                          world=spec.world_size, interleave=interleave)
        order = np.random.default_rng([spec.seed, epoch]).permutation(len(refs.shards))
        refs.shards = [refs.shards[i] for i in order]
        count = 0
        for ref in _shuffled(refs, np.random.default_rng([spec.seed, epoch, spec.rank]), buffer):
            count += 1
            yield ref
        if count == 0:
            raise OrbisError(f"{root}: the train split gives no frames to rank {spec.rank} of {spec.world_size}; "
                             f"re-run the `shards` stage or use fewer processes")


def image_batches(root: Path, spec: DataSpec, per_clip: int, interleave: int = 1,
                  buffer: int = SHUFFLE_BUFFER) -> Iterator[torch.Tensor]:
    """Endless train batches ``[spec.batch_size, 3, H, W]`` in [-1, 1] for one rank, from batch ``spec.start`` on.

    The stream is a pure function of ``(seed, rank, world_size)``; starting at
    ``start`` skips ``start`` batches of references without decoding them, so a
    resumed run sees exactly the batches an uninterrupted one would have.
    ``spec.num_workers`` threads decode upcoming batches ahead (OpenCV releases the GIL).
    """
    refs = itertools.islice(_train_refs(Path(root), spec, per_clip, interleave, buffer), spec.start * spec.batch_size,
                            None)
    groups = iter(lambda: list(itertools.islice(refs, spec.batch_size)), [])
    yield from _decode_ahead(groups, spec.num_workers)


def _decode_ahead(groups: Iterator[list[tuple[Clip, int]]], workers: int) -> Iterator[torch.Tensor]:
    """Decoded batches in stream order; with workers, up to ``2 * workers`` batches are decoded ahead."""
    if workers == 0:
        for group in groups:
            yield to_images(_decode(group))
        return
    with ThreadPoolExecutor(workers) as pool:
        pending: deque = deque()
        for group in groups:
            pending.append(pool.submit(_decode, group))
            if len(pending) > 2 * workers:
                yield to_images(pending.popleft().result())
        while pending:
            yield to_images(pending.popleft().result())


def _frames(root: Path, split: str, count: int, seed: int) -> Iterator[np.ndarray]:
    """The first ``count`` frames of a split, spread evenly over its clips; no shuffling, single process."""
    clips = load_manifest(root)["splits"].get(split, {}).get("samples", 0)
    if clips == 0:
        raise OrbisError(f"{Path(root) / 'manifest.json'}: no '{split}' clips; re-run the `shards` stage")
    dataset = FrameDataset(root, split, per_clip=math.ceil(count / clips), seed=seed, rank=0, world=1)
    return itertools.islice(iter(dataset), count)


def frame_batches(root: Path, split: str, count: int, batch_size: int, seed: int) -> Iterator[torch.Tensor]:
    """The frames of :func:`_frames` as image batches: evaluation, latent scale and FID sets."""
    frames = _frames(root, split, count, seed)
    while batch := list(itertools.islice(frames, batch_size)):
        yield to_images(np.stack(batch))


def read_frames(root: Path, split: str, count: int, seed: int) -> np.ndarray:
    """The frames of :func:`_frames` as one RGB uint8 array ``[N, H, W, 3]`` (a quarter of float's memory)."""
    frames = list(_frames(root, split, count, seed))
    if not frames:
        raise OrbisError(f"{root}: the '{split}' split has no frames; re-run the `shards` stage")
    return np.stack(frames)


def _check_geometry(root: Path, section: DetailTokenizerConfig | AbstractTokenizerConfig) -> None:
    manifest = load_manifest(root)
    preset = section.preset
    height, width = section.sizes().image_size
    if (manifest["width"], manifest["height"]) != (width, height):
        raise OrbisError(f"{Path(root) / 'manifest.json'}: frames are {manifest['width']}x{manifest['height']} but "
                         f"tokenizer preset '{preset}' takes {width}x{height}; use the profile whose data section "
                         f"matches the preset, or re-run the town/import and shards stages")


def save_grid(path: Path, rows: Sequence[torch.Tensor]) -> None:
    """A PNG with one row per batch of images (e.g. originals, reconstructions), written atomically."""
    grid = np.concatenate([np.concatenate(list(to_uint8(row[:GRID_IMAGES])), axis=1) for row in rows], axis=0)
    ok, png = cv2.imencode(".png", cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
    assert ok, "OpenCV failed to encode a PNG"
    with atomic_file(path) as tmp:
        tmp.write_bytes(png.tobytes())


# --------------------------------------------------------------------------- tasks


class _TokenizerTask:
    """What both tokenizer tasks share: the train stream, fixed validation frames, sample grids."""

    def __init__(self, cfg: DetailTokenizerConfig | AbstractTokenizerConfig, shards_root: Path, out_dir: Path):
        self.cfg, self.root, self.out_dir = cfg, Path(shards_root), Path(out_dir)
        _check_geometry(self.root, cfg)
        self._val: np.ndarray | None = None

    def batches(self, spec: DataSpec) -> Iterator[torch.Tensor]:
        return image_batches(self.root, spec, self.cfg.frames_per_clip, self.cfg.interleave_shards or 1)

    def val_batches(self, device: torch.device) -> Iterator[torch.Tensor]:
        """The ``eval_images`` validation frames (decoded once, kept as uint8), batch by batch."""
        if self._val is None:
            self._val = read_frames(self.root, "val", self.cfg.eval_images, self.cfg.train.seed)
        for start in range(0, len(self._val), self.cfg.train.batch_size):
            yield to_images(self._val[start:start + self.cfg.train.batch_size]).to(device)

    def sample_path(self, step: int) -> Path:
        return self.out_dir / "samples" / f"step_{step:06d}.png"


class DetailGAN(nn.Module):
    """The detail tokenizer and its discriminator in one module.

    One module means one checkpoint (and one EMA) holds both, and DDP wraps both;
    ``forward`` runs whichever part an update needs, so every update goes through
    the DDP wrapper and has its gradients synchronised.
    """

    def __init__(self, tokenizer: nn.Module, discriminator: nn.Module):
        super().__init__()
        self.tokenizer = tokenizer
        self.discriminator = discriminator

    def forward(self, images: torch.Tensor, gan: bool = False, fake: torch.Tensor | None = None) -> tuple:
        """With ``fake``: discriminator logits on (images, fake). Otherwise (recon, VQOutput,
        discriminator logits on recon if ``gan`` else None)."""
        if fake is not None:
            return self.discriminator(images), self.discriminator(fake)
        recon, vq = self.tokenizer(images)
        return recon, vq, self.discriminator(recon) if gan else None


class DetailTokenizerTask(_TokenizerTask):
    """E_L with the VQGAN objective (the authors' code, "Tokenizer"); LPIPS is left out (no VGG weights offline)."""

    cfg: DetailTokenizerConfig

    def __init__(self, cfg: DetailTokenizerConfig, shards_root: Path, out_dir: Path):
        super().__init__(cfg, shards_root, out_dir)
        if cfg.mae_checkpoint is not None and not Path(cfg.mae_checkpoint).is_file():
            raise OrbisError(f"tokenizer_detail.mae_checkpoint = {cfg.mae_checkpoint}: file not found; point it at "
                             f"the official MAE ViT weights or set it to null")
        self._fake: tuple[int, torch.Tensor] | None = None

    def build_model(self) -> DetailGAN:
        tokenizer = build_detail_tokenizer(self.cfg.sizes())
        if self.cfg.mae_checkpoint is not None:
            load_mae_encoder(tokenizer.encoder, self.cfg.mae_checkpoint)
        return DetailGAN(tokenizer, build_discriminator(self.cfg.sizes()))

    def loss(self, model: nn.Module, images: torch.Tensor, step: int) -> tuple[torch.Tensor, dict[str, Any]]:
        cfg = self.cfg
        gan = step >= cfg.disc_start
        recon, vq, logits_fake = model(images, gan=gan)
        rec, metrics = self.reconstruction_loss(recon, images)
        loss = rec + vq.vq_loss + entropy_weight(step, cfg.entropy_start, cfg.entropy_end,
                                                 cfg.entropy_decay_steps) * vq.entropy_loss
        metrics.update(codebook=vq.codebook_loss.detach(), commitment=vq.commitment_loss.detach(),
                       entropy=vq.entropy_loss.detach(), perplexity=vq.perplexity, used_fraction=vq.used_fraction)
        if gan:
            g_loss = generator_gan_loss(logits_fake)
            weight = adaptive_gan_weight(rec, g_loss, unwrap(model).tokenizer.last_layer, cfg.gan_scale)
            loss = loss + weight * g_loss
            metrics.update(g_loss=g_loss.detach(), gan_weight=weight)
            self._fake = (step, recon.detach())  # the discriminator scores this step's reconstructions
        return loss, metrics

    def reconstruction_loss(self, recon: torch.Tensor, images: torch.Tensor) -> tuple[torch.Tensor, dict[str, Any]]:
        """The reconstruction terms (taming's nll, which the adaptive GAN weight balances) and their metrics."""
        l1, mse = l1_reconstruction(recon, images), mse_reconstruction(recon, images)
        return self.cfg.l1_weight * l1 + self.cfg.mse_weight * mse, {"l1": l1.detach(), "mse": mse.detach()}

    def disc_loss(self, model: nn.Module, images: torch.Tensor, step: int) -> tuple[torch.Tensor, dict] | None:
        """Hinge loss on this step's images and reconstructions; skipped before ``disc_start``."""
        if step < self.cfg.disc_start:
            return None
        if self._fake is None or self._fake[0] != step:
            raise RuntimeError(f"no reconstructions of step {step}: the main loss must run before the discriminator")
        logits_real, logits_fake = model(images, fake=self._fake[1])
        self._fake = None
        return hinge_d_loss(logits_real, logits_fake), {"d_logits_real": logits_real.detach().mean(),
                                                        "d_logits_fake": logits_fake.detach().mean()}

    def extra_updates(self, model: DetailGAN) -> list[Update]:
        return [Update("disc", list(model.discriminator.parameters()), self.disc_loss, self.cfg.disc_lr_scale)]

    @torch.no_grad()
    def evaluate(self, model: DetailGAN, step: int) -> dict[str, float]:
        """PSNR/SSIM of the quantised path (as the codes decode), PSNR of the continuous path
        (what the world model's latents decode like), codebook usage, and a sample grid."""
        tokenizer = model.tokenizer
        device = next(tokenizer.parameters()).device
        scores: dict[str, list[torch.Tensor]] = {"psnr": [], "ssim": [], "psnr_continuous": []}
        indices, grid = [], None
        for images in self.val_batches(device):
            z = tokenizer.encode(images)
            vq = tokenizer.quantize(z)
            recon = tokenizer.decode(vq.quantized)
            scores["psnr"].append(psnr(recon, images, "none"))
            scores["ssim"].append(ssim(recon, images, "none"))
            scores["psnr_continuous"].append(psnr(tokenizer.decode(z), images, "none"))
            indices.append(vq.indices)
            grid = grid or (images, recon)
        save_grid(self.sample_path(step), grid)
        usage = codebook_usage(torch.cat(indices), tokenizer.quantizer.codebook_size)
        return {**{f"val_{k}": torch.cat(v).mean().item() for k, v in scores.items()},
                **{f"val_{k}": float(v) for k, v in usage.items()}}


class AbstractTokenizerTask(_TokenizerTask):
    """E_H aligned to a frozen teacher (paper eq. 3) plus the weak reconstruction of D_H.

    ``teacher`` is any frozen module mapping images in [-1, 1] to a feature map
    ``[B, teacher.feature_dim, h', w']``; it stays outside the model, so it is
    neither trained nor checkpointed. ``teacher_size`` resizes the images the
    teacher sees (DINOv2: 14 px per latent cell, so both grids match as in the
    reference); None feeds them as they are.
    """

    cfg: AbstractTokenizerConfig

    def __init__(self, cfg: AbstractTokenizerConfig, shards_root: Path, out_dir: Path, teacher: nn.Module,
                 teacher_size: tuple[int, int] | None = None):
        super().__init__(cfg, shards_root, out_dir)
        self.teacher, self.teacher_size = teacher, teacher_size

    def build_model(self) -> nn.Module:
        return build_abstract_tokenizer(self.cfg.sizes(), self.teacher.feature_dim, self.cfg.compress)

    @torch.no_grad()
    def teacher_features(self, images: torch.Tensor) -> torch.Tensor:
        if self.teacher_size is not None:
            images = F.interpolate(images, size=self.teacher_size, mode="bilinear", align_corners=False,
                                   antialias=True)
        return self.teacher.to(images.device)(images)

    def loss(self, model: nn.Module, images: torch.Tensor, step: int) -> tuple[torch.Tensor, dict[str, Any]]:
        _, predicted, recon = model(images)
        align = teacher_alignment_loss(predicted, self.teacher_features(images), self.cfg.alignment)
        l1 = l1_reconstruction(recon, images)
        return align + self.cfg.rec_weight * l1, {"align": align.detach(), "l1": l1.detach()}

    @torch.no_grad()
    def evaluate(self, model: nn.Module, step: int) -> dict[str, float]:
        """Alignment loss and cosine similarity to the teacher, PSNR of D_H, and a sample grid."""
        device = next(model.parameters()).device
        scores: dict[str, list[float]] = {"align": [], "cosine": [], "psnr": []}
        weights, grid = [], None
        for images in self.val_batches(device):
            _, predicted, recon = model(images)
            target = self.teacher_features(images)
            recon = recon.clamp(-1.0, 1.0)
            scores["align"].append(teacher_alignment_loss(predicted, target, self.cfg.alignment).item())
            scores["cosine"].append(1.0 - teacher_alignment_loss(predicted, target, "cosine").item())
            scores["psnr"].append(psnr(recon, images).item())
            weights.append(len(images))
            grid = grid or (images, recon)
        save_grid(self.sample_path(step), grid)
        return {f"val_{k}": float(np.average(v, weights=weights)) for k, v in scores.items()}


# --------------------------------------------------------------------------- after training


@torch.no_grad()
def latent_statistics(model: nn.Module, frames: Iterable[torch.Tensor], per_position: bool = True
                      ) -> tuple[torch.Tensor, torch.Tensor | None, dict[str, float]]:
    """``(scale, shift, metrics)`` normalising ``model.encode`` over the given image batches.

    The world model adds unit-variance noise to normalised latents. The paper scales each latent
    by one global factor, 1 / std over all elements (the latent diffusion "scale factor"; about
    4 for an L2-normalised 16-d latent). With ``per_position`` (this pipeline's default) the
    dataset's per-position, per-channel mean (a fixed template that carried ~99% of the abstract
    latent's energy) is removed first and each channel is scaled to unit variance, so that what
    varies between frames is what the predictors see at unit scale. ``metrics``: ``template_share``
    (share of the latent's energy in that mean) and ``latent_scale`` (the global factor).
    """
    device = next(model.parameters()).device
    total = square = None
    count = 0
    for images in frames:
        z = model.encode(images.to(device)).double()
        total = z.sum(0) if total is None else total + z.sum(0)
        square = z.square().sum(0) if square is None else square + z.square().sum(0)
        count += len(z)
    if count == 0:
        raise OrbisError("latent statistics need at least one frame")
    mean = total / count
    energy = float((square / count).mean())
    global_var = float((square / count).mean() - mean.mean() ** 2)
    if global_var <= 0:
        raise OrbisError("the encoded latent is constant (std 0); the tokenizer has collapsed, train it again")
    metrics = {"latent_scale": 1.0 / math.sqrt(global_var), "template_share": float(mean.square().mean()) / energy}
    if not per_position:
        return torch.tensor(metrics["latent_scale"]), None, metrics
    channel_var = (square / count - mean.square()).clamp_min(0).mean(dim=(1, 2))
    if float(channel_var.min()) <= 0:
        raise OrbisError("a latent channel never varies (std 0); the tokenizer has collapsed, train it again")
    return channel_var.rsqrt().float(), mean.float(), metrics


def load_fid_network(path: Path, device: torch.device | str = "cpu") -> torch.jit.ScriptModule:
    """The FID InceptionV3 TorchScript; its forward maps 299x299 inputs to the 2048-d pool features."""
    with warnings.catch_warnings():  # the FID network only exists as TorchScript; its deprecation is moot here
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.load(str(path), map_location=device).eval()


def fid_input(images: torch.Tensor) -> torch.Tensor:
    """Images in [-1, 1] -> the FID network's input, as the original TF FID code feeds it.

    Quantised to 8 bits (reconstructions are scored as saved images), resized to
    299x299 bilinearly (aspect not kept), then scaled as TF-slim Inception expects:
    (x - 128) / 128 for x in 0..255.
    """
    x = ((images.float() + 1.0) * 127.5).round().clamp(0, 255)
    x = F.interpolate(x, size=(FID_SIZE, FID_SIZE), mode="bilinear", align_corners=False)
    return (x - 128.0) / 128.0


@torch.no_grad()
def reconstruction_fid(model: nn.Module, inception_path: Path, val_frames: Iterable[torch.Tensor]) -> float:
    """FID between image batches and their quantised-path reconstructions (eval mode).

    Features are the 2048-d pool features of the FID InceptionV3; statistics and the
    distance are those of :mod:`orbis2.eval.metrics.fvd`.
    """
    model.eval()
    device = next(model.parameters()).device
    network = load_fid_network(inception_path, device)
    real, fake = [], []
    bar = tqdm(val_frames, desc="reconstruction FID", unit="batch", mininterval=0.5 if sys.stderr.isatty() else 30.0)
    for images in bar:
        images = images.to(device)
        recon, _ = model(images)
        real.append(network(fid_input(images)).double().cpu())
        fake.append(network(fid_input(recon.clamp(-1.0, 1.0))).double().cpu())
    real_stats = FeatureStats.from_features(torch.cat(real).numpy())
    fake_stats = FeatureStats.from_features(torch.cat(fake).numpy())
    return frechet_distance(real_stats.mean, real_stats.cov, fake_stats.mean, fake_stats.cov)


def _rank() -> int:
    return dist.get_rank() if dist.is_initialized() else 0


def _device() -> torch.device:
    return torch.device("cuda", torch.cuda.current_device()) if torch.cuda.is_available() else torch.device("cpu")


def _final_model(task: Any, model_path: Path) -> nn.Module:
    """The trained weights (EMA when EMA is on) in a fresh model, eval mode, on this process's device."""
    model = task.build_model()
    model.load_state_dict(load_weights(model_path))
    return model.to(_device()).eval().requires_grad_(False)


def train_detail_tokenizer(cfg: PipelineConfig, shards_root: Path, out_dir: Path, assets_dir: Path,
                           logger: Any = None) -> dict[str, float]:
    """The `tokenizer_detail` stage: train (resuming), then latent scale, reconstruction FID and ``tokenizer.pt``.

    Returns the final metrics on rank 0; other ranks (under torchrun) write nothing and
    return ``{}``. Re-running a finished stage only re-measures and re-saves.
    """
    tc, out_dir = cfg.tokenizer_detail, Path(out_dir)
    inception = asset_path(assets_dir, "inception_v3")  # fail before training, not after
    task = DetailTokenizerTask(tc, shards_root, out_dir)
    result = train(task, tc.train, out_dir, logger)
    if _rank() != 0:
        return {}
    model = _final_model(task, result.model_path)
    tokenizer = model.tokenizer
    metrics = task.evaluate(model, result.step)
    scale, shift, stats = latent_statistics(tokenizer, frame_batches(shards_root, "train", tc.scale_images,
                                                                     tc.train.batch_size, tc.train.seed),
                                            tc.latent_norm == "per_position")
    fid = reconstruction_fid(tokenizer, inception, frame_batches(shards_root, "val", tc.fid_images,
                                                                 tc.train.batch_size, tc.train.seed))
    metrics.update(rfid=fid, steps=result.step, **stats)
    save_tokenizer(out_dir / "tokenizer.pt", "detail", tokenizer, scale,
                   full_build(TOKENIZER_PRESETS, tc.preset, tc.model),
                   {"metrics": metrics, "profile": cfg.profile}, shift)
    return metrics


def train_abstract_tokenizer(cfg: PipelineConfig, shards_root: Path, out_dir: Path, assets_dir: Path,
                             logger: Any = None, section: str = "tokenizer_abstract") -> dict[str, float]:
    """The `tokenizer_abstract` stage: train against the configured teacher, then latent scale and ``tokenizer.pt``.

    ``section`` picks the params (``tokenizer_abstract_full``: the uncompressed variant). Returns the
    final metrics on rank 0 and ``{}`` on other ranks, like :func:`train_detail_tokenizer`.
    """
    tc, out_dir = cfg.section(section), Path(out_dir)
    teacher = build_teacher(tc.teacher, asset_path(assets_dir, TEACHER_ASSETS[tc.teacher]), tc.teacher_layer)
    sizes = tc.sizes()
    (height, width), patch = sizes.image_size, sizes.patch_size
    size = (height // patch * DINOV2_PATCH, width // patch * DINOV2_PATCH) if tc.teacher == "dinov2" else None
    task = AbstractTokenizerTask(tc, shards_root, out_dir, teacher, size)
    result = train(task, tc.train, out_dir, logger)
    if _rank() != 0:
        return {}
    model = _final_model(task, result.model_path)
    metrics = task.evaluate(model, result.step)
    scale, shift, stats = latent_statistics(model, frame_batches(shards_root, "train", tc.scale_images,
                                                                 tc.train.batch_size, tc.train.seed),
                                            tc.latent_norm == "per_position")
    metrics.update(steps=result.step, **stats)
    build = {**full_build(TOKENIZER_PRESETS, tc.preset, tc.model), "teacher_dim": model.teacher_dim,
             "compress": tc.compress}
    save_tokenizer(out_dir / "tokenizer.pt", "abstract", model, scale, build,
                   {"metrics": metrics, "teacher": tc.teacher, "profile": cfg.profile}, shift)
    return metrics
