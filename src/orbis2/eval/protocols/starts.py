"""Where evaluation rollouts start and how far they run: pure functions of the data section.

Shared by the rollouts (:mod:`orbis2.eval.protocols.systems`) and the ``truth`` stage, which renders the
true counterfactuals of the very starts the steering evaluation rolls out from; kept apart from the
models so that the truth stage does not depend on them.
"""

from __future__ import annotations

import numpy as np

from orbis2.config.sections import DataConfig
from orbis2.rollout import first_context_end, rollout_schedule


def rollout_steps(data: DataConfig, seconds: float) -> int:
    """Rollout steps (0.5 s each with the paper's windows) that cover ``seconds``."""
    advance = (data.detail_window - data.detail_context) * data.detail_stride / data.fps
    return int(np.ceil(seconds / advance - 1e-9))


def commanded_steps(data: DataConfig, steps: int) -> int:
    """Native steps from the last context frame to the last frame a rollout of ``steps`` generates."""
    first = first_context_end(data)
    return rollout_schedule(data, first, steps)[-1].detail_target[-1] - first


def sample_ends(length: int, data: DataConfig, steps: int, starts_per_clip: int) -> list[int]:
    """Clip-relative indices of the last context frame of ``starts_per_clip`` evenly spread rollout starts in a
    clip of ``length`` frames (none if the clip is too short for ``steps`` rollout steps after its context)."""
    first = first_context_end(data)
    last = length - 1 - commanded_steps(data, steps)
    if last < first:
        return []
    return [int(end) for end in np.unique(np.linspace(first, last, starts_per_clip).round().astype(int))]
