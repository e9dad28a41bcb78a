"""The checkpoint file formats of the trained networks: predictors and tokenizers.

Each file holds what rebuilds the architecture (``build``: the preset, its size overrides and the
builder's other arguments), the weights and what they mean; loading rebuilds, loads strictly and
freezes. Written atomically through a handle, so the same content gives the same bytes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from orbis2.errors import OrbisError
from orbis2.io import atomic_file, sha256_file
from orbis2.models import split_build
from orbis2.models.sizes import TOKENIZER_PRESETS
from orbis2.models.stdit import STDiT, build_stdit_from
from orbis2.models.tokenizer import build_abstract_tokenizer, build_detail_tokenizer

# --------------------------------------------------------------------------- predictors


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

    def nfe(self, default: int) -> int:
        """Euler steps to sample with: the predictor's own (a distilled predictor records them) or ``default``."""
        return int(self.meta.get("sampling", {}).get("nfe", default))


def load_recorded_weights(path: Path, model: nn.Module, state: dict, kind: str) -> None:
    """``state`` into ``model`` strictly; weights that do not fit the network the file's build describes stop
    with a line naming the file. Files written before builds recorded every size setting
    (:func:`orbis2.models.full_build`) took the defaults of their time, among them RMSNorm q/k norms and no
    CLS token in the tokenizer encoders: they no longer fit, and only training them again mends them."""
    try:
        model.load_state_dict(state)
    except RuntimeError as err:
        detail = str(err).split("\n\t")[1][:300] if "\n\t" in str(err) else str(err)[:300]
        raise OrbisError(f"{path}: its weights do not fit the {kind} its build describes ({detail}), as in a "
                         f"file written before the LayerNorm q/k norms and the encoders' CLS token became the "
                         f"defaults: run its training stage again") from None


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
    load_recorded_weights(path, model, blob["state_dict"], "predictor")
    model.to(device).eval().requires_grad_(False)
    return PredictorFile(model, blob["build"], blob["meta"], sha256_file(path))


# --------------------------------------------------------------------------- tokenizers


@dataclass
class TokenizerFile:
    """A trained tokenizer as the later stages load it, with the normalisation its latents get.

    The world model sees ``normalize(z) = (z - shift) * scale`` of the tokenizer's latent ``z``:
    ``shift`` [C, h, w] is the training data's per-position, per-channel mean (zeros for the
    paper's single global scale) and ``scale`` [C, 1, 1] the inverse standard deviation of what
    is left, per channel (one value repeated for the global scale). Rollouts are mapped back with
    ``denormalize`` before decoding. ``checksum`` is the SHA-256 of the file, recorded by caches
    built from it.
    """

    kind: str  # "detail" | "abstract"
    model: nn.Module
    scale: torch.Tensor  # [C, 1, 1]
    build: dict  # what rebuilds the architecture: preset (and size overrides), teacher_dim, compress
    checksum: str
    shift: torch.Tensor  # [C, h, w]

    def normalize(self, z: torch.Tensor) -> torch.Tensor:
        """Latent ``[..., C, h, w]`` -> what the predictors train on."""
        return (z - self.shift.to(z)) * self.scale.to(z)

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`normalize`: back to the tokenizer's latent, ready to decode."""
        return x / self.scale.to(x) + self.shift.to(x)


def latent_normalization(scale: float | torch.Tensor, shift: torch.Tensor | None, shape: tuple[int, ...]
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(scale [C, 1, 1], shift [C, h, w])`` as float32 from a global float or per-channel values."""
    c = shape[0]
    scale = torch.as_tensor(scale, dtype=torch.float32).reshape(-1, 1, 1).expand(c, 1, 1).clone()
    shift = torch.zeros(shape) if shift is None else torch.as_tensor(shift, dtype=torch.float32).reshape(shape)
    return scale, shift.clone()


def save_tokenizer(path: Path, kind: str, model: nn.Module, scale: float | torch.Tensor, build: dict,
                   extra: dict | None = None, shift: torch.Tensor | None = None) -> None:
    """Write ``{kind, build, scale, shift, state_dict, extra}`` atomically; same content, same bytes.

    ``scale`` is a float (the paper's global scale) or per-channel values; ``shift`` the
    per-position mean [C, h, w] (None: zeros). Both are stored in full ([C, 1, 1], [C, h, w]).
    """
    if kind not in ("detail", "abstract"):
        raise ValueError(f"kind must be 'detail' or 'abstract', got {kind!r}")
    shape = tuple(shift.shape) if shift is not None else _latent_shape(model)
    scale_t, shift_t = latent_normalization(scale, shift, shape)
    blob = {"kind": kind, "build": build, "scale": scale_t, "shift": shift_t, "state_dict": model.state_dict(),
            "extra": extra or {}}
    with atomic_file(Path(path)) as tmp, open(tmp, "wb") as handle:
        torch.save(blob, handle)  # through a handle: the bytes must not depend on the temp file's name


@torch.no_grad()
def _latent_shape(model: nn.Module) -> tuple[int, ...]:
    """[C, h, w] of the model's latent, from one blank image of its configured size."""
    height, width = model.encoder.image_size
    device = next(model.parameters()).device
    return tuple(model.encode(torch.zeros(1, 3, height, width, device=device)).shape[1:])


def load_tokenizer(path: Path, device: str | torch.device = "cpu") -> TokenizerFile:
    """Rebuild the architecture from the file, load the weights strictly, eval mode, frozen."""
    path = Path(path)
    if not path.is_file():
        raise OrbisError(f"{path}: tokenizer checkpoint not found; run its training stage first")
    blob = torch.load(path, map_location=device, weights_only=True)
    cfg, rest = split_build(TOKENIZER_PRESETS, blob["build"])
    builder = build_detail_tokenizer if blob["kind"] == "detail" else build_abstract_tokenizer
    model = builder(cfg, **rest)
    load_recorded_weights(path, model, blob["state_dict"], "tokenizer")
    model.to(device).eval().requires_grad_(False)
    if "shift" not in blob:
        raise OrbisError(f"{path}: written by an older version without the latent normalisation; "
                         f"re-run its tokenizer stage")
    return TokenizerFile(blob["kind"], model, blob["scale"].float(), blob["build"], sha256_file(path),
                         blob["shift"].float())
