"""World-model systems as the evaluation runs them: which predictors, their contexts, rollouts, decoding.

A *system* is a flat predictor or a top predictor cascaded into a bottom one
(paper Fig. 1 and Table 3):

==================  =========================================  ==========================
system              top predictor                              bottom / flat predictor
==================  =========================================  ==========================
hierarchical        ``abstract_tf`` (abstract, 2 Hz; ours)     ``detail`` (detail, 10 Hz)
flat_detail         -                                          ``flat_detail`` (Exp. 1)
flat_abstract       -                                          ``flat_abstract`` (Exp. 2)
top_detail          ``top_detail`` (detail, 2 Hz)              ``detail_on_detail`` (Exp. 4)
top_abstract_10hz   ``flat_abstract`` (abstract, 10 Hz)        ``detail`` (Exp. 5)
flat_abstract_full  -                                          ``flat_abstract_full``
==================  =========================================  ==========================

Exp. 5's bottom predictor is the hierarchy's own ``detail`` predictor: both are
trained on ground-truth abstract latents of the same two frames, so their
training is identical; only the top predictor feeding them differs. Contexts
come from the latent cache (the tokenizers' encodings of the real frames), and
rollouts are decoded by the tokenizer of the bottom predictor's latents (the
abstract tokenizer's weak decoder for ``flat_abstract``). ``flat_abstract_full``
runs on the uncompressed abstract latents (compression ablation).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from orbis2.accel import Inference, cast_for_inference, compile_decoder, compile_predictor, inference_autocast, set_tf32
from orbis2.config.sections import DataConfig, EvaluationConfig
from orbis2.data.images import to_uint8
from orbis2.errors import OrbisError
from orbis2.eval.protocols.starts import rollout_steps as rollout_steps  # where the rollouts import it from
from orbis2.eval.protocols.starts import sample_ends
from orbis2.latents import LatentCache
from orbis2.models.files import PredictorFile, TokenizerFile, load_predictor, load_tokenizer
from orbis2.registry import System, registry
from orbis2.rollout import (
    ScheduleStep,
    cascaded_rollout,
    detail_frames_per_step,
    flat_rollout,
    rollout_schedule,
)

# The systems and the main table's rows: registry.yaml (``systems``, ``main_table``).
SYSTEMS: dict[str, System] = registry().systems
MAIN_SYSTEMS = tuple(registry().main_table)
# Systems timed by the eval_speed_all stage only (``speed_systems``): the hierarchy with the few-step
# (distilled) detail predictor, sampled with the NFE its predictor file records.
SPEED_SYSTEMS: dict[str, System] = registry().speed_systems


@dataclass
class LoadedSystem:
    """A system's networks on one device, checked to share the tokenizers they were trained with."""

    name: str
    system: System
    bottom: PredictorFile
    top: PredictorFile | None
    tokenizers: dict[str, TokenizerFile]
    inference: Inference = field(default_factory=Inference)

    @property
    def device(self) -> torch.device:
        return next(self.bottom.model.parameters()).device

    @property
    def output_level(self) -> str:
        """Which latents the system generates, hence which tokenizer decodes them."""
        return self.bottom.meta["level"]

    @property
    def parameters(self) -> int:
        nets = [self.bottom.model] + ([self.top.model] if self.top is not None else [])
        return sum(p.numel() for net in nets for p in net.parameters())

    def step_frames(self, predictor: PredictorFile) -> int:
        """How many frames one of ``predictor``'s rollout steps adds (its window less its context)."""
        window = predictor.meta["window"]
        return window["window"] - window["context"]

    def context_indices(self, predictor: PredictorFile, step: ScheduleStep) -> tuple[int, ...]:
        """Native frame indices of a predictor's context at one rollout step (its rate's window)."""
        return step.abstract_context if predictor.meta["rate"] == "slow" else step.detail_context

    def bottom_nfe(self, default: int) -> int:
        """The bottom predictor's Euler steps: its own (a distilled predictor records them) or ``default``."""
        return self.bottom.nfe(default)

    @torch.no_grad()
    def rollout(self, contexts: dict[str, torch.Tensor], steps: int, generator: torch.Generator, top_nfe: int,
                bottom_nfe: int, steering: torch.Tensor | None = None,
                frames_per_step: int | None = None, subgoals: torch.Tensor | None = None) -> torch.Tensor:
        """Latents [B, 5 * steps, C, h, w] of ``output_level`` from the contexts (keys ``bottom`` and ``top``).

        ``frames_per_step`` (flat systems) runs the same network with another step length, e.g. 1 for an
        Orbis v1-style rollout (one frame per step); the rollout still covers ``steps`` * 0.5 s.
        ``subgoals`` (hierarchies): the top's frames given instead of sampled (:func:`cascaded_rollout`).
        """
        bottom_rate = float(self.bottom.meta["frame_rate"])
        if frames_per_step is not None:
            if self.top is not None:
                raise OrbisError(f"{self.name}: frames_per_step applies to flat systems only")
            native = self.step_frames(self.bottom)
            if native % frames_per_step:
                raise OrbisError(f"{self.name}: frames_per_step = {frames_per_step} must divide {native}")
            with inference_autocast(self.device, self.inference.precision):
                return flat_rollout(self.bottom.model, contexts["bottom"], steps * native // frames_per_step,
                                    frames_per_step, bottom_nfe, bottom_rate, generator,
                                    kv_cache=self.inference.kv_cache)
        if self.top is None and (steering is not None or subgoals is not None):
            raise OrbisError(f"{self.name}: flat systems are neither steered nor given subgoals")
        with inference_autocast(self.device, self.inference.precision):
            if self.top is None:
                return flat_rollout(self.bottom.model, contexts["bottom"], steps, self.step_frames(self.bottom),
                                    bottom_nfe, bottom_rate, generator, kv_cache=self.inference.kv_cache)
            top_rate = float(self.top.meta["frame_rate"])
            per_step = detail_frames_per_step(bottom_rate, top_rate, self.step_frames(self.top))
            if per_step != self.step_frames(self.bottom):
                raise OrbisError(f"{self.name}: the bottom predictor adds {self.step_frames(self.bottom)} frames per "
                                 f"step, but its {bottom_rate:g} Hz under a {top_rate:g} Hz top gives {per_step}; "
                                 f"retrain the pair on one params.yaml data section")
            details, _ = cascaded_rollout(
                self.top.model, self.bottom.model, contexts["bottom"], contexts["top"], steps, generator,
                abstract_nfe=top_nfe, detail_nfe=bottom_nfe, abstract_hz=top_rate, detail_hz=bottom_rate,
                steering=steering, top_frames_per_step=self.step_frames(self.top), kv_cache=self.inference.kv_cache,
                subgoals=subgoals, steering_guidance=self.inference.steering_guidance)
        return details

    @torch.no_grad()
    def decode(self, latents: torch.Tensor, chunk: int = 16) -> np.ndarray:
        """Normalised latents [B, T, C, h, w] -> RGB uint8 [B, T, H, W, 3] through the output level's tokenizer."""
        tokenizer = self.tokenizers[self.output_level]
        b, t = latents.shape[:2]
        with inference_autocast(self.device, self.inference.precision):
            frames = np.concatenate([to_uint8(tokenizer.model.decode(tokenizer.denormalize(part)))
                                     for part in latents.flatten(0, 1).split(chunk)])
        return frames.reshape(b, t, *frames.shape[1:])


def load_system(name: str, predictors: Mapping[str, Path], tokenizers: Mapping[str, Path],
                device: torch.device | str = "cpu", top_override: str | None = None,
                inference: Inference | None = None) -> LoadedSystem:
    """Load a system's predictors and both tokenizers; ``top_override`` swaps the top (e.g. the steered ``action``).

    ``predictors`` maps predictor names to their ``predictor.pt`` (at least the system's own, with the
    override), ``tokenizers`` levels to the ``tokenizer.pt`` of the system's latent set: the paths the
    DAG passes to the stage. ``inference`` sets precision, KV cache and compilation (compiled here, once
    per process and network).
    """
    known = {**SYSTEMS, **SPEED_SYSTEMS}
    if name not in known:
        raise OrbisError(f"unknown system {name!r}; choose from {sorted(known)}")
    system = known[name]
    top_stage = top_override or system.top
    stages = [stage for stage in dict.fromkeys([system.bottom, top_stage]) if stage]
    missing = [stage for stage in stages if stage not in predictors]
    if missing:
        raise OrbisError(f"system {name!r}: no predictor file given for {', '.join(missing)}")
    loaded_tokenizers = {kind: load_tokenizer(Path(path), device) for kind, path in tokenizers.items()}
    loaded = {stage: load_predictor(Path(predictors[stage]), device) for stage in stages}
    for stage, predictor in loaded.items():
        for kind, tokenizer in loaded_tokenizers.items():
            if predictor.meta["tokenizers"][kind]["checksum"] != tokenizer.checksum:
                raise OrbisError(f"{predictors[stage]} was trained on latents of another {kind} tokenizer than "
                                 f"{tokenizers[kind]}; re-run `{stage}`")
    inference = inference or Inference()
    for predictor in loaded.values():  # bf16 weights cast once on CUDA, not at every call (a no-op on the CPU)
        cast_for_inference(predictor.model, device, inference.precision)
    if inference.compile:
        for predictor in loaded.values():
            compile_predictor(predictor.model)
        for tokenizer in loaded_tokenizers.values():
            compile_decoder(tokenizer.model)
    return LoadedSystem(name, system, loaded[system.bottom], loaded.get(top_stage), loaded_tokenizers, inference)


# --------------------------------------------------------------------------- evaluation samples


@dataclass(frozen=True)
class Sample:
    """One rollout to evaluate: a clip of the cache and the native index of its last context frame."""

    key: str
    offset: int  # row of the clip's first frame in the split's cache arrays
    context_end: int


def eval_samples(cache: LatentCache, split: str, data: DataConfig, steps: int, starts_per_clip: int) -> list[Sample]:
    """Every clip of the split long enough for ``steps``, with ``starts_per_clip`` evenly spread starts."""
    clips = cache.index(split).clips  # in split order
    samples = []
    for key, offset, length in zip(clips["key"].tolist(), clips["offset"].tolist(), clips["length"].tolist()):
        for end in sample_ends(length, data, steps, starts_per_clip):
            samples.append(Sample(key, offset, end))
    if not samples:
        raise OrbisError(f"{cache.root}: no clip of the {split} split is long enough for {steps} rollout steps after "
                         f"its context; lower evaluation.seconds or use longer clips")
    return samples


def contexts_for(system: LoadedSystem, cache: LatentCache, split: str, data: DataConfig, samples: list[Sample],
                 device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """The real-frame context latents (scaled) of each predictor of the system, batched over ``samples``."""
    out = {}
    for role, predictor in (("bottom", system.bottom), ("top", system.top)):
        if predictor is None:
            continue
        indices = [np.array(system.context_indices(predictor, rollout_schedule(data, s.context_end, 1)[0]))
                   for s in samples]
        out[role] = cache_latents(cache, split, predictor.meta["level"], samples, indices).to(device)
    return out


def cache_latents(cache: LatentCache, split: str, level: str, samples: list[Sample],
                  indices: list[np.ndarray]) -> torch.Tensor:
    """Normalised cached latents [N, T, ...] of ``level`` at each sample's clip-relative native ``indices``."""
    arrays = cache.arrays(split)
    rows = [s.offset + np.asarray(idx) for s, idx in zip(samples, indices)]
    return cache.normalize(level, np.stack([arrays[level][r] for r in rows]))


def generated_indices(data: DataConfig, context_end: int, steps: int) -> np.ndarray:
    """Native indices of the frames a rollout generates, in order."""
    return np.array([i for step in rollout_schedule(data, context_end, steps) for i in step.detail_target])


# --------------------------------------------------------------------------- rollouts


def inference_settings(ev: EvaluationConfig) -> Inference:
    """Rollout precision, KV cache, compilation and steering guidance from ``evaluation``; sets the TF32 policy
    on CUDA."""
    if torch.cuda.is_available():
        set_tf32(True)
    return Inference(precision=ev.precision, compile=ev.compile, kv_cache=ev.kv_cache,
                     steering_guidance=ev.steering_guidance)


def batch_generator(device: torch.device | str, seed: int, batch: int) -> torch.Generator:
    """The noise of one evaluation batch: a generator seeded from ``(seed, batch)`` alone (numpy's SeedSequence
    spreads the pairs over independent streams), so that a batch draws the same noise whichever process, part or
    device runs it, and the batches of a split can be generated in any order or in parts."""
    state = np.random.SeedSequence([seed, batch]).generate_state(1, np.uint64)[0]
    return torch.Generator(device).manual_seed(int(state))


def batch_count(samples: int, batch_size: int) -> int:
    return -(-samples // batch_size)


def generate(system: LoadedSystem, cache: LatentCache, split: str, samples: list[Sample], steps: int,
             data: DataConfig, ev: EvaluationConfig, device: torch.device, steering: torch.Tensor | None = None,
             desc: str = "", subgoals: torch.Tensor | None = None, batches: range | None = None) -> torch.Tensor:
    """Rollout latents [N, 5 * steps, ...] of ``samples``, in batches of ``evaluation.batch_size``, each batch with
    the noise of :func:`batch_generator` (``evaluation.seed``, its index); ``subgoals`` [N, ...] as in
    :meth:`LoadedSystem.rollout`. ``batches``: only those batches (a part of the split), their samples in order;
    ``steering`` and ``subgoals`` still cover every sample."""
    batches = range(batch_count(len(samples), ev.batch_size)) if batches is None else batches
    out = []
    for batch in tqdm(batches, desc=desc or f"{system.name} {split}", unit="batch"):
        rows = slice(batch * ev.batch_size, (batch + 1) * ev.batch_size)
        contexts = contexts_for(system, cache, split, data, samples[rows], device)
        steer = None if steering is None else steering[rows].to(device)
        given = None if subgoals is None else subgoals[rows].to(device)
        gen = batch_generator(device, ev.seed, batch)
        out.append(system.rollout(contexts, steps, gen, ev.top_nfe, ev.bottom_nfe, steer, subgoals=given).cpu())
    return torch.cat(out)


def real_subgoals(system: LoadedSystem, cache: LatentCache, split: str, data: DataConfig, samples: list[Sample],
                  steps: int) -> torch.Tensor:
    """The real latents [N, steps, ...] at each rollout step's subgoal frame, in the top predictor's level: given
    to :func:`generate`, the hierarchy's bottom level alone (a reference for what the top's predictions cost)."""
    if system.top is None or system.step_frames(system.top) != 1:
        raise OrbisError(f"{system.name}: real subgoals need a top predictor of one frame per step")
    indices = [np.array([step.abstract_target for step in rollout_schedule(data, s.context_end, steps)])
               for s in samples]
    return cache_latents(cache, split, system.top.meta["level"], samples, indices)


def sample_clusters(cache: LatentCache, split: str, samples: list[Sample]) -> list[str]:
    """What a bootstrap resamples: each sample's episode (clips and starts of one episode are not independent)."""
    index = cache.index(split)
    return index.clips["episode"][index.find([s.key for s in samples])].tolist()
