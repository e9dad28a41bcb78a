"""Bring user videos into the raw episode layout (the ``import`` stage).

Input folder: one sub-folder per split (``train/``, ``val/``, ...); ``train`` and
``val`` must each end up with a usable video, or the import stops (a flat folder
is read as ``train`` only, so it stops for want of ``val``). Next to
``drive.mp4`` an optional ``drive.csv`` holds odometry with a header and the columns

- ``timestamp``: seconds from the first video frame, strictly increasing;
- ``speed``: m/s;
- ``yaw_rate``: rad/s, counter-clockwise (left turn) positive.

Videos at any frame rate at or above ``data.fps`` (23.976, 24, 25, 29.97, 30, 50,
60 ...) are resampled to ``data.fps`` by timestamps, each slot taking the nearest
source frame (:func:`orbis2.data.video.iter_resampled`); the largest timing error
goes into the index (``timing_error_ms``, with ``source_fps``). Frames are resized
to cover the configured resolution and centre-cropped. Odometry is interpolated
linearly at the kept frames' own source times (the clock the pictures were taken
on) and the episode is cut to the span the CSV covers; the pose column is the
integrated odometry (starting at the origin). Videos without a CSV are kept for
unconditional training: their odometry is NaN.

A bad video is skipped and listed (path, reason, problem and fix) in
``skipped.json`` beside the index, unless ``strict``; the import fails only when
no usable video is left for ``train`` or ``val``.
"""

from __future__ import annotations

import codecs
import csv
import hashlib
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from tqdm import tqdm

from orbis2.config.sections import SPLITS, DataConfig, ImportConfig
from orbis2.data.episodes import EpisodeRecord, RawIndex, write_odometry
from orbis2.data.parts import files_fingerprint, keyed_work, part_name, part_slice
from orbis2.data.video import VIDEO_SUFFIXES, VideoError, iter_resampled, probe, write_video
from orbis2.errors import OrbisError
from orbis2.io import atomic_file, move_into, write_json
from orbis2.kinematics import integrate_odometry

CSV_COLUMNS = ("timestamp", "speed", "yaw_rate")


class ImportProblem(OrbisError):
    """One input video (or its CSV) cannot be imported; ``reason`` is the short label the summary counts."""

    def __init__(self, message: str, reason: str = "odometry CSV"):
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class Skipped:
    path: str
    reason: str  # short label, counted in the summary
    problem: str  # the message: the file, what is wrong, the fix


def reason_of(err: OrbisError) -> str:
    return err.reason if isinstance(err, ImportProblem) else "video"


def summary_of(skipped: list[Skipped]) -> str:
    """``2 skipped (1 video, 1 odometry CSV)``, or ``0 skipped``."""
    counts: dict[str, int] = {}
    for s in skipped:
        counts[s.reason] = counts.get(s.reason, 0) + 1
    by_reason = ", ".join(f"{n} {reason}" for reason, n in sorted(counts.items()))
    return f"{len(skipped)} skipped" + (f" ({by_reason})" if by_reason else "")


def find_videos(folder: Path) -> list[tuple[str, Path]]:
    """(split, video) pairs: split sub-folders if any, else everything is ``train``."""
    if not folder.is_dir():
        raise ImportProblem(f"{folder}: no such folder; put your videos there or set import.videos in params.yaml")
    split_dirs = [folder / s for s in SPLITS if (folder / s).is_dir()]
    pairs = []
    for split_dir in split_dirs or [folder]:
        split = split_dir.name if split_dirs else "train"
        pairs += [(split, p) for p in sorted(split_dir.iterdir()) if p.suffix.lower() in VIDEO_SUFFIXES
                  and not p.is_dir()]
    if not pairs:
        raise ImportProblem(f"{folder}: no video files ({', '.join(VIDEO_SUFFIXES)}) found")
    return pairs


def input_files(folder: str | Path) -> list[str]:
    """Every file the import reads (videos and their CSVs), for the DAG to watch.

    A folder's timestamp changes only when its own entries do, not when a file is
    added to a split sub-folder, so the DAG lists the files. A folder that does not
    exist or holds no video is returned as is, so the stage runs and says what is wrong.
    """
    folder = Path(folder)
    try:
        videos = [video for _, video in find_videos(folder)]
    except ImportProblem:
        return [str(folder)]
    csvs = [video.with_suffix(".csv") for video in videos if video.with_suffix(".csv").is_file()]
    return sorted(str(path) for path in videos + csvs)


def check_outside(folder: Path, out: Path) -> None:
    """The input folder must not lie inside the stage's output, which is replaced (deleted) on success."""
    source, target = Path(folder).resolve(), Path(out).resolve()
    if source == target or target in source.parents:
        raise ImportProblem(f"{folder}: lies inside the import output {out}, which this stage replaces (your videos "
                            f"would be deleted); keep the originals elsewhere (e.g. data/videos) and pass that folder")


# Splits training reads (its loss on val): without one the pipeline would fail only after training started.
REQUIRED_SPLITS = ("train", "val")

# Beyond these the values are not m/s and rad/s of a car (km/h or degrees/s, most likely).
MAX_SPEED = 90.0  # m/s (324 km/h)
MAX_YAW_RATE = math.pi  # rad/s (180 degrees/s)


def read_odometry_csv(path: Path) -> dict[str, np.ndarray]:
    """The odometry columns of a CSV, refusing what would be silently misread.

    A byte-order mark, trailing commas or rows with a different number of fields
    than the header are errors (a CSV reader would shift or rename columns); so are
    negative speeds and speeds or yaw rates beyond what a car does (wrong units).
    """
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise ImportProblem(f"{path}: cannot read ({err})") from err
    if raw.startswith((codecs.BOM_UTF8, codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        raise ImportProblem(f"{path}: starts with a byte-order mark (saved as 'UTF-8 with BOM' or UTF-16); save it "
                            f"as plain UTF-8 CSV")
    try:
        lines = raw.decode("utf-8").splitlines()
    except UnicodeDecodeError as err:
        raise ImportProblem(f"{path}: not UTF-8 text ({err}); save it as plain UTF-8 CSV") from err
    rows = [row for row in csv.reader(lines) if row]
    if not rows:
        raise ImportProblem(f"{path}: empty; expected a header with {list(CSV_COLUMNS)} and data rows")
    header = [h.strip() for h in rows[0]]
    for number, row in enumerate(rows, start=1):
        if len(row) > 1 and row[-1].strip() == "":
            raise ImportProblem(f"{path}: line {number} ends with a trailing comma; remove the trailing commas")
        if len(row) != len(header):
            raise ImportProblem(f"{path}: line {number} has {len(row)} fields but the header has {len(header)}; "
                                f"every row needs one value per column")
    missing = [c for c in CSV_COLUMNS if c not in header]
    if missing:
        raise ImportProblem(f"{path}: missing column(s) {missing}; expected a header with {list(CSV_COLUMNS)}")
    try:
        values = {c: np.array([float(r[header.index(c)]) for r in rows[1:]], np.float64) for c in CSV_COLUMNS}
    except ValueError as err:
        raise ImportProblem(f"{path}: a value is not a number ({err})") from err
    if len(values["timestamp"]) < 2:
        raise ImportProblem(f"{path}: needs at least two rows")
    if not all(np.isfinite(v).all() for v in values.values()):
        raise ImportProblem(f"{path}: contains NaN or infinite values")
    if np.any(np.diff(values["timestamp"]) <= 0):
        bad = int(np.argmax(np.diff(values["timestamp"]) <= 0)) + 2
        raise ImportProblem(f"{path}: timestamps must be strictly increasing (data row {bad} is not)")
    speed, yaw_rate = values["speed"], np.abs(values["yaw_rate"])
    if speed.min() < 0:
        row = int(np.argmin(speed)) + 1
        raise ImportProblem(f"{path}: negative speed {speed[row - 1]:g} at data row {row}; speed is the forward "
                            f"speed in m/s, >= 0 (drop reversing segments)")
    if speed.max() > MAX_SPEED:
        row = int(np.argmax(speed)) + 1
        raise ImportProblem(f"{path}: speed {speed[row - 1]:g} at data row {row} is not a car's speed in m/s "
                            f"(over {MAX_SPEED:g}); convert it to m/s (km/h / 3.6, mph * 0.447)")
    if yaw_rate.max() > MAX_YAW_RATE:
        row = int(np.argmax(yaw_rate)) + 1
        raise ImportProblem(f"{path}: yaw rate {values['yaw_rate'][row - 1]:g} at data row {row} is over "
                            f"{MAX_YAW_RATE:.2f} rad/s; convert it to rad/s (degrees/s * pi / 180)")
    return values


def check_time_unit(path: Path, timestamps: np.ndarray, video_seconds: float) -> None:
    """Timestamps are seconds from the first frame: their span cannot exceed the video's length by much."""
    start, span = float(timestamps[0]), float(timestamps[-1] - timestamps[0])
    if start > video_seconds:
        raise ImportProblem(f"{path}: timestamps start at {start:g} s, after the video ends ({video_seconds:.1f} s); "
                            f"they must be seconds from the first video frame (subtract the first timestamp)")
    if span > 1.5 * video_seconds + 1.0:
        raise ImportProblem(f"{path}: timestamps span {span:g} but the video lasts {video_seconds:.1f} s; they must "
                            f"be in seconds (milliseconds: divide by 1000)")


def import_one(video: Path, split: str, stem: str, root: Path, data: DataConfig, cfg: ImportConfig) -> EpisodeRecord:
    """Import one video (and its CSV) as episode ``stem`` in ``root/<split>/``, frames streamed from the decoder to
    the writer (two frames in memory, whatever the video's length). On any problem the files it began are removed
    and the error names the input."""
    info = probe(video)
    csv_path = video.with_suffix(".csv")
    odo = read_odometry_csv(csv_path) if csv_path.exists() else None
    stats: dict[str, float] = {}
    times: list[float] = []  # the source time of every frame written
    late = []  # the odometry starts after the video's first frame (said once the whole video is checked)

    def frames() -> Iterator[np.ndarray]:
        for t, frame in iter_resampled(video, data.fps, (data.width, data.height), stats):
            if odo is not None:
                if not times and t < odo["timestamp"][0] - 1e-9:
                    late.append(t)
                if late or t > odo["timestamp"][-1] + 1e-9:
                    continue  # outside the odometry: read (the timing check covers the whole video), not written
            times.append(t)
            yield frame

    folder = root / split
    folder.mkdir(parents=True, exist_ok=True)
    try:
        write_video(folder / f"{stem}.mp4", frames(), data.fps)
        if info.frames and stats["source_frames"] < 0.9 * info.frames:
            raise VideoError(f"{video}: truncated: the container announces {info.frames} frames but only "
                             f"{stats['source_frames']} could be decoded; re-encode or replace the file")
        speed = yaw_rate = None
        if odo is not None:
            check_time_unit(csv_path, odo["timestamp"], stats["source_frames"] / stats["source_fps"])
            if late:
                raise ImportProblem(f"{csv_path}: starts at {odo['timestamp'][0]:.3f} s but the video starts at 0 s")
            t = np.array(times)
            speed = np.interp(t, odo["timestamp"], odo["speed"])
            yaw_rate = np.interp(t, odo["timestamp"], odo["yaw_rate"])
        if len(times) < data.window_span_frames:
            raise ImportProblem(f"{video}: {len(times)} frames at {data.fps} fps (after resampling"
                                f"{' and cutting to the odometry' if speed is not None else ''}) is shorter than "
                                f"one training window ({data.window_span_frames} frames)", reason="too short")
        nan = np.full(len(times), np.nan)
        pose = integrate_odometry(speed, yaw_rate, data.fps) if speed is not None else None
        write_odometry(folder / f"{stem}.parquet", data.fps, nan if speed is None else speed,
                       nan if yaw_rate is None else yaw_rate, pose)
    except BaseException:
        for begun in folder.glob(f"{stem}.*"):
            begun.unlink()
        raise
    return EpisodeRecord(split, stem, len(times), has_odometry=speed is not None, has_pose=speed is not None,
                         origin=str(video), source_fps=round(stats["source_fps"], 3),
                         timing_error_ms=round(stats["max_error_s"] * 1000, 3))


def episode_stem(folder: Path, split: str, video: Path) -> str:
    """``import_<split>_<digest>``: named by the video's path inside the input folder (its first 12 hex digits
    of SHA-256), never by how many videos came before it, so that an episode keeps its name (and its clips
    their keys) whatever else is imported, skipped, or imported by another part."""
    relative = Path(video).relative_to(folder).as_posix().encode("utf-8", "surrogateescape")
    return f"import_{split}_{hashlib.sha256(relative).hexdigest()[:12]}"


def import_videos(folder: Path, root: Path, data: DataConfig, cfg: ImportConfig, skip_bad: bool, parts: int = 1,
                  work: Path | None = None) -> tuple[RawIndex, list[Skipped]]:
    """Import every video into ``root``; stop at the first bad one unless ``skip_bad`` (then list what was skipped).

    Each of ``parts`` parts is imported (or resumed, see :func:`import_part`) in ``work`` (default:
    ``<root>.parts`` beside it), then gathered (:func:`gather_import`). Every split in
    ``REQUIRED_SPLITS`` must end up with at least one video.
    """
    work = keyed_work(Path(work) if work is not None else root.with_name(root.name + ".parts"),
                      {"data": asdict(data), "import": asdict(cfg)})
    written = [import_part(folder, work, data, cfg, skip_bad, part, parts) for part in range(parts)]
    return gather_import(folder, written, root, data)


def fingerprint(video: Path) -> list[int | None]:
    """What says a video (and its CSV) is the one a recorded outcome was made from
    (:func:`orbis2.data.parts.files_fingerprint`)."""
    return files_fingerprint([video, video.with_suffix(".csv")])


def import_part(folder: Path, work: Path, data: DataConfig, cfg: ImportConfig, skip_bad: bool, part: int = 0,
                parts: int = 1) -> dict[str, Any]:
    """Import part ``part`` of ``parts`` (a contiguous block of the videos, in :func:`find_videos`' order) into
    ``work/<part_name>/``: each video's episode files, then its outcome in ``done/<stem>.json`` (its record, or
    why it was skipped, and the :func:`fingerprint` of its inputs), written atomically.

    Resumes: a video whose outcome is recorded for the same inputs is not read again; one stopped half-way is
    imported again from the start. Returns the part's outcomes in order.
    """
    videos = find_videos(folder)
    dest = work / part_name(part, parts)
    (dest / "done").mkdir(parents=True, exist_ok=True)
    outcomes = []
    for split, video in tqdm(videos[part_slice(len(videos), part, parts)],
                             desc=f"import {part_name(part, parts)}", unit="video"):
        stem = episode_stem(folder, split, video)
        marker, mark = dest / "done" / f"{stem}.json", fingerprint(video)
        saved = json.loads(marker.read_text()) if marker.is_file() else None
        gathered = saved is not None and "record" in saved and not (dest / split / f"{stem}.mp4").is_file()
        if saved is None or saved["fingerprint"] != mark or gathered:  # (a gather moves the episodes out)
            saved = {"fingerprint": mark, **_import_outcome(video, split, stem, dest, data, cfg, skip_bad)}
            with atomic_file(marker) as tmp:
                write_json(tmp, saved)
        elif "skipped" in saved and not skip_bad:  # skipped by a run that allowed it; this one does not
            raise ImportProblem(saved["skipped"]["problem"], saved["skipped"]["reason"])
        outcomes.append(saved)
    return {"folder": str(dest), "outcomes": outcomes}


def _import_outcome(video: Path, split: str, stem: str, dest: Path, data: DataConfig, cfg: ImportConfig,
                    skip_bad: bool) -> dict[str, Any]:
    try:
        return {"record": asdict(import_one(video, split, stem, dest, data, cfg))}
    except OrbisError as err:
        if not skip_bad:
            raise
        return {"skipped": asdict(Skipped(str(video), reason_of(err), str(err)))}


def gather_import(folder: Path, parts_written: list[dict[str, Any]], root: Path,
                  data: DataConfig) -> tuple[RawIndex, list[Skipped]]:
    """The parts' episodes, in part order, moved into ``root`` (see :func:`orbis2.data.shards.gather_parts` for
    why moved) with ``index.json``; the videos skipped. Fails when no usable video is left for a required split
    (the episodes then stay in the parts)."""
    records, skipped, sources = [], [], []
    for written in parts_written:
        for outcome in written["outcomes"]:
            if "skipped" in outcome:
                skipped.append(Skipped(**outcome["skipped"]))
                continue
            records.append(EpisodeRecord(**outcome["record"]))
            sources.append(Path(written["folder"]))
    if not records:
        problems = "\n".join(f"  {s.path}: {s.problem}" for s in skipped)
        raise ImportProblem(f"{folder}: every video was skipped:\n{problems}")
    absent = [split for split in REQUIRED_SPLITS if not any(r.split == split for r in records)]
    if absent:
        flat = not any((folder / split).is_dir() for split in SPLITS)
        why = " (a folder without split sub-folders imports everything as train)" if flat else ""
        problems = "".join(f"\n  skipped: {s.problem}" for s in skipped)
        raise ImportProblem(f"{folder}: no {' or '.join(absent)} videos{why}; training needs both: put videos into "
                            f"{' and '.join(str(folder / split) + '/' for split in REQUIRED_SPLITS)}{problems}")
    for record, folder_of_part in zip(records, sources):
        (root / record.split).mkdir(parents=True, exist_ok=True)
        for source in (record.video(folder_of_part), record.odometry(folder_of_part)):
            move_into(source, root / record.split / source.name)
    index = RawIndex("import", data.fps, data.width, data.height, None, records)
    index.write(root)
    return index, skipped
