"""Pixel-space comparisons of decoded frames (numpy only: the evaluation stages import it without the
simulator the truth scoring needs)."""

from __future__ import annotations

import numpy as np


def psnr(generated: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per start and frame [N, T], PSNR (dB) of uint8 frames [N, T, H, W, 3] against the truth; capped at 100 dB
    for identical frames.

    One start at a time: the float64 differences of every start at once are 8 times the videos (1.9 GB per
    copy at the default profile's 32 six-second starts, three copies at the peak); a start's frames reduce
    alone, so the figures are the same to the bit.
    """
    mse = np.empty(generated.shape[:2])
    for n, (video, true) in enumerate(zip(generated, truth)):
        diff = video.astype(np.float64) - true.astype(np.float64)
        mse[n] = (diff ** 2).reshape(len(diff), -1).mean(-1)
    return np.minimum(10.0 * np.log10(255.0 ** 2 / np.maximum(mse, 1e-10)), 100.0)
