"""Window arithmetic of the two-rate hierarchy: which native frames a detail and an abstract window cover.

A module of its own so that rollout and training use it without importing the
shard reader (data layer) that also needs it.
"""

from __future__ import annotations

import numpy as np

from orbis2.config.sections import DataConfig


def window_indices(data: DataConfig, anchor: int) -> tuple[np.ndarray, np.ndarray]:
    """Native frame indices of the detail and abstract windows around ``anchor``."""
    detail = anchor + data.detail_stride * (np.arange(data.detail_window) - (data.detail_context - 1))
    abstract = anchor + data.abstract_stride * (np.arange(data.abstract_window) - (data.abstract_context - 1))
    return detail, abstract


def window_span(detail: np.ndarray, abstract: np.ndarray) -> np.ndarray:
    """Every native frame from the first to the last frame of the two windows."""
    return np.arange(min(detail.min(), abstract.min()), max(detail.max(), abstract.max()) + 1)
