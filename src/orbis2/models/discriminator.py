"""The detail tokenizer's GAN discriminator: the adversarial part of its VQGAN objective.

Its size is part of :class:`~orbis2.models.tokenizer.TokenizerConfig` (``disc_*``); the hinge losses
that score it and the adaptive GAN weight are in :mod:`orbis2.losses`.
"""

from __future__ import annotations

import torch
from torch import nn

from orbis2.accel import conv_layout
from orbis2.models.sizes import TokenizerConfig, tokenizer_config
from orbis2.models.tokenizer import group_norm


class PatchGANDiscriminator(nn.Module):
    """PatchGAN (pix2pix / taming NLayerDiscriminator): 3 layers, 64 filters.

    Taming uses BatchNorm; we default to GroupNorm because our batches are small
    (8 on CPU) and the real and fake batches are scored in separate calls, where
    batch statistics differ between the two and leak which is which.
    """

    def __init__(self, in_channels: int = 3, base_channels: int = 64, n_layers: int = 3, norm: str = "group"):
        super().__init__()
        if norm not in ("group", "batch"):
            raise ValueError(f"norm = {norm!r} must be 'group' or 'batch'")

        def norm_layer(ch: int) -> nn.Module:
            return group_norm(ch) if norm == "group" else nn.BatchNorm2d(ch)

        layers: list[nn.Module] = [
            nn.Conv2d(in_channels, base_channels, 4, stride=2, padding=1),
            nn.LeakyReLU(0.2),
        ]
        ch = base_channels
        for n in range(1, n_layers + 1):
            out = base_channels * min(2**n, 8)
            stride = 2 if n < n_layers else 1
            layers += [nn.Conv2d(ch, out, 4, stride=stride, padding=1, bias=False), norm_layer(out), nn.LeakyReLU(0.2)]
            ch = out
        layers.append(nn.Conv2d(ch, 1, 4, stride=1, padding=1))
        self.main = nn.Sequential(*layers)
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.normal_(module.weight, 0.0, 0.02)
            elif isinstance(module, (nn.GroupNorm, nn.BatchNorm2d)):
                nn.init.normal_(module.weight, 1.0, 0.02)
                nn.init.zeros_(module.bias)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.main(images)


def build_discriminator(config: TokenizerConfig | str = "default") -> PatchGANDiscriminator:
    """The discriminator of ``config``'s size (a preset's name stands for ``TOKENIZER_PRESETS[name]``)."""
    cfg = tokenizer_config(config) if isinstance(config, str) else config
    return conv_layout(PatchGANDiscriminator(3, cfg.disc_channels, cfg.disc_layers, cfg.disc_norm))
