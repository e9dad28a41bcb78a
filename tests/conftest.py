"""Shared fixtures: the project root, a config for the smoke profile, tiny synthetic videos."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from orbis2.config import load_config
from orbis2.data.video import write_video

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def smoke_cfg():
    return load_config(ROOT / "params.yaml", "smoke")


def moving_pattern(n: int, width: int, height: int, seed: int = 0) -> np.ndarray:
    """Frames of a textured pattern drifting sideways: real content for codecs and readers."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 255, (height, width * 2, 3), dtype=np.uint8)
    base = np.repeat(np.repeat(base[::8, ::8], 8, 0), 8, 1)[:height, : width * 2]
    return np.stack([np.ascontiguousarray(base[:, i : i + width]) for i in range(n)])


@pytest.fixture
def make_video(tmp_path):
    def make(name: str, n: int, fps: float, width: int = 160, height: int = 96, folder: Path | None = None) -> Path:
        path = (folder or tmp_path) / name
        path.parent.mkdir(parents=True, exist_ok=True)
        write_video(path, moving_pattern(n, width, height), fps)
        return path

    return make
