"""Bring user videos into the raw episode layout (the ``import`` stage).

Input folder: either flat (every video goes to ``train``) or with one sub-folder
per split (``train/``, ``val/``, ...). Next to ``drive.mp4`` an optional
``drive.csv`` holds odometry with a header and the columns

- ``timestamp``: seconds from the first video frame, strictly increasing;
- ``speed``: m/s;
- ``yaw_rate``: rad/s, counter-clockwise (left turn) positive.

Videos are resampled to ``data.fps`` by keeping every n-th frame (the source rate
must be an integer multiple, within ``import.fps_tolerance``), resized to cover
the configured resolution and centre-cropped. Odometry is interpolated linearly
at the kept frames' times and the episode is cut to the span the CSV covers; the
pose column is the integrated odometry (starting at the origin). Videos without
a CSV are kept for unconditional training: their odometry is NaN.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from orbis2.config import SPLITS, DataConfig, ImportConfig
from orbis2.data.episodes import EpisodeRecord, RawIndex, write_odometry
from orbis2.data.video import VIDEO_SUFFIXES, VideoError, probe, read_video, resample_stride, write_video
from orbis2.errors import OrbisError
from orbis2.kinematics import integrate_odometry

CSV_COLUMNS = ("timestamp", "speed", "yaw_rate")


class ImportProblem(OrbisError):
    """One input video (or its CSV) cannot be imported."""


@dataclass(frozen=True)
class Skipped:
    path: str
    problem: str


def find_videos(folder: Path) -> list[tuple[str, Path]]:
    """(split, video) pairs: split sub-folders if any, else everything is ``train``."""
    if not folder.is_dir():
        raise ImportProblem(f"{folder}: no such folder; put your videos there or set import.videos in params.yaml")
    split_dirs = [folder / s for s in SPLITS if (folder / s).is_dir()]
    pairs = []
    for split_dir in split_dirs or [folder]:
        split = split_dir.name if split_dirs else "train"
        pairs += [(split, p) for p in sorted(split_dir.iterdir()) if p.suffix.lower() in VIDEO_SUFFIXES]
    if not pairs:
        raise ImportProblem(f"{folder}: no video files ({', '.join(VIDEO_SUFFIXES)}) found")
    return pairs


def read_odometry_csv(path: Path) -> dict[str, np.ndarray]:
    try:
        with open(path, newline="") as handle:
            reader = csv.DictReader(handle)
            header = [h.strip() for h in reader.fieldnames or []]
            missing = [c for c in CSV_COLUMNS if c not in header]
            if missing:
                raise ImportProblem(f"{path}: missing column(s) {missing}; expected a header with {list(CSV_COLUMNS)}")
            rows = [{k.strip(): v for k, v in row.items()} for row in reader]
        values = {c: np.array([float(r[c]) for r in rows], np.float64) for c in CSV_COLUMNS}
    except (OSError, UnicodeDecodeError) as err:
        raise ImportProblem(f"{path}: cannot read ({err})") from err
    except (ValueError, TypeError) as err:
        raise ImportProblem(f"{path}: a value is not a number ({err})") from err
    if len(values["timestamp"]) < 2:
        raise ImportProblem(f"{path}: needs at least two rows")
    if np.any(np.diff(values["timestamp"]) <= 0):
        bad = int(np.argmax(np.diff(values["timestamp"]) <= 0)) + 2
        raise ImportProblem(f"{path}: timestamps must be strictly increasing (data row {bad} is not)")
    if not all(np.isfinite(v).all() for v in values.values()):
        raise ImportProblem(f"{path}: contains NaN or infinite values")
    return values


def import_one(video: Path, split: str, stem: str, root: Path, data: DataConfig, cfg: ImportConfig) -> EpisodeRecord:
    info = probe(video)
    stride = resample_stride(info.fps, data.fps, cfg.fps_tolerance, video)
    frames = read_video(video, stride, (data.width, data.height))
    expected = info.frames // stride
    if expected and len(frames) < 0.9 * expected:
        raise VideoError(f"{video}: truncated: the container announces {info.frames} frames but only "
                         f"{len(frames) * stride} could be decoded; re-encode or replace the file")
    csv_path = video.with_suffix(".csv")
    speed = yaw_rate = None
    if csv_path.exists():
        odo = read_odometry_csv(csv_path)
        t = np.arange(len(frames)) / data.fps
        covered = t <= odo["timestamp"][-1] + 1e-9
        if t[0] < odo["timestamp"][0] - 1e-9:
            raise ImportProblem(f"{csv_path}: starts at {odo['timestamp'][0]:.3f} s but the video starts at 0 s")
        frames, t = frames[covered], t[covered]
        speed = np.interp(t, odo["timestamp"], odo["speed"])
        yaw_rate = np.interp(t, odo["timestamp"], odo["yaw_rate"])
    if len(frames) < data.window_span_frames:
        raise ImportProblem(f"{video}: {len(frames)} frames at {data.fps} fps (after resampling"
                            f"{' and cutting to the odometry' if speed is not None else ''}) is shorter than one "
                            f"training window ({data.window_span_frames} frames)")
    folder = root / split
    folder.mkdir(parents=True, exist_ok=True)
    write_video(folder / f"{stem}.mp4", frames, data.fps)
    nan = np.full(len(frames), np.nan)
    pose = integrate_odometry(speed, yaw_rate, data.fps) if speed is not None else None
    write_odometry(folder / f"{stem}.parquet", data.fps, nan if speed is None else speed,
                   nan if yaw_rate is None else yaw_rate, pose)
    return EpisodeRecord(split, stem, len(frames), has_odometry=speed is not None, has_pose=speed is not None,
                         origin=str(video))


def import_videos(folder: Path, root: Path, data: DataConfig, cfg: ImportConfig,
                  skip_bad: bool) -> tuple[RawIndex, list[Skipped]]:
    """Import every video; stop at the first bad one unless ``skip_bad`` (then list what was skipped)."""
    records, skipped = [], []
    counters: dict[str, int] = {}
    for split, video in tqdm(find_videos(folder), desc="import: videos", unit="video"):
        stem = f"import_{split}_{counters.get(split, 0):05d}"
        try:
            records.append(import_one(video, split, stem, root, data, cfg))
            counters[split] = counters.get(split, 0) + 1
        except OrbisError as err:
            if not skip_bad:
                raise
            for leftover in (root / split).glob(f"{stem}.*"):
                leftover.unlink()
            skipped.append(Skipped(str(video), str(err)))
    if not records:
        problems = "\n".join(f"  {s.path}: {s.problem}" for s in skipped)
        raise ImportProblem(f"{folder}: every video was skipped:\n{problems}")
    index = RawIndex("import", data.fps, data.width, data.height, None, records)
    index.write(root)
    return index, skipped
