"""A small CNN that reads ego-motion from two consecutive frames: the learned inverse-dynamics instrument.

Input: frames t and t + 1 (RGB in [-1, 1], stacked on the channel axis, [B, 6, H, W]);
output: the controls over [t, t + 1), speed and yaw rate, in the standardised units
the checkpoint records. Strided convolutions keep the horizontal layout long enough
for the sign of the yaw rate (which side the scene flows to) to be read locally
before the global average.
"""

from __future__ import annotations

import torch
from torch import nn


class InverseDynamicsNet(nn.Module):
    def __init__(self, width: int = 32):
        super().__init__()
        chans = [6, width, 2 * width, 4 * width, 4 * width]
        layers: list[nn.Module] = []
        for i, (cin, cout) in enumerate(zip(chans[:-1], chans[1:])):
            layers += [nn.Conv2d(cin, cout, 5 if i == 0 else 3, stride=2, padding=2 if i == 0 else 1),
                       nn.GroupNorm(8 if cout % 8 == 0 else 1, cout), nn.GELU()]
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(chans[-1], 2)

    def forward(self, pair: torch.Tensor) -> torch.Tensor:
        if pair.ndim != 4 or pair.shape[1] != 6:
            raise ValueError(f"expected frame pairs [B, 6, H, W], got {tuple(pair.shape)}")
        return self.head(self.features(pair).mean(dim=(2, 3)))
