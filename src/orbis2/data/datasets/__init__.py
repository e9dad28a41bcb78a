"""Readers that turn the paper's datasets into the ``import`` layout: ``<split>/<name>.<video>`` at the
native frame rate, and ``<split>/<name>.csv`` with ``timestamp, speed, yaw_rate`` (seconds from the
first frame, m/s, rad/s counter-clockwise positive) where the dataset has ego motion.

One module per dataset (``nuplan``, ``physicalai_av``, ``bdd100k``, ``opendv``), each reading the
dataset's published layout with plain readers (SQLite, zip, Parquet, JSON): no devkit at run time.
Speed and yaw rate are derived from poses (positions and headings) where a dataset has them, the
same way for every dataset (:func:`motion_from_poses`).

Real downloads are partial and uneven (camera archives for a tenth of nuPlan's logs, chunks of
PhysicalAI-AV, removed YouTube videos), so a reader goes on past a bad item (a log, clip or
video): it is skipped and listed with its reason and fix in a :class:`Report`, written beside the
output; under ``strict`` the first bad item stops the run. A tree that lacks what every item needs
(the index, the meta file) stops the reader with a :class:`DatasetError` naming the file and the
fix. Each video and CSV is written atomically, so an interrupted run leaves no half-written file.
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from orbis2.errors import OrbisError
from orbis2.io import atomic_file


class DatasetError(OrbisError):
    """A dataset tree (or one item of it) lacks what a reader needs; the message names the file and the fix,
    ``reason`` is the short label a report counts skipped items by."""

    def __init__(self, message: str, reason: str = "unreadable"):
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class Skip:
    item: str  # the log, clip, video or chunk left out
    reason: str  # short label, counted in the summary
    problem: str  # the message: the file, what is wrong, the fix


@dataclass
class Report:
    """What a conversion wrote and what it left out, written to ``<out>/convert-<dataset>.json``.

    ``converted`` holds one entry per video with what a user should know about it (the
    bridged span of a late first GPS fix, where the yaw rate came from); ``skipped`` one
    :class:`Skip` per item left out. Under ``strict`` the first skip raises instead.
    """

    dataset: str
    out: Path
    strict: bool = False
    converted: list[dict] = field(default_factory=list)
    skipped: list[Skip] = field(default_factory=list)
    notes: dict[str, int] = field(default_factory=dict)  # counts not worth an entry each (e.g. chunks not downloaded)

    @property
    def path(self) -> Path:
        return self.out / f"convert-{self.dataset}.json"

    @property
    def videos(self) -> list[Path]:
        return [Path(entry["video"]) for entry in self.converted]

    def add(self, video: Path, **details) -> None:
        self.converted.append({"video": str(video), **details})

    def skip(self, item: str, err: OrbisError) -> None:
        """Leave ``item`` out for ``err`` (its message names the file and the fix); under ``strict``, raise it."""
        if self.strict:
            raise err
        self.skipped.append(Skip(str(item), getattr(err, "reason", "unreadable"), str(err)))

    def summary(self) -> str:
        """``bdd100k: 3 videos converted (2 with odometry), 2 skipped (1 late first fix, 1 no info file)``."""
        with_csv = sum(Path(v).with_suffix(".csv").is_file() for v in self.videos)
        counts: dict[str, int] = {}
        for s in self.skipped:
            counts[s.reason] = counts.get(s.reason, 0) + 1
        reasons = ", ".join(f"{n} {reason}" for reason, n in sorted(counts.items()))
        notes = "".join(f"; {n} {what}" for what, n in self.notes.items())
        return (f"{self.dataset}: {len(self.converted)} videos converted ({with_csv} with odometry), "
                f"{len(self.skipped)} skipped{f' ({reasons})' if reasons else ''}{notes}")

    def write(self) -> Path:
        self.out.mkdir(parents=True, exist_ok=True)
        with atomic_file(self.path) as tmp:
            tmp.write_text(json.dumps({"dataset": self.dataset, "summary": self.summary(), "notes": self.notes,
                                       "converted": self.converted, "skipped": [asdict(s) for s in self.skipped]},
                                      indent=2) + "\n")
        return self.path


def yaw_of_quaternion(qw, qx, qy, qz) -> np.ndarray:
    """Heading (rotation about z, counter-clockwise from +x) of unit quaternions (w, x, y, z)."""
    qw, qx, qy, qz = (np.asarray(q, np.float64) for q in (qw, qx, qy, qz))
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def motion_from_poses(t, x, y, yaw) -> tuple[np.ndarray, np.ndarray]:
    """(speed m/s, yaw rate rad/s) at the pose times by second-order central differences (``np.gradient``).

    Speed is the planar speed |d(x, y)/dt|, never negative (reversing reads as forward,
    which the importer's speed column assumes); the heading is unwrapped first.
    """
    t = np.asarray(t, np.float64)
    if len(t) < 3 or np.any(np.diff(t) <= 0):
        raise ValueError("poses need at least 3 strictly increasing timestamps")
    speed = np.hypot(np.gradient(np.asarray(x, np.float64), t, edge_order=2),
                     np.gradient(np.asarray(y, np.float64), t, edge_order=2))
    yaw_rate = np.gradient(np.unwrap(np.asarray(yaw, np.float64)), t, edge_order=2)
    return speed, yaw_rate


def native_rate(timestamps_s: np.ndarray, where: str) -> float:
    """A camera's frame rate from its timestamps (median spacing); the importer resamples any rate by timestamps,
    so it need not be an integer."""
    spacing = float(np.median(np.diff(timestamps_s)))
    if spacing <= 0:
        raise DatasetError(f"{where}: the frames' timestamps do not increase; the log is corrupt, download it again")
    return 1.0 / spacing


def write_odometry_csv(path: Path, t: np.ndarray, speed: np.ndarray, yaw_rate: np.ndarray) -> None:
    """The import layout's odometry CSV, written atomically."""
    with atomic_file(path) as tmp, tmp.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["timestamp", "speed", "yaw_rate"])
        writer.writerows([f"{a:.6f}", f"{b:.6f}", f"{c:.6f}"] for a, b, c in zip(t, speed, yaw_rate))


def heading_change_deg(yaw_rate: np.ndarray, t: np.ndarray) -> float:
    """Range of the integrated heading over a clip (degrees): how much the ego turns within it."""
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (yaw_rate[1:] + yaw_rate[:-1]) * np.diff(t))])
    return float(np.degrees(heading.max() - heading.min()))
