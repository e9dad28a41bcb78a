"""Per-town textures and sky: tileable noise with mip pyramids, and the sky panorama.

Built once per town (`Town._precompute`) and sampled by the kernels (`_tex` and `_sky_rgb` in
`orbis2.sim.kernels`). `_lin` turns the styles' sRGB colours into linear RGB.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from orbis2.sim.style import TownStyle


def _lin(rgb) -> np.ndarray:
    """sRGB-ish [0, 1] -> linear."""
    return np.asarray(rgb, np.float64) ** 2.2


def _noise_textures(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Four tileable noise channels with full mip pyramids: float32 [4, levels, size, size].

    0: fine grain, 1: large patches, 2: leafy blobs, 3: vertical streaks (dirt on walls, bark).
    Periodic by construction (filtered white noise in the Fourier domain), in [0, 1].
    """
    f = np.fft.fftfreq(size) * size
    fx, fy = np.meshgrid(f, f)

    def spectral(amp):
        spec = np.fft.fft2(rng.standard_normal((size, size))) * amp
        n = np.real(np.fft.ifft2(spec))
        return (n - n.mean()) / (n.std() + 1e-9)

    r = np.hypot(fx, fy)
    r[0, 0] = 1.0
    grain = spectral(np.where((r >= 2) & (r <= size / 2), r ** -0.6, 0.0))
    patches = spectral(np.where(r <= 40, r ** -1.6, 0.0))
    leaves = spectral(np.where((r >= 10) & (r <= 42), 1.0, 0.0))
    leaves = 0.5 * spectral(np.where((r >= 3) & (r <= 10), 1.0, 0.0)) + leaves
    rs = np.hypot(fx, fy * 8.0)
    rs[0, 0] = 1.0
    streaks = spectral(np.where(rs <= 80, rs ** -1.2, 0.0))
    chans = [0.5 + 0.17 * grain, 0.5 + 0.2 * patches, 0.5 + 0.5 * np.tanh(1.3 * leaves),
             0.5 + 0.18 * streaks]
    levels = int(math.log2(size)) + 1
    tex = np.zeros((4, levels, size, size), np.float32)
    for c, img in enumerate(chans):
        img = np.clip(img, 0.0, 1.0)
        for lev in range(levels):
            n = size >> lev
            tex[c, lev, :n, :n] = img
            if n > 1:
                img = img.reshape(n // 2, 2, n // 2, 2).mean(axis=(1, 3))
    return tex


def _sky_panorama(style: TownStyle, sun: np.ndarray, tex: np.ndarray, rng: np.random.Generator,
                  el0: float, el1: float, width: int = 1024, height: int = 160) -> np.ndarray:
    """Sky colour over (elevation, absolute azimuth): gradient, sun glow and clouds, linear RGB."""
    el = np.linspace(el0, el1, height)[:, None]
    az = (np.arange(width) + 0.5) / width * 2 * np.pi
    az = az[None, :]
    t = np.clip(el / (np.pi / 2), 0, 1) ** 0.45
    zen, hor = _lin(style.sky_zenith_rgb), _lin(style.sky_horizon_rgb)
    col = hor * (1 - t[..., None]) + zen * t[..., None]
    d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), -1)
    cosang = d @ sun
    sunc = _lin(style.sun_rgb)
    glow = 0.35 * np.exp((cosang - 1) * 12) + 0.8 * np.exp((cosang - 1) * 400)
    # Clouds: noise on a flat layer above the camera, faded toward the horizon.
    elc = np.maximum(el, 0.03)
    cot = np.cos(elc) / np.sin(elc)
    size = tex.shape[2]
    scale = 0.12
    off = rng.uniform(0, 1, 2)
    mu = ((np.cos(az) * cot * scale + off[0]) * size).astype(np.float32)
    mv = ((np.sin(az) * cot * scale + off[1]) * size).astype(np.float32)
    base = (0.6 * tex[1, 0] + 0.4 * tex[0, 0]).astype(np.float32)
    base = (base - base.mean()) / base.std()
    n = cv2.remap(base, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    thr = 1.2 - 2.2 * style.cloud_cover
    cover = np.clip((n - thr) / 0.9, 0, 1) * np.clip((el - 0.02) / 0.18, 0, 1)
    lit = np.clip(0.75 + 0.25 * (n - thr), 0.6, 1.2)
    cloud = (0.55 + 0.45 * hor.mean()) * lit[..., None] * np.array([1.0, 1.0, 1.02]) * 1.1
    col = col * (1 - cover[..., None]) + cloud * cover[..., None]
    col = col + sunc * glow[..., None] * (1 - 0.7 * cover[..., None])
    return col.astype(np.float32)
