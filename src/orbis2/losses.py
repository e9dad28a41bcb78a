"""Losses and image metrics as pure functions (no module state).

Images are in [-1, 1] throughout the project (the authors' code, "Tokenizer");
the metrics map them to [0, 1] first so PSNR and SSIM use the usual data range.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def l1_reconstruction(recon: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute pixel error (VQGAN's L1 term, weight 1 in the reference)."""
    return (recon - target).abs().mean()


def mse_reconstruction(recon: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared pixel error: not in VQGAN's objective; what PSNR measures (``tokenizer_detail.mse_weight``)."""
    return (recon - target).square().mean()


def feature_distance(maps_a: list[torch.Tensor], maps_b: list[torch.Tensor]) -> torch.Tensor:
    """LPIPS's distance without its learned channel weights (Zhang et al. 2018's unweighted variant): per map,
    features unit-normalised over channels at each position, their squared difference summed over channels and
    averaged over positions and batch; the maps' terms summed."""
    total = torch.zeros((), device=maps_a[0].device)
    for a, b in zip(maps_a, maps_b, strict=True):
        a = a / (a.norm(dim=1, keepdim=True) + 1e-10)
        b = b / (b.norm(dim=1, keepdim=True) + 1e-10)
        total = total + (a - b).square().sum(1).mean()
    return total


def hinge_d_loss(logits_real: torch.Tensor, logits_fake: torch.Tensor) -> torch.Tensor:
    """Discriminator hinge loss (taming): 0.5 * (E[relu(1 - D(x))] + E[relu(1 + D(x_hat))])."""
    return 0.5 * (F.relu(1.0 - logits_real).mean() + F.relu(1.0 + logits_fake).mean())


def generator_gan_loss(logits_fake: torch.Tensor) -> torch.Tensor:
    """Generator side of the hinge GAN: -E[D(x_hat)]."""
    return -logits_fake.mean()


def adaptive_gan_weight(
    rec_loss: torch.Tensor, gan_loss: torch.Tensor, last_layer: torch.Tensor, scale: float = 0.1
) -> torch.Tensor:
    """Balance the GAN term against reconstruction (taming VQGAN eq. 7).

    weight = ||grad_L rec|| / (||grad_L gan|| + 1e-4) at the decoder's last
    layer L, clamped to [0, 1e4], detached, times ``scale`` (0.1 in the reference).
    """
    rec_grad = torch.autograd.grad(rec_loss, last_layer, retain_graph=True)[0]
    gan_grad = torch.autograd.grad(gan_loss, last_layer, retain_graph=True)[0]
    weight = rec_grad.norm() / (gan_grad.norm() + 1e-4)
    return weight.clamp(0.0, 1e4).detach() * scale


def teacher_alignment_loss(pred: torch.Tensor, target: torch.Tensor, kind: str = "l2") -> torch.Tensor:
    """Distance between P(z) [B, C, h, w] and the teacher's patch features [B, C, h', w'].

    ``kind="l2"``: paper eq. 3, the squared L2 distance per patch (summed over
    channels), averaged over patches and batch. ``kind="cosine"``: 1 - cosine
    similarity per patch, the loss of the v1 reference code. A teacher grid of
    a different size is resized bilinearly to the predicted grid.
    """
    if pred.shape[:2] != target.shape[:2]:
        raise ValueError(f"pred {tuple(pred.shape)} and target {tuple(target.shape)} differ in batch or channels")
    if target.shape[-2:] != pred.shape[-2:]:
        target = F.interpolate(target, size=pred.shape[-2:], mode="bilinear", align_corners=False)
    if kind == "l2":
        return (pred - target).pow(2).sum(dim=1).mean()
    if kind == "cosine":
        return (1.0 - F.cosine_similarity(pred, target, dim=1)).mean()
    raise ValueError(f"kind = {kind!r} must be 'l2' or 'cosine'")


def entropy_weight(step: int, start: float = 0.01, end: float = 0.001, decay_steps: int = 10000) -> float:
    """Weight of the quantiser's entropy term: linear decay start -> end over
    ``decay_steps``, then constant (reference VQEntropyLossScheduler: 0.01 -> 0.001 in 10k steps)."""
    if step >= decay_steps:
        return end
    return start + (end - start) * max(step, 0) / decay_steps


def _to_unit(x: torch.Tensor) -> torch.Tensor:
    return ((x.float() + 1.0) / 2.0).clamp(0.0, 1.0)


def _reduce(values: torch.Tensor, reduction: str) -> torch.Tensor:
    if reduction == "mean":
        return values.mean()
    if reduction == "none":
        return values
    raise ValueError(f"reduction = {reduction!r} must be 'mean' or 'none'")


def psnr(a: torch.Tensor, b: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """PSNR in dB of images [B, C, H, W] in [-1, 1], on the [0, 1] range; inf where identical.

    ``reduction="none"`` gives one value per image; "mean" averages them.
    """
    mse = (_to_unit(a) - _to_unit(b)).pow(2).flatten(1).mean(dim=1)
    return _reduce(10.0 * torch.log10(1.0 / mse), reduction)


def _gaussian_window(size: int, sigma: float, channels: int, device: torch.device) -> torch.Tensor:
    coords = torch.arange(size, dtype=torch.float32, device=device) - (size - 1) / 2
    g = torch.exp(-(coords**2) / (2 * sigma**2))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(channels, 1, size, size).contiguous()


def ssim(
    a: torch.Tensor, b: torch.Tensor, reduction: str = "mean", window_size: int = 11, sigma: float = 1.5
) -> torch.Tensor:
    """SSIM (Wang et al. 2004) of images [B, C, H, W] in [-1, 1], on the [0, 1] range.

    Standard settings: 11x11 Gaussian window with sigma 1.5, K1 = 0.01,
    K2 = 0.03, valid filtering, mean over channels and positions per image.
    """
    x, y = _to_unit(a), _to_unit(b)
    channels = x.shape[1]
    window = _gaussian_window(window_size, sigma, channels, x.device)

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, window, groups=channels)

    c1, c2 = 0.01**2, 0.03**2
    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return _reduce(ssim_map.flatten(1).mean(dim=1), reduction)
