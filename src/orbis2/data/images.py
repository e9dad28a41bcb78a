"""Decoded images to the library's frames: RGB ``uint8`` arrays, as videos and figures take them.

The networks see images in [-1, 1] ``[B, 3, H, W]``; everything that is written or shown
(:mod:`orbis2.data.video`, the figures) takes RGB ``uint8`` ``[H, W, 3]``.
"""

from __future__ import annotations

import numpy as np
import torch


def to_uint8(images: torch.Tensor) -> np.ndarray:
    """Decoded images ``[B, 3, H, W]`` in [-1, 1] -> RGB uint8 ``[B, H, W, 3]`` (on the CPU).

    Converted on the images' device, so that only bytes leave it; callers decode in chunks and
    convert each one, which keeps float copies of whole videos out of memory.
    """
    pixels = ((images.detach().float().clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8)
    return pixels.permute(0, 2, 3, 1).cpu().numpy()
