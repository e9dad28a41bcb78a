"""Which profile a command runs at: the one the artifacts it reads were made with.

A run's profile travels with its outputs. A checkpoint records it (``meta.profile`` of a predictor,
``extra.profile`` of a tokenizer); one written before it did is recognised by what the profile decides
in it (a tokenizer's preset, a predictor's preset and size overrides). The shard manifest and videos
are recognised by their frame size and rate (videos only where the size is a profile's: a video of
another size is not a run's artifact). Each artifact thus names the profiles it is consistent with.

``orbis2 rollout``, ``orbis2 evaluate`` and a stage run by hand call :func:`resolve_profile` with what
they read: ``--profile`` is used as given; otherwise params.yaml's ``profile`` where every artifact
agrees with it, else the one profile they all agree on. Artifacts of two different profiles, or
artifacts that fit several profiles but not params.yaml's, are an error naming the files and the fix.
The returned line says which profile is used and why; commands print it.
"""

from __future__ import annotations

import json
import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from orbis2.config.params import PROFILES, PipelineConfig, load_params, parse_config
from orbis2.data.video import VIDEO_SUFFIXES, VideoError, probe
from orbis2.errors import OrbisError
from orbis2.registry import registry

SHARD_MANIFEST = "manifest.json"


@dataclass(frozen=True)
class Evidence:
    """What one artifact says about the profile it was made with."""

    path: Path
    profiles: frozenset[str]  # the profiles it is consistent with
    how: str  # what it was recognised by, for messages

    def describe(self) -> str:
        names = " or ".join(p for p in PROFILES if p in self.profiles)
        return f"{self.path} ({self.how}: profile {names})"


def resolve_profile(params: Path | str, given: str | None, artifacts: Iterable[Path | None]
                    ) -> tuple[PipelineConfig, str]:
    """The config to run with and a line saying which profile it is and why (see the module docstring)."""
    raw = load_params(params)
    if given is not None:
        return parse_config(raw, given, source=str(params)), f"profile {given} (--profile)"
    configs = {profile: parse_config(raw, profile, source=str(params)) for profile in PROFILES}
    evidence = [found for path in artifacts if path is not None and (found := evidence_of(Path(path), configs))]
    chosen, why = choose(evidence, raw.get("profile"), str(params))
    return configs[chosen], f"profile {chosen} ({why})"


def choose(evidence: list[Evidence], file_profile: str, params: str) -> tuple[str, str]:
    """The profile and the reason, from the artifacts' evidence and params.yaml's ``profile``."""
    if not evidence:
        return file_profile, f"{params}"
    agreed = frozenset(PROFILES)
    for i, found in enumerate(evidence):
        if not agreed & found.profiles:
            other = next((e for e in evidence[:i] if not e.profiles & found.profiles), evidence[0])
            raise OrbisError(f"{other.describe()} and {found.describe()} come from different runs; pass files of "
                             f"one run, or --profile to choose")
        agreed &= found.profiles
    witness = evidence[0].path
    if file_profile in agreed:
        return file_profile, f"{params}, as {witness} says"
    if len(agreed) == 1:
        (profile,) = agreed
        return profile, f"as {witness} says; {params} says {file_profile}"
    names = " or ".join(p for p in PROFILES if p in agreed)
    raise OrbisError(f"{evidence[0].describe()} fits profile {names}, not {params}'s {file_profile}; pass "
                     f"--profile with the one it was made with")


def evidence_of(path: Path, configs: dict[str, PipelineConfig]) -> Evidence | None:
    """What ``path`` says about its profile; None for a file that says nothing (missing, unreadable, foreign)."""
    if not path.is_file():
        return None
    suffix = path.suffix.lower()
    if suffix == ".pt":
        return checkpoint_evidence(path, configs)
    if path.name == SHARD_MANIFEST:
        return manifest_evidence(path, configs)
    if suffix in VIDEO_SUFFIXES:
        return video_evidence(path, configs)
    return None


def checkpoint_evidence(path: Path, configs: dict[str, PipelineConfig]) -> Evidence | None:
    """A tokenizer or predictor file: its recorded profile, else the profiles whose presets built it."""
    import torch  # here: the stages that never read a checkpoint (the town) need not import it

    try:
        blob = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except (OSError, RuntimeError, pickle.UnpicklingError, EOFError, ValueError):
        return None  # the loader says what is wrong with it
    if not isinstance(blob, dict) or not isinstance(blob.get("build"), dict):
        return None
    build, notes = blob["build"], blob.get("meta") or blob.get("extra") or {}
    if notes.get("profile") in PROFILES:
        return Evidence(path, frozenset([notes["profile"]]), "recorded")
    if "kind" in blob:  # a tokenizer
        kind = blob["kind"]
        sections = [f"tokenizer_{name}" for name, k in registry().tokenizers.items() if k == kind]
        fits = {p for p, cfg in configs.items() if any(_sizes_fit(build, cfg.section(s)) for s in sections)}
        return Evidence(path, frozenset(fits), f"{kind} tokenizer preset {build.get('preset')!r}")
    stage = notes.get("stage")
    fits = set()
    for profile, cfg in configs.items():
        section = cfg.stages.get(stage)
        if section is not None and _sizes_fit(build, section):
            fits.add(profile)
    return Evidence(path, frozenset(fits), f"{stage or 'predictor'} preset {build.get('preset')!r} and sizes")


def _sizes_fit(build: dict, section) -> bool:
    """A file's recorded ``build`` is of ``section``'s size: the same preset, and every override it sets."""
    return build.get("preset") == section.preset and all(build.get(k) == v for k, v in section.model.items())


def manifest_evidence(path: Path, configs: dict[str, PipelineConfig]) -> Evidence | None:
    """The shard manifest: the frame size and rate its clips were cut at."""
    try:
        manifest = json.loads(path.read_text())
        size = (int(manifest["width"]), int(manifest["height"]), float(manifest["fps"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None
    fits = {p for p, cfg in configs.items() if (cfg.data.width, cfg.data.height, float(cfg.data.fps)) == size}
    return Evidence(path, frozenset(fits), f"{size[0]}x{size[1]} frames at {size[2]:g} fps")


def video_evidence(path: Path, configs: dict[str, PipelineConfig]) -> Evidence | None:
    """A video of a profile's frame size; None for any other size (not a run's artifact)."""
    try:
        info = probe(path)
    except (VideoError, OSError):
        return None
    fits = {p for p, cfg in configs.items() if (cfg.data.width, cfg.data.height) == (info.width, info.height)}
    return Evidence(path, frozenset(fits), f"{info.width}x{info.height} frames") if fits else None

