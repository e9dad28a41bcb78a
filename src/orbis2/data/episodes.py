"""The raw episode layout shared by the embedded town and imported videos.

::

    data/raw/<source>/
        index.json                      source, native fps, resolution, camera, episodes
        <split>/<stem>.mp4              RGB video at the native rate
        <split>/<stem>.parquet          one row per frame (columns below)
        <split>/<stem>.labels.npz       optional: frames, depth (float16 m), semantic (uint8)

Odometry columns: ``frame`` (int), ``t`` (s), ``speed`` (m/s), ``yaw_rate`` (rad/s,
counter-clockwise positive), ``x``, ``y``, ``yaw`` (camera pose in a world frame;
NaN where unknown). Speed and yaw rate at frame k are the controls over
``[t_k, t_k+1)``; integrating them reproduces the pose column (see
:func:`orbis2.kinematics.integrate_odometry`). Videos without odometry have NaN
speed and yaw rate, and ``has_odometry = false`` in the index.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from orbis2.errors import OrbisError
from orbis2.io import atomic_file, npz_bytes, write_json

ODOMETRY_COLUMNS = ("frame", "t", "speed", "yaw_rate", "x", "y", "yaw")


class EpisodeError(OrbisError):
    """A raw episode folder is missing or inconsistent; the message names the file."""


@dataclass
class EpisodeRecord:
    split: str
    stem: str
    frames: int
    has_odometry: bool
    has_pose: bool
    label_frames: list[int] = field(default_factory=list)
    origin: str = ""  # where it came from: town seed or the user's video path
    source_fps: float | None = None  # an imported video's own rate (from its timestamps)
    timing_error_ms: float | None = None  # resampling to the index's fps: largest |source time - slot time|

    def video(self, root: Path) -> Path:
        return root / self.split / f"{self.stem}.mp4"

    def odometry(self, root: Path) -> Path:
        return root / self.split / f"{self.stem}.parquet"

    def labels(self, root: Path) -> Path:
        return root / self.split / f"{self.stem}.labels.npz"


@dataclass
class RawIndex:
    source: str
    fps: int
    width: int
    height: int
    camera: dict[str, float] | None
    episodes: list[EpisodeRecord]

    def write(self, root: Path) -> None:
        write_json(root / "index.json", asdict(self))

    @classmethod
    def read(cls, root: Path) -> "RawIndex":
        path = Path(root) / "index.json"
        if not path.is_file():
            raise EpisodeError(f"{path}: missing; run the `town` or `import` stage first")
        try:
            raw: dict[str, Any] = json.loads(path.read_text())
            raw["episodes"] = [EpisodeRecord(**e) for e in raw["episodes"]]
            return cls(**raw)
        except (ValueError, TypeError, KeyError) as err:
            raise EpisodeError(f"{path}: malformed index ({err}); re-run the stage that wrote it") from err

    def split(self, name: str) -> list[EpisodeRecord]:
        return [e for e in self.episodes if e.split == name]


def write_odometry(path: Path, fps: int, speed: np.ndarray, yaw_rate: np.ndarray,
                   pose: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> None:
    n = len(speed)
    nan = np.full(n, np.nan)
    x, y, yaw = pose if pose is not None else (nan, nan, nan)
    table = pa.table({
        "frame": np.arange(n, dtype=np.int32),
        "t": np.arange(n, dtype=np.float64) / fps,
        "speed": np.asarray(speed, np.float64),
        "yaw_rate": np.asarray(yaw_rate, np.float64),
        "x": np.asarray(x, np.float64),
        "y": np.asarray(y, np.float64),
        "yaw": np.asarray(yaw, np.float64),
    })
    with atomic_file(path) as tmp:
        pq.write_table(table, tmp)


def read_odometry(path: Path) -> dict[str, np.ndarray]:
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowInvalid) as err:
        raise EpisodeError(f"{path}: cannot read odometry ({err})") from err
    missing = set(ODOMETRY_COLUMNS) - set(table.column_names)
    if missing:
        raise EpisodeError(f"{path}: missing odometry columns {sorted(missing)}")
    return {c: table.column(c).to_numpy() for c in ODOMETRY_COLUMNS}


def write_labels(path: Path, frames: list[int], depth: np.ndarray, semantic: np.ndarray) -> None:
    """Depth is stored as float16 metres (sky = inf), semantics as Cityscapes train ids."""
    data = npz_bytes(frames=np.asarray(frames, np.int32), depth=depth.astype(np.float16),
                     semantic=semantic.astype(np.uint8))
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)
