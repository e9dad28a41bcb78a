"""Each model family's size: a typed config and its presets (``smoke``, ``default``, ``paper``).

Apart from the networks so that reading ``params.yaml``, which checks each stage's preset and size
overrides, needs no torch: every Snakemake invocation and stage parses it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from orbis2.models import ModelConfig, preset_config


@dataclass(frozen=True)
class TokenizerConfig(ModelConfig):
    """A tokenizer's size: ViT encoder, quantiser, both decoders and the discriminator.

    The defaults are the reference values every preset shares (the authors' code, "Tokenizer").
    """

    KIND = "tokenizer"

    image_size: tuple[int, int]  # (height, width)
    patch_size: int
    embed_dim: int
    depth: int
    num_heads: int
    codebook_size: int
    decoder_channels: int
    decoder_mult: tuple[int, ...]  # one channel multiplier per resolution: 2 ** (len - 1) = patch_size
    decoder_res_blocks: int
    abstract_decoder_channels: int
    abstract_decoder_mult: tuple[int, ...]
    abstract_decoder_res_blocks: int
    latent_dim: int = 16
    beta: float = 0.25
    bypass_prob: float = 0.5
    entropy_temperature: float = 0.01
    mlp_ratio: float = 4.0
    learn_pos_embed: bool = False
    # As the authors' released tokenizer (docs/differences.md): a CLS token in each ViT encoder, with its own
    # position row, dropped after the last block (the paper leaves it open; their code's choice). Theirs also has
    # a 1x1 conv from the latent to this many channels before each decoder's first conv (0: none, ours; a linear
    # map before a conv adds no function the conv cannot learn), which only their imported weights use.
    cls_token: bool = True
    decoder_in_channels: int = 0
    abstract_decoder_in_channels: int = 0
    disc_channels: int = 64
    disc_layers: int = 3
    disc_norm: str = "group"

    def check(self) -> None:
        self.positive("patch_size", "embed_dim", "depth", "num_heads", "codebook_size", "decoder_channels",
                      "abstract_decoder_channels", "latent_dim", "mlp_ratio", "disc_channels", "disc_layers")
        height, width = self.image_size
        if height % self.patch_size or width % self.patch_size:
            self.fail(f"image_size = {self.image_size} is not divisible by patch_size = {self.patch_size}")
        self.divisible("embed_dim", "num_heads")
        self.divisible("embed_dim", 4)  # 2-D sin-cos positions
        for name in ("decoder_mult", "abstract_decoder_mult"):
            upscale = 2 ** (len(getattr(self, name)) - 1)
            if upscale != self.patch_size:
                self.fail(f"{name}: the decoder upsamples x{upscale} but the patch size is {self.patch_size}: "
                          f"use {int(math.log2(self.patch_size)) + 1} channel multipliers")
        if not 0 <= self.bypass_prob <= 1:
            self.fail(f"bypass_prob = {self.bypass_prob} must lie in [0, 1]")
        if self.disc_norm not in ("group", "batch"):
            self.fail(f"disc_norm = {self.disc_norm!r} must be 'group' or 'batch'")


TOKENIZER_PRESETS: dict[str, TokenizerConfig] = {
    # Tests and CI: 128x72, patch 8 -> 9x16 grid, a CPU step in a few tens of ms.
    "smoke": TokenizerConfig(
        image_size=(72, 128), patch_size=8, embed_dim=64, depth=2, num_heads=2, codebook_size=512,
        decoder_channels=16, decoder_mult=(1, 1, 2, 4), decoder_res_blocks=1,
        abstract_decoder_channels=16, abstract_decoder_mult=(1, 1, 2, 2), abstract_decoder_res_blocks=1,
        disc_channels=16,
    ),
    # Laptop run: 256x160, patch 16 -> 10x16 grid, hundreds of steps on 2 CPU cores.
    "default": TokenizerConfig(
        image_size=(160, 256), patch_size=16, embed_dim=192, depth=4, num_heads=3, codebook_size=1024,
        decoder_channels=16, decoder_mult=(1, 1, 2, 2, 4), decoder_res_blocks=1,
        abstract_decoder_channels=16, abstract_decoder_mult=(1, 1, 1, 2, 2), abstract_decoder_res_blocks=1,
        disc_channels=16,
    ),
    # Paper: 512x288, ViT-B/16 encoder (86M, MAE-initialisable) and a taming
    # decoder whose width is set so that it has the paper's 91M parameters.
    "paper": TokenizerConfig(
        image_size=(288, 512), patch_size=16, embed_dim=768, depth=12, num_heads=12, codebook_size=16384,
        decoder_channels=192, decoder_mult=(1, 1, 2, 2, 4), decoder_res_blocks=3,
        abstract_decoder_channels=64, abstract_decoder_mult=(1, 1, 2, 2, 4), abstract_decoder_res_blocks=1,
    ),
}


def tokenizer_config(preset: str, **overrides) -> TokenizerConfig:
    """A preset's size with ``overrides``; an unknown preset or key, a wrong type or an impossible size raises."""
    return preset_config(TOKENIZER_PRESETS, preset, overrides)


# The values of the STDiTConfig options below (the first of each is the default).
QK_NORMS = ("layer", "rms")
CAUSAL_MASKS = ("hard", "additive")
RATE_ENCODINGS = ("interleaved", "geometric")
TIMESTEPS = ("per_frame", "global")
STEERING_POOLS = ("head_mean", "sum", "mean")


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
    # Choices in which the authors' released networks can differ (docs/differences.md): where the paper leaves one
    # open, the default is their code's; where the paper decides it, or their configs do, ours. What
    # orbis2.models.official records when it imports their weights is theirs (docs/official-weights.md).
    qk_norm: str = "layer"  # query/key norm per head: "layer" (LayerNorm with bias, theirs) | "rms" (RMSNorm)
    causal_mask: str = "hard"  # "hard" | "additive" (theirs: +1 on the allowed scores, the future leaks in)
    time_attn_norm: bool = True  # False (theirs): the temporal attention reads the residual stream un-normalised
    cross_attention: bool = True  # detail predictor: the gated cross-attention to the abstract tokens (theirs: none)
    abstract_positions: bool = True  # detail predictor: 2-D sin-cos positions on the abstract tokens (theirs: none)
    rate_encoding: str = "interleaved"  # frame-rate features: "interleaved" (theirs) | "geometric" (DiT's, of Hz)
    rate_range: tuple[float, float] = (2.0, 15.0)  # "interleaved": the rates mapped to [0, 1]
    tau_scale: float = 1000.0  # the noise-level features are of tau_scale * tau (theirs: the sampler's timescale)
    timestep: str = "per_frame"  # "per_frame" | "global" (theirs: every frame gets the last frame's noise level)
    steering_pool: str = "head_mean"  # steering tokens: "head_mean" (SiLU, linear, mean) | "sum" | "mean" (theirs)

    def check(self) -> None:
        self.positive("hidden_size", "depth", "num_heads", "cond_dim", "mlp_ratio", "patch_size", "max_frames",
                      "steering_features", "steering_len", "tau_scale")
        for name in ("hidden_size", "cond_dim"):
            self.divisible(name, "num_heads")
            self.divisible(name, 4)  # 2-D sin-cos positions
        for name, allowed in (("qk_norm", QK_NORMS), ("causal_mask", CAUSAL_MASKS), ("rate_encoding", RATE_ENCODINGS),
                              ("timestep", TIMESTEPS), ("steering_pool", STEERING_POOLS)):
            if getattr(self, name) not in allowed:
                self.fail(f"{name} = {getattr(self, name)!r} must be one of {', '.join(allowed)}")
        if self.rate_range[1] <= self.rate_range[0]:
            self.fail(f"rate_range = {self.rate_range} must be (low, high) with low < high")


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
