"""First-stage tokenizers of Orbis 2: their blocks, the two tokenizers and their typed sizes.

Two tokenizers share the blocks below (paper Sec. 3.2 and Appendix "Tokenizer"):

* ``DetailTokenizer`` (E_L): ViT encoder -> 1x1 conv to a 16-d latent -> L2
  normalisation -> vector quantiser (bypassed for half the samples while
  training) -> taming-style CNN decoder. Trained with the VQGAN objective.
* ``AbstractTokenizer`` (E_H): its own ViT encoder -> 16-d L2-normalised latent,
  a projection head P predicting a frozen teacher's patch features (paper
  eq. 3) and a lightweight decoder D_H as a weak reconstruction regulariser.

The world model consumes the *continuous* normalised latent of ``encode``; the
quantiser only regularises it (the authors' code, "Tokenizer"). The detail tokenizer's GAN
discriminator is in :mod:`orbis2.models.discriminator`, the checkpoint file in :mod:`orbis2.models.files`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from orbis2.accel import conv_layout
from orbis2.models.sizes import TokenizerConfig, tokenizer_config

# --------------------------------------------------------------------------- ViT encoder


def sincos_pos_embed_2d(embed_dim: int, grid_hw: tuple[int, int],
                        device: torch.device | str | None = None) -> torch.Tensor:
    """Fixed 2-D sin-cos position embedding [h*w, D] in MAE's layout, built on ``device``.

    As in MAE, the first half of the channels encodes the column (x) and the
    second half the row (y), so an MAE checkpoint's embedding and ours agree.
    Built where it is used, so a forward on an accelerator copies nothing from the host.
    """
    if embed_dim % 4:
        raise ValueError(f"embed_dim = {embed_dim} must be a multiple of 4 for 2-D sin-cos")
    h, w = grid_hw
    quarter = embed_dim // 4
    omega = 1.0 / 10000 ** (torch.arange(quarter, dtype=torch.float64, device=device) / quarter)
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float64, device=device), torch.arange(w, dtype=torch.float64, device=device),
        indexing="ij",
    )

    def encode(pos: torch.Tensor) -> torch.Tensor:
        angles = pos.reshape(-1, 1) * omega
        return torch.cat([angles.sin(), angles.cos()], dim=1)

    return torch.cat([encode(xs), encode(ys)], dim=1).float()


class PatchEmbed(nn.Module):
    """Non-overlapping patches -> tokens; ``proj`` matches MAE's key name."""

    def __init__(self, patch_size: int, in_channels: int, embed_dim: int):
        super().__init__()
        self.proj = nn.Conv2d(in_channels, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class Attention(nn.Module):
    """Multi-head self-attention (fused qkv as in MAE/timm, SDPA kernel)."""

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"dim = {dim} is not divisible by num_heads = {num_heads}")
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, d = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, d // self.num_heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(b, n, d))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class Block(nn.Module):
    """Pre-norm transformer block; LayerNorm eps 1e-6 as in MAE's ViT."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, num_heads)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class ViTEncoder(nn.Module):
    """ViT over a fixed (H, W) image returning patch tokens as [B, D, H/p, W/p].

    Only patch tokens are used downstream (the authors' code, "Tokenizer"). The
    position embedding is the 2-D sin-cos table of the (non-square) grid, frozen
    like MAE's unless ``learn_pos_embed``. With ``cls_token`` (the tokenizer's
    default, as the authors' released encoders and timm's MAE ViT) a learned CLS
    token with its own position row (zeros, MAE's) takes part in attention and
    is dropped after the last block. Module names follow MAE's checkpoint so
    ``load_mae_encoder`` is a near-identity map.
    """

    def __init__(
        self,
        image_size: tuple[int, int],
        patch_size: int,
        embed_dim: int,
        depth: int,
        num_heads: int,
        mlp_ratio: float = 4.0,
        in_channels: int = 3,
        learn_pos_embed: bool = False,
        cls_token: bool = False,
    ):
        super().__init__()
        height, width = image_size
        if height % patch_size or width % patch_size:
            raise ValueError(f"image size {image_size} is not divisible by patch size {patch_size}")
        self.image_size = (height, width)
        self.patch_size = patch_size
        self.embed_dim = embed_dim
        self.grid_size = (height // patch_size, width // patch_size)
        self.patch_embed = PatchEmbed(patch_size, in_channels, embed_dim)
        positions = sincos_pos_embed_2d(embed_dim, self.grid_size)
        self.prefix = 1 if cls_token else 0
        if cls_token:
            self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
            positions = torch.cat([torch.zeros(1, embed_dim), positions])
        self.pos_embed = nn.Parameter(positions.unsqueeze(0), requires_grad=learn_pos_embed)
        self.blocks = nn.ModuleList(Block(embed_dim, num_heads, mlp_ratio) for _ in range(depth))
        self.norm = nn.LayerNorm(embed_dim, eps=1e-6)
        self._init_weights()

    def _init_weights(self) -> None:
        """MAE's initialisation: xavier-uniform linears and patch projection, the CLS token normal(0.02)."""
        w = self.patch_embed.proj.weight
        nn.init.xavier_uniform_(w.view(w.shape[0], -1))
        nn.init.zeros_(self.patch_embed.proj.bias)
        if self.prefix:
            nn.init.normal_(self.cls_token, std=0.02)
        for module in self.blocks.modules():
            if isinstance(module, nn.Linear):
                nn.init.xavier_uniform_(module.weight)
                nn.init.zeros_(module.bias)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if tuple(images.shape[-2:]) != self.image_size:
            raise ValueError(f"expected images of size {self.image_size}, got {tuple(images.shape[-2:])}")
        x = self.patch_embed(images)
        if self.prefix:
            x = torch.cat([self.cls_token.expand(x.shape[0], -1, -1), x], dim=1)
        x = x + self.pos_embed
        for block in self.blocks:
            x = block(x)
        x = self.norm(x)[:, self.prefix:]
        h, w = self.grid_size
        return x.transpose(1, 2).reshape(x.shape[0], self.embed_dim, h, w)


def load_mae_encoder(encoder: ViTEncoder, path: str | Path) -> ViTEncoder:
    """Initialise ``encoder`` from an official MAE ViT checkpoint (paper App. "Tokenizer").

    Accepts the facebookresearch/mae file (``{"model": state_dict}``) or a bare
    state dict with the same names (timm's MAE weights). Block, patch and norm
    keys map one to one; ``pos_embed`` loses its CLS row and its square grid is
    bicubically resized to ours (an encoder with ``cls_token`` keeps both); MAE's
    ``mask_token`` and ``decoder_*`` keys are ignored. Any missing or mis-shaped weight raises.
    """
    state = torch.load(path, map_location="cpu", weights_only=True)
    state = state.get("model", state)
    ours = {k: v for k, v in state.items() if k in encoder.state_dict() and k != "pos_embed"}
    pos = state["pos_embed"][:, 1:]
    side = math.isqrt(pos.shape[1])
    if side * side != pos.shape[1]:
        raise ValueError(f"MAE pos_embed has {pos.shape[1]} patch positions, not a square grid")
    pos = pos.reshape(1, side, side, -1).permute(0, 3, 1, 2)
    pos = F.interpolate(pos.float(), size=encoder.grid_size, mode="bicubic", align_corners=False)
    ours["pos_embed"] = torch.cat([state["pos_embed"][:, :encoder.prefix].float(), pos.flatten(2).transpose(1, 2)],
                                  dim=1)
    encoder.load_state_dict(ours, strict=True)
    return encoder


# --------------------------------------------------------------------------- quantiser


@dataclass(frozen=True)
class VQOutput:
    """What the quantiser hands on.

    ``quantized`` is the decoder input: the straight-through quantised latent,
    or the continuous one for samples where ``bypassed`` is true. The entropy
    term is returned unweighted: its weight schedule belongs to the caller.
    """

    quantized: torch.Tensor
    indices: torch.Tensor
    codebook_loss: torch.Tensor
    commitment_loss: torch.Tensor
    entropy_loss: torch.Tensor
    bypassed: torch.Tensor
    perplexity: torch.Tensor
    used_fraction: torch.Tensor

    @property
    def vq_loss(self) -> torch.Tensor:
        """Codebook + (already beta-weighted) commitment loss."""
        return self.codebook_loss + self.commitment_loss


def codebook_usage(indices: torch.Tensor, codebook_size: int) -> dict[str, float]:
    """Usage statistics of a set of code indices.

    perplexity = exp(entropy of the empirical code distribution): K for uniform
    use of K codes, 1 for a collapsed codebook. dead_codes counts codes never hit.
    """
    counts = torch.bincount(indices.flatten().long(), minlength=codebook_size).double()
    probs = counts / counts.sum()
    nonzero = probs[probs > 0]
    used = int((counts > 0).sum())
    return {
        "perplexity": float(torch.exp(-(nonzero * nonzero.log()).sum())),
        "dead_codes": codebook_size - used,
        "used_fraction": used / codebook_size,
    }


class VectorQuantizer(nn.Module):
    """Cosine-similarity VQ over L2-normalised latents (the authors' code, "Tokenizer").

    Input: latents already L2-normalised along channels. The codebook is
    normalised on every use, so nearest-by-cosine equals nearest-by-L2 and the
    squared distance is 2 - 2 cos. Gradients pass straight through. Losses:
    codebook ||sg[z] - e||^2 and commitment beta ||z - sg[e]||^2 (beta 0.25).
    The entropy term (per-sample entropy minus codebook entropy of softmax(-d/T)
    assignments, T = 0.01 as the reference's inverse temperature 100) pushes
    confident yet diverse code use. While training, each sample independently
    skips quantisation with probability ``bypass_prob`` (0.5 in the reference).
    """

    def __init__(
        self,
        codebook_size: int = 16384,
        latent_dim: int = 16,
        beta: float = 0.25,
        bypass_prob: float = 0.5,
        entropy_temperature: float = 0.01,
    ):
        super().__init__()
        if not 0.0 <= bypass_prob <= 1.0:
            raise ValueError(f"bypass_prob = {bypass_prob} must lie in [0, 1]")
        self.codebook_size = codebook_size
        self.latent_dim = latent_dim
        self.beta = beta
        self.bypass_prob = bypass_prob
        self.entropy_temperature = entropy_temperature
        self.codebook = nn.Parameter(F.normalize(torch.randn(codebook_size, latent_dim), dim=1))

    def normalized_codebook(self) -> torch.Tensor:
        return F.normalize(self.codebook, dim=1)

    def lookup(self, indices: torch.Tensor) -> torch.Tensor:
        """Codes for an index map [B, h, w] -> [B, C, h, w]."""
        return self.normalized_codebook()[indices].permute(0, 3, 1, 2)

    def _entropy(self, sq_dist: torch.Tensor) -> torch.Tensor:
        probs = (-sq_dist / self.entropy_temperature).softmax(dim=-1)
        per_sample = -(probs * probs.clamp_min(1e-5).log()).sum(-1).mean()
        avg = probs.mean(0)
        codebook = -(avg * avg.clamp_min(1e-5).log()).sum()
        return per_sample - codebook

    def forward(self, z: torch.Tensor) -> VQOutput:
        b, c, h, w = z.shape
        codes = self.normalized_codebook()
        flat = z.permute(0, 2, 3, 1).reshape(-1, c)
        sq_dist = 2.0 - 2.0 * flat @ codes.t()
        indices = sq_dist.argmin(dim=1)
        z_q = codes[indices].view(b, h, w, c).permute(0, 3, 1, 2)

        codebook_loss = F.mse_loss(z_q, z.detach())
        commitment_loss = self.beta * F.mse_loss(z, z_q.detach())
        entropy_loss = self._entropy(sq_dist) if self.training else z.new_zeros(())
        quantized = z + (z_q - z).detach()

        if self.training and self.bypass_prob > 0:
            bypassed = torch.rand(b, device=z.device) < self.bypass_prob
            quantized = torch.where(bypassed.view(b, 1, 1, 1), z, quantized)
        else:
            bypassed = torch.zeros(b, dtype=torch.bool, device=z.device)

        with torch.no_grad():
            counts = z.new_zeros(self.codebook_size).index_add_(0, indices, z.new_ones(indices.shape))
            probs = counts / counts.sum()
            perplexity = torch.exp(-(probs * probs.clamp_min(1e-12).log()).sum())
            used_fraction = (counts > 0).float().mean()
        return VQOutput(
            quantized=quantized,
            indices=indices.view(b, h, w),
            codebook_loss=codebook_loss,
            commitment_loss=commitment_loss,
            entropy_loss=entropy_loss,
            bypassed=bypassed,
            perplexity=perplexity,
            used_fraction=used_fraction,
        )


# --------------------------------------------------------------------------- CNN decoder


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm(32) as in taming; fewer groups only for widths not divisible by 32."""
    return nn.GroupNorm(math.gcd(32, channels), channels, eps=1e-6)


class ResBlock(nn.Module):
    def __init__(self, in_channels: int, out_channels: int, dropout: float = 0.0):
        super().__init__()
        self.norm1 = group_norm(in_channels)
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, padding=1)
        self.norm2 = group_norm(out_channels)
        self.dropout = nn.Dropout(dropout)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1)
        self.shortcut = (
            nn.Conv2d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(self.dropout(F.silu(self.norm2(h))))
        return self.shortcut(x) + h


class AttnBlock(nn.Module):
    """Single-head spatial self-attention with a residual (taming's AttnBlock)."""

    def __init__(self, channels: int):
        super().__init__()
        self.norm = group_norm(channels)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.proj = nn.Conv2d(channels, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        q, k, v = self.qkv(self.norm(x)).reshape(b, 3, 1, c, h * w).transpose(-1, -2).unbind(1)
        out = F.scaled_dot_product_attention(q, k, v)
        return x + self.proj(out.transpose(-1, -2).reshape(b, c, h, w))


class Upsample(nn.Module):
    """Nearest-neighbour x2 followed by a 3x3 conv."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.interpolate(x, scale_factor=2.0, mode="nearest"))


class ConvDecoder(nn.Module):
    """Taming-style CNN decoder from a latent grid to an RGB image.

    conv_in -> mid (ResBlock, attention, ResBlock) -> one level per entry of
    ``channel_mult`` from the last (widest, lowest resolution) to the first,
    each with ``num_res_blocks`` ResBlocks (attention after each at the lowest
    resolution only), a nearest x2 upsampling between levels, then
    GroupNorm-SiLU-conv_out. Upscale factor = 2 ** (len(channel_mult) - 1).
    The reference builds num_res_blocks + 1 = 3 blocks per decoder level
    from its config value 2; our ``num_res_blocks`` is the literal count.
    ``in_channels`` > 0 puts a 1x1 conv from the latent to that many channels
    before conv_in (``latent_in``, the authors' released decoders' post_quant_conv).
    """

    def __init__(
        self,
        latent_dim: int,
        base_channels: int = 128,
        channel_mult: Sequence[int] = (1, 1, 2, 2, 4),
        num_res_blocks: int = 3,
        out_channels: int = 3,
        dropout: float = 0.0,
        in_channels: int = 0,
    ):
        super().__init__()
        widths = [base_channels * m for m in channel_mult]
        self.upscale = 2 ** (len(widths) - 1)
        ch = widths[-1]
        self.latent_in = nn.Conv2d(latent_dim, in_channels, 1) if in_channels else nn.Identity()
        self.conv_in = nn.Conv2d(in_channels or latent_dim, ch, 3, padding=1)
        self.mid = nn.Sequential(ResBlock(ch, ch, dropout), AttnBlock(ch), ResBlock(ch, ch, dropout))
        levels = []
        for i, width in reversed(list(enumerate(widths))):
            layers = []
            for _ in range(num_res_blocks):
                layers.append(ResBlock(ch, width, dropout))
                ch = width
                if i == len(widths) - 1:
                    layers.append(AttnBlock(ch))
            if i > 0:
                layers.append(Upsample(ch))
            levels.append(nn.Sequential(*layers))
        self.up = nn.Sequential(*levels)
        self.norm_out = group_norm(ch)
        self.conv_out = nn.Conv2d(ch, out_channels, 3, padding=1)

    @property
    def last_layer(self) -> torch.Tensor:
        """Weight used by the adaptive GAN weight (taming: the decoder's last conv)."""
        return self.conv_out.weight

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        h = self.up(self.mid(self.conv_in(self.latent_in(z))))
        return self.conv_out(F.silu(self.norm_out(h)))


# --------------------------------------------------------------------------- tokenizers


class DetailTokenizer(nn.Module):
    """E_L: pixel-aligned detail latent trained with the VQGAN objective (paper Sec. 3.2)."""

    def __init__(self, encoder: ViTEncoder, quantizer: VectorQuantizer, decoder: ConvDecoder):
        super().__init__()
        self.encoder = encoder
        self.quant_conv = nn.Conv2d(encoder.embed_dim, quantizer.latent_dim, 1)
        self.quantizer = quantizer
        self.decoder = decoder

    @property
    def latent_dim(self) -> int:
        return self.quantizer.latent_dim

    @property
    def last_layer(self) -> torch.Tensor:
        return self.decoder.last_layer

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """Images in [-1, 1] -> continuous L2-normalised latent [B, 16, h, w] (pre-quantisation)."""
        return F.normalize(self.quant_conv(self.encoder(images)), dim=1)

    def quantize(self, z: torch.Tensor) -> VQOutput:
        return self.quantizer(z)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latent -> images clamped to [-1, 1] (for viewing and metrics, not for losses)."""
        return self.decoder(z).clamp(-1.0, 1.0)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, VQOutput]:
        """Reconstruction (unclamped, for the losses) and the quantiser's output."""
        vq = self.quantize(self.encode(images))
        return self.decoder(vq.quantized), vq


class AbstractTokenizer(nn.Module):
    """E_H with projection head P and light decoder D_H (paper Sec. 3.2, eq. 3).

    ``compress=True``: z is a 16-d L2-normalised latent and P is a 1x1 conv
    16 -> teacher_dim. ``compress=False`` (the paper's RAE comparison, App.
    "full DINO space"): no bottleneck; a 1x1 conv maps the encoder straight to
    the teacher's dimension and that prediction itself is the latent.
    """

    def __init__(
        self,
        encoder: ViTEncoder,
        decoder: ConvDecoder,
        teacher_dim: int,
        latent_dim: int = 16,
        compress: bool = True,
    ):
        super().__init__()
        self.compress = compress
        self.teacher_dim = teacher_dim
        self.latent_dim = latent_dim if compress else teacher_dim
        self.encoder = encoder
        self.quant_conv = nn.Conv2d(encoder.embed_dim, self.latent_dim, 1)
        self.projection = nn.Conv2d(latent_dim, teacher_dim, 1) if compress else nn.Identity()
        self.decoder = decoder

    @property
    def last_layer(self) -> torch.Tensor:
        return self.decoder.last_layer

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """Images in [-1, 1] -> abstract latent z [B, latent_dim, h, w]."""
        z = self.quant_conv(self.encoder(images))
        return F.normalize(z, dim=1) if self.compress else z

    def predict_teacher(self, z: torch.Tensor) -> torch.Tensor:
        """P(z): the teacher's patch features predicted on the latent grid."""
        return self.projection(z)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latent -> images clamped to [-1, 1] (for viewing and metrics, not for losses)."""
        return self.decoder(z).clamp(-1.0, 1.0)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(z, P(z), unclamped D_H(z))."""
        z = self.encode(images)
        return z, self.predict_teacher(z), self.decoder(z)


def _config(config: TokenizerConfig | str) -> TokenizerConfig:
    return tokenizer_config(config) if isinstance(config, str) else config


def _encoder(cfg: TokenizerConfig) -> ViTEncoder:
    return ViTEncoder(
        image_size=cfg.image_size,
        patch_size=cfg.patch_size,
        embed_dim=cfg.embed_dim,
        depth=cfg.depth,
        num_heads=cfg.num_heads,
        mlp_ratio=cfg.mlp_ratio,
        learn_pos_embed=cfg.learn_pos_embed,
        cls_token=cfg.cls_token,
    )


def build_detail_tokenizer(config: TokenizerConfig | str = "default") -> DetailTokenizer:
    """The detail tokenizer of ``config``'s size (a preset's name stands for ``TOKENIZER_PRESETS[name]``)."""
    cfg = _config(config)
    quantizer = VectorQuantizer(
        codebook_size=cfg.codebook_size,
        latent_dim=cfg.latent_dim,
        beta=cfg.beta,
        bypass_prob=cfg.bypass_prob,
        entropy_temperature=cfg.entropy_temperature,
    )
    decoder = ConvDecoder(cfg.latent_dim, cfg.decoder_channels, cfg.decoder_mult, cfg.decoder_res_blocks,
                          in_channels=cfg.decoder_in_channels)
    return conv_layout(DetailTokenizer(_encoder(cfg), quantizer, decoder))


def build_abstract_tokenizer(
    config: TokenizerConfig | str = "default", teacher_dim: int = 768, compress: bool = True
) -> AbstractTokenizer:
    """The abstract tokenizer of ``config``'s size, aligned to a ``teacher_dim``-channel teacher."""
    cfg = _config(config)
    latent_dim = cfg.latent_dim if compress else teacher_dim
    decoder = ConvDecoder(
        latent_dim, cfg.abstract_decoder_channels, cfg.abstract_decoder_mult, cfg.abstract_decoder_res_blocks,
        in_channels=cfg.abstract_decoder_in_channels,
    )
    return conv_layout(AbstractTokenizer(_encoder(cfg), decoder, teacher_dim, cfg.latent_dim, compress))
