"""Networks, one file per model with all of its blocks; each family's sizes are a typed config in ``sizes``."""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, ClassVar, TypeVar

from orbis2.typecheck import field_types, typed

C = TypeVar("C", bound="ModelConfig")

# meta["source"] of a network file converted from the authors' release (orbis2.models.official writes it,
# orbis2.tasks.official and orbis2.inference read it)
OFFICIAL_SOURCE = "the authors' release"


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Base of a model family's size config (``STDiTConfig``, ``TokenizerConfig``): a frozen dataclass.

    Every construction checks the fields' types (``orbis2.typecheck``: an int is
    accepted for a float, a list for a tuple) and the family's invariants
    (:meth:`check`); a ``ValueError`` names the family (``KIND``) and the field.
    """

    KIND: ClassVar[str] = "model"

    def __post_init__(self) -> None:
        hints = field_types(type(self))
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, typed(hints[f.name], getattr(self, f.name), f"{self.KIND}: {f.name}"))
        self.check()

    def check(self) -> None:
        """Raise ``ValueError`` when the sizes cannot build a network (overridden per family)."""

    def fail(self, message: str) -> typing.NoReturn:
        raise ValueError(f"{self.KIND}: {message}")

    def positive(self, *names: str) -> None:
        for name in names:
            if getattr(self, name) <= 0:
                self.fail(f"{name} = {getattr(self, name)} must be positive")

    def divisible(self, name: str, by: str | int) -> None:
        divisor = getattr(self, by) if isinstance(by, str) else by
        if getattr(self, name) % divisor:
            what = f"{by} = {divisor}" if isinstance(by, str) else str(divisor)
            self.fail(f"{name} = {getattr(self, name)} is not divisible by {what}")

    def with_overrides(self: C, **overrides: Any) -> C:
        """A copy with ``overrides`` applied; an unknown key, a wrong type or a broken invariant raises."""
        known = [f.name for f in dataclasses.fields(self)]
        unknown = [key for key in overrides if key not in known]
        if unknown:
            keys = ", ".join(repr(key) for key in unknown)
            self.fail(f"unknown key{'s' * (len(unknown) > 1)} {keys} (known: {', '.join(sorted(known))})")
        return dataclasses.replace(self, **overrides)


def preset_config(presets: dict[str, C], preset: str, overrides: dict[str, Any]) -> C:
    """``presets[preset]`` with ``overrides`` applied; an unknown preset or override raises ``ValueError``."""
    if preset not in presets:
        kind = next(iter(presets.values())).KIND
        raise ValueError(f"{kind}: unknown preset {preset!r} (known: {', '.join(presets)})")
    return presets[preset].with_overrides(**overrides)


def full_build(presets: dict[str, C], preset: str, overrides: dict[str, Any]) -> dict[str, Any]:
    """The size part of a ``build`` dict a file records: ``preset`` and every field of its config with
    ``overrides`` applied. A file that names its whole architecture loads as what was trained, whatever later
    changes to a preset or a default (the LayerNorm q/k norms and the frame-rate features became the defaults
    after files had recorded only their overrides)."""
    return {"preset": preset, **dataclasses.asdict(preset_config(presets, preset, overrides))}


def split_build(presets: dict[str, C], build: dict[str, Any]) -> tuple[C, dict[str, Any]]:
    """A saved ``build`` dict (``preset``, size overrides, other builder arguments) -> (config, other arguments)."""
    rest = dict(build)
    preset = rest.pop("preset")
    fields = {f.name for f in dataclasses.fields(next(iter(presets.values())))}
    overrides = {key: rest.pop(key) for key in build if key in fields}
    return preset_config(presets, preset, overrides), rest
