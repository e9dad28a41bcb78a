"""BDD100K: the driving videos with their GPS/IMU info files -> the import layout.

The published layout: ``bdd100k/videos/{train,val}/<name>.mov`` (40 s, 30 fps; the older
archive unpacks to ``videos/100k/{train,val}/``, both are searched) and one info file per
video, ``bdd100k/info/100k/{train,val}/<name>.json``, with ``startTime`` (ms since the
epoch, the first frame) and ``locations``: the phone's fused fixes at 1 Hz, each
``timestamp`` (ms), ``latitude``, ``longitude``, ``speed`` (m/s, negative when unknown)
and ``course`` (degrees clockwise from north, negative when unknown); ``gyro`` and
``accelerometer`` are the raw phone streams (``timestamp``, ``x``, ``y``, ``z``; rad/s and
m/s^2, about 50 Hz, in the phone's own axes).

Speed is the fixes' ``speed``. The yaw rate comes from the gyro where the file has one: the
rotation rate about the vertical, which is the mean accelerometer direction (the phone is
fixed to the car, so this works however it is mounted), its sign chosen to agree with the
course's turning (phones differ in whether the accelerometer reads gravity as + or -). The
1 Hz course is a poor substitute at low speed, where its direction is noise (it swings far
beyond what the gyro measures); it is used only without a gyro (rate of change, unwrapped,
sign flipped to counter-clockwise positive). Fixes with unknown speed or course are dropped.

The first fix often comes a few seconds after the first frame; up to ``max_fix_delay``
seconds are bridged by holding the first fix's speed back to the first frame (the yaw rate
comes from the gyro, which runs from the start, where there is one), and the bridged span is
recorded in the report. A later first fix, or a missing info file (unless
``allow_missing_info``: then linked without a CSV), skips the video. Videos are linked, not
copied.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from orbis2.data.datasets import DatasetError, Item, Report, convert_items, reader_key, write_odometry_csv

SPLITS = ("train", "val")
VIDEO_SUFFIXES = (".mov", ".mp4")
MAX_FIX_DELAY = 5.0  # seconds of a late first fix bridged by default (3.3 s seen in published samples)
MIN_GYRO_SAMPLES = 10


def video_folders(root: Path, split: str) -> list[Path]:
    """``videos/<split>/`` and the older archive's ``videos/100k/<split>/``, those that exist."""
    return [f for f in (root / "videos" / split, root / "videos" / "100k" / split) if f.is_dir()]


def info_path(root: Path, split: str, stem: str) -> Path:
    """The info file of a video: ``info/100k/<split>/`` as published, or ``info/<split>/``."""
    for folder in (root / "info" / "100k" / split, root / "info" / split):
        if (folder / f"{stem}.json").is_file():
            return folder / f"{stem}.json"
    return root / "info" / "100k" / split / f"{stem}.json"


def course_motion(path: Path, info: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(seconds from the first frame, speed, yaw rate from the course) at the usable fixes."""
    fixes = [f for f in info["locations"] if f.get("speed", -1) >= 0 and f.get("course", -1) >= 0]
    t = np.array([f["timestamp"] for f in fixes], np.float64)
    keep = np.concatenate([[True], np.diff(t) > 0]) if len(t) else np.array([], bool)
    if keep.sum() < 3:
        raise DatasetError(f"{path}: {int(keep.sum())} usable location fixes (speed and course known); the video "
                           f"has no odometry, leave it out or import it without a CSV", reason="no usable fixes")
    t = (t[keep] - float(info["startTime"])) / 1000.0
    speed = np.array([f["speed"] for f in fixes], np.float64)[keep]
    heading = -np.unwrap(np.radians([f["course"] for f in fixes]))[keep]
    return t, speed, np.gradient(heading, t, edge_order=2)


def stream(info: dict, name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(seconds from the first frame, [N, 3] x, y, z) of a raw sensor stream, None when absent or too short."""
    samples = [s for s in info.get(name) or [] if all(k in s for k in ("timestamp", "x", "y", "z"))]
    if len(samples) < MIN_GYRO_SAMPLES:
        return None
    t = (np.array([s["timestamp"] for s in samples], np.float64) - float(info["startTime"])) / 1000.0
    xyz = np.array([[s["x"], s["y"], s["z"]] for s in samples], np.float64)
    order = np.argsort(t, kind="stable")
    t, xyz = t[order], xyz[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    return t[keep], xyz[keep]


def gyro_yaw_rate(info: dict, t_fix: np.ndarray, course_rate: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(times, yaw rate) about the vertical from the gyro, or None without gyro and accelerometer."""
    gyro, accel = stream(info, "gyro"), stream(info, "accelerometer")
    if gyro is None or accel is None:
        return None
    up = accel[1].mean(axis=0)
    if np.linalg.norm(up) < 1e-6:
        return None
    yaw_rate = gyro[1] @ (up / np.linalg.norm(up))
    agreement = float(np.dot(yaw_rate, np.interp(gyro[0], t_fix, course_rate)))
    return gyro[0], yaw_rate if agreement >= 0 else -yaw_rate


def odometry(path: Path, max_fix_delay: float = MAX_FIX_DELAY) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """(seconds from the first frame, speed, yaw rate, details for the report) of one info file."""
    try:
        info = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise DatasetError(f"{path}: not a readable JSON info file ({err}); download the info archive again",
                           reason="unreadable info file") from err
    if "startTime" not in info or "locations" not in info:
        raise DatasetError(f"{path}: lacks startTime or locations; use the info files of the 100K release",
                           reason="unreadable info file")
    t, speed, course_rate = course_motion(path, info)
    first = float(t[t >= 0][0]) if (t >= 0).any() else float("nan")
    if not first <= max_fix_delay:
        raise DatasetError(f"{path}: the first location fix is {first:.2f} s after the first frame (at most "
                           f"{max_fix_delay:g} s are bridged, --max-fix-delay); leave the video out or import it "
                           f"without a CSV", reason="late first fix")
    gyro = gyro_yaw_rate(info, t, course_rate)
    if gyro is not None:  # the CSV on the gyro's clock, speed interpolated from the fixes (held before the first)
        inside = (gyro[0] >= 0) & (gyro[0] <= t[-1])
        t_out, yaw_rate = gyro[0][inside], gyro[1][inside]
        if len(t_out) >= 2 and t_out[0] > 0:
            t_out, yaw_rate = np.concatenate([[0.0], t_out]), np.concatenate([[yaw_rate[0]], yaw_rate])
        speed_out = np.interp(t_out, t, speed)
    else:  # fixes from the first frame on, the first held back to 0 s
        inside = t >= 0
        t_out, speed_out, yaw_rate = t[inside], speed[inside], course_rate[inside]
        if t_out[0] > 0:
            t_out, speed_out, yaw_rate = (np.concatenate([[v0], v]) for v0, v in
                                          ((0.0, t_out), (speed_out[0], speed_out), (yaw_rate[0], yaw_rate)))
    if len(t_out) < 2:
        raise DatasetError(f"{path}: fewer than 2 odometry samples after the first frame; leave the video out or "
                           f"import it without a CSV", reason="no usable fixes")
    details = {"bridged_s": round(first, 3), "yaw_rate_from": "gyro" if gyro is not None else "course"}
    return t_out, speed_out, yaw_rate, details


def convert(root: Path, out: Path, allow_missing_info: bool = False, max_fix_delay: float = MAX_FIX_DELAY,
            strict: bool = False, parts: int = 1, part: int | None = None) -> Report:
    """Link every video of ``videos/{train,val}`` (or ``videos/100k/{train,val}``) into ``out/<split>/`` with its
    odometry CSV; a video without a usable info file is skipped and reported (``allow_missing_info``: linked
    without a CSV when the file is missing). One item per video, in parts
    (:func:`orbis2.data.datasets.convert_items`)."""
    videos = [(split, video) for split in SPLITS for folder in video_folders(root, split)
              for video in sorted(folder.iterdir()) if video.suffix.lower() in VIDEO_SUFFIXES]
    if not videos:
        raise DatasetError(f"{root / 'videos'}: no .mov video in train/ or val/ (nor 100k/train/, 100k/val/); pass "
                           f"the bdd100k folder holding videos/ and info/")
    items = [Item(f"{split}/{video.name}", (video, info_path(root, split, video.stem)),
                  lambda report, split=split, video=video: convert_video(root, out, split, video, allow_missing_info,
                                                                         max_fix_delay, report))
             for split, video in videos]
    key = reader_key(__file__, root=root, allow_missing_info=allow_missing_info, max_fix_delay=max_fix_delay,
                     strict=strict)
    return convert_items(Report("bdd100k", out, strict), items, key, parts, part)


def convert_video(root: Path, out: Path, split: str, video: Path, allow_missing_info: bool, max_fix_delay: float,
                  report: Report) -> None:
    """Link one video into ``out/<split>/`` with its odometry CSV, or report why it was left out."""
    info = info_path(root, split, video.stem)
    target = out / split / video.name
    details: dict = {}
    try:
        if info.is_file():
            t, speed, yaw_rate, details = odometry(info, max_fix_delay)
            write_odometry_csv(target.with_suffix(".csv"), t, speed, yaw_rate)
        elif not allow_missing_info:
            raise DatasetError(f"{info}: missing for {video}; download the info archive (bdd100k_info) or pass "
                               f"--allow-missing-info to import such videos without odometry",
                               reason="no info file")
    except DatasetError as err:
        report.skip(str(video), err)
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    target.unlink(missing_ok=True)
    os.symlink(video.resolve(), target)
    report.add(target, split=split, **details)
