"""The ST-DiT's parts below its blocks: how latent frames become tokens and back, attention, MLP,
embedders, and the containers of what a forward reads besides its noisy frames (computed once per
sampling call by :meth:`~orbis2.models.stdit.STDiT.plan`).

The blocks and the model built from them are in :mod:`orbis2.models.stdit`; the paper deviations that
add inputs to the tokens are in :mod:`orbis2.models.deviations`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from orbis2.models.sizes import STEERING_POOLS
from orbis2.models.tokenizer import sincos_pos_embed_2d


def modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return x * (1 + scale) + shift


def sinusoidal_embedding(values: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """``values`` [...] -> [..., dim] cos/sin features at geometric frequencies (DiT's timestep features)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=values.device, dtype=torch.float32) / half)
    angles = values.float()[..., None] * freqs
    return torch.cat([torch.cos(angles), torch.sin(angles)], dim=-1)


def interleaved_embedding(values: torch.Tensor, dim: int, value_range: tuple[float, float]) -> torch.Tensor:
    """``values`` [B] -> [B, dim]: (v - lo) / (hi - lo) times 1 / 10000^(2 floor(i / 2) / dim), sine on the even
    channels and cosine on the odd ones (the frame-rate encoding of the authors' released networks)."""
    lo, hi = value_range
    normalized = (values.float() - lo) / (hi - lo)
    index = torch.arange(dim, device=values.device, dtype=torch.float32)
    features = normalized[:, None] * (1 / (10000 ** (2 * (index // 2) / dim)))
    out = torch.empty_like(features)
    out[:, 0::2] = torch.sin(features[:, 0::2])
    out[:, 1::2] = torch.cos(features[:, 1::2])
    return out


def rate_embedding(frame_rate: torch.Tensor | float | None, batch: int, dim: int, device: torch.device,
                   encoding: str = "interleaved", rate_range: tuple[float, float] = (2.0, 15.0)
                   ) -> torch.Tensor | None:
    """Frame rate in Hz (a number or [B]) -> features [B, dim] built on ``device`` (no host copy).

    ``interleaved`` (the default, the authors' code's): :func:`interleaved_embedding` of the rate normalised over
    ``rate_range``; ``geometric``: DiT's timestep features of the rate in Hz.
    """
    if frame_rate is None:
        return None
    if isinstance(frame_rate, torch.Tensor):
        rate = frame_rate.to(device=device, dtype=torch.float32).expand(batch)
    else:
        rate = torch.full((batch,), float(frame_rate), device=device, dtype=torch.float32)
    if encoding == "interleaved":
        return interleaved_embedding(rate, dim, rate_range)
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


def qk_norm(kind: str, head_dim: int) -> nn.Module:
    """Query/key normalisation per head: ``layer`` (LayerNorm with bias and eps 1e-5, the default, as the
    authors' code) or ``rms`` (RMSNorm)."""
    if kind == "layer":
        return nn.LayerNorm(head_dim)
    return nn.RMSNorm(head_dim, eps=1e-6)


class Attention(nn.Module):
    """Multi-head self-attention with qk-norm, through SDPA (flash attention on GPU).

    ``causal`` is a hard mask (``is_causal=True``) with ``causal_mask="hard"``. ``"additive"`` reproduces the
    authors' released networks, whose "causal" float mask of ones only adds +1 to the scores of the past and
    present and lets the future leak in; it exists only to run those weights as they were trained.
    """

    def __init__(self, dim: int, num_heads: int, norm: str = "layer", causal_mask: str = "hard"):
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"dim = {dim} is not divisible by num_heads = {num_heads}")
        self.num_heads = num_heads
        self.additive_causal = causal_mask == "additive"
        head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.q_norm = qk_norm(norm, head_dim)
        self.k_norm = qk_norm(norm, head_dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, causal: bool = False, past: tuple[torch.Tensor, torch.Tensor] | None = None,
                return_kv: bool = False) -> torch.Tensor | tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """``past``: earlier positions' keys and values [B, H, P, d], read only: this call's keys/values are
        concatenated after them (inside a compiled graph, so a CUDA-graph replay mutates none of its inputs) and
        its queries attend over all P + n. ``return_kv``: also return this call's (keys, values) [B, H, n, d]."""
        b, n, d = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, d // self.num_heads).permute(2, 0, 3, 1, 4)
        q, k = self.q_norm(q).to(v.dtype), self.k_norm(k).to(v.dtype)  # bf16 under autocast: flash-eligible
        own = (k, v)
        mask = None
        if past is not None:
            n_past = past[0].shape[2]
            k, v = torch.cat([past[0], k], dim=2), torch.cat([past[1], v], dim=2)
            if causal and n > 1:  # query i sees every cached position and its own first i + 1
                mask = torch.ones(n, n_past + n, dtype=torch.bool, device=x.device).tril(n_past)
            causal = False
        elif causal and self.additive_causal:
            mask, causal = torch.ones(n, n, dtype=q.dtype, device=x.device).tril(), False
        out = self.proj(F.scaled_dot_product_attention(q, k, v, attn_mask=mask, is_causal=causal)
                        .transpose(1, 2).reshape(b, n, d))
        return (out, own) if return_kv else out


class CrossAttention(nn.Module):
    """Queries from the detail tokens, keys/values from the abstract conditioning tokens (qk-norm, SDPA)."""

    def __init__(self, dim: int, context_dim: int, num_heads: int, norm: str = "layer"):
        super().__init__()
        if context_dim % num_heads:
            raise ValueError(f"cond_dim = {context_dim} is not divisible by num_heads = {num_heads}")
        self.num_heads = num_heads
        head_dim = context_dim // num_heads
        self.q = nn.Linear(dim, context_dim)
        self.kv = nn.Linear(context_dim, 2 * context_dim)
        self.q_norm = qk_norm(norm, head_dim)
        self.k_norm = qk_norm(norm, head_dim)
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


def adaln_norm(dim: int) -> nn.LayerNorm:
    """LayerNorm without affine parameters: adaLN supplies shift and scale (DiT)."""
    return nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)


# --------------------------------------------------------------------------- embedders


class NoiseLevelEmbedder(nn.Module):
    """tau in [0, 1] -> D: 256-d sinusoidal features of ``scale`` * tau, then an MLP (DiT's timestep embedder).

    Our scale 1000 puts tau on DiT's timestep scale so the geometric frequencies
    resolve small differences in noise level; the authors' released networks
    record theirs with the sampler (its ``timescale``).
    """

    def __init__(self, hidden_size: int, frequency_dim: int = 256, scale: float = 1000.0):
        super().__init__()
        self.frequency_dim = frequency_dim
        self.scale = scale
        self.mlp = nn.Sequential(nn.Linear(frequency_dim, hidden_size), nn.SiLU(), nn.Linear(hidden_size, hidden_size))

    def forward(self, tau: torch.Tensor) -> torch.Tensor:
        features = sinusoidal_embedding(tau * self.scale, self.frequency_dim)
        return self.mlp(features.to(self.mlp[0].weight.dtype))


class SteeringEmbedder(nn.Module):
    """Steering sequence [B, S, K] (e.g. speed and yaw rate; NaN = missing) -> [B, D] (the authors' code, "Steering").

    Each element's token is the sum over features of a small MLP (1 -> D -> D)
    of that value, or of a learned "no value" embedding where it is NaN, plus a
    learned position embedding. With ``pool="head_mean"`` (ours) tokens pass SiLU
    and a linear layer before the mean over the sequence: a purely linear mean
    would reduce the position embeddings to a constant and lose the order of the
    sequence. That output layer starts at zero and the null embedding (steering
    dropout) at zero, so an embedder added to a pre-trained unconditional
    predictor leaves it unchanged at the start of the fine-tune (paper
    "Action-conditioning"). ``pool="sum"`` or ``"mean"`` is the authors' released
    embedder: the tokens summed or averaged as they are, and no value at all
    (every element missing, ``max_len`` long) as the unconditional input.
    Values should be roughly unit scale (normalise speed in m/s by the caller).
    """

    def __init__(self, hidden_size: int, num_features: int, max_len: int, pool: str = "head_mean"):
        super().__init__()
        if pool not in STEERING_POOLS:
            raise ValueError(f"steering pool {pool!r} is not one of {', '.join(STEERING_POOLS)}")
        self.pool = pool
        self.feature_mlps = nn.ModuleList(
            nn.Sequential(nn.Linear(1, hidden_size), nn.SiLU(), nn.Linear(hidden_size, hidden_size))
            for _ in range(num_features)
        )
        self.no_value = nn.Parameter(torch.zeros(num_features, hidden_size))
        self.position = nn.Parameter(torch.zeros(max_len, hidden_size))
        if pool == "head_mean":
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
        if self.pool == "head_mean":
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
        steering = steering.to(self.position.dtype)
        total = self.position[:s].expand(b, s, -1)
        for i, mlp in enumerate(self.feature_mlps):
            value = steering[..., i : i + 1]
            missing = torch.isnan(value)
            total = total + torch.where(missing, self.no_value[i], mlp(torch.nan_to_num(value, nan=0.0)))
        return total

    def unconditional(self) -> torch.Tensor:
        """The embedding [D] of no steering: the null embedding, or (pooled as released) no value anywhere."""
        if self.pool == "head_mean":
            return self.null
        missing = torch.full((1, self.position.shape[0], len(self.feature_mlps)),
                             float("nan"), device=self.position.device, dtype=self.position.dtype)
        return self._pool(self.tokens(missing))[0]

    def _pool(self, tokens: torch.Tensor) -> torch.Tensor:
        if self.pool == "head_mean":
            return self.out(F.silu(tokens)).mean(dim=1)
        return tokens.sum(dim=1) if self.pool == "sum" else tokens.mean(dim=1)

    def forward(self, steering: torch.Tensor, drop: torch.Tensor | None = None) -> torch.Tensor:
        embedding = self._pool(self.tokens(steering))
        if drop is not None:
            embedding = torch.where(drop.reshape(-1, 1), self.unconditional().to(embedding.dtype), embedding)
        return embedding


class AbstractConditioner(nn.Module):
    """Abstract latents at their frame slots -> conditioning tokens [B, F, N, cond_dim].

    Paper Appendix "Detailed short-horizon predictor": a linear patchify (resized
    to the detail grid first if the grids differ), zero where ``cond_mask`` says
    the slot carries no latent, plus a learned frame-position MLP of i/(F-1) for
    every slot (the authors' code, "Hierarchy wiring") and the fixed 2-D sin-cos
    position, so the cross-attention keys know where each token lies (``positions=False``: none, as in the
    authors' released detail predictor, which has no cross-attention).
    """

    def __init__(self, abstract_channels: int, cond_dim: int, patch_size: int, positions: bool = True):
        super().__init__()
        self.patch_size = patch_size
        self.positions = positions
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
        tokens = tokens + self.frame_position(slot[:, None])[None, :, None]
        if not self.positions:
            return tokens
        p = self.patch_size
        return tokens + grid_positions(tokens.shape[-1], h // p, w // p, tokens.device).to(tokens.dtype)


# --------------------------------------------------------------------------- what a forward reads


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


@dataclass
class TemporalKVCache:
    """Per block, the temporal attention's keys and values [B*N, H, F_c, d] of a clean context window (each
    cached forward concatenates its own target frames' after them), and the context's last frame [B, C, h, w]
    (the :class:`SteeringShift` input of a first target frame)."""

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
