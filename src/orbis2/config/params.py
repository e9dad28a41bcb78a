"""Reading params.yaml: profile resolution, the one check of every key, and the resolved :class:`PipelineConfig`.

``params.yaml`` is the single source of every hyper-parameter and seed: the
section dataclasses (``orbis2.config.sections``, ``orbis2.config.training``) have
no defaults, so a missing key is an error naming the section, the key and the
file. Each stage has a section; inside a section, ``all`` holds the values shared
by every profile and ``smoke`` / ``default`` / ``gpu`` / ``paper`` hold what
differs (every section names all four, so that DVC tracks exactly ``<section>.all``
and the active profile). The top-level ``profile`` key picks one; the resolved
section is ``all`` updated by the profile's mapping (nested mappings are merged
key by key), on top of the section named by ``extends`` if any (shared bases are
named ``_...``). Which tokenizer and predictor sections exist, and their types,
follows registry.yaml; ``preset`` (model size) is the one value the loader
supplies: it follows the profile unless a section sets it.

Resolution is strict: an unknown key, a value of the wrong type
(``orbis2.typecheck``) or an impossible value (each section's ``validate``) stops
with a :class:`~orbis2.errors.ConfigError` naming the key, e.g. ``data.default.fps``.
The Snakefile runs this check when it is read, so a typo fails at ``snakemake -n``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from orbis2.config.sections import (
    AssetsConfig,
    DataConfig,
    EvaluationConfig,
    ImportConfig,
    LatentsConfig,
    ShardsConfig,
    TownConfig,
    TruthConfig,
)
from orbis2.config.training import (
    AbstractTokenizerConfig,
    DetailTokenizerConfig,
    InverseDynamicsConfig,
    TokenizerSection,
    predictor_config_type,
)
from orbis2.errors import ConfigError
from orbis2.typecheck import MissingKeyError, build

PROFILES = ("smoke", "default", "gpu", "paper")
SECTION_PARTS = ("all", *PROFILES)
# Top-level keys that are not sections: the profile, how training stages start, how many parts the data
# stages split into, and the imported release the DAG starts from (orbis2.tasks.official).
SETTINGS = ("profile", "train_launcher", "parts", "official_weights")

# Section names in params.yaml whose Python attribute differs (``import`` is a keyword).
SECTION_ATTRS = {"import": "import_"}
FIXED_SECTIONS: dict[str, type] = {
    "data": DataConfig,
    "town": TownConfig,
    "import": ImportConfig,
    "shards": ShardsConfig,
    "assets": AssetsConfig,
    "latents": LatentsConfig,
    "evaluation": EvaluationConfig,
    "inverse_dynamics": InverseDynamicsConfig,
    "truth": TruthConfig,
}



def section_types() -> dict[str, type]:
    """Every params.yaml stage section and its type: the fixed ones plus one per registry.yaml tokenizer/predictor."""
    from orbis2.registry import registry

    reg = registry()
    kinds = {"detail": DetailTokenizerConfig, "abstract": AbstractTokenizerConfig}
    stages = {f"tokenizer_{name}": kinds[kind] for name, kind in reg.tokenizers.items()}
    stages |= {name: predictor_config_type(spec) for name, spec in reg.predictors.items()}
    return {**FIXED_SECTIONS, **stages}


@dataclass(frozen=True)
class PipelineConfig:
    """Every stage's resolved section for one profile."""

    profile: str
    # A folder written by `orbis2 import-weights` that the tokenizer and predictor stages start from
    # (orbis2.tasks.official); None: everything is trained here.
    official_weights: str | None
    data: DataConfig
    town: TownConfig
    import_: ImportConfig
    shards: ShardsConfig
    assets: AssetsConfig
    latents: LatentsConfig
    evaluation: EvaluationConfig
    inverse_dynamics: InverseDynamicsConfig
    truth: TruthConfig
    # The tokenizer and predictor sections, one per registry.yaml entry (also reachable as attributes).
    stages: dict[str, Any]

    def section(self, name: str) -> Any:
        if name in self.stages:
            return self.stages[name]
        return getattr(self, SECTION_ATTRS.get(name, name))

    def with_section(self, name: str, value: Any) -> PipelineConfig:
        """A copy with one section replaced (``dataclasses.replace`` for registry sections too)."""
        if name in self.stages:
            return dataclasses.replace(self, stages={**self.stages, name: value})
        return dataclasses.replace(self, **{SECTION_ATTRS.get(name, name): value})

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name == "stages":
            raise AttributeError(name)
        try:
            return self.stages[name]
        except KeyError:
            raise AttributeError(f"PipelineConfig has no section {name!r}") from None

    def validate(self) -> None:
        d = self.data
        abstract_ahead = (d.abstract_window - d.abstract_context) * d.abstract_stride
        if abstract_ahead != (d.detail_window - d.detail_context) * d.detail_stride:
            raise ConfigError(
                f"data.{self.profile}: the abstract prediction ({d.abstract_window - d.abstract_context} frames at "
                f"{d.abstract_hz} Hz) must end on the last detail prediction ({d.detail_window - d.detail_context} "
                f"frames at {d.detail_hz} Hz): the detail predictor is conditioned on that abstract subgoal"
            )
        tokenizers = {name: s.sizes() for name, s in self.stages.items() if isinstance(s, TokenizerSection)}
        grids = {name: (sizes.image_size, sizes.patch_size) for name, sizes in tokenizers.items()}
        if len(set(grids.values())) > 1:
            listed = ", ".join(f"{name}: {size[1]}x{size[0]} frames, patch {patch}"
                               for name, (size, patch) in sorted(grids.items()))
            raise ConfigError(f"{self.profile}: the tokenizers must share one latent grid (the detail predictor reads "
                              f"the abstract latents cell by cell beside its own), but {listed}; give every "
                              f"tokenizer section the same preset and patch_size (`_tokenizer.model`)")
        min_clip = self.data.window_span_frames / self.data.fps
        for split, seconds in self.shards.clip_seconds.items():
            if seconds < min_clip:
                raise ConfigError(
                    f"shards.{self.profile}.clip_seconds.{split} = {seconds} is shorter than one "
                    f"training window ({min_clip:.2f} s)"
                )
            if seconds > self.town.episode_seconds[split]:
                raise ConfigError(
                    f"shards.{self.profile}.clip_seconds.{split} = {seconds} exceeds "
                    f"town.episode_seconds.{split} = {self.town.episode_seconds[split]}"
                )


# --------------------------------------------------------------------------- loading


class _UniqueKeyLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # libyaml's parser where installed
    """YAML's safe loader, except that a key given twice in one mapping is an error (not "last one wins")."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, Any] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue  # "<<: *anchor" entries may be overridden, that is their purpose
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    "while reading a mapping", node.start_mark,
                    f"key {key!r} is given twice (first {seen[key]}); keep one", key_node.start_mark)
            seen[key] = f"line {key_node.start_mark.line + 1}"
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str) -> Any:
    """Parse YAML safely, rejecting duplicate keys; how the project reads params.yaml everywhere."""
    return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a safe loader subclass


def load_params(path: str | Path = "params.yaml") -> dict[str, Any]:
    """params.yaml's mapping as written (duplicate keys rejected), not yet resolved or checked."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: not found; run from the project root or pass --params")
    try:
        raw = load_yaml(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}") from err
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: the top level must be a mapping")
    return raw


def resolve_section(raw: dict[str, Any], name: str, profile: str, _seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """``<name>.all`` updated by ``<name>.<profile>``, on top of the section it ``extends`` (resolved the same way).

    A plain mapping, validated later; nested mappings are merged key by key.
    """
    if name not in raw:
        where = f"{_seen[-1]}.extends" if _seen else "params.yaml"
        raise ConfigError(f"{where}: no section '{name}' in params.yaml")
    if name in _seen:
        raise ConfigError(f"params.yaml: sections extend each other in a loop: {' -> '.join([*_seen, name])}")
    section = _section_shape(raw, name)
    merged: dict[str, Any] = {}
    if section.get("extends") is not None:
        merged = resolve_section(raw, section["extends"], profile, (*_seen, name))
    for part in ("all", profile):
        merged = _deep_merge(merged, section[part] or {})
    return merged


def section_chain(raw: dict[str, Any], name: str) -> list[str]:
    """``name`` and the sections it extends, nearest first (what a stage's params depend on)."""
    chain = [name]
    while isinstance(raw.get(chain[-1]), dict) and raw[chain[-1]].get("extends") and len(chain) <= len(raw):
        chain.append(raw[chain[-1]]["extends"])
    return chain


def load_config(path: str | Path = "params.yaml", profile: str | None = None) -> PipelineConfig:
    """Read params.yaml and return the validated config of ``profile`` (default: its ``profile`` key)."""
    return parse_config(load_params(path), profile, source=str(path))


def parse_config(raw: dict[str, Any], profile: str | None = None, source: str = "params.yaml") -> PipelineConfig:
    """The validated config of ``profile`` (default: ``raw["profile"]``) from params.yaml's mapping.

    ``source`` names the file in the error for a missing key.
    """
    profile = profile or raw.get("profile")
    if profile not in PROFILES:
        raise ConfigError(f"profile = {profile!r} must be one of {list(PROFILES)}")
    if not isinstance(raw.get("train_launcher"), str):
        raise ConfigError(f"{source}: train_launcher = {raw.get('train_launcher')!r} must be a command "
                          f"(python, or a torchrun command line); add `train_launcher: python` at the top level")
    parts = raw.get("parts")
    if not isinstance(parts, int) or isinstance(parts, bool) or parts < 1:
        raise ConfigError(f"{source}: parts = {parts!r} must be a whole number >= 1 (how many jobs each data stage "
                          f"splits into); add `parts: 1` at the top level")
    official = raw.get("official_weights")
    if "official_weights" not in raw or (official is not None and (not isinstance(official, str)
                                                                    or not official.strip())):
        raise ConfigError(f"{source}: official_weights = {official!r} must be null or the folder `orbis2 "
                          f"import-weights` wrote; add `official_weights: null` at the top level")
    types_ = section_types()
    unknown = {key for key in raw if not key.startswith("_")} - {*SETTINGS, *types_}
    if unknown:
        raise ConfigError(f"{source}: unknown top-level key(s) {sorted(unknown)}; a stage section needs a "
                          f"registry.yaml entry, a shared base a name starting with '_'")
    for name in set(raw) - set(SETTINGS):
        _section_shape(raw, name)
    sections: dict[str, Any] = {"stages": {}}
    for name, cls in types_.items():
        values = resolve_section(raw, name, profile)
        if "preset" in {f.name for f in dataclasses.fields(cls)}:
            values.setdefault("preset", profile)  # model size follows the profile unless the section says otherwise
        try:
            obj = build(cls, values, f"{name}.{profile}")
        except MissingKeyError as err:
            raise _missing(err, raw, name, source) from None
        obj.validate(f"{name}.{profile}")
        if name in FIXED_SECTIONS:
            sections[SECTION_ATTRS.get(name, name)] = obj
        else:
            sections["stages"][name] = obj
    cfg = PipelineConfig(profile=profile, official_weights=official, **sections)
    cfg.validate()
    return cfg


def as_dict(obj: Any) -> dict[str, Any]:
    return dataclasses.asdict(obj)


def flatten(mapping: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (for MLflow params)."""
    out: dict[str, Any] = {}
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = value
    return out


# --------------------------------------------------------------------------- helpers


def _section_shape(raw: dict[str, Any], name: str) -> dict[str, Any]:
    """Section ``name`` of params.yaml, which must map ``all`` and every profile (and maybe ``extends``) to mappings."""
    section = raw[name]
    if not isinstance(section, dict):
        raise ConfigError(f"{name} must be a mapping with keys 'all' and the profiles {list(PROFILES)}")
    unknown = set(section) - {"extends", *SECTION_PARTS}
    if unknown:
        raise ConfigError(f"{name}: unknown key(s) {sorted(unknown)}; allowed: 'all', 'extends', {list(PROFILES)}")
    absent = [part for part in SECTION_PARTS if part not in section]
    if absent:
        raise ConfigError(f"{name}: no {absent}; every section names 'all' and each profile ({{}} where nothing "
                          f"differs), so that DVC tracks exactly {name}.all and the active profile")
    for part in SECTION_PARTS:
        if not isinstance(section[part] or {}, dict):
            raise ConfigError(f"{name}.{part} must be a mapping")
    if "extends" in section and not isinstance(section["extends"], str):
        raise ConfigError(f"{name}.extends must name another section")
    return section


def _missing(err: MissingKeyError, raw: dict[str, Any], name: str, source: str) -> ConfigError:
    """The error for keys absent from a resolved section: which, where, and where to add them."""
    profile, *nested = err.where.split(".")[1:]
    keys = [".".join([*nested, key]) for key in err.keys]
    bases = section_chain(raw, name)[1:]
    also = f" (or in the section it extends, {' -> '.join(bases)})" if bases else ""
    return ConfigError(f"{source}: section '{name}' has no value for {keys} in profile {profile}: every setting "
                       f"comes from params.yaml (the code has no defaults); add it under {name}.all{also}, "
                       f"or under each profile")


def _deep_merge(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out
