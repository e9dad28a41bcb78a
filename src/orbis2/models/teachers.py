"""Frozen feature teachers for the abstract tokenizer.

Every teacher takes images as float [B, 3, H, W] in [-1, 1] and returns a patch
feature map [B, C, h, w]; it owns the input normalisation its network was
trained with, so callers never need to know it.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from orbis2.accel import conv_layout

# TF-slim Inception expects x/128 - 1 for x in 0..255, i.e. [0, 1] maps to [-1, 255/128 - 1].
_INCEPTION_RANGE = (-1.0, 0.9921875)
INCEPTION_LAYERS = ("mixed_3", "mixed_4", "mixed_5", "mixed_6", "mixed_7")  # the 768-channel 17x17 (7x14 here) maps
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


class _FrozenTeacher(nn.Module):
    """Teachers never train: eval mode is pinned and gradients are off."""

    def _freeze(self) -> None:
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> "_FrozenTeacher":
        return super().train(False)


def _inception_layers(path: str | Path, wanted: tuple[str, ...]) -> list[tuple[str, nn.Module]]:
    """The FID network's ``net.layers`` children, named, up to the last of ``wanted``."""
    with warnings.catch_warnings():  # the FID network only exists as TorchScript; its deprecation is moot here
        warnings.simplefilter("ignore", DeprecationWarning)
        scripted = torch.jit.load(str(path), map_location="cpu")
    children = list(scripted.net.layers.named_children())
    names = [name for name, _ in children]
    if missing := [name for name in wanted if name not in names]:
        raise ValueError(f"{path}: no layer {', '.join(map(repr, missing))} in net.layers (found {names})")
    return children[: max(names.index(name) for name in wanted) + 1]


def _inception_input(images: torch.Tensor) -> torch.Tensor:
    """Images in [-1, 1] mapped to the TF-slim range the FID network was trained with."""
    low, high = _INCEPTION_RANGE
    return ((images + 1) / 2).clamp(0, 1) * (high - low) + low


class InceptionTeacher(_FrozenTeacher):
    """InceptionV3 (the FID network, TorchScript) cut after ``layer``: a 768-channel map.

    A 144x256 frame gives a 7x14 map. The TorchScript's ``net.layers`` is run child by child,
    so the later stages (and the 8x8 pooling that needs 299x299 inputs) never run. The shallower
    ``mixed_4`` keeps more of the scene's geometry (a linear probe recovers the ego's yaw rate
    from two of its maps 0.5 s apart far better than from ``mixed_7``'s).
    """

    feature_dim = 768

    def __init__(self, path: str | Path, layer: str = "mixed_7"):
        super().__init__()
        if layer not in INCEPTION_LAYERS:
            raise ValueError(f"teacher_layer {layer!r} must be one of {INCEPTION_LAYERS}")
        self.layers = nn.ModuleList(module for _, module in _inception_layers(path, (layer,)))
        self._freeze()

    @torch.no_grad()
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = _inception_input(images)
        for layer in self.layers:
            x = layer(x)
        return x


PERCEPTUAL_TAPS = ("conv_2", "conv_4", "mixed_2")  # 64, 192 and 288 channels at 1/2, 1/4 and 1/8 of the frame


class InceptionPerceptual(_FrozenTeacher):
    """InceptionV3 (the FID network) as a perceptual network: its maps at ``taps``, with gradients to the input.

    The paper's detail tokenizer trains with LPIPS, whose VGG weights are not available offline; this is the same
    recipe on the one ImageNet network we have (post-ReLU maps at three scales, compared by
    :func:`orbis2.losses.feature_distance`). Measured as a lever (``tools/tokenizer_levers.py --perceptual``).
    """

    def __init__(self, path: str | Path, taps: tuple[str, ...] = PERCEPTUAL_TAPS):
        super().__init__()
        children = _inception_layers(path, taps)
        self.names = [name for name, _ in children]
        self.taps = taps
        self.layers = nn.ModuleList(module for _, module in children)
        self._freeze()

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        x = _inception_input(images)
        maps = []
        for name, layer in zip(self.names, self.layers):
            x = layer(x)
            if name in self.taps:
                maps.append(x)
        return maps


class LayerScale(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class PatchEmbed(nn.Module):
    def __init__(self, patch_size: int, dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, patch_size, patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class Attention(nn.Module):
    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, dim * 3)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, c // self.num_heads).permute(2, 0, 3, 1, 4)
        x = F.scaled_dot_product_attention(q, k, v)
        return self.proj(x.transpose(1, 2).reshape(b, n, c))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class Block(nn.Module):
    def __init__(self, dim: int, num_heads: int, mlp_ratio: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, num_heads)
        self.ls1 = LayerScale(dim)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class DinoV2ViT(nn.Module):
    """ViT with DINOv2's parameter names, so the official checkpoints load strictly.

    Defaults are ViT-B/14 trained at 518x518 (37x37 patches). Other grids get the
    position embedding resampled bicubically exactly as DINOv2 does it (scale factor
    with the +0.1 offset), so features match the official code at any input size.
    """

    def __init__(self, embed_dim: int = 768, depth: int = 12, num_heads: int = 12, patch_size: int = 14,
                 mlp_ratio: float = 4.0, img_size: int = 518):
        super().__init__()
        self.patch_size = patch_size
        self.embed_dim = embed_dim
        num_patches = (img_size // patch_size) ** 2
        self.patch_embed = PatchEmbed(patch_size, embed_dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, num_patches + 1, embed_dim))
        self.mask_token = nn.Parameter(torch.zeros(1, embed_dim))  # used only in DINOv2 training; kept for loading
        self.blocks = nn.ModuleList(Block(embed_dim, num_heads, mlp_ratio) for _ in range(depth))
        self.norm = nn.LayerNorm(embed_dim, eps=1e-6)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)

    def interpolate_pos_encoding(self, h: int, w: int) -> torch.Tensor:
        """Position embedding for an h x w patch grid (class token first)."""
        grid = self.pos_embed.shape[1] - 1
        side = int(math.sqrt(grid))
        if h * w == grid and h == w:
            return self.pos_embed
        patch_pos = self.pos_embed[:, 1:].float().reshape(1, side, side, -1).permute(0, 3, 1, 2)
        patch_pos = F.interpolate(patch_pos, scale_factor=((h + 0.1) / side, (w + 0.1) / side), mode="bicubic")
        patch_pos = patch_pos.permute(0, 2, 3, 1).reshape(1, h * w, -1)
        return torch.cat([self.pos_embed[:, :1].float(), patch_pos], dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised images [B, 3, H, W] (H, W multiples of the patch size) -> patch tokens [B, C, H/p, W/p]."""
        b, _, height, width = x.shape
        if height % self.patch_size or width % self.patch_size:
            raise ValueError(f"DINOv2 input {height}x{width} is not a multiple of the patch size {self.patch_size}")
        h, w = height // self.patch_size, width // self.patch_size
        tokens = torch.cat([self.cls_token.expand(b, -1, -1), self.patch_embed(x)], dim=1)
        tokens = tokens + self.interpolate_pos_encoding(h, w).to(tokens.dtype)
        for block in self.blocks:
            tokens = block(tokens)
        patches = self.norm(tokens)[:, 1:]
        return patches.transpose(1, 2).reshape(b, self.embed_dim, h, w)


def load_dinov2_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Read an official DINOv2 ViT-B/14 state dict and check it fits :class:`DinoV2ViT` exactly."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    with torch.device("meta"):
        model = DinoV2ViT()
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = sorted(k for k in set(expected) & set(state) if state[k].shape != expected[k].shape)
    if missing or unexpected or wrong:
        raise ValueError(
            f"{path} is not the official DINOv2 ViT-B/14 state dict (dinov2_vitb14_pretrain.pth): "
            f"missing keys {missing[:8]}{'...' if len(missing) > 8 else ''}, unexpected keys {unexpected[:8]}"
            f"{'...' if len(unexpected) > 8 else ''}, wrong shapes {wrong[:8]}"
        )
    return state


class DinoV2Teacher(_FrozenTeacher):
    """DINOv2 ViT-B/14 patch features after the final norm: [B, 768, H/14, W/14]."""

    feature_dim = 768

    def __init__(self, path: str | Path):
        super().__init__()
        state = load_dinov2_state_dict(path)
        with torch.device("meta"):
            self.vit = DinoV2ViT()
        self.vit.load_state_dict(state, strict=True, assign=True)
        self.register_buffer("mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self._freeze()

    @torch.no_grad()
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.vit(((images + 1) / 2 - self.mean) / self.std)


def build_teacher(name: str, path: Path, layer: str | None = None) -> nn.Module:
    """Teacher by config name: "inception" (default, from the registry; ``layer`` picks its cut) or
    "dinov2" (the paper's; its last layer)."""
    if name == "inception":
        return conv_layout(InceptionTeacher(path, layer or "mixed_7"))
    if name == "dinov2":
        return DinoV2Teacher(path)
    raise ValueError(f"unknown teacher {name!r}; choose one of ['dinov2', 'inception']")
