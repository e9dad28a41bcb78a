"""The one type checker of typed configs: params.yaml sections (``orbis2.config``) and model sizes (``orbis2.models``).

Values come from YAML or JSON (params.yaml, a checkpoint's saved build), so an int
is accepted for a float and a list for a tuple, and a mapping given for a dataclass
is built into it. Every failure is a :class:`~orbis2.errors.ConfigError` naming
where the value sits (``data.smoke.fps``, ``ST-DiT: depth``).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from functools import cache
from typing import Any

from orbis2.errors import ConfigError


class MissingKeyError(ConfigError):
    """A dataclass field without a default is absent from the mapping it is built from."""

    def __init__(self, where: str, keys: list[str]) -> None:
        self.where, self.keys = where, keys
        super().__init__(f"{where}: missing key(s) {keys}")


@cache
def field_types(cls: type) -> dict[str, Any]:
    """The resolved annotations of dataclass ``cls`` (postponed annotations are strings until resolved)."""
    return typing.get_type_hints(cls)


def typed(tp: Any, value: Any, where: str) -> Any:
    """``value`` as a ``tp`` (int -> float, list -> tuple, mapping -> dataclass), or a ConfigError naming ``where``."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [arg for arg in args if arg is not type(None)]
        if len(options) == 1:
            return typed(options[0], value, where)  # an optional value: keep the inner error, it is more precise
        for arg in options:
            try:
                return typed(arg, value, where)
            except ConfigError:
                continue
    elif origin is list:
        if isinstance(value, list):
            return [typed(args[0], v, f"{where}[{i}]") for i, v in enumerate(value)]
    elif origin is tuple:
        items = args[:1] * len(value) if args[1:] == (Ellipsis,) and isinstance(value, (list, tuple)) else args
        if isinstance(value, (list, tuple)) and len(value) == len(items):
            return tuple(typed(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(items, value)))
    elif origin is dict:
        if isinstance(value, dict):
            return {typed(args[0], k, where): typed(args[1], v, f"{where}.{k}") for k, v in value.items()}
    elif dataclasses.is_dataclass(tp):
        return value if isinstance(value, tp) else build(tp, value, where)
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif tp in (int, bool, str):
        if isinstance(value, tp) and (tp is bool or not isinstance(value, bool)):
            return value
    else:
        raise TypeError(f"unsupported config type {tp} at {where}")
    raise ConfigError(f"{where} must be {_describe(tp)}, got {value!r} ({type(value).__name__})")


def build(cls: type, values: Any, where: str) -> Any:
    """Dataclass ``cls`` from the mapping ``values``: every key known, every field without a default given, typed."""
    if not isinstance(values, dict):
        raise ConfigError(f"{where} must be a mapping, got {values!r}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = set(values) - set(fields)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(fields)}")
    missing = [name for name, f in fields.items() if name not in values
               and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if missing:
        raise MissingKeyError(where, missing)
    hints = field_types(cls)
    kwargs = {name: typed(hints[name], value, f"{where}.{name}") for name, value in values.items()}
    try:
        return cls(**kwargs)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from err


def _describe(tp: Any) -> str:
    if typing.get_origin(tp) is None and isinstance(tp, type):
        return tp.__name__
    return str(tp).replace("typing.", "").replace("NoneType", "None")
