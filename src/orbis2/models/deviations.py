"""Deviations from the paper in the ST-DiT: inputs that move a latent frame sideways (docs/differences.md).

Two pathways the paper does not have, each switched by a size field of the ST-DiT
(``STDiTConfig.steering_shift``, ``STDiTConfig.subgoal_shift``; off at the ``paper`` preset's profile):

* :class:`SteeringShift` (docs/differences.md, "Steering pathway"): the steered predictor also sees
  the frame before the prediction moved sideways by the commanded turn;
* :class:`SubgoalShift` (docs/differences.md, "Subgoal pathway"): the detail predictor also sees the
  last context frame moved sideways as far as its abstract subgoal moved.

Both rest on :func:`translate_columns` and the shift search :func:`best_sideways_shift` over
:data:`TURN_SEARCH`, which the counterfactual-turn training targets and the conditioning
diagnostics use too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from orbis2.models.stdit_layers import conditioned_slots, patchify


def translate_columns(x: torch.Tensor, columns: torch.Tensor) -> torch.Tensor:
    """Latent grids [B, C, h, w] moved sideways by ``columns`` [B] (content at column j lands on j + columns).

    Linear interpolation, differentiable in ``columns``; zero (the dataset's per-position
    mean, in the latent cache's normalisation) enters from the border. The sampling grid is the one
    ``F.affine_grid`` makes for a pure translation, bit for bit, built by broadcasting: ``affine_grid``'s
    batched matrix product took 9 ms per call in the steering evaluation's shift search.
    """
    _, _, h, w = x.shape
    shift = -2.0 * columns.to(x.dtype) / max(w - 1, 1)
    across = torch.linspace(-1, 1, w, device=x.device, dtype=x.dtype) + shift[:, None, None]  # [B, 1, w]
    down = torch.linspace(-1, 1, h, device=x.device, dtype=x.dtype)[:, None]  # [h, 1]
    grid = torch.stack(torch.broadcast_tensors(across, down), dim=-1)  # [B, h, w, 2]: (x, y) per output cell
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=True)


# (reach, step) in columns of the searched grid of a turn's sideways motion between latents 0.5 s apart:
# covers the default town's fastest turns.
TURN_SEARCH = (6.0, 0.25)


def best_sideways_shift(before: torch.Tensor, after: torch.Tensor, reach: float, step: float) -> torch.Tensor:
    """How far grids [B, C, h, w] moved sideways from ``before`` to ``after``, in columns [B].

    The shift of ``before`` (:func:`translate_columns`) among -reach .. reach in ``step`` that best
    matches ``after`` over the columns every candidate fills (``ceil(reach)`` from each border
    are left out).
    All candidates are moved in one batched call (one kernel instead of one per candidate).
    """
    margin = math.ceil(reach)
    shifts = torch.arange(-reach, reach + step / 2, step, device=before.device)
    b, n = len(before), len(shifts)
    moved = translate_columns(before.repeat(n, 1, 1, 1), shifts.repeat_interleave(b)).unflatten(0, (n, b))
    errors = ((moved - after)[..., margin:-margin] ** 2).flatten(2).mean(dim=2).T
    return shifts[errors.argmin(dim=1)]


class SteeringShift(nn.Module):
    """The commanded turn as an input of the predicted frame: the frame before it, moved sideways.

    A deviation from the paper, whose steering enters only through adaLN. A turn
    moves the whole abstract latent grid sideways (on the default profile's town
    the best sideways shift between latents 0.5 s apart correlates 0.96 with the
    yaw rate), and a per-channel modulation cannot express a translation: the
    small predictors never learned the yaw rate through adaLN alone. Here the
    frame before the predicted one is moved sideways by each of ``RATES`` x the
    mean (unit-scale) yaw-rate feature x the grid width, the copies are
    patch-embedded together and added to the predicted frame's tokens. Fixed
    rates and a learned embedding (zero at the start, so the steered model
    starts as the pre-trained one) keep the gradient useful from the first
    step; a single learned rate started at zero drifted the wrong way.
    """

    RATES = (1 / 64, 1 / 32, 1 / 16, 1 / 8)  # grid widths per unit of the yaw-rate feature

    def __init__(self, latent_channels: int, hidden_size: int, patch_size: int, yaw_feature: int = 1):
        super().__init__()
        self.patch_size, self.yaw_feature = patch_size, yaw_feature
        self.embed = nn.Linear(len(self.RATES) * patch_size * patch_size * latent_channels, hidden_size)
        self.register_buffer("rates", torch.empty(len(self.RATES)), persistent=False)  # on the model's device
        self.reset_buffers()
        self.reset_parameters()

    def reset_buffers(self) -> None:
        """The fixed rates; run again when the network is allocated from the meta device
        (:func:`orbis2.models.meta.materialize`), since the rates are not in the state dict."""
        with torch.no_grad():
            self.rates.copy_(torch.tensor(self.RATES))

    def reset_parameters(self) -> None:
        nn.init.zeros_(self.embed.weight)
        nn.init.zeros_(self.embed.bias)

    def columns(self, steering: torch.Tensor, width: int) -> torch.Tensor:
        """Steering [B, S, K] -> sideways shifts [len(RATES), B] in latent columns (a missing yaw rate counts as 0)."""
        yaw = torch.nan_to_num(steering[..., self.yaw_feature].float(), nan=0.0).mean(dim=1)
        return self.rates.to(yaw.dtype)[:, None] * width * yaw

    def forward(self, previous: torch.Tensor, steering: torch.Tensor,
                drop: torch.Tensor | None = None) -> torch.Tensor:
        """Previous frame [B, C, h, w] and steering [B, S, K] -> tokens [B, N, D] to add to the predicted frame.

        Zero where ``drop`` (steering dropout, or no steering known): the unconditional path has no shift input.
        """
        moved = torch.cat([translate_columns(previous, shift)
                           for shift in self.columns(steering, previous.shape[-1])], dim=1)
        tokens = self.embed(patchify(moved[:, None], self.patch_size).to(self.embed.weight.dtype))[:, 0]
        if drop is not None:
            tokens = torch.where(drop.reshape(-1, 1, 1), torch.zeros_like(tokens), tokens)
        return tokens


class SubgoalShift(nn.Module):
    """The subgoal's sideways motion as an input of the predicted frames: the last context frame, moved sideways.

    A deviation from the paper, whose detail predictor reads the abstract latents
    only through adaLN and cross-attention. A turn moves the whole latent grid
    sideways (the default town: the best shift between abstract latents 0.5 s
    apart correlates 0.93 with the yaw rate, and the detail grid moves 0.92 as
    far), but the small detail predictors carried about a quarter of the turn
    the real subgoal shows. Here the shift between the two conditioned latents
    (the last context slot's and the subgoal's) is searched
    (:func:`best_sideways_shift`, no gradient), scaled to the predicted grid's
    width and spread linearly over the frames between them; each predicted
    frame gets the last context frame moved by its share, patch-embedded by a
    zero-initialised linear map (so training starts from the plain predictor)
    and added to its tokens.
    """

    def __init__(self, latent_channels: int, hidden_size: int, patch_size: int):
        super().__init__()
        self.patch_size = patch_size
        self.embed = nn.Linear(patch_size * patch_size * latent_channels, hidden_size)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        nn.init.zeros_(self.embed.weight)
        nn.init.zeros_(self.embed.bias)

    def forward(self, x: torch.Tensor, cond_frames: torch.Tensor, slots: torch.Tensor | Sequence[int],
                n_frames: int | None = None) -> tuple[int, torch.Tensor] | None:
        """Frames [B, F', C, h, w] from the window's first up to at least slot ``first`` (the first conditioned one),
        conditioning [B, F, C_a, h_a, w_a] at ``slots`` (a mask [B, F] or the slots, :func:`conditioned_slots`)
        -> (first, tokens [B, F - first - 1, N, D]) for the frames
        after ``first`` of the ``n_frames``-frame window (default F'); None with fewer than two conditioned slots.

        Depends on clean frames only in a rollout (``first`` is a context slot): fixed over its Euler steps.
        """
        slots = conditioned_slots(slots)
        if len(slots) < 2:
            return None
        first, last = slots[0], slots[-1]
        n_frames = x.shape[1] if n_frames is None else n_frames
        width = x.shape[-1]
        with torch.no_grad():
            columns = best_sideways_shift(cond_frames[:, first].float(), cond_frames[:, last].float(),
                                          *TURN_SEARCH) * (width / cond_frames.shape[-1])
        previous = x[:, first]
        moved = torch.stack([translate_columns(previous, columns * (j - first) / (last - first))
                             for j in range(first + 1, n_frames)], dim=1)
        return first, self.embed(patchify(moved, self.patch_size).to(self.embed.weight.dtype))

