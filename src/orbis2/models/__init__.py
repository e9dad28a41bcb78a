"""Networks, one file per model with all of its blocks; each family's sizes are a typed config beside it."""

from __future__ import annotations

import dataclasses
import typing
from functools import cache
from typing import Any, ClassVar, TypeVar

C = TypeVar("C", bound="ModelConfig")


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Base of a model family's size config (``STDiTConfig``, ``TokenizerConfig``): a frozen dataclass.

    Every construction checks the fields' types (an int is accepted for a float,
    a list for a tuple) and the family's invariants (:meth:`check`); a
    ``ValueError`` names the family (``KIND``) and the field.
    """

    KIND: ClassVar[str] = "model"

    def __post_init__(self) -> None:
        hints = _hints(type(self))
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, _typed(self.KIND, f.name, hints[f.name], getattr(self, f.name)))
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


def split_build(presets: dict[str, C], build: dict[str, Any]) -> tuple[C, dict[str, Any]]:
    """A saved ``build`` dict (``preset``, size overrides, other builder arguments) -> (config, other arguments)."""
    rest = dict(build)
    preset = rest.pop("preset")
    fields = {f.name for f in dataclasses.fields(next(iter(presets.values())))}
    overrides = {key: rest.pop(key) for key in build if key in fields}
    return preset_config(presets, preset, overrides), rest


@cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _typed(kind: str, name: str, tp: Any, value: Any) -> Any:
    """``value`` as a ``tp`` (int -> float, list -> tuple), or a ``ValueError`` naming the field."""
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        if isinstance(value, (list, tuple)):
            items = args[:1] * len(value) if args[1:] == (Ellipsis,) else args
            if len(items) == len(value) and all(_is(a, v) for a, v in zip(items, value)):
                return tuple(value)
    elif _is(tp, value):
        return float(value) if tp is float else value
    raise ValueError(f"{kind}: {name} must be {_name(tp)}, got {value!r} ({type(value).__name__})")


def _is(tp: type, value: Any) -> bool:
    if isinstance(value, bool):
        return tp is bool
    return isinstance(value, (int, float)) if tp is float else isinstance(value, tp)


def _name(tp: Any) -> str:
    return getattr(tp, "__name__", None) if typing.get_origin(tp) is None else str(tp).replace("typing.", "")
