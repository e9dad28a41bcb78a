"""Spatio-Temporal DiT (ST-DiT) predictor of Orbis 2: every block in one file.

Over 600 lines on purpose: the network, its blocks, its typed sizes and its file format
read together, as DiT's models.py.

One network serves both levels of the hierarchy (paper Sec. 3.2, 4.2 and
Appendix "Model details"):

* the abstract predictor F_H: causal temporal attention, optionally steered by
  an ego-motion sequence (the embedding is added to the noise-level embedding
  that feeds adaLN, paper "Action-conditioning"), and with ``steering_shift``
  also through the frame before the prediction moved sideways by the commanded
  turn (:class:`SteeringShift`, a deviation from the paper);
* the detail predictor F_L: bidirectional temporal attention, conditioned on
  abstract latents placed at frame slots, through a per-token gated adaLN path
  and a gated spatial cross-attention layer in every block, and with
  ``subgoal_shift`` also through the last context frame moved sideways as far
  as the subgoal moved (:class:`SubgoalShift`, a deviation from the paper).

Inputs are latent frames ``x`` [B, F, C, h, w] with one noise level per frame
``tau`` [B, F], so the same network is trained with teacher forcing (context at
tau = 0) and diffusion forcing (independent tau per frame). It returns the
flow-matching velocity [B, F, C, h, w] (``orbis2.flow``).

Block layout follows the reference STDiT (the authors' code, "Predictor"): spatial
attention, spatial MLP, temporal attention, temporal MLP, each with its own
adaLN-Zero shift/scale/gate. With hidden 768, depth 24 that gives the paper's
512M parameters; the abstract conditioning adds the paper's 43M because its
tokens live at half the width (``cond_dim``), which is what lets both the adaLN
path and the cross-attention fit that budget.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint

from orbis2.errors import OrbisError
from orbis2.io import atomic_file, sha256_file
from orbis2.models import ModelConfig, preset_config, split_build
from orbis2.models.tokenizer import sincos_pos_embed_2d

# Initial gates of the abstract conditioning paths: small but non-zero (paper Appendix "Model details").
COND_GATE_BIAS = -2.0  # adaLN path gate sigmoid(-2) ~ 0.12
CROSS_GATE_INIT = 0.1  # cross-attention gate tanh(0.1) ~ 0.1


def modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return x * (1 + scale) + shift


def sinusoidal_embedding(values: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """``values`` [...] -> [..., dim] cos/sin features at geometric frequencies (DiT's timestep features)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=values.device, dtype=torch.float32) / half)
    angles = values.float()[..., None] * freqs
    return torch.cat([torch.cos(angles), torch.sin(angles)], dim=-1)


def rate_embedding(frame_rate: torch.Tensor | float | None, batch: int, dim: int,
                   device: torch.device) -> torch.Tensor | None:
    """Frame rate in Hz (a number or [B]) -> sinusoidal features [B, dim] built on ``device`` (no host copy)."""
    if frame_rate is None:
        return None
    if isinstance(frame_rate, torch.Tensor):
        rate = frame_rate.to(device=device, dtype=torch.float32).expand(batch)
    else:
        rate = torch.full((batch,), float(frame_rate), device=device, dtype=torch.float32)
    return sinusoidal_embedding(rate, dim)


def conditioned_slots(cond_mask: torch.Tensor | Sequence[int]) -> tuple[int, ...]:
    """The frame slots that carry an abstract latent, the same in every sample, from ``cond_mask`` [B, F].

    Reads the mask on the host (a device sync) and checks it once: callers that know their slots
    (rollouts, training windows) pass them as a tuple instead, which keeps the forward free of host syncs.
    """
    if not isinstance(cond_mask, torch.Tensor):
        return tuple(int(slot) for slot in cond_mask)
    mask = cond_mask.bool()
    counts = mask.sum(dim=1)
    if (counts != counts[0]).any():
        raise ValueError(f"every sample needs the same number of conditioned slots, got {counts.tolist()}")
    if not bool((mask == mask[0]).all()):
        raise ValueError("every sample needs the same conditioned slots (cond_mask rows differ)")
    return tuple(mask[0].nonzero().flatten().tolist())


def grid_positions(dim: int, h: int, w: int, device: torch.device) -> torch.Tensor:
    """Fixed 2-D sin-cos positions [h*w, dim] of a patch grid, built on ``device`` (no host copy)."""
    return sincos_pos_embed_2d(dim, (h, w), device)


def patchify(x: torch.Tensor, p: int) -> torch.Tensor:
    """[B, F, C, h, w] -> [B, F, (h/p)(w/p), p*p*C], row-major over the patch grid."""
    b, f, c, h, w = x.shape
    if h % p or w % p:
        raise ValueError(f"latent grid {h}x{w} is not divisible by patch size {p}")
    x = x.reshape(b, f, c, h // p, p, w // p, p).permute(0, 1, 3, 5, 4, 6, 2)
    return x.reshape(b, f, (h // p) * (w // p), p * p * c)


def unpatchify(tokens: torch.Tensor, p: int, c: int, h: int, w: int) -> torch.Tensor:
    """Inverse of ``patchify``: [B, F, N, p*p*C] -> [B, F, C, h, w]."""
    b, f = tokens.shape[:2]
    x = tokens.reshape(b, f, h // p, w // p, p, p, c).permute(0, 1, 6, 2, 4, 3, 5)
    return x.reshape(b, f, c, h, w)


# --------------------------------------------------------------------------- layers


class Attention(nn.Module):
    """Multi-head self-attention with qk-norm (RMSNorm per head), through SDPA (flash attention on GPU).

    ``causal`` is a hard mask (``is_causal=True``): the reference code's float
    mask of ones only adds +1 to the scores and lets the future leak in.
    """

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"dim = {dim} is not divisible by num_heads = {num_heads}")
        self.num_heads = num_heads
        head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.q_norm = nn.RMSNorm(head_dim, eps=1e-6)
        self.k_norm = nn.RMSNorm(head_dim, eps=1e-6)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, causal: bool = False, past: tuple[torch.Tensor, torch.Tensor] | None = None,
                keep: list | None = None) -> torch.Tensor:
        """``past``: key and value buffers [B, H, P + n, d] holding earlier positions' keys/values in their first
        P positions; this call writes its own n after them, in place, and attends over the whole buffer.
        ``keep``: a list that receives this call's (keys, values)."""
        b, n, d = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, d // self.num_heads).permute(2, 0, 3, 1, 4)
        q, k = self.q_norm(q).to(v.dtype), self.k_norm(k).to(v.dtype)  # bf16 under autocast: flash-eligible
        if keep is not None:
            keep.append((k, v))
        mask = None
        if past is not None:
            n_past = past[0].shape[2] - n
            past[0][:, :, n_past:].copy_(k)
            past[1][:, :, n_past:].copy_(v)
            k, v = past
            if causal and n > 1:  # query i sees every cached position and its own first i + 1
                mask = torch.ones(n, n_past + n, dtype=torch.bool, device=x.device).tril(n_past)
            causal = False
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, is_causal=causal)
        return self.proj(out.transpose(1, 2).reshape(b, n, d))


class CrossAttention(nn.Module):
    """Queries from the detail tokens, keys/values from the abstract conditioning tokens (qk-norm, SDPA)."""

    def __init__(self, dim: int, context_dim: int, num_heads: int):
        super().__init__()
        if context_dim % num_heads:
            raise ValueError(f"cond_dim = {context_dim} is not divisible by num_heads = {num_heads}")
        self.num_heads = num_heads
        head_dim = context_dim // num_heads
        self.q = nn.Linear(dim, context_dim)
        self.kv = nn.Linear(context_dim, 2 * context_dim)
        self.q_norm = nn.RMSNorm(head_dim, eps=1e-6)
        self.k_norm = nn.RMSNorm(head_dim, eps=1e-6)
        self.proj = nn.Linear(context_dim, dim)

    def keys_values(self, context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Context [B, M, cond_dim] -> keys and values [B, H, M, d]: fixed while the context is."""
        b, m = context.shape[:2]
        k, v = self.kv(context).reshape(b, m, 2, self.num_heads, -1).permute(2, 0, 3, 1, 4)
        return self.k_norm(k).to(v.dtype), v

    def forward(self, x: torch.Tensor, keys: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
        b, n, _ = x.shape
        inner = self.q.out_features
        q = self.q(x).reshape(b, n, self.num_heads, -1).transpose(1, 2)
        out = F.scaled_dot_product_attention(self.q_norm(q).to(values.dtype), keys, values)
        return self.proj(out.transpose(1, 2).reshape(b, n, inner))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x), approximate="tanh"))


def _norm(dim: int) -> nn.LayerNorm:
    """LayerNorm without affine parameters: adaLN supplies shift and scale (DiT)."""
    return nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)


# --------------------------------------------------------------------------- embedders


class NoiseLevelEmbedder(nn.Module):
    """tau in [0, 1] -> D: 256-d sinusoidal features of 1000 * tau, then an MLP (DiT's timestep embedder).

    The 1000x puts tau on DiT's timestep scale so the geometric frequencies
    resolve small differences in noise level.
    """

    def __init__(self, hidden_size: int, frequency_dim: int = 256):
        super().__init__()
        self.frequency_dim = frequency_dim
        self.mlp = nn.Sequential(nn.Linear(frequency_dim, hidden_size), nn.SiLU(), nn.Linear(hidden_size, hidden_size))

    def forward(self, tau: torch.Tensor) -> torch.Tensor:
        features = sinusoidal_embedding(tau * 1000.0, self.frequency_dim)
        return self.mlp(features.to(self.mlp[0].weight.dtype))


class SteeringEmbedder(nn.Module):
    """Steering sequence [B, S, K] (e.g. speed and yaw rate; NaN = missing) -> [B, D] (the authors' code, "Steering").

    Each element's token is the sum over features of a small MLP (1 -> D -> D)
    of that value, or of a learned "no value" embedding where it is NaN, plus a
    learned position embedding. Tokens pass SiLU and a linear layer before the
    mean over the sequence: a purely linear mean would reduce the position
    embeddings to a constant and lose the order of the sequence. That output
    layer starts at zero and the null embedding (steering dropout) at zero, so
    an embedder added to a pre-trained unconditional predictor leaves it
    unchanged at the start of the fine-tune (paper "Action-conditioning").
    Values should be roughly unit scale (normalise speed in m/s by the caller).
    """

    def __init__(self, hidden_size: int, num_features: int, max_len: int):
        super().__init__()
        self.feature_mlps = nn.ModuleList(
            nn.Sequential(nn.Linear(1, hidden_size), nn.SiLU(), nn.Linear(hidden_size, hidden_size))
            for _ in range(num_features)
        )
        self.no_value = nn.Parameter(torch.zeros(num_features, hidden_size))
        self.position = nn.Parameter(torch.zeros(max_len, hidden_size))
        self.out = nn.Linear(hidden_size, hidden_size)
        self.null = nn.Parameter(torch.zeros(hidden_size))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        for mlp in self.feature_mlps:
            for layer in (mlp[0], mlp[2]):
                nn.init.xavier_uniform_(layer.weight)
                nn.init.zeros_(layer.bias)
        nn.init.normal_(self.no_value, std=0.02)
        nn.init.normal_(self.position, std=0.02)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        nn.init.zeros_(self.null)

    def tokens(self, steering: torch.Tensor) -> torch.Tensor:
        """Per-element tokens [B, S, D] before pooling."""
        b, s, k = steering.shape
        if k != len(self.feature_mlps):
            raise ValueError(f"steering has {k} features per step, the embedder expects {len(self.feature_mlps)}")
        if s > self.position.shape[0]:
            raise ValueError(f"steering has {s} steps, more than the embedder's max_len = {self.position.shape[0]}")
        steering = steering.to(self.out.weight.dtype)
        total = self.position[:s].expand(b, s, -1)
        for i, mlp in enumerate(self.feature_mlps):
            value = steering[..., i : i + 1]
            missing = torch.isnan(value)
            total = total + torch.where(missing, self.no_value[i], mlp(torch.nan_to_num(value, nan=0.0)))
        return total

    def forward(self, steering: torch.Tensor, drop: torch.Tensor | None = None) -> torch.Tensor:
        embedding = self.out(F.silu(self.tokens(steering))).mean(dim=1)
        if drop is not None:
            embedding = torch.where(drop.reshape(-1, 1), self.null.to(embedding.dtype), embedding)
        return embedding


def translate_columns(x: torch.Tensor, columns: torch.Tensor) -> torch.Tensor:
    """Latent grids [B, C, h, w] moved sideways by ``columns`` [B] (content at column j lands on j + columns).

    Linear interpolation, differentiable in ``columns``; zero (the dataset's per-position
    mean, in the latent cache's normalisation) enters from the border.
    """
    b, _, h, w = x.shape
    theta = torch.zeros(b, 2, 3, device=x.device, dtype=x.dtype)
    theta[:, 0, 0] = 1.0
    theta[:, 1, 1] = 1.0
    theta[:, 0, 2] = -2.0 * columns.to(x.dtype) / max(w - 1, 1)
    grid = F.affine_grid(theta, [b, 1, h, w], align_corners=True)
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
        self.register_buffer("rates", torch.tensor(self.RATES), persistent=False)  # on the model's device
        self.reset_parameters()

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


class AbstractConditioner(nn.Module):
    """Abstract latents at their frame slots -> conditioning tokens [B, F, N, cond_dim].

    Paper Appendix "Detailed short-horizon predictor": a linear patchify (resized
    to the detail grid first if the grids differ), zero where ``cond_mask`` says
    the slot carries no latent, plus a learned frame-position MLP of i/(F-1) for
    every slot (the authors' code, "Hierarchy wiring") and the fixed 2-D sin-cos
    position, so the cross-attention keys know where each token lies.
    """

    def __init__(self, abstract_channels: int, cond_dim: int, patch_size: int):
        super().__init__()
        self.patch_size = patch_size
        self.patchify = nn.Linear(patch_size * patch_size * abstract_channels, cond_dim)
        self.frame_position = nn.Sequential(nn.Linear(1, cond_dim), nn.SiLU(), nn.Linear(cond_dim, cond_dim))

    def forward(self, cond_frames: torch.Tensor, slots: tuple[int, ...], grid_hw: tuple[int, int]) -> torch.Tensor:
        """``slots``: the conditioned frame slots (:func:`conditioned_slots`); the other slots' latents are zeroed."""
        b, f, c, ha, wa = cond_frames.shape
        h, w = grid_hw
        if (ha, wa) != (h, w):
            resized = F.interpolate(cond_frames.flatten(0, 1), size=(h, w), mode="bilinear", align_corners=False)
            cond_frames = resized.reshape(b, f, c, h, w)
        tokens = self.patchify(patchify(cond_frames, self.patch_size).to(self.patchify.weight.dtype))
        keep = torch.zeros(f, device=tokens.device, dtype=tokens.dtype)
        for s in slots:
            keep[s] = 1.0
        tokens = tokens * keep[None, :, None, None]
        slot = torch.arange(f, device=tokens.device, dtype=tokens.dtype) / max(f - 1, 1)
        p = self.patch_size
        grid = grid_positions(tokens.shape[-1], h // p, w // p, tokens.device).to(tokens.dtype)
        return tokens + self.frame_position(slot[:, None])[None, :, None] + grid


# --------------------------------------------------------------------------- blocks


class STDiTBlock(nn.Module):
    """Space-time DiT block: spatial attention, spatial MLP, temporal attention, temporal MLP.

    Each sub-layer is adaLN-Zero modulated (shift, scale, gate) by the
    per-frame conditioning vector. With ``cond_dim`` the block also takes the
    abstract conditioning (paper Appendix "Model details"): before the block,
    x += sigmoid(gate) * modulate(LN(x), shift, scale) with shift/scale/gate
    per token from the aligned conditioning tokens; after spatial attention, a
    gated cross-attention to the sample's conditioning tokens, gate tanh(alpha).
    """

    def __init__(self, hidden_size: int, num_heads: int, mlp_ratio: float, cond_dim: int | None = None):
        super().__init__()
        mlp_hidden = int(hidden_size * mlp_ratio)
        self.space_norm, self.space_mlp_norm = _norm(hidden_size), _norm(hidden_size)
        self.time_norm, self.time_mlp_norm = _norm(hidden_size), _norm(hidden_size)
        self.space_attn = Attention(hidden_size, num_heads)
        self.space_mlp = Mlp(hidden_size, mlp_hidden)
        self.time_attn = Attention(hidden_size, num_heads)
        self.time_mlp = Mlp(hidden_size, mlp_hidden)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(hidden_size, 12 * hidden_size))
        self.has_cond = cond_dim is not None
        if self.has_cond:
            self.cond_norm = _norm(hidden_size)
            self.cond_modulation = nn.Sequential(nn.SiLU(), nn.Linear(cond_dim, 3 * hidden_size))
            self.cross_norm = _norm(hidden_size)
            self.cross_attn = CrossAttention(hidden_size, cond_dim, num_heads)
            self.cross_gate = nn.Parameter(torch.zeros(hidden_size))

    def modulation(self, c: torch.Tensor) -> torch.Tensor:
        """The adaLN output [B, F, 1, 12 D] for the per-frame conditioning ``c`` [B, F, D]: it depends on the
        noise levels (and steering) alone, so a sampler computes it before its Euler loop."""
        return self.adaLN_modulation(c)[:, :, None]

    def conditioning(self, cond_tokens: torch.Tensor | None, cond_context: torch.Tensor | None
                     ) -> BlockConditioning | None:
        """The abstract conditioning's per-token modulation and cross-attention keys/values (fixed while the
        conditioning frames are); None without conditioning."""
        if cond_tokens is None:
            return None
        shift, scale, gate = self.cond_modulation(cond_tokens).chunk(3, dim=-1)
        keys, values = self.cross_attn.keys_values(cond_context) if cond_context is not None else (None, None)
        return BlockConditioning(shift, scale, torch.sigmoid(gate), keys, values)

    def forward(
        self,
        x: torch.Tensor,
        modulation: torch.Tensor,
        causal: bool,
        cond: BlockConditioning | None = None,
        time_past: tuple[torch.Tensor, torch.Tensor] | None = None,
        time_keep: list | None = None,
    ) -> torch.Tensor:
        """x [B, F, N, D]; ``modulation`` from :meth:`modulation`; ``cond`` from :meth:`conditioning`.

        ``time_past`` / ``time_keep``: the temporal attention's key/value cache (:class:`TemporalKVCache`).
        """
        b, f, n, d = x.shape
        if cond is not None:
            x = x + cond.gate * modulate(self.cond_norm(x), cond.shift, cond.scale)
        (sh_sa, sc_sa, g_sa, sh_sm, sc_sm, g_sm,
         sh_ta, sc_ta, g_ta, sh_tm, sc_tm, g_tm) = modulation.chunk(12, dim=-1)

        h = modulate(self.space_norm(x), sh_sa, sc_sa).reshape(b * f, n, d)
        x = x + g_sa * self.space_attn(h).reshape(b, f, n, d)
        if cond is not None and cond.keys is not None:
            h = self.cross_attn(self.cross_norm(x).reshape(b, f * n, d), cond.keys, cond.values)
            x = x + torch.tanh(self.cross_gate) * h.reshape(b, f, n, d)
        x = x + g_sm * self.space_mlp(modulate(self.space_mlp_norm(x), sh_sm, sc_sm))

        h = modulate(self.time_norm(x), sh_ta, sc_ta).permute(0, 2, 1, 3).reshape(b * n, f, d)
        h = self.time_attn(h, causal=causal, past=time_past, keep=time_keep).reshape(b, n, f, d).permute(0, 2, 1, 3)
        x = x + g_ta * h
        return x + g_tm * self.time_mlp(modulate(self.time_mlp_norm(x), sh_tm, sc_tm))


class FinalLayer(nn.Module):
    """adaLN final layer of DiT: modulated LayerNorm, then a linear map back to patches (zero-initialised)."""

    def __init__(self, hidden_size: int, patch_size: int, out_channels: int):
        super().__init__()
        self.norm = _norm(hidden_size)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(hidden_size, 2 * hidden_size))
        self.linear = nn.Linear(hidden_size, patch_size * patch_size * out_channels)

    def modulation(self, c: torch.Tensor) -> torch.Tensor:
        return self.adaLN_modulation(c)[:, :, None]

    def forward(self, x: torch.Tensor, modulation: torch.Tensor) -> torch.Tensor:
        shift, scale = modulation.chunk(2, dim=-1)
        return self.linear(modulate(self.norm(x), shift, scale))


def _block_step(block: STDiTBlock, x: torch.Tensor, c: torch.Tensor, causal: bool, cond_tokens: torch.Tensor | None,
                cond_context: torch.Tensor | None) -> torch.Tensor:
    """One block with its modulation and conditioning computed here: inside an activation checkpoint they are
    recomputed in the backward pass instead of kept."""
    return block(x, block.modulation(c), causal, block.conditioning(cond_tokens, cond_context))


@dataclass
class BlockConditioning:
    """One block's abstract conditioning: the per-token adaLN path (shift, scale and sigmoid(gate)
    [B, F, N, D]) and the cross-attention's keys and values [B, H, M, d] (None without conditioned slots)."""

    shift: torch.Tensor
    scale: torch.Tensor
    gate: torch.Tensor
    keys: torch.Tensor | None
    values: torch.Tensor | None


@dataclass
class WindowConstants:
    """What a forward reads besides the noisy frames and their noise levels: fixed over the Euler steps of
    one sampling call, so :meth:`STDiT.plan` computes it once.

    ``positions`` [N, D] and ``rate`` [B, D] (fp32), the abstract conditioning tokens [B, F, N, cond_dim] and
    cross-attention context [B, M, cond_dim], per block the conditioning (``blocks``, when precomputed), and the
    :class:`SubgoalShift` input (first conditioned slot, tokens of the frames after it).
    """

    positions: torch.Tensor
    rate: torch.Tensor | None
    cond_tokens: torch.Tensor | None = None
    cond_context: torch.Tensor | None = None
    blocks: list[BlockConditioning | None] | None = None
    subgoal: tuple[int, torch.Tensor] | None = None


# --------------------------------------------------------------------------- model


class STDiT(nn.Module):
    """The ST-DiT velocity network (see the module docstring).

    Token positions: fixed 2-D sin-cos over the patch grid, a learned frame
    embedding and a sinusoidal frame-rate encoding (the authors' code, "Predictor").
    Frame embeddings are aligned to the last frame (frame i of F uses slot
    max_frames - F + i, as in the reference code), so the predicted frame has
    the same embedding whatever the context length, including the linear-probe
    protocol's context-free input.
    """

    def __init__(
        self,
        latent_channels: int,
        hidden_size: int,
        depth: int,
        num_heads: int,
        mlp_ratio: float = 4.0,
        patch_size: int = 1,
        max_frames: int = 16,
        causal: bool = False,
        abstract_channels: int | None = None,
        cond_dim: int | None = None,
        steering: bool = False,
        steering_features: int = 2,
        steering_len: int = 16,
        steering_shift: bool = False,
        subgoal_shift: bool = False,
    ):
        super().__init__()
        self.latent_channels = latent_channels
        # Activation checkpointing of the first ``checkpoint_blocks`` blocks while training (their activations
        # are recomputed in the backward pass); set by the training loop, not part of the architecture.
        self.checkpoint_blocks = 0
        self.hidden_size = hidden_size
        self.patch_size = patch_size
        self.max_frames = max_frames
        self.causal = causal
        self.abstract_channels = abstract_channels
        block_cond_dim = None
        if abstract_channels is not None:
            block_cond_dim = cond_dim or hidden_size
            self.abstract = AbstractConditioner(abstract_channels, block_cond_dim, patch_size)
        self.x_embedder = nn.Linear(patch_size * patch_size * latent_channels, hidden_size)
        self.tau_embedder = NoiseLevelEmbedder(hidden_size)
        self.frame_embed = nn.Parameter(torch.zeros(max_frames, hidden_size))
        self.steering = SteeringEmbedder(hidden_size, steering_features, steering_len) if steering else None
        self.steering_shift = (SteeringShift(latent_channels, hidden_size, patch_size)
                               if steering and steering_shift else None)
        if subgoal_shift and abstract_channels is None:
            raise ValueError("subgoal_shift needs abstract conditioning (the detail predictor)")
        self.subgoal_shift = SubgoalShift(latent_channels, hidden_size, patch_size) if subgoal_shift else None
        self.blocks = nn.ModuleList(
            STDiTBlock(hidden_size, num_heads, mlp_ratio, block_cond_dim) for _ in range(depth)
        )
        self.final_layer = FinalLayer(hidden_size, patch_size, latent_channels)
        self._initialize()

    def _initialize(self) -> None:
        """DiT initialisation (xavier, zero adaLN and final layer) plus small non-zero conditioning paths."""

        def basic(module: nn.Module) -> None:
            if isinstance(module, nn.Linear):
                nn.init.xavier_uniform_(module.weight)
                nn.init.zeros_(module.bias)

        self.apply(basic)
        nn.init.trunc_normal_(self.frame_embed, std=0.02)
        nn.init.normal_(self.tau_embedder.mlp[0].weight, std=0.02)
        nn.init.normal_(self.tau_embedder.mlp[2].weight, std=0.02)
        for block in self.blocks:
            nn.init.zeros_(block.adaLN_modulation[-1].weight)
            nn.init.zeros_(block.adaLN_modulation[-1].bias)
            if block.has_cond:
                # Small non-zero shift/scale and gates sigmoid(-2) ~ 0.12 and
                # tanh(0.1) ~ 0.1: the paths start weak but carry gradient.
                nn.init.normal_(block.cond_modulation[-1].weight, std=0.02)
                bias = block.cond_modulation[-1].bias
                nn.init.zeros_(bias)
                nn.init.constant_(bias[2 * self.hidden_size :], COND_GATE_BIAS)
                nn.init.constant_(block.cross_gate, CROSS_GATE_INIT)
        nn.init.zeros_(self.final_layer.adaLN_modulation[-1].weight)
        nn.init.zeros_(self.final_layer.adaLN_modulation[-1].bias)
        nn.init.zeros_(self.final_layer.linear.weight)
        nn.init.zeros_(self.final_layer.linear.bias)
        if self.steering is not None:
            self.steering.reset_parameters()
        if self.steering_shift is not None:
            self.steering_shift.reset_parameters()
        if self.subgoal_shift is not None:
            self.subgoal_shift.reset_parameters()

    def conditioning(
        self,
        tau: torch.Tensor,
        steering: torch.Tensor | None = None,
        steering_drop: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Per-frame adaLN input [B, F, D]: the frame's tau embedding plus the steering embedding.

        A steered model given no steering uses the null (dropout) embedding,
        i.e. it runs unconditionally.
        """
        c = self.tau_embedder(tau)
        if self.steering is None:
            if steering is not None or steering_drop is not None:
                raise ValueError("this predictor was built without steering (steering=False) but got a steering input")
            return c
        if steering is None:
            return c + self.steering.null.to(c.dtype)
        return c + self.steering(steering, steering_drop)[:, None]

    def embed(self, x: torch.Tensor, constants: WindowConstants, total_frames: int | None = None,
              first: int = 0) -> torch.Tensor:
        """Latent frames [B, F, C, h, w] -> tokens [B, F, N, D] with all position encodings added.

        ``x`` may be frames ``first`` .. ``first + F - 1`` of a window of ``total_frames`` (the KV-cached path).
        """
        f = x.shape[1]
        total = f if total_frames is None else total_frames
        if total > self.max_frames:
            raise ValueError(f"got {total} frames but the predictor has max_frames = {self.max_frames}")
        tokens = self.x_embedder(patchify(x, self.patch_size).to(self.x_embedder.weight.dtype))
        tokens = tokens + constants.positions.to(tokens.dtype)
        start = self.max_frames - total + first
        tokens = tokens + self.frame_embed[start : start + f, None]
        if constants.rate is not None:
            tokens = tokens + constants.rate.to(tokens.dtype)[:, None, None]
        return tokens

    def window_constants(
        self,
        frames: torch.Tensor,
        n_frames: int,
        frame_rate: torch.Tensor | float | None = None,
        cond_frames: torch.Tensor | None = None,
        cond_mask: torch.Tensor | Sequence[int] | None = None,
        per_block: bool = False,
    ) -> WindowConstants:
        """The :class:`WindowConstants` of an ``n_frames`` window whose first frames are ``frames`` [B, F', C, h, w]
        (the whole window, or its clean context: the :class:`SubgoalShift` reads the first conditioned slot only).

        ``cond_mask``: [B, F] or the conditioned slots (:func:`conditioned_slots`); ``per_block``: also each block's
        conditioning (a sampler's precomputation; a training forward computes it inside each block's checkpoint).
        """
        b, _, _, h, w = frames.shape
        p = self.patch_size
        constants = WindowConstants(grid_positions(self.hidden_size, h // p, w // p, frames.device),
                                    rate_embedding(frame_rate, b, self.hidden_size, frames.device))
        if self.abstract_channels is None:
            if cond_frames is not None or cond_mask is not None:
                raise ValueError("this predictor was built without abstract conditioning but got cond_frames")
            return constants
        if cond_frames is None or cond_mask is None:
            raise ValueError("the detail predictor needs cond_frames [B, F, C_a, h_a, w_a] and cond_mask [B, F]")
        if cond_frames.shape[:2] != (b, n_frames) or (isinstance(cond_mask, torch.Tensor)
                                                      and tuple(cond_mask.shape) != (b, n_frames)):
            shape = tuple(cond_mask.shape) if isinstance(cond_mask, torch.Tensor) else cond_mask
            raise ValueError(f"cond_frames {tuple(cond_frames.shape)} and cond_mask {shape} "
                             f"must have one slot per input frame ({n_frames})")
        slots = conditioned_slots(cond_mask)
        if any(not 0 <= s < n_frames for s in slots) or list(slots) != sorted(set(slots)):
            raise ValueError(f"conditioned slots {slots} must be distinct and ascending in 0..{n_frames - 1}")
        constants.cond_tokens = self.abstract(cond_frames, slots, (h, w))
        if slots:
            constants.cond_context = torch.cat([constants.cond_tokens[:, s] for s in slots], dim=1)
        if per_block:
            constants.blocks = [block.conditioning(constants.cond_tokens, constants.cond_context)
                                for block in self.blocks]
        if self.subgoal_shift is not None:
            if slots and slots[0] >= frames.shape[1]:
                raise ValueError(f"the subgoal shift reads slot {slots[0]}, beyond the {frames.shape[1]} frames given")
            constants.subgoal = self.subgoal_shift(frames, cond_frames, slots, n_frames)
        return constants

    def modulations(self, c: torch.Tensor) -> list[torch.Tensor]:
        """Every block's adaLN output, then the final layer's, for the conditioning ``c`` [B, F, D]."""
        return [block.modulation(c) for block in self.blocks] + [self.final_layer.modulation(c)]

    def _tokens(self, x: torch.Tensor, constants: WindowConstants, total: int, first: int,
                previous: torch.Tensor | None, steering: torch.Tensor | None,
                steering_drop: torch.Tensor | None = None) -> torch.Tensor:
        """Embedded frames plus the shift inputs (:class:`SteeringShift` from ``previous``, :class:`SubgoalShift`)."""
        tokens = self.embed(x, constants, total, first)
        if previous is not None:
            tokens = self._shift_input(tokens, previous, steering, steering_drop)
        if constants.subgoal is not None:
            first_slot, extra = constants.subgoal
            tokens = torch.cat([tokens[:, : first_slot + 1], tokens[:, first_slot + 1:] + extra.to(tokens.dtype)],
                               dim=1)
        return tokens

    def forward(
        self,
        x: torch.Tensor,
        tau: torch.Tensor,
        frame_rate: torch.Tensor | float | None = None,
        cond_frames: torch.Tensor | None = None,
        cond_mask: torch.Tensor | Sequence[int] | None = None,
        steering: torch.Tensor | None = None,
        steering_drop: torch.Tensor | None = None,
        features_from_block: int | None = None,
    ) -> torch.Tensor:
        """Velocity [B, F, C, h, w] for latents ``x`` [B, F, C, h, w] at noise levels ``tau`` [B, F].

        ``frame_rate``: Hz, a number or [B]. ``cond_frames``/``cond_mask``:
        abstract latents [B, F, C_a, h_a, w_a] at the slots where ``cond_mask``
        [B, F] is true, or ``cond_mask`` as the tuple of those slots, which keeps the
        forward free of host syncs (detail predictor only). ``steering`` [B, S, K] with
        optional per-sample ``steering_drop`` [B] (steered predictor only).
        ``features_from_block=k`` returns instead the token features after
        block k counted from the end (k=1: the last block) as [B, F, D, h/p, w/p],
        for the linear probes; later blocks are skipped.
        """
        b, f, _, h, w = x.shape
        if tuple(tau.shape) != (b, f):
            raise ValueError(f"tau must be one noise level per frame [B, F] = {[b, f]}, got {list(tau.shape)}")
        depth = len(self.blocks)
        if features_from_block is not None and not 1 <= features_from_block <= depth:
            raise ValueError(f"features_from_block = {features_from_block} must be in 1..{depth}")
        c = self.conditioning(tau, steering, steering_drop)
        constants = self.window_constants(x, f, frame_rate, cond_frames, cond_mask)
        tokens = self._tokens(x, constants, f, 0, x[:, -2] if f >= 2 else None, steering, steering_drop)
        for index, block in enumerate(self.blocks):
            args = (block, tokens, c, self.causal, constants.cond_tokens, constants.cond_context)
            if index < self.checkpoint_blocks and self.training and torch.is_grad_enabled():
                tokens = checkpoint(_block_step, *args, use_reentrant=False)
            else:
                tokens = _block_step(*args)
            if features_from_block is not None and index == depth - features_from_block:
                p = self.patch_size
                return tokens.transpose(2, 3).reshape(b, f, self.hidden_size, h // p, w // p)
        out = self.final_layer(tokens, self.final_layer.modulation(c))
        return unpatchify(out, self.patch_size, self.latent_channels, h, w).to(x.dtype)

    def _shift_input(self, tokens: torch.Tensor, previous: torch.Tensor, steering: torch.Tensor | None,
                     steering_drop: torch.Tensor | None = None) -> torch.Tensor:
        """``tokens`` [B, F, N, D] with the :class:`SteeringShift` input added to the last frame's."""
        if self.steering_shift is None or steering is None:
            return tokens
        shift = self.steering_shift(previous, steering, steering_drop).to(tokens.dtype)
        return torch.cat([tokens[:, :-1], tokens[:, -1:] + shift[:, None]], dim=1)

    # ------------------------------------------------------------- KV cache (causal predictor, clean context)

    def uses_kv_cache(self, kv_cache: bool) -> bool:
        """Whether sampling with ``kv_cache`` asked for caches the context: exact for a causal predictor
        without abstract conditioning only."""
        return kv_cache and self.causal and self.abstract_channels is None

    def _check_cacheable(self) -> None:
        if not self.causal or self.abstract_channels is not None:
            raise ValueError("the KV cache needs a causal predictor without abstract conditioning (the abstract one)")

    @torch.no_grad()
    def build_kv_cache(
        self,
        context: torch.Tensor,
        n_target: int,
        frame_rate: torch.Tensor | float | None = None,
        steering: torch.Tensor | None = None,
    ) -> TemporalKVCache:
        """Run the clean context [B, F_c, C, h, w] (tau = 0) once and keep every block's temporal keys/values.

        Exact because context frames attend only to earlier frames (causal) and
        their noise level never changes during sampling: their features are the
        same at every Euler step of one rollout step, so :meth:`forward_cached`
        needs to run only the target frames. The keys/values go into buffers sized
        for context and targets, which each cached forward fills in place.
        """
        self._check_cacheable()
        b, f_c = context.shape[:2]
        tau = torch.zeros(b, f_c, device=context.device, dtype=context.dtype)
        c = self.conditioning(tau, steering)
        constants = self.window_constants(context, f_c + n_target, frame_rate)
        tokens = self.embed(context, constants, total_frames=f_c + n_target)
        keys: list[tuple[torch.Tensor, torch.Tensor]] = []
        for block in self.blocks:
            tokens = block(tokens, block.modulation(c), True, time_keep=keys)
        buffers = []
        for k, v in keys:
            k_buf, v_buf = k.new_empty((*k.shape[:2], f_c + n_target, k.shape[3])), v.new_empty(
                (*v.shape[:2], f_c + n_target, v.shape[3]))
            k_buf[:, :, :f_c] = k
            v_buf[:, :, :f_c] = v
            buffers.append((k_buf, v_buf))
        return TemporalKVCache(buffers, f_c, n_target, context[:, -1])

    def forward_cached(
        self,
        x: torch.Tensor,
        tau: torch.Tensor,
        cache: TemporalKVCache,
        frame_rate: torch.Tensor | float | None = None,
        steering: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Velocity of the target frames ``x`` [B, F_t, C, h, w] at ``tau`` [B, F_t] after a cached context.

        Equals ``forward(cat(context, x), cat(0, tau))[:, F_c:]`` (a test checks it).
        """
        self._check_cacheable()
        b, f = x.shape[:2]
        if f != cache.n_target or tuple(tau.shape) != (b, f):
            raise ValueError(f"the cache was built for {cache.n_target} target frames, got x {tuple(x.shape)} "
                             f"and tau {tuple(tau.shape)}")
        constants = self.window_constants(x, cache.n_context + f, frame_rate)
        return self._cached_velocity(x, self.modulations(self.conditioning(tau, steering)), cache, constants, steering)

    def _cached_velocity(self, x: torch.Tensor, modulations: list[torch.Tensor], cache: TemporalKVCache,
                         constants: WindowConstants, steering: torch.Tensor | None) -> torch.Tensor:
        f, (h, w) = x.shape[1], x.shape[-2:]
        tokens = self._tokens(x, constants, cache.n_context + f, cache.n_context,
                              x[:, -2] if f >= 2 else cache.last_context, steering)
        for block, modulation, past in zip(self.blocks, modulations, cache.keys_values):
            tokens = block(tokens, modulation, True, time_past=past)
        out = self.final_layer(tokens, modulations[-1])
        return unpatchify(out, self.patch_size, self.latent_channels, h, w).to(x.dtype)

    # ------------------------------------------------------------- sampling: fixed inputs computed once

    def modulation_table(self, taus: Sequence[float], batch: int, n_context: int, n_target: int,
                         steering: torch.Tensor | None = None, cached: bool = False,
                         device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32
                         ) -> list[list[torch.Tensor]]:
        """Per Euler step (target noise level ``taus[i]``, clean context), :meth:`modulations`: all adaLN
        matmuls of a sampling call, out of its Euler loop. Without steering it is the same for every rollout step.
        ``cached``: for the KV-cached forward (target frames only)."""
        table = []
        for tau in taus:
            tau_target = torch.full((batch, n_target), tau, device=device, dtype=dtype)
            if not cached:
                tau_target = torch.cat([torch.zeros(batch, n_context, device=device, dtype=dtype), tau_target], dim=1)
            table.append(self.modulations(self.conditioning(tau_target, steering)))
        return table

    @torch.no_grad()
    def plan(
        self,
        context: torch.Tensor,
        n_target: int,
        taus: Sequence[float],
        frame_rate: torch.Tensor | float | None = None,
        cond_frames: torch.Tensor | None = None,
        cond_mask: torch.Tensor | Sequence[int] | None = None,
        steering: torch.Tensor | None = None,
        kv_cache: bool = True,
        modulations: list[list[torch.Tensor]] | None = None,
    ) -> SamplingPlan:
        """Everything the Euler steps at target noise levels ``taus`` after the clean ``context`` [B, F_c, C, h, w]
        read that does not change from one step to the next, computed once (:meth:`planned_velocity`).

        Inputs are checked here, once; the steps then hold no host sync. ``kv_cache``: keep the context's
        temporal keys/values where exact (causal, no abstract conditioning). ``modulations``: a
        :meth:`modulation_table` computed earlier for the same taus and inputs (reused across rollout steps).
        """
        b, f_c = context.shape[:2]
        cached = self.uses_kv_cache(kv_cache)
        cache = self.build_kv_cache(context, n_target, frame_rate, steering) if cached else None
        constants = self.window_constants(context, f_c + n_target, frame_rate, cond_frames, cond_mask, per_block=True)
        if modulations is None:
            modulations = self.modulation_table(taus, b, f_c, n_target, steering, cached, context.device,
                                                context.dtype)
        if len(modulations) != len(taus):
            raise ValueError(f"the modulation table has {len(modulations)} steps, the sampler {len(taus)}")
        return SamplingPlan(context, n_target, constants, modulations, steering, cache)

    def planned_velocity(self, plan: SamplingPlan, x: torch.Tensor, step: int) -> torch.Tensor:
        """Velocity of the target frames ``x`` [B, F_t, C, h, w] at Euler step ``step`` of ``plan``: equals
        ``forward(cat(context, x), cat(0, taus[step]), ...)[:, F_c:]`` bit for bit (a test checks it)."""
        modulations = plan.modulations[step]
        if plan.cache is not None:
            return self._cached_velocity(x, modulations, plan.cache, plan.constants, plan.steering)
        window = torch.cat([plan.context, x], dim=1)
        f, (h, w) = window.shape[1], window.shape[-2:]
        tokens = self._tokens(window, plan.constants, f, 0, window[:, -2] if f >= 2 else None, plan.steering)
        conds = plan.constants.blocks or [None] * len(self.blocks)
        for block, modulation, cond in zip(self.blocks, modulations, conds):
            tokens = block(tokens, modulation, self.causal, cond)
        out = self.final_layer(tokens, modulations[-1])
        return unpatchify(out, self.patch_size, self.latent_channels, h, w).to(window.dtype)[:, plan.context.shape[1]:]


@dataclass
class TemporalKVCache:
    """Per block, key and value buffers [B*N, H, F_c + F_t, d] of the temporal attention: a clean context
    window's in the first F_c positions, the latest target frames' after them (written in place by each
    cached forward); and the context's last frame [B, C, h, w] (the :class:`SteeringShift` input of a first
    target frame)."""

    keys_values: list[tuple[torch.Tensor, torch.Tensor]]
    n_context: int
    n_target: int
    last_context: torch.Tensor


@dataclass
class SamplingPlan:
    """An ST-DiT's inputs that stay fixed over the Euler steps of one sampling call (:meth:`STDiT.plan`)."""

    context: torch.Tensor
    n_target: int
    constants: WindowConstants
    modulations: list[list[torch.Tensor]]
    steering: torch.Tensor | None
    cache: TemporalKVCache | None


# --------------------------------------------------------------------------- sizes


@dataclass(frozen=True)
class STDiTConfig(ModelConfig):
    """An ST-DiT's size: what :func:`build_stdit` needs besides the latents and the level's wiring."""

    KIND = "ST-DiT"

    hidden_size: int
    depth: int
    num_heads: int
    cond_dim: int  # width of the abstract conditioning tokens (the detail predictor's adaLN and cross-attention)
    mlp_ratio: float = 4.0
    patch_size: int = 1
    max_frames: int = 16
    steering_features: int = 2
    steering_len: int = 16
    steering_shift: bool = False  # steered predictor only: SteeringShift (a deviation from the paper)
    subgoal_shift: bool = False  # detail predictor only: SubgoalShift (a deviation from the paper)

    def check(self) -> None:
        self.positive("hidden_size", "depth", "num_heads", "cond_dim", "mlp_ratio", "patch_size", "max_frames",
                      "steering_features", "steering_len")
        for name in ("hidden_size", "cond_dim"):
            self.divisible(name, "num_heads")
            self.divisible(name, 4)  # 2-D sin-cos positions


STDIT_PRESETS: dict[str, STDiTConfig] = {
    # Tests and CI: a CPU step in tens of milliseconds.
    "smoke": STDiTConfig(hidden_size=64, depth=2, num_heads=2, cond_dim=32),
    # Laptop scale. The default profile reads its 16x10 latent grid in 2x2 patches (params.yaml
    # `_predictor.default.model`: patch_size 2); the gpu profile widens this preset to 384 x 8 blocks.
    "default": STDiTConfig(hidden_size=128, depth=4, num_heads=4, cond_dim=64),
    # Paper: 32x18 latents of 16 channels; 512M (abstract) and 555M (detail) parameters.
    "paper": STDiTConfig(hidden_size=768, depth=24, num_heads=16, cond_dim=384),
}


def stdit_config(preset: str, **overrides) -> STDiTConfig:
    """A preset's size with ``overrides``; an unknown preset or key, a wrong type or an impossible size raises."""
    return preset_config(STDIT_PRESETS, preset, overrides)


def build_stdit(
    config: STDiTConfig | str,
    latent_channels: int,
    causal: bool,
    abstract_channels: int | None = None,
    steering: bool = False,
) -> STDiT:
    """An ST-DiT of ``config``'s size (a preset's name stands for ``STDIT_PRESETS[name]``).

    Abstract predictor: ``causal=True`` (and ``steering=True`` for the action
    fine-tune). Detail predictor: ``causal=False, abstract_channels=C_a``.
    """
    cfg = stdit_config(config) if isinstance(config, str) else config
    return STDiT(
        latent_channels=latent_channels,
        causal=causal,
        abstract_channels=abstract_channels,
        steering=steering,
        **asdict(cfg),
    )


def build_stdit_from(build: dict) -> STDiT:
    """The ST-DiT a ``build`` dict describes: ``preset``, size overrides and the other :func:`build_stdit` arguments."""
    cfg, rest = split_build(STDIT_PRESETS, build)
    return build_stdit(cfg, **rest)


# --------------------------------------------------------------------------- files


@dataclass
class PredictorFile:
    """A trained predictor as rollouts and evaluation load it.

    ``build`` is what :func:`build_stdit_from` takes: the preset, its size
    overrides and the level's wiring (latent channels, causal, conditioning,
    steering); ``meta`` what the weights mean: which latents (tokenizer
    checksums, scales), rates and windows.
    """

    model: STDiT
    build: dict
    meta: dict
    checksum: str


def save_predictor(path: Path, model: nn.Module, build: dict, meta: dict) -> None:
    """Write ``{build, meta, state_dict}`` atomically; same content, same bytes."""
    blob = {"build": build, "meta": meta, "state_dict": model.state_dict()}
    with atomic_file(Path(path)) as tmp, open(tmp, "wb") as handle:
        torch.save(blob, handle)


def load_predictor(path: Path, device: str | torch.device = "cpu") -> PredictorFile:
    """Rebuild the architecture from the file, load the weights strictly, eval mode, frozen."""
    path = Path(path)
    if not path.is_file():
        raise OrbisError(f"{path}: predictor checkpoint not found; run its training stage first")
    blob = torch.load(path, map_location=device, weights_only=True)
    model = build_stdit_from(blob["build"])
    model.load_state_dict(blob["state_dict"])
    model.to(device).eval().requires_grad_(False)
    return PredictorFile(model, blob["build"], blob["meta"], sha256_file(path))
