"""Spatio-Temporal DiT (ST-DiT) predictor of Orbis 2: its blocks, the model and its typed sizes, as DiT's models.py.

One network serves both levels of the hierarchy (paper Sec. 3.2, 4.2 and
Appendix "Model details"):

* the abstract predictor F_H: causal temporal attention, optionally steered by
  an ego-motion sequence (the embedding is added to the noise-level embedding
  that feeds adaLN, paper "Action-conditioning"), and with ``steering_shift``
  also through the frame before the prediction moved sideways by the commanded
  turn (:class:`~orbis2.models.deviations.SteeringShift`, a deviation from the paper);
* the detail predictor F_L: bidirectional temporal attention, conditioned on
  abstract latents placed at frame slots, through a per-token gated adaLN path
  and a gated spatial cross-attention layer in every block, and with
  ``subgoal_shift`` also through the last context frame moved sideways as far
  as the subgoal moved (:class:`~orbis2.models.deviations.SubgoalShift`, a deviation from the paper).

Inputs are latent frames ``x`` [B, F, C, h, w] with one noise level per frame
``tau`` [B, F], so the same network is trained with teacher forcing (context at
tau = 0) and diffusion forcing (independent tau per frame). It returns the
flow-matching velocity [B, F, C, h, w] (``orbis2.flow``).

Block layout follows the reference STDiT (the authors' code, "Predictor"): spatial
attention, spatial MLP, temporal attention, temporal MLP, each with its own
adaLN-Zero shift/scale/gate. With hidden 768, depth 24 that gives the paper's
512M parameters; the abstract conditioning adds the paper's 43M because its
tokens live at half the width (``cond_dim``), which is what lets both the adaLN
path and the cross-attention fit that budget. The layers below the blocks are in
:mod:`orbis2.models.stdit_layers`, the checkpoint file in :mod:`orbis2.models.files`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint

from orbis2.models import split_build
from orbis2.models.deviations import SteeringShift, SubgoalShift
from orbis2.models.sizes import STDIT_PRESETS, STDiTConfig, stdit_config
from orbis2.models.stdit_layers import (
    AbstractConditioner,
    Attention,
    BlockConditioning,
    CrossAttention,
    Mlp,
    NoiseLevelEmbedder,
    SamplingPlan,
    SteeringEmbedder,
    TemporalKVCache,
    WindowConstants,
    adaln_norm,
    conditioned_slots,
    grid_positions,
    modulate,
    patchify,
    rate_embedding,
    unpatchify,
)

# Initial gates of the abstract conditioning paths: small but non-zero (paper Appendix "Model details").
COND_GATE_BIAS = -2.0  # adaLN path gate sigmoid(-2) ~ 0.12
CROSS_GATE_INIT = 0.1  # cross-attention gate tanh(0.1) ~ 0.1


# --------------------------------------------------------------------------- blocks


class STDiTBlock(nn.Module):
    """Space-time DiT block: spatial attention, spatial MLP, temporal attention, temporal MLP.

    Each sub-layer is adaLN-Zero modulated (shift, scale, gate) by the
    per-frame conditioning vector. With ``cond_dim`` the block also takes the
    abstract conditioning (paper Appendix "Model details"): before the block,
    x += sigmoid(gate) * modulate(LN(x), shift, scale) with shift/scale/gate
    per token from the aligned conditioning tokens; after spatial attention, a
    gated cross-attention to the sample's conditioning tokens, gate tanh(alpha) (none with
    ``cross_attention=False``, as in the authors' released detail predictor).
    """

    def __init__(self, hidden_size: int, num_heads: int, mlp_ratio: float, cond_dim: int | None = None,
                 qk_norm: str = "layer", causal_mask: str = "hard", time_attn_norm: bool = True,
                 cross_attention: bool = True):
        super().__init__()
        mlp_hidden = int(hidden_size * mlp_ratio)
        self.space_norm, self.space_mlp_norm = adaln_norm(hidden_size), adaln_norm(hidden_size)
        # time_attn_norm=False: the temporal attention reads the residual stream itself (the authors' released
        # blocks without their temporal adaLN); its shift/scale/gate rows are then the constants 0, 0, 1.
        self.time_norm = adaln_norm(hidden_size) if time_attn_norm else nn.Identity()
        self.time_mlp_norm = adaln_norm(hidden_size)
        self.space_attn = Attention(hidden_size, num_heads, qk_norm, causal_mask)
        self.space_mlp = Mlp(hidden_size, mlp_hidden)
        self.time_attn = Attention(hidden_size, num_heads, qk_norm, causal_mask)
        self.time_mlp = Mlp(hidden_size, mlp_hidden)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(hidden_size, 12 * hidden_size))
        self.has_cond = cond_dim is not None
        self.has_cross = self.has_cond and cross_attention
        if self.has_cond:
            self.cond_norm = adaln_norm(hidden_size)
            self.cond_modulation = nn.Sequential(nn.SiLU(), nn.Linear(cond_dim, 3 * hidden_size))
        if self.has_cross:
            self.cross_norm = adaln_norm(hidden_size)
            self.cross_attn = CrossAttention(hidden_size, cond_dim, num_heads, qk_norm)
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
        keys, values = (self.cross_attn.keys_values(cond_context) if self.has_cross and cond_context is not None
                        else (None, None))
        return BlockConditioning(shift, scale, torch.sigmoid(gate), keys, values)

    def forward(
        self,
        x: torch.Tensor,
        modulation: torch.Tensor,
        causal: bool,
        cond: BlockConditioning | None = None,
        time_past: tuple[torch.Tensor, torch.Tensor] | None = None,
        return_kv: bool = False,
    ) -> torch.Tensor | tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """x [B, F, N, D]; ``modulation`` from :meth:`modulation`; ``cond`` from :meth:`conditioning`.

        ``time_past``: the context's temporal keys/values (:class:`TemporalKVCache`); ``return_kv``: also return
        this call's temporal (keys, values), which builds that cache. Both are returned, never kept in Python
        state, so a compiled block traces the same graph whichever block of whichever depth it serves.
        """
        b, f, n, d = x.shape
        if cond is not None:  # the sums cast to the residual stream's dtype: the norms' fp32 would promote it
            x = x + (cond.gate * modulate(self.cond_norm(x), cond.shift, cond.scale)).to(x.dtype)
        (sh_sa, sc_sa, g_sa, sh_sm, sc_sm, g_sm,
         sh_ta, sc_ta, g_ta, sh_tm, sc_tm, g_tm) = modulation.chunk(12, dim=-1)

        h = modulate(self.space_norm(x), sh_sa, sc_sa).reshape(b * f, n, d)
        x = x + g_sa * self.space_attn(h).reshape(b, f, n, d)
        if cond is not None and cond.keys is not None:
            h = self.cross_attn(self.cross_norm(x).reshape(b, f * n, d), cond.keys, cond.values)
            x = x + (torch.tanh(self.cross_gate) * h.reshape(b, f, n, d)).to(x.dtype)
        x = x + g_sm * self.space_mlp(modulate(self.space_mlp_norm(x), sh_sm, sc_sm))

        h = modulate(self.time_norm(x), sh_ta, sc_ta).permute(0, 2, 1, 3).reshape(b * n, f, d)
        h = self.time_attn(h, causal=causal, past=time_past, return_kv=return_kv)
        if return_kv:
            h, kv = h
        x = x + g_ta * h.reshape(b, n, f, d).permute(0, 2, 1, 3)
        x = x + g_tm * self.time_mlp(modulate(self.time_mlp_norm(x), sh_tm, sc_tm))
        return (x, kv) if return_kv else x


class FinalLayer(nn.Module):
    """adaLN final layer of DiT: modulated LayerNorm, then a linear map back to patches (zero-initialised)."""

    def __init__(self, hidden_size: int, patch_size: int, out_channels: int):
        super().__init__()
        self.norm = adaln_norm(hidden_size)
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


# --------------------------------------------------------------------------- model


class STDiT(nn.Module):
    """The ST-DiT velocity network (see the module docstring).

    Token positions: fixed 2-D sin-cos over the patch grid, a learned frame
    embedding and a sinusoidal frame-rate encoding (the authors' code, "Predictor").
    Frame embeddings are aligned to the last frame (frame i of F uses slot
    max_frames - F + i, as in the reference code), so the predicted frame has
    the same embedding whatever the context length, including the linear-probe
    protocol's context-free input.

    The options after ``subgoal_shift`` (sizes.STDiTConfig documents each) default to the authors' code's
    choice where the paper leaves it open and to ours where the paper decides it; the other values reproduce
    the authors' released networks (:mod:`orbis2.models.official`).
    ``timestep="global"`` conditions every frame on the last frame's noise level (their sampler's "global"
    timestep: the clean context sees the target's), which makes the context's features depend on the step,
    so such a predictor never caches them (:meth:`uses_kv_cache`).
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
        qk_norm: str = "layer",
        causal_mask: str = "hard",
        time_attn_norm: bool = True,
        cross_attention: bool = True,
        abstract_positions: bool = True,
        rate_encoding: str = "interleaved",
        rate_range: tuple[float, float] = (2.0, 15.0),
        tau_scale: float = 1000.0,
        timestep: str = "per_frame",
        steering_pool: str = "head_mean",
    ):
        super().__init__()
        self.latent_channels = latent_channels
        # Activation checkpointing of the first ``checkpoint_blocks`` blocks while training (their activations
        # are recomputed in the backward pass); set by the training loop, not part of the architecture.
        self.checkpoint_blocks = 0
        # Whether the blocks run as CUDA graphs (set by orbis2.accel.compile_predictor): every whole-network call
        # then starts a new graph generation (:meth:`begin_graph_generation`).
        self.cuda_graphs = False
        self.hidden_size = hidden_size
        self.patch_size = patch_size
        self.max_frames = max_frames
        self.causal = causal
        self.causal_mask = causal_mask
        self.rate_encoding = rate_encoding
        self.rate_range = tuple(rate_range)
        self.timestep = timestep
        self.abstract_channels = abstract_channels
        block_cond_dim = None
        if abstract_channels is not None:
            block_cond_dim = cond_dim or hidden_size
            self.abstract = AbstractConditioner(abstract_channels, block_cond_dim, patch_size, abstract_positions)
        self.x_embedder = nn.Linear(patch_size * patch_size * latent_channels, hidden_size)
        self.tau_embedder = NoiseLevelEmbedder(hidden_size, scale=tau_scale)
        self.frame_embed = nn.Parameter(torch.zeros(max_frames, hidden_size))
        self.steering = (SteeringEmbedder(hidden_size, steering_features, steering_len, steering_pool) if steering
                         else None)
        self.steering_shift = (SteeringShift(latent_channels, hidden_size, patch_size)
                               if steering and steering_shift else None)
        if subgoal_shift and abstract_channels is None:
            raise ValueError("subgoal_shift needs abstract conditioning (the detail predictor)")
        self.subgoal_shift = SubgoalShift(latent_channels, hidden_size, patch_size) if subgoal_shift else None
        self.blocks = nn.ModuleList(
            STDiTBlock(hidden_size, num_heads, mlp_ratio, block_cond_dim, qk_norm, causal_mask, time_attn_norm,
                       cross_attention) for _ in range(depth)
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
                if block.has_cross:
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

    def begin_graph_generation(self) -> None:
        """Start a new CUDA-graph generation when the blocks run as CUDA graphs; a no-op otherwise.

        Called at the start of every whole-network call (forward, KV-cache build, cached forward, planned
        Euler step): the blocks of one call then form one generation, each block's graph reading the previous
        block's output, and a later call may reuse their memory, because what outlives a call (the velocity,
        the KV cache) is computed or copied outside the graphs.
        """
        if self.cuda_graphs:
            torch.compiler.cudagraph_mark_step_begin()

    def conditioning(
        self,
        tau: torch.Tensor,
        steering: torch.Tensor | None = None,
        steering_drop: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Per-frame adaLN input [B, F, D]: the frame's tau embedding plus the steering embedding.

        A steered model given no steering uses the null (dropout) embedding,
        i.e. it runs unconditionally. ``timestep="global"``: every frame gets the last frame's tau.
        """
        if self.timestep == "global":
            tau = tau[:, -1:].expand_as(tau)
        c = self.tau_embedder(tau)
        if self.steering is None:
            if steering is not None or steering_drop is not None:
                raise ValueError("this predictor was built without steering (steering=False) but got a steering input")
            return c
        if steering is None:
            return c + self.steering.unconditional().to(c.dtype)
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
        tokens = tokens + self.frame_embed[start : start + f, None].to(tokens.dtype)
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
                                    rate_embedding(frame_rate, b, self.hidden_size, frames.device,
                                                   self.rate_encoding, self.rate_range))
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
        self.begin_graph_generation()
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
        (hard mask) without abstract conditioning whose context is conditioned on its own noise level only."""
        return kv_cache and self._cacheable()

    def _cacheable(self) -> bool:
        return (self.causal and self.causal_mask == "hard" and self.timestep == "per_frame"
                and self.abstract_channels is None)

    def _check_cacheable(self) -> None:
        if not self._cacheable():
            raise ValueError("the KV cache needs a causal predictor (hard mask, per-frame noise levels) without "
                             "abstract conditioning (the abstract one)")

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
        needs to run only the target frames. The keys/values are copied out of the
        blocks' outputs: under CUDA graphs those are overwritten by the next graph
        generation (the next Euler step), the copies are not.
        """
        self._check_cacheable()
        self.begin_graph_generation()
        b, f_c = context.shape[:2]
        tau = torch.zeros(b, f_c, device=context.device, dtype=context.dtype)
        c = self.conditioning(tau, steering)
        constants = self.window_constants(context, f_c + n_target, frame_rate)
        tokens = self.embed(context, constants, total_frames=f_c + n_target)
        keys_values = []
        for block in self.blocks:
            tokens, (k, v) = block(tokens, block.modulation(c), True, return_kv=True)
            keys_values.append((k.clone(), v.clone()))
        return TemporalKVCache(keys_values, f_c, n_target, context[:, -1])

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
        self.begin_graph_generation()
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
        self.begin_graph_generation()
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
