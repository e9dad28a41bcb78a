"""What each predictor of the hierarchy sees: its windows, the detail predictor's abstract conditioning,
the steered predictor's inputs.

Training (``orbis2.tasks.predictors``), rollouts (``orbis2.rollout``, the ``orbis2`` command) and
evaluation (``orbis2.eval``) build a predictor's inputs with these functions and no others, so a change
here reaches all of them together (``tests/test_hierarchy.py`` builds a training batch and a rollout
step from one clip and checks that the networks receive the same tensors).

- The detail predictor F_L (10 Hz, 5 context + 5 target frames) is conditioned on two abstract
  latents: the last abstract context latent, at its last context frame (the same native frame), and
  the subgoal, at its last target frame (paper eq. for F_L; the authors' code, "Hierarchy wiring").
  Every other slot carries zeros.
- The steered abstract predictor reads speed and yaw rate over the native odometry rows from its last
  context frame up to the predicted one (row k holds the controls over [t_k, t_k+1)), each divided
  by the scale its file records (the authors' code, "Steering").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from orbis2.config.sections import DataConfig
from orbis2.errors import OrbisError

STEERING_FEATURES = ("speed", "yaw_rate")


# --------------------------------------------------------------------------- windows


def window_indices(data: DataConfig, anchor: int) -> tuple[np.ndarray, np.ndarray]:
    """Native frame indices of the detail and abstract windows around ``anchor``."""
    detail = anchor + data.detail_stride * (np.arange(data.detail_window) - (data.detail_context - 1))
    abstract = anchor + data.abstract_stride * (np.arange(data.abstract_window) - (data.abstract_context - 1))
    return detail, abstract


def window_span(detail: np.ndarray, abstract: np.ndarray) -> np.ndarray:
    """Every native frame from the first to the last frame of the two windows."""
    return np.arange(min(detail.min(), abstract.min()), max(detail.max(), abstract.max()) + 1)


def anchor_range(data: DataConfig, n_frames: int) -> range:
    """Anchors whose two windows both fit inside a clip of ``n_frames``."""
    detail, abstract = window_indices(data, 0)
    first = -min(detail.min(), abstract.min())
    last = n_frames - 1 - max(detail.max(), abstract.max())
    return range(first, last + 1)


def window_key(level: str, rate: str) -> str:
    """The :class:`~orbis2.latents.LatentWindowDataset` item key of ``level`` latents in the ``rate`` window."""
    return {("detail", "fast"): "detail", ("abstract", "slow"): "abstract",
            ("detail", "slow"): "detail_slow", ("abstract", "fast"): "abstract_fast"}[level, rate]


def rate_geometry(data: DataConfig, rate: str) -> tuple[int, int, int]:
    """(frames per second, window length, context length) of the ``slow`` or ``fast`` window."""
    if rate == "slow":
        return data.abstract_hz, data.abstract_window, data.abstract_context
    return data.detail_hz, data.detail_window, data.detail_context


# --------------------------------------------------------------------------- detail conditioning


def condition_slots(n_context: int, n_target: int) -> tuple[int, int]:
    """The detail window's conditioned slots: its last context frame and its last target frame."""
    return n_context - 1, n_context + n_target - 1


def detail_condition_slots(data: DataConfig) -> dict[int, int]:
    """Detail frame slot -> abstract window index of the latent placed there.

    The last detail context frame gets the last abstract context latent (same native frame) and the
    last predicted detail frame gets the abstract subgoal (the predicted abstract frame).
    """
    detail, abstract = window_indices(data, 0)
    context_slot, subgoal_slot = condition_slots(data.detail_context, data.detail_window - data.detail_context)
    slots = {context_slot: data.abstract_context - 1, subgoal_slot: data.abstract_window - 1}
    for slot, index in slots.items():
        if detail[slot] != abstract[index]:
            raise OrbisError(f"detail slot {slot} (native frame {detail[slot]}) and abstract index {index} "
                             f"(native frame {abstract[index]}) are not the same frame; check the data section")
    return slots


def condition_frames(last_context: torch.Tensor, subgoal: torch.Tensor, n_context: int,
                     n_target: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """``cond_frames`` [B, F, C, h, w] of one detail window from its two abstract latents [B, C, h, w], and the
    conditioned slots (the ``cond_mask`` given as slots: known without reading a tensor, so the forward
    needs no host sync)."""
    slots = condition_slots(n_context, n_target)
    cond = last_context.new_zeros((last_context.shape[0], n_context + n_target, *last_context.shape[1:]))
    cond[:, slots[0]] = last_context
    cond[:, slots[1]] = subgoal
    return cond, slots


def detail_condition(slow: torch.Tensor, data: DataConfig, slots: dict[int, int] | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """A training window's slow latents [B, A, C, h, w] -> ``cond_frames`` [B, F_detail, C, h, w] and
    ``cond_mask`` [B, F_detail]: :func:`condition_frames` of the latents the slots point at.

    The slow window holds abstract latents (the hierarchy) or detail ones (Exp. 4's bottom predictor).
    ``slots``: :func:`detail_condition_slots` of ``data`` when the caller has them already (the training
    step, which must not run the window arithmetic inside a compiled region).
    """
    (_, context_index), (_, subgoal_index) = sorted((detail_condition_slots(data) if slots is None
                                                     else slots).items())
    frames, conditioned = condition_frames(slow[:, context_index], slow[:, subgoal_index], data.detail_context,
                                           data.detail_window - data.detail_context)
    mask = torch.zeros(slow.shape[0], data.detail_window, dtype=torch.bool, device=slow.device)
    mask[:, list(conditioned)] = True
    return frames, mask


# --------------------------------------------------------------------------- steering


def steering_rows(data: DataConfig, anchor: int) -> range:
    """Native odometry rows that steer the abstract prediction of the window whose last context frame is
    ``anchor``: from that frame up to (not including) the predicted one."""
    abstract = window_indices(data, anchor)[1]
    return range(int(abstract[data.abstract_context - 1]), int(abstract[-1]))


def steering_interval(data: DataConfig) -> slice:
    """:func:`steering_rows` as rows of a training window's native odometry span (``item["odometry"]``)."""
    first = int(window_span(*window_indices(data, 0))[0])
    rows = steering_rows(data, 0)
    return slice(rows.start - first, rows.stop - first)


def scale_steering(raw: torch.Tensor, scale: Sequence[float]) -> torch.Tensor:
    """Speed and yaw rate [..., 2] (m/s, rad/s) -> the steered predictor's unit-scale input, in float32.

    ``scale``: the (speed, yaw rate) divisors of the predictor (``ActionConfig.speed_scale``,
    ``yaw_rate_scale``; recorded in its file as ``meta["steering"]["scale"]``).
    """
    raw = raw.float()
    return raw / raw.new_tensor(list(scale))


def raw_steering(odometry: torch.Tensor, has_odometry: torch.Tensor, interval: slice
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Training windows' native odometry spans [B, S, 2] -> speed and yaw rate over the steering
    ``interval`` [B, T, 2], and ``unknown`` [B]: no odometry, or a NaN in the interval."""
    raw = odometry[:, interval]
    return raw, ~has_odometry.bool() | torch.isnan(raw).flatten(1).any(dim=1)


def steering_features(odometry: torch.Tensor, has_odometry: torch.Tensor, data: DataConfig,
                      scale: Sequence[float], interval: slice | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Training windows' native odometry spans [B, S, 2] -> unit-scale steering [B, T, 2] and ``unknown`` [B].

    An ``unknown`` sample must run unconditionally: its values are zeroed. ``interval``: the
    :func:`steering_interval` of ``data`` when the caller has it (the training step).
    """
    raw, unknown = raw_steering(odometry, has_odometry, steering_interval(data) if interval is None else interval)
    values = scale_steering(raw, scale)
    return torch.where(unknown[:, None, None], torch.zeros_like(values), values), unknown
