"""The authors' released Orbis 2 networks in our checkpoint files (``orbis2 import-weights``).

The authors publish trained weights with inference code only (``hf download sud0301/orbis2``): a release
folder holds ``L1/config.yaml`` (the detail predictor, which names the tokenizer's and the abstract
predictor's folders), ``L1/config_distill.yaml`` (the same with the distilled abstract predictor) and, per
network, ``config.yaml`` + ``checkpoints/last.ckpt`` (Lightning checkpoints: ``state_dict`` with the
predictor under ``vit.*``, its EMA under ``ema_vit.*`` (what sampling uses, so what we convert) and a copy of
the tokenizer under ``ae.*``).

Their networks differ from ours in choices the paper leaves open; each has an option in our models
(``sizes.STDiTConfig``, ``sizes.TokenizerConfig``) whose default is ours and which the import sets to theirs,
so the converted files rebuild their architecture from the ``build`` dict they record. Weights map one to
one except: the patch embedding's conv becomes a linear map; their 9-way adaLN (plus an optional 3-way one
for the temporal attention) becomes our 12-way one (constant rows 0, 0, 1 where their temporal attention has
no adaLN); their velocity x - eps becomes ours, eps - x, by negating the final linear layer; the decoders'
separate q, k, v convs become one qkv conv. Their "causal" temporal mask adds +1 to the allowed scores and
lets the future leak into earlier frames: the import keeps our hard mask unless asked for theirs
(``causal_mask="additive"``), which is what reproduces their outputs.

Loading trusts no code: checkpoints are read with ``torch.load(weights_only=True)``; the non-tensor objects a
Lightning checkpoint carries (hyper-parameters, loop states) are rebuilt as inert placeholders
(:func:`read_checkpoint`) and never used. Every config key is either converted, known to matter only for
training (recorded in the manifest) or refused with one line naming it.
"""

from __future__ import annotations

import json
import os
import pickle
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import yaml

from orbis2.errors import OrbisError
from orbis2.io import atomic_dir, sha256_file, write_json
from orbis2.models import OFFICIAL_SOURCE, split_build
from orbis2.models.files import save_predictor, save_tokenizer
from orbis2.models.sizes import TOKENIZER_PRESETS
from orbis2.models.stdit import build_stdit_from
from orbis2.models.stdit_layers import grid_positions
from orbis2.models.tokenizer import build_abstract_tokenizer, build_detail_tokenizer

ENV_ROOT = "ORBIS2_MODELS_DIR"  # their configs name the other networks' folders through this variable
DEFAULT_SCALES = {"detail": 4.0, "abstract": 3.45062}  # their PredictorModule's enc_scale and enc_scale_dino
DEFAULT_CONSISTENCY_GRIDS = {1: [0.99], 2: [0.99, 0.8333], 4: [0.99, 0.9375, 0.8333, 0.625]}
VIT_HEAD_DIM = 64  # every ViT their tokenizer encoders name (MAE ViT-B/16 and ViT-L/16) has 64-d heads


class ReleaseError(OrbisError):
    """A release folder this importer cannot convert: the message names the file (and key) and the fix."""


# --------------------------------------------------------------------------- reading their files


class _Placeholder:
    """An inert stand-in for a non-tensor object in a Lightning checkpoint: takes any arguments and state and
    does nothing with them (no code of the checkpoint's classes runs)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args, self.kwargs = args, kwargs

    def __setstate__(self, state: Any) -> None:
        self.state = state


_UNSUPPORTED_GLOBAL = re.compile(r"(?:Unsupported global: GLOBAL|Unsupported class) ([\w.]+)")


def read_checkpoint(path: Path) -> dict[str, torch.Tensor]:
    """The ``state_dict`` of a Lightning checkpoint, read with ``weights_only=True``.

    Objects of other classes in the file (Lightning's hyper-parameters, OmegaConf configs, loop states) are
    allow-listed one by one as :class:`_Placeholder` under their own names, so the file loads without running
    any of its code; only the state dict's tensors are used.
    """
    if not path.is_file():
        raise ReleaseError(f"{path}: checkpoint not found; download the whole release (hf download sud0301/orbis2)")
    stand_ins: list[tuple[type, str]] = []
    for _ in range(64):
        try:
            with torch.serialization.safe_globals(stand_ins):
                blob = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
            break
        except pickle.UnpicklingError as err:
            found = _UNSUPPORTED_GLOBAL.search(str(err))
            if found is None:
                raise ReleaseError(f"{path}: not a readable checkpoint ({str(err).splitlines()[0][:200]})") from err
            name = found.group(1)
            stand_ins.append((type(name.rsplit(".", 1)[-1], (_Placeholder,), {}), name))
        except (RuntimeError, OSError, EOFError) as err:
            raise ReleaseError(f"{path}: not a readable checkpoint ({str(err).splitlines()[0][:200]})") from err
    else:
        raise ReleaseError(f"{path}: more than 64 kinds of objects besides tensors; not a Lightning checkpoint")
    state = blob.get("state_dict") if isinstance(blob, dict) else None
    if not isinstance(state, dict):
        raise ReleaseError(f"{path}: has no state_dict; pass the release's checkpoints/last.ckpt")
    return state


def read_config(path: Path) -> dict:
    if not path.is_file():
        raise ReleaseError(f"{path}: config not found; download the whole release (hf download sud0301/orbis2)")
    try:
        config = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ReleaseError(f"{path}: not valid YAML ({str(err).splitlines()[0]})") from err
    if not isinstance(config, dict) or not isinstance(config.get("model"), dict):
        raise ReleaseError(f"{path}: has no `model` section; pass the release's config.yaml")
    return config


def release_folder(reference: str, root: Path, config: Path, key: str) -> Path:
    """A network's folder named in a config (``${oc.env:ORBIS2_MODELS_DIR}/tokenizer`` or a path): the
    variable stands for the release ``root``; a path that does not exist is looked up by its last
    components under ``root``."""
    text = str(reference)
    for pattern in ("${oc.env:" + ENV_ROOT + "}", "${" + ENV_ROOT + "}", "$" + ENV_ROOT):
        text = text.replace(pattern, str(root))
    path = Path(os.path.expanduser(text))
    if not path.is_absolute():
        path = root / path
    if (path / "config.yaml").is_file():
        return path
    parts = Path(text).parts
    for start in range(len(parts)):
        candidate = root.joinpath(*parts[start:])
        if (candidate / "config.yaml").is_file():
            return candidate
    raise ReleaseError(f"{config}: {key} = {reference!r} names no folder with a config.yaml under {root}; "
                       f"download the whole release")


# --------------------------------------------------------------------------- checking their config keys


@dataclass
class Section:
    """One config mapping being converted: which keys were read, which matter only for training."""

    path: Path
    key: str
    params: dict
    used: set[str] = field(default_factory=set)
    training_only: dict[str, Any] = field(default_factory=dict)

    def get(self, name: str, default: Any = None) -> Any:
        self.used.add(name)
        return self.params.get(name, default)

    def require(self, name: str) -> Any:
        self.used.add(name)
        if name not in self.params:
            raise ReleaseError(f"{self.path}: {self.key}.{name} is missing; pass the release's unmodified config")
        return self.params[name]

    def expect(self, name: str, allowed: tuple, default: Any) -> Any:
        """A key whose other values this importer does not convert."""
        value = self.get(name, default)
        if value not in allowed:
            raise ReleaseError(f"{self.path}: {self.key}.{name} = {value!r} is not supported (supported: "
                               f"{', '.join(repr(a) for a in allowed)})")
        return value

    def ignore(self, *names: str) -> None:
        """Keys that only training reads: recorded, not converted."""
        for name in names:
            if name in self.params:
                self.used.add(name)
                self.training_only[name] = self.params[name]

    def sub(self, name: str, default: dict | None = None) -> Section:
        value = self.get(name, default)
        if not isinstance(value, dict):
            raise ReleaseError(f"{self.path}: {self.key}.{name} must be a mapping, got {value!r}")
        return Section(self.path, f"{self.key}.{name}", value)

    def done(self) -> None:
        """Refuse what was neither converted nor known to be training-only."""
        unknown = sorted(set(self.params) - self.used)
        if unknown:
            raise ReleaseError(f"{self.path}: {self.key}.{unknown[0]} is not a key this importer knows "
                               f"(a newer release?); nothing was written")


def target_of(section: Section, allowed: tuple[str, ...]) -> tuple[str, Section]:
    """The ``target`` class of an instantiate-from-config mapping (checked) and its ``params``."""
    target = section.expect("target", allowed, None)
    params = section.sub("params", {})
    section.done()
    return target.rsplit(".", 1)[-1], params


# --------------------------------------------------------------------------- predictors

STEERING_CONDITIONERS = tuple(f"networks.DiT.dit_v2.{name}" for name in (
    "SequenceGlobalAdditiveConditioner", "PerFrameSequenceGlobalAdditiveConditioner"))
GENERATORS = ("networks.DiT.dit_v2.DiT", "networks.DiT.dit_v2.SpatialL2CtxAndLastDiT")
BLOCKS = ("modules.dit.STDiTBlock", "modules.dit.STDiTBlockWithSpatialL2")
SAMPLERS = ("modules.fm_samplers.FlowMatchingSamplerEuler", "modules.fm_samplers.FlowMatchingSamplerHeun",
            "modules.fm_samplers.FlowMatchingSamplerHeunPlusEuler",
            "models.second_stage.cd_model_v2.ConsistencyDistillationSampler")
DIT_TRAINING_ONLY = ("dropout", "ctx_noise_aug_ratio", "ctx_noise_aug_prob", "drop_ctx_rate", "log_adaln_mean_abs",
                     "log_adaln_grad", "adaln_gate_init_std", "train_steering_adaln_only")


@dataclass
class PredictorSpec:
    """What a predictor's config says: the ``build`` dict of our network, the sampler, the latent grid."""

    build: dict
    grid: tuple[int, int]
    sampling: dict
    steering_len: int | None
    positional_steering: bool
    num_context_frames: int | None
    training_only: dict


def predictor_spec(generator: Section, sampler: Section, causal_mask: str) -> PredictorSpec:
    """Our ``build`` dict for their generator config (``DiT`` or ``SpatialL2CtxAndLastDiT``) and sampler config."""
    kind, params = target_of(generator, GENERATORS)
    detail = kind == "SpatialL2CtxAndLastDiT"
    grid = params.require("input_size")
    grid = (int(grid[0]), int(grid[1])) if isinstance(grid, list | tuple) else (int(grid), int(grid))
    hidden = int(params.require("hidden_size"))
    latent_channels = int(params.get("in_channels", 32))
    options: dict[str, Any] = {
        "hidden_size": hidden, "depth": int(params.require("depth")), "num_heads": int(params.require("num_heads")),
        "cond_dim": hidden, "mlp_ratio": float(params.get("mlp_ratio", 4.0)),
        "patch_size": int(params.get("patch_size", 2)), "max_frames": int(params.get("max_num_frames", 6)),
        "rate_range": tuple(float(v) for v in params.get("frequency_range", (2, 15))), "qk_norm": "layer",
        "rate_encoding": "interleaved", "cross_attention": False, "abstract_positions": False,
    }
    params.expect("learn_sigma", (False,), False)
    params.expect("norm_layer", ("layer_norm",), "layer_norm")
    params.expect("mlp_block", ("mlp",), "mlp")
    params.expect("frame_embedding_alignment", ("suffix",), "suffix")
    params.ignore(*DIT_TRAINING_ONLY)
    block_kind, block = target_of(params.sub("block_config"), BLOCKS)
    if (block_kind == "STDiTBlockWithSpatialL2") != detail:
        raise ReleaseError(f"{params.path}: {params.key}.block_config.target {block_kind} does not fit {kind}")
    causal = bool(block.get("causal_time_attn", False))
    options["time_attn_norm"] = bool(block.get("modulate_time_attn", False))
    options["causal_mask"] = causal_mask if causal else "hard"
    block.ignore("dropout_rate")
    block.done()
    steering_len, positional = None, False
    conditioner = params.get("conditioner_config")
    if conditioner is not None:
        _, cond = target_of(params.sub("conditioner_config"), STEERING_CONDITIONERS)
        options["steering_pool"] = cond.expect("aggregation", ("sum", "mean"), "sum")
        positional = bool(cond.get("add_positional_embedding", False))
        steering_len = int(cond.get("sequence_length") or 1)
        cond.get("hidden_size")
        embedders = cond.sub("condition_configs")
        names = sorted(embedders.params)
        if names != ["steering"]:
            raise ReleaseError(f"{params.path}: {embedders.key} conditions on {names}; only `steering` is supported")
        _, embedder = target_of(embedders.sub("steering"), ("modules.steering.LinearSteeringEmbedder",))
        embedders.done()
        options["steering_features"] = int(embedder.require("num_input_features"))
        embedder.get("hidden_size")
        embedder.get("learnable_no_value_embedding")
        embedder.done()
        options["steering_len"] = steering_len
        cond.done()
    sem_channels = num_context = None
    if detail:
        sem_channels = int(params.require("sem_in_channels"))
        num_context = int(params.require("num_context_frames"))
    params.done()

    sampler_kind, sampler_params = target_of(sampler, SAMPLERS)
    options["tau_scale"] = float(sampler_params.get("timescale", 1.0))
    options["timestep"] = sampler_params.expect("timestep_conditioning", ("global", "per_frame"), "global")
    sampler_params.expect("integration_t_eps", (0, 0.0), 0.0)
    sampling: dict[str, Any] = {"method": "euler"}
    if sampler_kind == "ConsistencyDistillationSampler":
        sampler_params.expect("sample_fresh_noise", (True,), True)
        grids = {**DEFAULT_CONSISTENCY_GRIDS, **{int(k): [float(t) for t in v] for k, v in
                                                  (sampler_params.get("sample_t_grids") or {}).items()}}
        sampling = {"method": "consistency", "grids": {str(k): v for k, v in sorted(grids.items())}}
    elif sampler_kind != "FlowMatchingSamplerEuler":  # recorded: our rollouts take Euler steps (docs)
        sampling = {"method": "heun" if sampler_kind == "FlowMatchingSamplerHeun" else "heun_then_euler",
                    "authors_sampler": _jsonable({"target": sampler_kind, **sampler_params.params})}
        sampler_params.get("step_schedule")
    sampler_params.done()
    build = {"preset": "paper", **options, "latent_channels": latent_channels, "causal": causal,
             "abstract_channels": sem_channels, "steering": conditioner is not None}
    training_only = {**params.training_only, **block.training_only}
    return PredictorSpec(build, grid, sampling, steering_len, positional, num_context, training_only)


def convert_predictor(state: dict[str, torch.Tensor], spec: PredictorSpec, source: str) -> dict[str, torch.Tensor]:
    """Their DiT state dict (keys without ``vit.``/``ema_vit.``) -> ours for ``spec.build``, checked for a strict
    load; ``source`` names it in errors."""
    b = spec.build
    d, p, c = b["hidden_size"], b["patch_size"], b["latent_channels"]
    their = dict(state)
    out: dict[str, torch.Tensor] = {}

    def take(key: str) -> torch.Tensor:
        if key not in their:
            raise ReleaseError(f"{source}: has no {key}; is it the checkpoint its config describes?")
        return their.pop(key)

    pos = take("pos_embed")
    expected = grid_positions(d, spec.grid[0] // p, spec.grid[1] // p, torch.device("cpu"))
    fits = tuple(pos.shape[-2:]) == tuple(expected.shape)
    if not fits or (not pos.is_meta and not torch.allclose(pos[0].float(), expected, atol=1e-5)):  # meta: shapes only
        raise ReleaseError(f"{source}: pos_embed is not the fixed 2-D sin-cos table of a {spec.grid} grid")
    conv = take("x_embedder.proj.weight")
    out["x_embedder.weight"] = conv.permute(0, 2, 3, 1).reshape(d, p * p * c)
    out["x_embedder.bias"] = take("x_embedder.proj.bias")
    for i in (0, 2):
        for name in ("weight", "bias"):
            out[f"tau_embedder.mlp.{i}.{name}"] = take(f"t_embedder.mlp.{i}.{name}")
    out["frame_embed"] = take("frame_emb")[0, :, 0]
    for i in range(b["depth"]):
        src, dst = f"blocks.{i}.", f"blocks.{i}."
        weight, bias = take(src + "adaLN_modulation.1.weight"), take(src + "adaLN_modulation.1.bias")
        if b["time_attn_norm"]:
            time_w = take(src + "adaLN_time_attn_modulation.1.weight")
            time_b = take(src + "adaLN_time_attn_modulation.1.bias")
        else:  # no temporal adaLN: shift 0, scale 0, gate 1 whatever the conditioning
            time_w = weight.new_zeros(3 * d, d)
            time_b = torch.cat([bias.new_zeros(2 * d), bias.new_ones(d)])
        out[dst + "adaLN_modulation.1.weight"] = torch.cat([weight[: 6 * d], time_w, weight[6 * d:]])
        out[dst + "adaLN_modulation.1.bias"] = torch.cat([bias[: 6 * d], time_b, bias[6 * d:]])
        for attn in ("space_attn", "time_attn"):
            for part in ("qkv", "q_norm", "k_norm", "proj"):
                for name in ("weight", "bias"):
                    out[f"{dst}{attn}.{part}.{name}"] = take(f"{src}{attn}.{part}.{name}")
        for mlp in ("space_mlp", "time_mlp"):
            for part in ("fc1", "fc2"):
                for name in ("weight", "bias"):
                    out[f"{dst}{mlp}.{part}.{name}"] = take(f"{src}{mlp}.{part}.{name}")
        if b["abstract_channels"] is not None:
            for name in ("weight", "bias"):
                out[f"{dst}cond_modulation.1.{name}"] = take(f"{src}spatial_to_mod.1.{name}")
    for name in ("weight", "bias"):
        out[f"final_layer.adaLN_modulation.1.{name}"] = take(f"final_layer.adaLN_modulation.1.{name}")
        out[f"final_layer.linear.{name}"] = -take(f"final_layer.linear.{name}")  # x - eps -> eps - x
    if b["abstract_channels"] is not None:
        for name in ("weight", "bias"):
            out[f"abstract.patchify.{name}"] = take(f"l2_patchify.{name}")
            for i in (0, 2):
                out[f"abstract.frame_position.{i}.{name}"] = take(f"position_proj.{i}.{name}")
    if b["steering"]:
        prefix = "conditioner.condition_embedders.steering."
        for k in range(b["steering_features"]):
            for i in (0, 2):
                for name in ("weight", "bias"):
                    out[f"steering.feature_mlps.{k}.{i}.{name}"] = take(f"{prefix}embedders.{k}.{i}.{name}")
        out["steering.no_value"] = take(prefix + "no_value_embeddings")
        out["steering.position"] = (take("conditioner.positional_embeddings.steering") if spec.positional_steering
                                    else torch.zeros(b["steering_len"], d))
    if their:
        raise ReleaseError(f"{source}: {sorted(their)[0]} has no counterpart in our predictor; nothing was written")
    return out


# --------------------------------------------------------------------------- tokenizer

TOKENIZERS = tuple(f"models.first_stage.vqgan.{name}" for name in (
    "VQModelIFExtraSepEncSepDec", "VQModelIFExtraSepEncSepDecJointSem"))
TOKENIZER_TRAINING_ONLY = ("loss_config", "grad_acc_steps", "cont_ratio_trainig", "ignore_keys", "monitor",
                           "entropy_loss_weight_scheduler_config", "distill_model_type", "min_lr_multiplier",
                           "only_decoder", "scale_equivariance", "sem_dec_loss_weight")
# What of their tokenizer checkpoint has no counterpart in ours, and why.
LEFT_OUT = {"distill": "their frozen teacher (DINOv2)", "loss": "the discriminator and LPIPS (training only)",
            "quantize2": "the abstract codebook (the abstract tokenizer hands on its continuous latent)"}


@dataclass
class TokenizerSpec:
    """Our tokenizers' ``build`` dicts (size overrides of the ``paper`` preset) from their tokenizer config."""

    detail: dict
    abstract: dict
    decoder_levels: int
    decoder_blocks: int
    training_only: dict


def _encoder_sizes(section: Section) -> dict:
    _, params = target_of(section, ("networks.tokenizer.pretrained_models.Encoder",))
    params.expect("pretrained_encoder", ("MAE", "MAE_VIT_L"), "MAE")
    size = params.require("resolution")
    image_size = (int(size[0]), int(size[1])) if isinstance(size, list | tuple) else (int(size), int(size))
    sizes = {"image_size": image_size, "patch_size": int(params.get("patch_size", 16)),
             "embed_dim": int(params.get("z_channels", 768))}
    params.expect("normalize_embedding", (True,), True)
    params.get("channels")
    params.get("e_dim")
    params.ignore("use_pretrained_weights")
    params.done()
    return sizes


def tokenizer_spec(model: Section, vit_depth: int, teacher_dim: int) -> TokenizerSpec:
    """Sizes of their ``VQModelIFExtraSepEncSepDec*``: two MAE ViT encoders, two taming decoders, one VQ each
    (ours keeps the detail one; the abstract tokenizer uses its continuous latent only)."""
    _, params = target_of(model, TOKENIZERS)
    rec, sem = _encoder_sizes(params.sub("encoder_config")), _encoder_sizes(params.sub("encoder_config2"))
    if rec != sem:
        raise ReleaseError(f"{params.path}: encoder_config and encoder_config2 differ ({rec} vs {sem}); "
                           f"our two encoders share one size")
    _, dec = target_of(params.sub("decoder_config"), ("networks.tokenizer.ae.Decoder",))
    mult = tuple(int(m) for m in dec.require("ch_mult"))
    blocks = int(dec.require("num_res_blocks")) + 1
    resolution = dec.get("resolution", list(rec["image_size"]))
    low = (resolution[0] if isinstance(resolution, list | tuple) else resolution) // 2 ** (len(mult) - 1)
    heights = {low * 2 ** k for k in range(len(mult))}
    if set(dec.get("attn_resolutions", [])) & heights != {low}:
        raise ReleaseError(f"{dec.path}: {dec.key}.attn_resolutions = {dec.params.get('attn_resolutions')} puts "
                           f"attention elsewhere than the lowest resolution ({low}); not supported")
    dec.expect("out_ch", (3,), 3)
    dec.expect("resamp_with_conv", (True,), True)
    dec.expect("give_pre_end", (False,), False)
    dec.ignore("dropout", "in_channels", "double_z")
    width = int(dec.require("ch"))
    in_channels = int(dec.require("z_channels"))
    dec.done()
    quant = {}
    for key in ("quantizer_config", "quantizer_config2"):
        _, q = target_of(params.sub(key), ("modules.quantize.VectorQuantizer",))
        quant[key] = {"codebook_size": int(q.require("n_e")), "latent_dim": int(q.require("e_dim")),
                      "beta": float(q.get("beta", 0.25))}
        q.expect("normalize_embedding", (True,), True)
        q.ignore("diversity_gamma", "frac_per_sample_entropy", "token_noise", "legacy", "sane_index_shape",
                 "remap", "unknown_index")
        q.done()
    if quant["quantizer_config"]["latent_dim"] != quant["quantizer_config2"]["latent_dim"]:
        raise ReleaseError(f"{params.path}: the two quantisers' e_dim differ; our tokenizers share latent_dim")
    params.ignore(*TOKENIZER_TRAINING_ONLY)
    params.done()
    sizes = {**rec, "depth": vit_depth, "num_heads": max(1, rec["embed_dim"] // VIT_HEAD_DIM), "cls_token": True,
             "learn_pos_embed": True, **quant["quantizer_config"], "decoder_channels": width, "decoder_mult": mult,
             "decoder_res_blocks": blocks, "abstract_decoder_channels": width, "abstract_decoder_mult": mult,
             "abstract_decoder_res_blocks": blocks, "decoder_in_channels": in_channels,
             "abstract_decoder_in_channels": in_channels}
    sizes = {k: list(v) if isinstance(v, tuple) else v for k, v in sizes.items()}
    detail = {"preset": "paper", **sizes}
    abstract = {**detail, "teacher_dim": teacher_dim, "compress": True}
    return TokenizerSpec(detail, abstract, len(mult), blocks, params.training_only)


def _decoder_keys(their: str, ours: str, levels: int, blocks: int) -> dict[str, str]:
    """Their taming decoder's module prefixes -> ours (:class:`~orbis2.models.tokenizer.ConvDecoder`)."""
    names = {f"{their}conv_in.": f"{ours}conv_in.", f"{their}norm_out.": f"{ours}norm_out.",
             f"{their}conv_out.": f"{ours}conv_out.", f"{their}mid.block_1.": f"{ours}mid.0.",
             f"{their}mid.attn_1.": f"{ours}mid.1.", f"{their}mid.block_2.": f"{ours}mid.2."}
    for level in range(levels):
        index, lowest = 0, level == levels - 1
        for block in range(blocks):
            names[f"{their}up.{level}.block.{block}."] = f"{ours}up.{levels - 1 - level}.{index}."
            index += 1
            if lowest:
                names[f"{their}up.{level}.attn.{block}."] = f"{ours}up.{levels - 1 - level}.{index}."
                index += 1
        if level > 0:
            names[f"{their}up.{level}.upsample."] = f"{ours}up.{levels - 1 - level}.{index}."
    return names


def _rename_decoder_tensor(rest: str, value: torch.Tensor, pending: dict[str, torch.Tensor]
                           ) -> list[tuple[str, torch.Tensor]]:
    """One decoder parameter under its module prefix in our names; q, k and v wait in ``pending`` to become qkv."""
    if rest.startswith("nin_shortcut."):
        return [("shortcut." + rest[len("nin_shortcut."):], value)]
    if rest.startswith("proj_out."):
        return [("proj." + rest[len("proj_out."):], value)]
    head = rest.split(".", 1)[0]
    if head in ("q", "k", "v"):
        pending[rest] = value
        name = rest.split(".", 1)[1]
        if all(f"{part}.{name}" in pending for part in "qkv"):
            return [(f"qkv.{name}", torch.cat([pending.pop(f"{part}.{name}") for part in "qkv"]))]
        return []
    return [(rest, value)]


def convert_tokenizer(state: dict[str, torch.Tensor], spec: TokenizerSpec, source: str
                      ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor], list[str]]:
    """Their tokenizer's state dict -> (our detail tokenizer's, our abstract tokenizer's, what was left out)."""
    detail_map = {"encoder.encoder.": "encoder.", "quant_conv.": "quant_conv.",
                  "post_quant_conv.": "decoder.latent_in.",
                  **_decoder_keys("decoder.", "decoder.", spec.decoder_levels, spec.decoder_blocks)}
    abstract_map = {"encoder2.encoder.": "encoder.", "quant_conv2.": "quant_conv.",
                    "post_quant_conv_sem.": "decoder.latent_in.", "post_quant_conv_distill.": "projection.",
                    **_decoder_keys("decoder_sem.", "decoder.", spec.decoder_levels, spec.decoder_blocks)}
    detail: dict[str, torch.Tensor] = {}
    abstract: dict[str, torch.Tensor] = {}
    left_out: list[str] = []
    pending: dict[str, dict[str, torch.Tensor]] = {}
    for key, value in state.items():
        if key == "quantize.embedding.weight":
            detail["quantizer.codebook"] = value
            continue
        if key.split(".", 1)[0] in LEFT_OUT:
            left_out.append(key)
            continue
        for mapping, out in ((detail_map, detail), (abstract_map, abstract)):
            prefix = max((p for p in mapping if key.startswith(p)), key=len, default=None)
            if prefix is not None:
                rest = key[len(prefix):]
                for name, tensor in _rename_decoder_tensor(rest, value, pending.setdefault(prefix, {})):
                    out[mapping[prefix] + name] = tensor
                break
        else:
            raise ReleaseError(f"{source}: {key} has no counterpart in our tokenizers; nothing was written")
    left = [f"{prefix}{name}" for prefix, names in pending.items() for name in names]
    if left:
        raise ReleaseError(f"{source}: {left[0]} came without its q/k/v siblings; is the checkpoint complete?")
    return detail, abstract, sorted({k.split(".", 1)[0] for k in left_out})


def _vit_depth(state: dict[str, torch.Tensor], source: str) -> int:
    blocks = {int(m.group(1)) for k in state if (m := re.match(r"encoder\.encoder\.blocks\.(\d+)\.", k))}
    if not blocks:
        raise ReleaseError(f"{source}: has no encoder.encoder.blocks; is it the tokenizer's checkpoint?")
    return max(blocks) + 1


# --------------------------------------------------------------------------- the release folder

PREDICTOR_MODULES = tuple(f"models.second_stage.{name}" for name in (
    "fm_model_v2.PredictorModule", "fm_model_v2.L1L2PredL2PredictorModule",
    "cd_model_v2.ConsistencyDistillPredictorModule"))
MODULE_TRAINING_ONLY = ("objective_config", "adjust_lr_to_batch_size", "warmup_steps", "min_lr_multiplier",
                        "use_precomputed_training_inputs", "init_weights_path", "allow_different_resolution_checkpoint",
                        "teacher_ckpt_path", "cd_ema_mu", "cd_weight_decay")
STEERING_PREPROCESSORS = ("L2SteeringEndpointConditionPreprocessor", "SpeedYawDirectConditionPreprocessor",
                          "SpeedYawMovingGoalConditionPreprocessor")
PREPROCESSORS = tuple(f"models.second_stage.fm_conditions_v2.{name}" for name in (
    "ConditionPreprocessor", "L2EndpointConditionPreprocessor", *STEERING_PREPROCESSORS))
FIRST_STAGE = tuple(f"models.second_stage.fm_model_v2.{name}" for name in (
    "FirstStageHandler", "IFSelectBranchFirstStageHandler"))
BRANCHES = {"rec": "rec", "x0": "rec", "h": "rec", 0: "rec", "sem": "sem", "x1": "sem", "h2": "sem", 1: "sem"}


@dataclass
class Network:
    """One of their predictor configs, read, and its EMA weights converted (none for ``L1/config_distill.yaml``,
    read for the abstract predictor it names)."""

    config_file: Path
    spec: PredictorSpec
    state: dict[str, torch.Tensor]
    scales: dict[str, float]
    num_pred_frames: int
    branch: str
    frame_rate: float | None
    tokenizer: tuple[Path, Path]  # config and checkpoint
    preprocessor: dict
    checkpoint: Path | None


def network_files(section: Section, root: Path) -> tuple[Path, Path]:
    """The config and checkpoint of a network another config names (``folder`` and ``ckpt_path``)."""
    folder = release_folder(section.require("folder"), root, section.path, f"{section.key}.folder")
    checkpoint = folder / (section.get("ckpt_path") or "checkpoints/last.ckpt")
    section.done()
    return folder / "config.yaml", checkpoint


def read_network(config_file: Path, root: Path, causal_mask: str, checkpoint: Path | None) -> Network:
    """A predictor's config and the EMA weights of ``checkpoint`` (None: the config alone)."""
    config = read_config(config_file)
    model = Section(config_file, "model", config["model"])
    _, params = target_of(model, PREDICTOR_MODULES)
    tokenizer = network_files(params.sub("tokenizer_config"), root)
    spec = predictor_spec(params.sub("generator_config"), params.sub("sampler_config", {
        "target": "modules.fm_samplers.FlowMatchingSamplerEuler"}), causal_mask)
    branch = "rec"
    if params.get("first_stage_handler_config") is not None:
        _, handler = target_of(params.sub("first_stage_handler_config"), FIRST_STAGE)
        branch = BRANCHES.get(handler.get("encoder_branch", "rec"))
        if branch is None:
            raise ReleaseError(f"{config_file}: {handler.key}.encoder_branch = {handler.params['encoder_branch']!r} "
                               f"is not supported")
        handler.done()
    preprocessor: dict = {}
    if params.get("condition_preprocessor_config") is not None:
        kind, pre = target_of(params.sub("condition_preprocessor_config"), PREPROCESSORS)
        if kind in STEERING_PREPROCESSORS:  # how their raw speed and yaw rate become the steering input: recorded
            preprocessor["steering"] = {"preprocessor": kind, **_jsonable(pre.params)}
            pre.used.update(pre.params)
        if "l2_predictor_config" in pre.params:
            preprocessor["l2"] = network_files(pre.sub("l2_predictor_config"), root)
        for key in ("l2_predictor_frame_rate", "l2_pred_NFE", "num_context_frames"):
            if key in pre.params:
                preprocessor[key] = pre.get(key)
        pre.expect("use_z_l2_start", (True,), True)  # the last context latent at the last context frame, as ours
        pre.ignore("l2_context_latent")  # whether their rollout is given latents or frames
        pre.done()
    scales = {"detail": float(params.get("enc_scale", DEFAULT_SCALES["detail"])),
              "abstract": float(params.get("enc_scale_dino", DEFAULT_SCALES["abstract"]))}
    num_pred_frames = int(params.get("num_pred_frames", 1))
    params.ignore(*MODULE_TRAINING_ONLY)
    params.done()
    spec.training_only.update(params.training_only)
    validation = (((config.get("data") or {}).get("params") or {}).get("validation") or {}).get("params") or {}
    frame_rate = validation.get("frame_rate")
    converted: dict[str, torch.Tensor] = {}
    if checkpoint is not None:
        ema = {k[len("ema_vit."):]: v for k, v in read_checkpoint(checkpoint).items() if k.startswith("ema_vit.")}
        if not ema:
            raise ReleaseError(f"{checkpoint}: has no ema_vit.* weights (the EMA network sampling uses)")
        converted = convert_predictor(ema, spec, str(checkpoint))
    return Network(config_file, spec, converted, scales, num_pred_frames, branch,
                   float(frame_rate) if frame_rate is not None else None, tokenizer, preprocessor, checkpoint)


def _check_build(build: dict, state: dict[str, torch.Tensor], what: str,
                 builder: Callable[[dict], torch.nn.Module]) -> None:
    """The converted weights load strictly into the network ``build`` describes (built on the meta device)."""
    with torch.device("meta"):
        model = builder(build)
    ours = model.state_dict()
    missing = sorted(set(ours) - set(state))
    extra = sorted(set(state) - set(ours))
    wrong = sorted(k for k in set(ours) & set(state) if tuple(ours[k].shape) != tuple(state[k].shape))
    if missing or extra or wrong:
        first = (missing or extra or wrong)[0]
        raise ReleaseError(f"{what}: converted weights do not fit our network at {first} "
                           f"({len(missing)} missing, {len(extra)} extra, {len(wrong)} mis-shaped)")


def _tokenizer_builder(kind: str) -> Callable[[dict], torch.nn.Module]:
    def build(spec: dict) -> torch.nn.Module:
        cfg, rest = split_build(TOKENIZER_PRESETS, spec)
        return (build_detail_tokenizer(cfg) if kind == "detail" else build_abstract_tokenizer(cfg, **rest))
    return build


def import_release(folder: Path, out: Path, causal_mask: str = "hard") -> dict:
    """Convert a downloaded release ``folder`` into our files under ``out`` and return the manifest written there.

    ``out`` gets ``tokenizers/{detail,abstract}/tokenizer.pt``, ``predictors/{detail,abstract_tf,
    abstract_distilled}/predictor.pt`` (the distilled one when ``L1/config_distill.yaml`` exists) and
    ``manifest.json``: the source files' SHA-256, the builds, what was converted, left out or only recorded.
    Everything is read and converted first; the folder is then written beside ``out`` and swapped in whole.
    """
    folder = Path(folder)
    l1_config = folder / "L1" / "config.yaml"
    detail = read_network(l1_config, folder, causal_mask, folder / "L1" / "checkpoints" / "last.ckpt")
    networks = {"detail": detail}
    distill_config = folder / "L1" / "config_distill.yaml"
    for name, config_file in (("abstract_tf", l1_config), ("abstract_distilled", distill_config)):
        if name == "abstract_distilled" and not config_file.is_file():
            continue
        top = detail if config_file == l1_config else read_network(config_file, folder, causal_mask, None)
        if "l2" not in top.preprocessor:
            raise ReleaseError(f"{config_file}: model.params.condition_preprocessor_config.params."
                               f"l2_predictor_config is missing; pass the release's L1 config")
        l2_config, l2_checkpoint = top.preprocessor["l2"]
        networks[name] = read_network(l2_config, folder, causal_mask, l2_checkpoint)
        networks[name].spec.sampling["nfe"] = int(top.preprocessor.get("l2_pred_NFE", 10))
    tokenizers = {net.tokenizer for net in networks.values()}
    if len(tokenizers) != 1:
        raise ReleaseError(f"{l1_config}: the networks name different tokenizers ({sorted(map(str, tokenizers))})")
    tok_config, tok_checkpoint = tokenizers.pop()
    tok_state = read_checkpoint(tok_checkpoint)
    projection = tok_state.get("post_quant_conv_distill.weight")
    if projection is None:
        raise ReleaseError(f"{tok_checkpoint}: has no post_quant_conv_distill (the abstract tokenizer's projection "
                           f"head); pass the tokenizer's own checkpoint")
    tok_spec = tokenizer_spec(Section(tok_config, "model", read_config(tok_config)["model"]),
                              _vit_depth(tok_state, str(tok_checkpoint)), int(projection.shape[0]))
    detail_tok, abstract_tok, left_out = convert_tokenizer(tok_state, tok_spec, str(tok_checkpoint))
    _check_build(tok_spec.detail, detail_tok, f"{tok_checkpoint} (detail)", _tokenizer_builder("detail"))
    _check_build(tok_spec.abstract, abstract_tok, f"{tok_checkpoint} (abstract)", _tokenizer_builder("abstract"))
    for name, net in networks.items():
        _check_build(net.spec.build, net.state, str(net.checkpoint), build_stdit_from)
        expected = "rec" if name == "detail" else "sem"
        if net.branch != expected:
            raise ReleaseError(f"{net.config_file}: predicts the {net.branch} latents; the {name} predictor "
                               f"must predict the {expected} ones")
    with atomic_dir(Path(out)) as tmp:
        return _write_release(tmp, folder, causal_mask, networks, tok_spec, detail_tok, abstract_tok, left_out,
                              (tok_config, tok_checkpoint))


def _write_release(out: Path, folder: Path, causal_mask: str, configs: dict[str, Network], tok_spec: TokenizerSpec,
                   detail_tok: dict[str, torch.Tensor], abstract_tok: dict[str, torch.Tensor], left_out: list[str],
                   tokenizer: tuple[Path, Path]) -> dict:
    """The converted files and the manifest, under ``out`` (a fresh folder that replaces the output when done)."""
    detail = configs["detail"]
    tok_config, tok_checkpoint = tokenizer
    tok_paths = {kind: out / "tokenizers" / kind / "tokenizer.pt" for kind in ("detail", "abstract")}
    for kind, build, state in (("detail", tok_spec.detail, detail_tok), ("abstract", tok_spec.abstract, abstract_tok)):
        model = _tokenizer_builder(kind)(build)
        model.load_state_dict(state, strict=True)
        save_tokenizer(tok_paths[kind], kind, model, detail.scales[kind], build,
                       extra={"source": OFFICIAL_SOURCE, "checkpoint": _relative(tok_checkpoint, folder)})
    checksums = {kind: sha256_file(path) for kind, path in tok_paths.items()}
    written = {f"tokenizers/{kind}": str(path.relative_to(out)) for kind, path in tok_paths.items()}
    for name, net in configs.items():
        model = build_stdit_from(net.spec.build)
        model.load_state_dict(net.state, strict=True)
        meta = {"source": OFFICIAL_SOURCE, "level": "detail" if name == "detail" else "abstract",
                "tokenizers": {kind: {"checksum": checksums[kind]} for kind in ("detail", "abstract")},
                "frame_rate": net.frame_rate, "latent_grid": list(net.spec.grid),
                "num_pred_frames": net.num_pred_frames, "sampling": net.spec.sampling}
        if name == "detail":
            n_context = net.spec.num_context_frames
            meta["condition_slots"] = [n_context - 1, n_context + net.num_pred_frames - 1]
            meta["abstract_frame_rate"] = detail.preprocessor.get("l2_predictor_frame_rate")
        if net.spec.build["steering"]:
            meta["authors_steering"] = {"steps": net.spec.steering_len,
                                        "preprocessor": net.preprocessor.get("steering")}
            steering = converted_steering(net.preprocessor.get("steering"), net.frame_rate, net.spec.steering_len)
            if steering is not None:  # what orbis2 rollout and orbis2 play feed a steered predictor
                meta["steering"] = steering
        path = out / "predictors" / name / "predictor.pt"
        save_predictor(path, model, net.spec.build, meta)
        written[f"predictors/{name}"] = str(path.relative_to(out))
    sources = [p for net in configs.values() for p in (net.config_file, net.checkpoint)] + [tok_config, tok_checkpoint]
    sources += [p for p in [folder / "L1" / "config_distill.yaml"] if p.is_file()]
    manifest = {
        "files": {_relative(p, folder): sha256_file(p) for p in sorted(set(sources))},
        "written": written,
        "causal_mask": causal_mask,
        "builds": {"tokenizers/detail": tok_spec.detail, "tokenizers/abstract": tok_spec.abstract,
                   **{f"predictors/{name}": net.spec.build for name, net in configs.items()}},
        "scales": detail.scales,
        "left_out": {"tokenizer": {f"{prefix}.*": LEFT_OUT[prefix] for prefix in left_out},
                     "predictors": "vit.* (training weights; their EMA ema_vit.* is converted) and ae.*"},
        "training_only": {"tokenizer": _jsonable(tok_spec.training_only),
                          **{name: _jsonable(net.spec.training_only) for name, net in configs.items()}},
    }
    write_json(out / "manifest.json", manifest)
    return manifest


def converted_steering(preprocessor: dict | None, frame_rate: float | None, steps: int | None) -> dict | None:
    """Our ``meta["steering"]`` for their ``SpeedYawDirectConditionPreprocessor``, or None where it does not
    convert (their moving goals integrate a path from the commands; a config without the predictor's frame rate).

    Their steering input is the raw ``[speed, yaw_rate]`` (m/s, rad/s) times ``speed_scale``/``yaw_rate_scale``,
    sampled from an odometry sequence at ``frame_rate x odometry_steps_per_image_frame`` Hz at the rows
    ``anchor + steering_offsets``, the anchor being the context frame ``context_frame_anchor_index`` (-1: the
    last); each rollout step moves the anchor on by the predicted frames. In our terms: speed and yaw rate
    divided by ``scale`` at ``offsets_s`` seconds after each step's last context frame
    (:func:`orbis2.rollout.steering_sequences`), which may lie beyond the predicted frame.
    """
    if (preprocessor is None or frame_rate is None
            or preprocessor.get("preprocessor") != "SpeedYawDirectConditionPreprocessor"):
        return None
    offsets = [int(o) for o in preprocessor["steering_offsets"]]
    odometry_hz = frame_rate * int(preprocessor["odometry_steps_per_image_frame"])
    anchor = int(preprocessor.get("context_frame_anchor_index", -1))
    scales = [float(preprocessor.get("speed_scale", 1.0)), float(preprocessor.get("yaw_rate_scale", 1.0))]
    if (anchor >= 0 or 0.0 in scales or len(offsets) != steps
            or preprocessor.get("steering_format", "speed_yawrate") != "speed_yawrate"):
        return None  # an anchor counted from the context's start depends on its length: not converted
    return {"features": ["speed", "yaw_rate"], "scale": [1.0 / v for v in scales],
            "offsets_s": [(anchor + 1) / frame_rate + o / odometry_hz for o in offsets],
            "interval": "the authors': speed and yaw rate at offsets_s seconds after the last context frame"}


def _relative(path: Path, root: Path) -> str:
    """``path`` as the release names it (relative to its folder when inside)."""
    try:
        return str(path.resolve().relative_to(root.resolve()))
    except ValueError:
        return str(path)


def _jsonable(value: Any) -> Any:
    return json.loads(json.dumps(value, default=str))
