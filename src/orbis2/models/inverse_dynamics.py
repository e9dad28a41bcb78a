"""A small CNN that reads ego-motion from the dense optical flow between two frames (the learned instrument).

Input: the flow field from frame t to t + 1 ([B, 2, H, W], pixels per frame, from
``orbis2.eval.metrics.inverse_dynamics.pair_flow``); output: the controls over [t, t + 1),
speed and yaw rate, in the standardised units the checkpoint records. Reading flow
rather than raw pixels is what lets a network trained on a few hundred town frames
generalise to unseen scenes: yaw is a near-uniform horizontal flow, speed an
expansion whose size grows towards the image edges, whatever the texture.
"""

from __future__ import annotations

import torch
from torch import nn

IN_CHANNELS = 2  # horizontal and vertical optical flow


class InverseDynamicsNet(nn.Module):
    def __init__(self, width: int = 32):
        super().__init__()
        chans = [IN_CHANNELS, width, 2 * width, 4 * width, 4 * width]
        layers: list[nn.Module] = []
        for i, (cin, cout) in enumerate(zip(chans[:-1], chans[1:])):
            layers += [nn.Conv2d(cin, cout, 5 if i == 0 else 3, stride=2, padding=2 if i == 0 else 1),
                       nn.GroupNorm(8 if cout % 8 == 0 else 1, cout), nn.GELU()]
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(chans[-1], 2)

    def forward(self, flow: torch.Tensor) -> torch.Tensor:
        if flow.ndim != 4 or flow.shape[1] != IN_CHANNELS:
            raise ValueError(f"expected flow fields [B, {IN_CHANNELS}, H, W], got {tuple(flow.shape)}")
        return self.head(self.features(flow).mean(dim=(2, 3)))
