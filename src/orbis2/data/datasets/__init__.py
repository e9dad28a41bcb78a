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

A conversion runs in parts (:func:`convert_items`): each reader lists its items (a log, a clip, a
video) in a fixed order and part i of N converts the i-th contiguous block of them, so that
N jobs (an array on a cluster) convert a dataset side by side. Output names come from the items
(the log, clip or video id), never from their order, so parts write into one folder; each part logs
each item once its files are in place, and a part started again skips the items it logged (unless
their source files changed). Without ``part`` every part not yet done runs, then the report of all
of them is written: the report and the files do not depend on how many parts there were.
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from orbis2.data.parts import PartLog, files_fingerprint, keyed_work, part_name, part_slice
from orbis2.errors import OrbisError
from orbis2.io import atomic_file
from orbis2.sources import code_version


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


@dataclass(frozen=True)
class Item:
    """One unit of a conversion that a part converts, logs and, started again, skips."""

    name: str  # the log, clip or video, as the part's log names it (unique among the items)
    sources: tuple[Path, ...]  # the files it is made from: their sizes and times say whether a logged outcome holds
    convert: Callable[[Report], None]  # converts it, adding to the report what it wrote or left out
    entry: str = ""  # what else it is made from (its line of a meta file), compared like the sources


def convert_items(report: Report, items: list[Item], key: dict[str, Any], parts: int = 1, part: int | None = None,
                  limit: int | None = None) -> Report:
    """Convert ``items`` in ``parts`` parts (only part ``part`` when given) into ``report``, in item order.

    A part's progress lives in ``<out>.convert-parts/<dataset>/<part_name>/done.jsonl`` beside the output folder
    (outside it: the import reads that folder), keyed by ``key`` (the reader's settings and code: a folder made
    from another key is emptied). An item is logged with what it wrote and left out once its files are in place;
    a logged item whose sources are unchanged and whose videos are still there is not converted again, so a
    killed part loses at most the item in flight. ``limit``: stop once that many videos are converted (one part
    only: how far a part goes would depend on the parts before it)."""
    if limit is not None and parts > 1:
        raise DatasetError(f"--limit {limit} with --parts {parts}: a limit counts converted videos in order, which "
                           f"parts cannot know of each other; drop --limit or convert in one part")
    work = keyed_work(report.out.parent / f"{report.out.name}.convert-parts" / report.dataset, key)
    for p in range(parts) if part is None else [part]:
        log = PartLog(work / part_name(p, parts))
        logged = {event["item"]: event for event in log.events}
        for item in items[part_slice(len(items), p, parts)]:
            if limit is not None and len(report.converted) >= limit:
                break
            mark = [*files_fingerprint(list(item.sources)), item.entry]
            saved = logged.get(item.name)
            converted = [json.loads(entry) for entry in saved["converted"]] if saved else []
            if (saved is None or saved["fingerprint"] != mark
                    or not all(Path(entry["video"]).exists() for entry in converted)):
                done = Report(report.dataset, report.out, report.strict)
                item.convert(done)
                converted = done.converted
                saved = {"item": item.name, "fingerprint": mark, "skipped": [asdict(s) for s in done.skipped],
                         "converted": [json.dumps(entry) for entry in converted]}  # as text: keeps the keys' order
                log.add(saved)
            report.converted += converted
            report.skipped += [Skip(**s) for s in saved["skipped"]]
    return report


def reader_key(module: str, **settings: Any) -> dict[str, Any]:
    """The key of a reader's parts: its settings (paths as given) and the code of the reader ``module`` (its
    ``__file__``) and what it imports, so that a fixed reader converts again."""

    def plain(value: Any) -> Any:  # as JSON reads it back
        return [plain(v) for v in value] if isinstance(value, (list, tuple)) else (
            str(value) if isinstance(value, Path) else value)

    return {"code": code_version(module), **{k: plain(v) for k, v in settings.items()}}


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
