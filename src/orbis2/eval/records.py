"""The evaluation records the report reads: found by name, parsed, and read strictly.

``read_evals`` and ``load_eval`` return a dict keyed by kind (``fvd`` and ``probe``: name -> record;
``steering``, ``speed``, ``conditioning``: one record each) with the file each came from. A value
is read with :func:`get`, which stops with an ``OrbisError`` naming the file and the stage that
writes it when the value is missing or null, so no table is ever padded with guesses.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

from orbis2.errors import OrbisError
from orbis2.registry import registry

PROBE_TARGETS = tuple(registry().probe_targets)  # registry.yaml: every probe target
EVAL_KINDS = ("steering", "speed", "conditioning")  # one file each, beside the per-system and per-target ones


def _file_and_stage(kind: str, name: str | None) -> tuple[str, str]:
    if kind in ("fvd", "probe"):
        return f"{kind}_{name}.json", f"eval_{kind}_{name}"
    if kind == "compression":  # built by compression_from_evals, not read from a file
        return "the compression rows (fvd_flat_abstract_full.json)", "eval_fvd_flat_abstract_full"
    return f"{kind}.json", f"eval_{kind}"


def read_evals(fvd: Mapping[str, str | Path], probe: Mapping[str, str | Path], steering: str | Path | None = None,
               speed: str | Path | None = None, conditioning: str | Path | None = None) -> dict:
    """The evaluation JSON files given (``fvd``: system -> file, ``probe``: target -> file, and the steering,
    speed and conditioning files), keyed by kind and name; a file that does not exist is simply absent."""
    evals: dict = {"fvd": {}, "probe": {}, "files": {"fvd": {}, "probe": {}}}
    for kind, files, key in (("fvd", fvd, "model"), ("probe", probe, "target")):
        for name, path in files.items():
            path = Path(path)
            evals["files"][kind][name] = path
            if path.exists():
                data = _read_json(path)
                if data.get(key) != name:
                    found = data.get(key)
                    raise OrbisError(f"{path} says {key}={found!r}, expected {name!r}: re-run eval_{kind}_{name}")
                evals[kind][name] = data
    for kind, path in (("steering", steering), ("speed", speed), ("conditioning", conditioning)):
        if path is not None:
            evals["files"][kind] = Path(path)
            if Path(path).exists():
                evals[kind] = _read_json(Path(path))
    return evals


def load_eval(folder: str | Path) -> dict:
    """Every evaluation JSON present in ``folder`` under the names the evaluation stages give them by default
    (``fvd_<system>.json``, ``probe_<target>.json``, ``steering.json``, ...): :func:`read_evals` of that folder."""
    folder = Path(folder)
    evals = read_evals({name: folder / _file_and_stage("fvd", name)[0] for name in registry().systems},
                       {name: folder / _file_and_stage("probe", name)[0] for name in PROBE_TARGETS},
                       **{kind: folder / f"{kind}.json" for kind in EVAL_KINDS})
    return evals | {"folder": str(folder)}


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise OrbisError(f"cannot read {path}: {err}; re-run the stage that writes it") from err
    if not isinstance(data, dict):
        raise OrbisError(f"{path} holds {type(data).__name__}, expected a JSON object; re-run the stage that writes it")
    return data


def where(evals: Mapping, kind: str, name: str | None = None) -> str:
    file, stage = _file_and_stage(kind, name)
    given = evals.get("files", {}).get(kind)
    given = given.get(name) if isinstance(given, Mapping) else given
    path = given if given is not None else Path(evals.get("folder", "reports/eval")) / file
    if name is None and Path(path).stem == f"{kind}_all":  # the full report's speed and conditioning records
        stage += "_all"
    return f"{path} (written by stage {stage})"


def doc(evals: Mapping, kind: str, name: str | None = None) -> dict:
    """The parsed file, or an error naming it and the stage that produces it."""
    found = evals.get(kind, {}).get(name) if name is not None else evals.get(kind)
    if found is None:
        raise OrbisError(f"missing {where(evals, kind, name)}: run that stage first")
    return found


def has(evals: Mapping, kind: str, name: str | None = None) -> bool:
    return (evals.get(kind, {}).get(name) if name is not None else evals.get(kind)) is not None


def get(evals: Mapping, kind: str, name: str | None, *keys: str | int) -> Any:
    """A value deep in a file; missing or null is an error (strict: no blank metric cells)."""
    value: Any = doc(evals, kind, name)
    for i, key in enumerate(keys):
        try:
            value = value[key]
        except (KeyError, IndexError, TypeError):
            value = None
        if value is None:
            path = ".".join(str(k) for k in keys[: i + 1])
            raise OrbisError(f"{where(evals, kind, name)} has no value for {path}: re-run that stage")
    return value

