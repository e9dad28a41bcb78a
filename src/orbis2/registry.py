"""The DAG's registry (``registry.yaml``): tokenizers, latent sets, predictors, systems, probe targets, main table.

One declarative file that the Snakefile, the dvc.yaml generator, the config and
the reports read, so that an ablation is one entry there plus one params.yaml
section. It also holds the folder layout (:func:`layout_path`): the rules place
every file by it and pass the paths to the stage scripts, which, like the
``orbis2`` command, default to it when run by hand; library code receives paths as
arguments instead of spelling ``data/...`` itself.

The file is looked up in ``$ORBIS2_REGISTRY``, else ``./registry.yaml`` (the
project root the DAG runs in), else beside the source tree (editable installs).
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import yaml

from orbis2.errors import OrbisError

LEVELS = ("abstract", "detail")
RATES = ("slow", "fast")
OBJECTIVES = ("diffusion_forcing", "teacher_forcing", "reflow")
TOKENIZER_KINDS = ("detail", "abstract")
SCOPES = ("main", "all")  # the report targets: reports/main_table.csv and reports/all


class RegistryError(OrbisError):
    """registry.yaml is missing, malformed or refers to an entry it does not define."""


@dataclass(frozen=True)
class PredictorSpec:
    """What distinguishes the predictor stages (see ``registry.yaml``, ``predictors``)."""

    level: str  # "abstract" or "detail": which latents the predictor models
    rate: str  # "slow" (abstract_hz window, causal) or "fast" (detail_hz window, bidirectional)
    objective: str  # "diffusion_forcing", "teacher_forcing" or "reflow" (distillation from init_from)
    condition: str | None = None  # latents of the slow subgoals a bottom predictor is conditioned on
    steering: bool = False
    latents: str = "compressed"  # which latent set it trains on
    probe: bool = True  # linearly probed (eval_probe_<name>)

    @property
    def causal(self) -> bool:
        return self.rate == "slow"


@dataclass(frozen=True)
class System:
    """Names the predictor stages of one evaluated system."""

    label: str
    bottom: str
    top: str | None = None
    latents: str = "compressed"  # the latent set its predictors were trained on

    @property
    def stages(self) -> list[str]:
        return [s for s in (self.top, self.bottom) if s is not None]


@dataclass(frozen=True)
class LatentSetEntry:
    """A latent cache (the DAG stage ``stage``) and the tokenizer of each level."""

    stage: str
    tokenizers: dict[str, str]  # level -> tokenizers entry
    skip_splits: tuple[str, ...] = ()

    @property
    def root(self) -> Path:
        return layout_path("latents", self.stage)

    def tokenizer_file(self, level: str) -> Path:
        return layout_path("tokenizer", self.tokenizers[level]) / "tokenizer.pt"


@dataclass(frozen=True)
class Representation:
    """A probe target that is not a predictor: a tokenizer encoder, or the teacher."""

    latents: str
    teacher: bool = False


@dataclass(frozen=True)
class Registry:
    layout: dict[str, str]
    tokenizers: dict[str, str]  # name -> kind
    latent_sets: dict[str, LatentSetEntry]
    predictors: dict[str, PredictorSpec]
    systems: dict[str, System]
    speed_systems: dict[str, System]  # timed by eval_speed_all only
    representations: dict[str, Representation]
    main_table: dict[str, str] = field(default_factory=dict)  # system -> probed predictor, row order
    baselines: dict[str, str] = field(default_factory=dict)  # the same, for reports/all's extra rows

    def table(self, scope: str) -> dict[str, str]:
        """Table 1's systems (-> probed predictor) of a report scope: ``main``, or ``all`` (baselines first)."""
        if scope not in SCOPES:
            raise ValueError(f"scope {scope!r}: one of {SCOPES}")
        return {**self.baselines, **self.main_table} if scope == "all" else dict(self.main_table)

    def timed_systems(self, scope: str) -> dict[str, System]:
        """The systems the scope's speed stage times: Table 1's, and in ``all`` the speed-only systems."""
        return {**{name: self.systems[name] for name in self.table(scope)},
                **(self.speed_systems if scope == "all" else {})}

    def table_predictors(self, scope: str) -> list[str]:
        """Every predictor of the scope's Table 1 systems, main systems first (top before bottom)."""
        systems = [*self.main_table, *(self.baselines if scope == "all" else {})]
        return list(dict.fromkeys(p for name in systems for p in self.systems[name].stages))

    def conditioning_predictors(self, scope: str) -> list[str]:
        """What ``eval_conditioning`` (scope ``main``) or ``eval_conditioning_all`` reads: the predictors of the
        scope's Table 1 systems and the steered top one, main ones first."""
        return list(dict.fromkeys([*self.table_predictors("main"), self.steered, *self.table_predictors(scope)]))

    @property
    def steered(self) -> str:
        """The steered predictor (``steering: true``, unique: checked when parsed): the top predictor that
        eval_steering cascades into the hierarchy's bottom one, and the one the CLI steers."""
        return next(name for name, spec in self.predictors.items() if spec.steering)

    @property
    def probe_targets(self) -> list[str]:
        return [*self.representations, *(n for n, s in self.predictors.items() if s.probe)]

    def target_latents(self, target: str) -> str:
        """The latent set whose tokenizers a probe target is read with."""
        if target in self.representations:
            return self.representations[target].latents
        return self.predictors[target].latents


def registry_file() -> Path:
    if os.environ.get("ORBIS2_REGISTRY"):
        return Path(os.environ["ORBIS2_REGISTRY"])
    here = Path("registry.yaml")
    return here if here.is_file() else Path(__file__).resolve().parents[2] / "registry.yaml"


def _entries(raw: dict, key: str, cls: type, where: Path) -> dict:
    """``cls`` per entry; strings interned, so a name pickles (in a checkpoint's meta) as the literal would."""
    out = {}
    for name, value in (raw.get(key) or {}).items():
        try:
            out[name] = cls(**{k: sys.intern(v) if isinstance(v, str) else v for k, v in value.items()})
        except TypeError as err:
            raise RegistryError(f"{where}: {key}.{name}: {err}; see the comment above `{key}`") from err
    return out


def parse_registry(raw: dict, where: Path = Path("registry.yaml")) -> Registry:
    """Build and cross-check a :class:`Registry` from the file's mapping."""
    if not isinstance(raw, dict):
        raise RegistryError(f"{where}: the top level must be a mapping")
    sets = {n: LatentSetEntry(v["stage"], dict(v["tokenizers"]), tuple(v.get("skip_splits", ())))
            for n, v in (raw.get("latent_sets") or {}).items()}
    reg = Registry(layout=dict(raw.get("layout") or {}),
                   tokenizers={n: v["kind"] for n, v in (raw.get("tokenizers") or {}).items()},
                   latent_sets=sets,
                   predictors=_entries(raw, "predictors", PredictorSpec, where),
                   systems=_entries(raw, "systems", System, where),
                   speed_systems=_entries(raw, "speed_systems", System, where),
                   representations=_entries(raw, "representations", Representation, where),
                   main_table=dict(raw.get("main_table") or {}),
                   baselines=dict(raw.get("baselines") or {}))
    problems = [f"tokenizers.{n}.kind = {k!r} must be one of {TOKENIZER_KINDS}"
                for n, k in reg.tokenizers.items() if k not in TOKENIZER_KINDS]
    for name, s in reg.latent_sets.items():
        problems += [f"latent_sets.{name}.tokenizers.{level} = {t!r} is not under `tokenizers`"
                     for level, t in s.tokenizers.items() if t not in reg.tokenizers]
    for name, p in reg.predictors.items():
        for key, value, allowed in (("level", p.level, LEVELS), ("rate", p.rate, RATES),
                                    ("objective", p.objective, OBJECTIVES),
                                    ("condition", p.condition, (None, *LEVELS)),
                                    ("latents", p.latents, tuple(reg.latent_sets))):
            if value not in allowed:
                problems.append(f"predictors.{name}.{key} = {value!r} must be one of {list(allowed)}")
    steered = [name for name, p in reg.predictors.items() if p.steering]
    if len(steered) != 1:
        problems.append(f"predictors: exactly one needs `steering: true` (the steered top predictor), "
                        f"found {', '.join(steered) or 'none'}")
    for name, s in [*reg.systems.items(), *reg.speed_systems.items()]:
        problems += [f"systems.{name}: predictor {p!r} is not under `predictors`"
                     for p in s.stages if p not in reg.predictors]
        if s.latents not in reg.latent_sets:
            problems.append(f"systems.{name}.latents = {s.latents!r} is not under `latent_sets`")
    problems += [f"representations.{n}.latents = {r.latents!r} is not under `latent_sets`"
                 for n, r in reg.representations.items() if r.latents not in reg.latent_sets]
    for key in ("main_table", "baselines"):
        for system, target in getattr(reg, key).items():
            if system not in reg.systems or target not in reg.probe_targets:
                problems.append(f"{key}.{system}: {target!r} must name a system and a probe target")
    problems += [f"baselines.{s}: already a main_table row" for s in reg.baselines if s in reg.main_table]
    if problems:
        raise RegistryError(f"{where}: " + "; ".join(problems))
    return reg


@lru_cache(maxsize=None)
def _load(file: str) -> Registry:
    where = Path(file)
    if not where.is_file():
        raise RegistryError(f"{where}: not found; run from the project root or set ORBIS2_REGISTRY")
    try:
        raw = yaml.safe_load(where.read_text())
    except yaml.YAMLError as err:
        raise RegistryError(f"{where}: not valid YAML: {err}") from err
    return parse_registry(raw, where)


def registry() -> Registry:
    """The registry in use (read once per file)."""
    return _load(str(registry_file()))


def layout_path(kind: str, name: str | None = None) -> Path:
    """Where an artifact lives, from ``layout`` (``layout_path("predictor", "detail")`` -> data/predictors/detail)."""
    layout = registry().layout
    if kind not in layout:
        raise RegistryError(f"{registry_file()}: layout has no {kind!r}")
    template = layout[kind]
    return Path(template.format(name=name) if "{name}" in template else template)
