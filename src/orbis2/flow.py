"""Flow matching for the predictors, as pure functions (paper Sec. 3.1, eq. 1 and 2).

Convention of the paper: x_tau = (1 - tau) x + tau eps, tau = 0 is data and
tau = 1 is noise; the network regresses the velocity eps - x and sampling
integrates from tau = 1 down to tau = 0. Frames carry their own noise level,
tau [B, F], which is what lets one network serve teacher forcing (clean context
at tau = 0) and diffusion forcing (an independent tau per frame).

``model_fn(x, tau, **cond) -> velocity`` takes all frames [B, F, C, h, w] with
tau [B, F]; ``cond`` (frame rate, abstract conditioning, steering) is passed
through untouched. All randomness comes from an explicit ``torch.Generator``
(drawn on the generator's device, then moved), so runs are reproducible.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

ModelFn = Callable[..., torch.Tensor]

NULL_CONTEXT_TAU = 1.0
"""Noise level of a dropped ("null") context frame, whose content is zeros.

Used by context dropout in teacher forcing and by the linear-probe protocol
("context set to null", paper Appendix "Linear probing details").
"""


def _per_frame(tau: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """tau [B, F] -> [B, F, 1, 1, 1] in ``like``'s dtype, to broadcast over a frame's latent."""
    return tau.to(like.dtype).reshape(*tau.shape, *([1] * (like.ndim - tau.ndim)))


def _randn(shape: torch.Size | tuple[int, ...], like: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    return torch.randn(shape, generator=generator, device=generator.device).to(like)


def _rand(shape: tuple[int, ...], like: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    return torch.rand(shape, generator=generator, device=generator.device).to(like)


def interpolate(x: torch.Tensor, eps: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """x_tau = (1 - tau) x + tau eps, with tau [B, F] (one level per frame)."""
    t = _per_frame(tau, x)
    return (1 - t) * x + t * eps


def velocity_target(x: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """d x_tau / d tau = eps - x, the regression target of eq. 1."""
    return eps - x


def null_context(context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A dropped context: zero frames and their noise level ``NULL_CONTEXT_TAU`` [B, F_c]."""
    tau = torch.full(context.shape[:2], NULL_CONTEXT_TAU, device=context.device, dtype=context.dtype)
    return torch.zeros_like(context), tau


def teacher_forcing_draws(context: torch.Tensor, target: torch.Tensor, generator: torch.Generator
                          ) -> dict[str, torch.Tensor]:
    """The random numbers of one :func:`teacher_forcing_loss`, in its order of drawing.

    Drawn apart from the loss so that the loss itself (:func:`teacher_forcing_from_draws`)
    holds no generator and compiles to one graph with the network.
    """
    b = context.shape[0]
    return {"eps": _randn(target.shape, target, generator), "tau": _rand((b, 1), target, generator),
            "noise_draw": _rand((b,), target, generator), "aug": _randn(context.shape, context, generator),
            "drop_draw": _rand((b,), target, generator)}


def teacher_forcing_from_draws(
    model_fn: ModelFn,
    context: torch.Tensor,
    target: torch.Tensor,
    draws: dict[str, torch.Tensor],
    context_noise_prob: float = 0.0,
    context_noise_std: float = 0.1,
    context_drop_prob: float = 0.0,
    **cond,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """:func:`teacher_forcing_loss` given its :func:`teacher_forcing_draws`; metrics stay tensors (no host sync)."""
    b, n_context = context.shape[:2]
    eps = draws["eps"]
    tau_target = draws["tau"].expand(b, target.shape[1])
    tau_context = torch.zeros(b, n_context, device=target.device, dtype=target.dtype)

    per_sample = (b,) + (1,) * (context.ndim - 1)
    noised = draws["noise_draw"] < context_noise_prob
    context = torch.where(noised.reshape(per_sample), context + draws["aug"] * context_noise_std, context)
    dropped = draws["drop_draw"] < context_drop_prob
    null, null_tau = null_context(context)
    context = torch.where(dropped.reshape(per_sample), null, context)
    tau_context = torch.where(dropped[:, None], null_tau, tau_context)

    x = torch.cat([context, interpolate(target, eps, tau_target)], dim=1)
    tau = torch.cat([tau_context, tau_target], dim=1)
    velocity = model_fn(x, tau, **cond)[:, n_context:]
    loss = F.mse_loss(velocity.float(), velocity_target(target, eps).float())
    metrics = {"loss": loss.detach(), "context_noised": noised.float().mean(),
               "context_dropped": dropped.float().mean()}
    return loss, metrics


def teacher_forcing_loss(
    model_fn: ModelFn,
    context: torch.Tensor,
    target: torch.Tensor,
    generator: torch.Generator,
    context_noise_prob: float = 0.0,
    context_noise_std: float = 0.1,
    context_drop_prob: float = 0.0,
    **cond,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Eq. 1: clean context at tau = 0, one tau ~ U[0, 1] per sample for all target frames.

    ``context`` [B, F_c, ...] and ``target`` [B, F_t, ...] are packed on the
    frame axis; the MSE is on the target frames only (the authors' code,
    "Predictor"). Per sample, with ``context_noise_prob`` the context gets
    ``context_noise_std`` * N(0, 1) added (it stays at tau = 0), and with
    ``context_drop_prob`` it is replaced by the null context (``null_context``),
    which trains the context-free path the linear probes use (reference v1
    code: 0.5 / 0.1 / 0.2). Metrics are 0-dim tensors, read by the caller when it logs.
    """
    return teacher_forcing_from_draws(model_fn, context, target, teacher_forcing_draws(context, target, generator),
                                      context_noise_prob, context_noise_std, context_drop_prob, **cond)


def diffusion_forcing_draws(frames: torch.Tensor, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """The random numbers of one :func:`diffusion_forcing_loss` (noise, then one tau per frame)."""
    return {"eps": _randn(frames.shape, frames, generator), "tau": _rand(tuple(frames.shape[:2]), frames, generator)}


def diffusion_forcing_from_draws(model_fn: ModelFn, frames: torch.Tensor, draws: dict[str, torch.Tensor],
                                 **cond) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """:func:`diffusion_forcing_loss` given its :func:`diffusion_forcing_draws`; metrics stay tensors."""
    eps, tau = draws["eps"], draws["tau"]
    velocity = model_fn(interpolate(frames, eps, tau), tau, **cond)
    loss = F.mse_loss(velocity.float(), velocity_target(frames, eps).float())
    return loss, {"loss": loss.detach(), "tau_mean": tau.float().mean()}


def diffusion_forcing_loss(
    model_fn: ModelFn, frames: torch.Tensor, generator: torch.Generator, **cond
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Eq. 2: an independent tau_i ~ U[0, 1] for every frame of every sample, loss on all frames."""
    return diffusion_forcing_from_draws(model_fn, frames, diffusion_forcing_draws(frames, generator), **cond)


def guided_velocity(conditional: torch.Tensor, unconditional: torch.Tensor, scale: float) -> torch.Tensor:
    """Classifier-free guidance (Ho and Salimans, 2022): ``unconditional + scale * (conditional - unconditional)``.

    Scale 1 is the conditional velocity, 0 the unconditional one; above 1 the conditioning's effect is
    extrapolated. Needs a model trained with its conditioning dropped at times (steering dropout).
    """
    return unconditional + scale * (conditional - unconditional)


def euler_grid(nfe: int) -> list[float]:
    """The uniform noise-level grid 1 = tau_0 > ... > tau_nfe = 0 of :func:`euler_sample`, as Python numbers:
    read once per sampling call, so the Euler steps themselves never read a tensor back."""
    return torch.linspace(1.0, 0.0, nfe + 1).tolist()


@torch.no_grad()
def euler_sample(
    model_fn: ModelFn,
    context: torch.Tensor,
    n_target: int,
    nfe: int,
    generator: torch.Generator,
    target_fn: ModelFn | None = None,
    noise: torch.Tensor | None = None,
    **cond,
) -> torch.Tensor:
    """Sample ``n_target`` frames after ``context`` [B, F_c, C, h, w]: Euler from tau = 1 to 0 in ``nfe`` steps.

    Uniform grid, context at tau = 0 throughout (paper "Inference protocol":
    15 NFE abstract, 30 NFE detail). Returns the target frames [B, n_target, C, h, w].
    ``target_fn(x_target, step)``, when given, replaces the full-window call with one
    that returns the target frames' velocity alone at Euler step ``step`` (tau =
    ``euler_grid(nfe)[step]``), from inputs it prepared before the loop (the KV-cached
    context, the modulations of every step, the conditioning); the noise drawn is the same.
    ``noise`` [B, n_target, C, h, w] replaces the draw (the start of a given ODE path).
    """
    b, n_context = context.shape[:2]
    x = _randn((b, n_target, *context.shape[2:]), context, generator) if noise is None else noise
    tau_context = torch.zeros(b, n_context, device=context.device, dtype=context.dtype)
    grid = euler_grid(nfe)
    for step, (tau_now, tau_next) in enumerate(zip(grid[:-1], grid[1:])):
        if target_fn is not None:
            velocity = target_fn(x, step)
        else:
            tau_target = torch.full((b, n_target), tau_now, device=context.device, dtype=context.dtype)
            tau = torch.cat([tau_context, tau_target], dim=1)
            velocity = model_fn(torch.cat([context, x], dim=1), tau, **cond)[:, n_context:]
        x = x + (tau_next - tau_now) * velocity.to(x.dtype)
    return x


def reflow_draws(context: torch.Tensor, n_target: int, generator: torch.Generator, teacher_fn: ModelFn,
                 teacher_nfe: int, **cond) -> dict[str, torch.Tensor]:
    """The teacher's (noise, sample) pair and the student's tau for one :func:`reflow_loss`, in its order."""
    b = context.shape[0]
    eps = _randn((b, n_target, *context.shape[2:]), context, generator)
    with torch.no_grad():
        x_teacher = euler_sample(teacher_fn, context, n_target, teacher_nfe, generator, noise=eps, **cond).detach()
    return {"eps": eps, "x_teacher": x_teacher, "tau": _rand((b, 1), context, generator)}


def reflow_from_draws(model_fn: ModelFn, context: torch.Tensor, draws: dict[str, torch.Tensor],
                      **cond) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """:func:`reflow_loss` given its :func:`reflow_draws`: the student's regression of the straight path."""
    eps, x_teacher = draws["eps"], draws["x_teacher"]
    b, n_context = context.shape[:2]
    tau_target = draws["tau"].expand(b, eps.shape[1])
    tau = torch.cat([torch.zeros(b, n_context, device=context.device, dtype=context.dtype), tau_target], dim=1)
    x = torch.cat([context, interpolate(x_teacher, eps, tau_target)], dim=1)
    velocity = model_fn(x, tau, **cond)[:, n_context:]
    loss = F.mse_loss(velocity.float(), velocity_target(x_teacher, eps).float())
    return loss, {"loss": loss.detach()}


def reflow_loss(
    model_fn: ModelFn,
    teacher_fn: ModelFn,
    context: torch.Tensor,
    n_target: int,
    generator: torch.Generator,
    teacher_nfe: int,
    **cond,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Rectified-flow reflow distillation (Liu et al., 2023, "Flow straight and fast"), with eq. 1's conditioning.

    The teacher integrates its ODE from noise ``eps`` to a sample ``x_T``
    (``teacher_nfe`` Euler steps, clean context); the student regresses the
    straight path between the pair: x_tau = (1 - tau) x_T + tau eps, target
    eps - x_T. Paths of the reflowed field are nearly straight, so a few Euler
    steps land where the teacher's many steps do. Same interpolant, target and
    sampler as the teacher's flow matching; only the pairing of data and noise
    changes (coupled by the teacher instead of independent).
    """
    draws = reflow_draws(context, n_target, generator, teacher_fn, teacher_nfe, **cond)
    return reflow_from_draws(model_fn, context, draws, **cond)


@torch.no_grad()
def consistency_sample(
    model_fn: ModelFn,
    context: torch.Tensor,
    n_target: int,
    grid: list[float],
    generator: torch.Generator,
    noises: torch.Tensor | None = None,
    **cond,
) -> torch.Tensor:
    """Few-step consistency sampling, as the authors' distilled abstract predictor samples (Song et al., 2023,
    "Consistency models", multistep sampling).

    At each noise level tau_k of the descending ``grid`` (their 4-step grid: 0.99, 0.9375, 0.8333, 0.625) the
    current estimate of the clean target is noised again to tau_k with fresh noise (the first step starts from
    noise alone), the network runs once (context clean) and its endpoint x_tau - tau_k * velocity becomes the
    estimate: one network call per grid level, the last estimate returned. ``noises`` [len(grid), B, n_target,
    C, h, w] replaces the draws (one per level, in order).
    """
    b, n_context = context.shape[:2]
    shape = (b, n_target, *context.shape[2:])
    tau_context = torch.zeros(b, n_context, device=context.device, dtype=context.dtype)
    estimate = None
    for step, level in enumerate(grid):
        eps = _randn(shape, context, generator) if noises is None else noises[step]
        x = eps if estimate is None else (1 - level) * estimate + level * eps
        tau = torch.cat([tau_context, torch.full((b, n_target), level, device=context.device, dtype=context.dtype)],
                        dim=1)
        velocity = model_fn(torch.cat([context, x], dim=1), tau, **cond)[:, n_context:]
        estimate = x - level * velocity.to(x.dtype)
    return estimate
