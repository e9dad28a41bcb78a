"""The records the report reads, gathered: :class:`Evals` holds every evaluation record of a run (typed models of
:mod:`orbis2.eval.records`), with the file each came from, so that a missing one is named with the stage that
writes it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, TypeVar

from orbis2.errors import OrbisError
from orbis2.eval.records import (
    EVAL_KINDS,
    PROBE_TARGETS,
    CompressionRecord,
    ConditioningRecord,
    FvdRecord,
    ProbeRecord,
    Record,
    SpeedRecord,
    SteeringRecord,
    from_json,
)
from orbis2.registry import registry

T = TypeVar("T")

KIND_TYPES: dict[str, type[Record]] = {"fvd": FvdRecord, "probe": ProbeRecord, "steering": SteeringRecord,
                                       "speed": SpeedRecord, "conditioning": ConditioningRecord}


def _file_and_stage(kind: str, name: str | None) -> tuple[str, str]:
    if kind in ("fvd", "probe"):
        return f"{kind}_{name}.json", f"eval_{kind}_{name}"
    if kind == "compression":  # built by compression_from_evals, not read from a file
        return "the compression rows (fvd_flat_abstract_full.json)", "eval_fvd_flat_abstract_full"
    return f"{kind}.json", f"eval_{kind}"


def _stage_of(kind: str, name: str | None, path: Path) -> str:
    stage = _file_and_stage(kind, name)[1]
    if name is None and path.stem == f"{kind}_all":  # the full report's speed and conditioning records
        stage += "_all"
    return stage


@dataclass
class Evals:
    """The records the report reads: FVD by system, probes by target, one steering, speed and conditioning
    record, and the compression rows the full report builds; with the file each came from (or would have)."""

    fvd: dict[str, FvdRecord] = field(default_factory=dict)
    probe: dict[str, ProbeRecord] = field(default_factory=dict)
    steering: SteeringRecord | None = None
    speed: SpeedRecord | None = None
    conditioning: ConditioningRecord | None = None
    compression: CompressionRecord | None = None
    files: dict[str, Any] = field(default_factory=lambda: {"fvd": {}, "probe": {}})
    folder: Path | None = None

    def where(self, kind: str, name: str | None = None) -> str:
        """The record's file and the stage that writes it, for messages."""
        file, _ = _file_and_stage(kind, name)
        given = self.files.get(kind)
        given = given.get(name) if isinstance(given, Mapping) else given
        path = Path(given) if given is not None else (self.folder or Path("reports/eval")) / file
        return f"{path} (written by stage {_stage_of(kind, name, path)})"

    def has(self, kind: str, name: str | None = None) -> bool:
        found = getattr(self, kind)
        return (name in found) if name is not None else found is not None

    def _need(self, found: T | None, kind: str, name: str | None = None) -> T:
        if found is None:
            raise OrbisError(f"missing {self.where(kind, name)}: run that stage first")
        return found

    def fvd_record(self, system: str) -> FvdRecord:
        return self._need(self.fvd.get(system), "fvd", system)

    def probe_record(self, target: str) -> ProbeRecord:
        return self._need(self.probe.get(target), "probe", target)

    def steering_record(self) -> SteeringRecord:
        return self._need(self.steering, "steering")

    def speed_record(self) -> SpeedRecord:
        return self._need(self.speed, "speed")

    def conditioning_record(self) -> ConditioningRecord:
        return self._need(self.conditioning, "conditioning")

    def compression_record(self) -> CompressionRecord:
        return self._need(self.compression, "compression")

    def value(self, found: T | None, kind: str, name: str | None, path: str) -> T:
        """``found``, a value the report needs that its record may leave out (None): else an error naming the
        file, the key (``path``) and the stage."""
        if found is None:
            raise OrbisError(f"{self.where(kind, name)} has no value for {path}: re-run that stage")
        return found

    def entry(self, mapping: Mapping[str, T] | None, key: str, kind: str, name: str | None, path: str) -> T:
        """``mapping[key]`` (a split, mode, instrument or system the configuration asks for), or an error naming
        the file, ``path.key`` and the stage."""
        found = mapping.get(key) if mapping is not None else None
        return self.value(found, kind, name, f"{path}.{key}")


def read_evals(fvd: Mapping[str, str | Path], probe: Mapping[str, str | Path], steering: str | Path | None = None,
               speed: str | Path | None = None, conditioning: str | Path | None = None) -> Evals:
    """The evaluation records given (``fvd``: system -> file, ``probe``: target -> file, and the steering,
    speed and conditioning files), each read strictly; a file that does not exist is simply absent."""
    evals = Evals()
    for kind, files, key in (("fvd", fvd, "model"), ("probe", probe, "target")):
        found = getattr(evals, kind)
        for name, path in files.items():
            path = Path(path)
            evals.files[kind][name] = path
            if path.exists():
                record = from_json(KIND_TYPES[kind], path, _stage_of(kind, name, path))
                if getattr(record, key) != name:
                    raise OrbisError(f"{path} says {key}={getattr(record, key)!r}, expected {name!r}: "
                                     f"re-run eval_{kind}_{name}")
                found[name] = record
    for kind, given in (("steering", steering), ("speed", speed), ("conditioning", conditioning)):
        if given is not None:
            path = Path(given)
            evals.files[kind] = path
            if path.exists():
                setattr(evals, kind, from_json(KIND_TYPES[kind], path, _stage_of(kind, None, path)))
    return evals


def load_eval(folder: str | Path) -> Evals:
    """Every evaluation record present in ``folder`` under the names the evaluation stages give them by default
    (``fvd_<system>.json``, ``probe_<target>.json``, ``steering.json``, ...): :func:`read_evals` of that folder."""
    folder = Path(folder)
    evals = read_evals({name: folder / _file_and_stage("fvd", name)[0] for name in registry().systems},
                       {name: folder / _file_and_stage("probe", name)[0] for name in PROBE_TARGETS},
                       **{kind: folder / f"{kind}.json" for kind in EVAL_KINDS})
    evals.folder = folder
    return evals
