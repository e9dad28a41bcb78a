"""Autoregressive rollouts: the cascaded hierarchical one and single-branch baselines.

Protocol (paper Appendix "Inference protocol", the authors' code, "Hierarchy
wiring"): per step the abstract predictor samples one latent at 2 Hz from its
5-frame context (15 NFE); the detail predictor samples the next 5 frames at
10 Hz from its 5-frame context (30 NFE), conditioned on the last abstract
context latent (aligned with its last context frame) and the predicted one
(aligned with its last target frame). Then both windows slide: the detail
context takes the 5 new frames, the abstract context the predicted latent. One
step therefore advances 0.5 s at both rates, which is what keeps the two
windows aligned for any rollout length.

The window bookkeeping is pure (:func:`rollout_schedule`) and uses the same
``window_indices`` as training, so a rollout sees its frames at exactly the
offsets the predictors were trained on.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from orbis2.config.sections import DataConfig
from orbis2.errors import OrbisError
from orbis2.flow import ModelFn, consistency_sample, euler_grid, euler_sample, guided_velocity
from orbis2.hierarchy import condition_frames, scale_steering, steering_rows, window_indices

StepCallback = Callable[[int], None]
# The paper's Euler steps per sample (its inference protocol): a rollout's defaults, unless a predictor
# records its own (a distilled detail predictor) or the evaluation config sets fewer for the CPU.
ABSTRACT_NFE = 15
DETAIL_NFE = 30


@dataclass(frozen=True)
class ScheduleStep:
    """Native frame indices of one rollout step."""

    detail_context: tuple[int, ...]
    detail_target: tuple[int, ...]
    abstract_context: tuple[int, ...]
    abstract_target: int
    steering: tuple[int, ...]  # odometry samples conditioning this step's abstract prediction


def check_step_alignment(data: DataConfig) -> None:
    """One step must advance both windows by the same time, or they drift apart over a rollout."""
    detail_advance = (data.detail_window - data.detail_context) * data.detail_stride
    abstract_advance = (data.abstract_window - data.abstract_context) * data.abstract_stride
    if detail_advance != abstract_advance:
        raise ValueError(
            f"a rollout step advances the detail window by {detail_advance} native frames but the abstract "
            f"window by {abstract_advance}; the windows must cover the same time per step"
        )


def first_context_end(data: DataConfig) -> int:
    """Earliest native index of the last context frame: the abstract context reaches furthest back."""
    detail, abstract = window_indices(data, 0)
    return -int(min(detail.min(), abstract.min()))


def rollout_schedule(data: DataConfig, context_end: int, steps: int) -> list[ScheduleStep]:
    """Per step, the native frame indices of both windows, with the last real context frame at ``context_end``.

    Step k is a training window anchored ``k`` steps (0.5 s each) later; its
    context frames after ``context_end`` are earlier steps' predictions. The
    steering samples are the training windows' (:func:`~orbis2.hierarchy.steering_rows`).
    """
    check_step_alignment(data)
    if context_end < first_context_end(data):
        raise ValueError(f"context_end = {context_end} leaves no room for the context windows "
                         f"(needs >= {first_context_end(data)})")
    advance = (data.detail_window - data.detail_context) * data.detail_stride
    schedule = []
    for k in range(steps):
        anchor = context_end + k * advance
        detail, abstract = window_indices(data, anchor)
        schedule.append(ScheduleStep(
            detail_context=tuple(int(i) for i in detail[: data.detail_context]),
            detail_target=tuple(int(i) for i in detail[data.detail_context:]),
            abstract_context=tuple(int(i) for i in abstract[: data.abstract_context]),
            abstract_target=int(abstract[data.abstract_context]),
            steering=tuple(steering_rows(data, anchor)),
        ))
    return schedule


def steering_offsets(steering: dict, fps: int, path: Path) -> list[int] | None:
    """The native frames after each step's last context frame an imported predictor's steering is sampled at
    (its ``meta["steering"]["offsets_s"]``, :func:`orbis2.models.official.converted_steering`); None for ours,
    which read the step's own rows (``ScheduleStep.steering``)."""
    if "offsets_s" not in steering:
        return None
    frames = [seconds * fps for seconds in steering["offsets_s"]]
    if any(abs(f - round(f)) > 1e-6 for f in frames):
        raise OrbisError(f"{path}: the authors' steering samples the odometry at {steering['offsets_s']} s, not at "
                         f"whole frames of this profile's {fps} fps; pass the profile whose data section matches "
                         f"the release")
    return [round(f) for f in frames]


def steering_sequences(schedule: list[ScheduleStep], speed: np.ndarray, yaw_rate: np.ndarray,
                       scale: Sequence[float], offsets: Sequence[int] | None = None) -> torch.Tensor:
    """Per-step steering [steps, S, 2] of the steered predictor (:func:`~orbis2.hierarchy.scale_steering` by its
    ``scale``) from native-rate speed and yaw rate.

    ``offsets`` (:func:`steering_offsets`): sample each step at its last context frame plus these frames instead of
    its own rows; past the end of ``speed`` the last value holds (a commanded speed is held until changed)."""
    if offsets is None:
        index = np.array([step.steering for step in schedule])
    else:
        index = np.minimum([[step.abstract_context[-1] + o for o in offsets] for step in schedule], len(speed) - 1)
    return scale_steering(torch.from_numpy(np.stack([np.asarray(speed)[index], np.asarray(yaw_rate)[index]], -1)),
                          scale)


def target_velocity(model: ModelFn, context: torch.Tensor, n_target: int, nfe: int, kv_cache: bool, cond: dict,
                    modulations: list | None = None) -> ModelFn:
    """The target frames' velocity as a function of (x_target, Euler step) after the clean ``context``.

    An ST-DiT computes what stays fixed over the Euler steps once (``model.plan``: the conditioning, every
    step's modulations, the context's temporal keys/values where exact), so each step runs the network's
    blocks alone, without a host sync; any other velocity function is called on the whole window.
    ``modulations``: the model's modulation table for these steps, computed earlier (the same every step).
    """
    taus = euler_grid(nfe)[:-1]
    if hasattr(model, "plan"):
        plan = model.plan(context, n_target, taus, kv_cache=kv_cache, modulations=modulations, **cond)
        return functools.partial(model.planned_velocity, plan)
    b, n_context = context.shape[:2]
    tau_context = torch.zeros(b, n_context, device=context.device, dtype=context.dtype)

    def velocity(x: torch.Tensor, step: int) -> torch.Tensor:
        tau = torch.full((b, n_target), taus[step], device=context.device, dtype=context.dtype)
        return model(torch.cat([context, x], dim=1), torch.cat([tau_context, tau], dim=1), **cond)[:, n_context:]

    return velocity


def unsteered_modulations(model: ModelFn, context: torch.Tensor, n_target: int, nfe: int,
                          kv_cache: bool) -> list | None:
    """An ST-DiT's modulation table (``model.modulation_table``) for sampling without steering: it depends on
    the noise levels alone, so a rollout computes it once for all its steps; None for other velocity functions."""
    if not hasattr(model, "modulation_table"):
        return None
    b, n_context = context.shape[:2]
    return model.modulation_table(euler_grid(nfe)[:-1], b, n_context, n_target, None, model.uses_kv_cache(kv_cache),
                                  context.device, context.dtype)


def sample_frames(model: ModelFn, context: torch.Tensor, n_target: int, nfe: int, generator: torch.Generator,
                  kv_cache: bool = True, guidance: float = 1.0, modulations: list | None = None,
                  grid: list[float] | None = None, **cond) -> torch.Tensor:
    """``euler_sample``, with what stays fixed over its Euler steps computed once per call
    (:func:`target_velocity`): the context's temporal keys/values where exact, the conditioning, the
    modulations (``modulations``: precomputed for an unsteered call, :func:`unsteered_modulations`).

    ``guidance`` != 1 with a ``steering`` input: classifier-free guidance on the steering
    (:func:`orbis2.flow.guided_velocity`), the unsteered velocity from the same model given no steering
    (its dropout embedding); two evaluations per Euler step, the same noise.
    ``grid``: a consistency-distilled predictor's noise levels (the authors' distilled abstract predictor):
    :func:`orbis2.flow.consistency_sample` instead, one network call per level (``nfe`` unused).
    """
    if grid is not None:
        if cond.get("steering") is not None and guidance != 1.0:
            raise ValueError("steering guidance needs an Euler sampler; a consistency-distilled predictor has none")
        return consistency_sample(model, context, n_target, grid, generator, **cond)
    if cond.get("steering") is not None and guidance != 1.0:
        steered = target_velocity(model, context, n_target, nfe, kv_cache, cond)
        free = target_velocity(model, context, n_target, nfe, kv_cache,
                               {k: v for k, v in cond.items() if k != "steering"})
        return euler_sample(model, context, n_target, nfe, generator,
                            target_fn=lambda x, step: guided_velocity(steered(x, step), free(x, step), guidance))
    if cond.get("steering") is not None:
        modulations = None  # the table depends on the steering
    velocity = target_velocity(model, context, n_target, nfe, kv_cache, cond, modulations)
    return euler_sample(model, context, n_target, nfe, generator, target_fn=velocity)


def _slide(context: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
    """Append ``new`` frames to the context window and drop as many of its oldest frames."""
    return torch.cat([context, new], dim=1)[:, -context.shape[1]:]


def _step_steering(steering: torch.Tensor | None, k: int, batch: int, steps: int) -> dict:
    if steering is None:
        return {}
    if steering.ndim != 4 or steering.shape[:2] != (batch, steps):
        raise ValueError(f"steering must be [B, steps, S, K] = [{batch}, {steps}, S, K], got {list(steering.shape)}")
    return {"steering": steering[:, k]}


def detail_frames_per_step(detail_hz: float, abstract_hz: float, top_frames_per_step: int = 1) -> int:
    """Detail frames one cascaded step adds: the bottom fills the top's step (``top_frames_per_step`` frames at
    ``abstract_hz``) at ``detail_hz``."""
    frames = detail_hz * top_frames_per_step / abstract_hz
    if frames < 1 or frames != int(frames):
        raise ValueError(f"detail_hz = {detail_hz:g} over {top_frames_per_step} top frame(s) at abstract_hz = "
                         f"{abstract_hz:g} is {frames:g} detail frames per step; the rates must give a whole number")
    return int(frames)


RolloutChunk = tuple[torch.Tensor, torch.Tensor]  # one step's detail latents and top frames


@torch.no_grad()
def cascaded_steps(
    abstract_model: ModelFn,
    detail_model: ModelFn,
    detail_context: torch.Tensor,
    abstract_context: torch.Tensor,
    generator: torch.Generator,
    abstract_nfe: int = ABSTRACT_NFE,
    detail_nfe: int = DETAIL_NFE,
    *,
    abstract_hz: float,
    detail_hz: float,
    steered: bool = False,
    top_frames_per_step: int = 1,
    kv_cache: bool = True,
    subgoals: torch.Tensor | None = None,
    steering_guidance: float = 1.0,
    abstract_grid: list[float] | None = None,
) -> Generator[RolloutChunk | None, torch.Tensor | None, None]:
    """The hierarchical rollout one 0.5 s step at a time, for a caller that decides each step's steering as it
    goes (``orbis2 play``) as well as for :func:`cascaded_rollout`, which loops over it.

    Start it with ``next()`` (it yields None once set up); then each ``send(steering)`` runs one step and
    returns its chunk (detail latents [B, frames_per_step, ...], top frames [B, top_frames_per_step, ...]).
    ``steering`` [B, S, K] conditions that step's top prediction; send None throughout when not ``steered``.
    ``subgoals``: the top's frames given, consumed ``top_frames_per_step`` a step. ``abstract_grid``: the top
    predictor's consistency grid, when it is consistency-distilled (:func:`sample_frames`). Everything else as
    in :func:`cascaded_rollout`.
    """
    n_context = detail_context.shape[1]
    frames_per_step = detail_frames_per_step(detail_hz, abstract_hz, top_frames_per_step)
    detail_table = unsteered_modulations(detail_model, detail_context, frames_per_step, detail_nfe, kv_cache)
    top_table = None
    if not steered and subgoals is None and abstract_grid is None:
        top_table = unsteered_modulations(abstract_model, abstract_context, top_frames_per_step, abstract_nfe,
                                          kv_cache)
    steering = yield None
    k = 0
    while True:
        if subgoals is None:
            cond = {} if steering is None else {"steering": steering}
            top = sample_frames(abstract_model, abstract_context, top_frames_per_step, abstract_nfe, generator,
                                kv_cache, steering_guidance, top_table, abstract_grid, frame_rate=abstract_hz, **cond)
        else:
            top = subgoals[:, k * top_frames_per_step:(k + 1) * top_frames_per_step]
        cond_frames, cond_mask = condition_frames(abstract_context[:, -1], top[:, -1], n_context, frames_per_step)
        new = sample_frames(detail_model, detail_context, frames_per_step, detail_nfe, generator, kv_cache,
                            modulations=detail_table, frame_rate=detail_hz, cond_frames=cond_frames,
                            cond_mask=cond_mask)
        detail_context = _slide(detail_context, new)
        abstract_context = _slide(abstract_context, top)
        k += 1
        steering = yield new, top


@torch.no_grad()
def cascaded_rollout(
    abstract_model: ModelFn,
    detail_model: ModelFn,
    detail_context: torch.Tensor,
    abstract_context: torch.Tensor,
    steps: int,
    generator: torch.Generator,
    abstract_nfe: int = ABSTRACT_NFE,
    detail_nfe: int = DETAIL_NFE,
    *,
    abstract_hz: float,
    detail_hz: float,
    steering: torch.Tensor | None = None,
    on_step: StepCallback | None = None,
    top_frames_per_step: int = 1,
    kv_cache: bool = True,
    subgoals: torch.Tensor | None = None,
    steering_guidance: float = 1.0,
    abstract_grid: list[float] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Hierarchical rollout; returns detail latents [B, frames_per_step * steps, ...] and the top
    predictor's frames [B, top_frames_per_step * steps, ...]: ``steps`` steps of :func:`cascaded_steps`.

    The rates are the caller's: params.yaml's ``data`` section (``data.abstract_hz``, ``data.detail_hz``)
    or the rates the predictors were trained at; the detail frames per step follow from them
    (:func:`detail_frames_per_step`: 5 at the paper's 10 and 2 Hz).

    ``detail_context`` [B, 5, C, h, w] and ``abstract_context`` [B, 5, C_a, h_a, w_a]
    are scaled latents whose last frames show the same instant. ``steering``
    [B, steps, S, 2] conditions the abstract predictor step by step (None:
    unconditional). ``on_step(k)`` is called after step k (progress bars).

    The top predictor is the paper's abstract one by default (1 frame at 2 Hz per
    step). The hierarchy ablations put other top predictors here: detail latents
    at 2 Hz (Exp. 4), or abstract latents at 10 Hz (Exp. 5, ``top_frames_per_step``
    = 5, ``abstract_hz`` = 10); the subgoal is always the top's last new frame.
    ``kv_cache``: cache a causal top predictor's context keys/values (:func:`sample_frames`).
    ``subgoals`` [B, top_frames_per_step * steps, ...]: the top's frames given, not sampled (the real
    future abstract latents: the bottom level's reference rollout). ``steering_guidance``: classifier-free
    guidance on the top's steering (:func:`sample_frames`; 1 = none, the paper's sampler). ``abstract_grid``:
    the top's consistency grid when it is consistency-distilled (:func:`sample_frames`).
    """
    b = detail_context.shape[0]
    detail_frames_per_step(detail_hz, abstract_hz, top_frames_per_step)  # refuse bad rates before any check below
    if subgoals is not None and subgoals.shape[1] != top_frames_per_step * steps:
        raise ValueError(f"subgoals must hold {top_frames_per_step * steps} frames, got {subgoals.shape[1]}")
    stepper = cascaded_steps(abstract_model, detail_model, detail_context, abstract_context, generator,
                             abstract_nfe, detail_nfe, abstract_hz=abstract_hz, detail_hz=detail_hz,
                             steered=steering is not None, top_frames_per_step=top_frames_per_step,
                             kv_cache=kv_cache, subgoals=subgoals, steering_guidance=steering_guidance,
                             abstract_grid=abstract_grid)
    next(stepper)
    details, tops = [], []
    for k in range(steps):
        new, top = stepper.send(_step_steering(steering, k, b, steps).get("steering"))
        details.append(new)
        tops.append(top)
        if on_step is not None:
            on_step(k)
    stepper.close()
    return torch.cat(details, dim=1), torch.cat(tops, dim=1)


@torch.no_grad()
def flat_rollout(
    model: ModelFn,
    context: torch.Tensor,
    steps: int,
    frames_per_step: int,
    nfe: int,
    frame_rate: float,
    generator: torch.Generator,
    steering: torch.Tensor | None = None,
    on_step: StepCallback | None = None,
    kv_cache: bool = True,
) -> torch.Tensor:
    """Single-branch baseline: the same sliding window, no abstract conditioning.

    Returns [B, frames_per_step * steps, ...]; ``kv_cache`` as in :func:`cascaded_rollout`.
    """
    b = context.shape[0]
    frames = []
    table = None if steering is not None else unsteered_modulations(model, context, frames_per_step, nfe, kv_cache)
    for k in range(steps):
        new = sample_frames(model, context, frames_per_step, nfe, generator, kv_cache, modulations=table,
                            frame_rate=frame_rate, **_step_steering(steering, k, b, steps))
        context = _slide(context, new)
        frames.append(new)
        if on_step is not None:
            on_step(k)
    return torch.cat(frames, dim=1)
