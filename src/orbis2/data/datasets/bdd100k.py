"""BDD100K: the driving videos with their GPS/IMU info files -> the import layout.

The published layout: ``bdd100k/videos/{train,val}/<name>.mov`` (40 s, 30 fps) and one
info file per video, ``bdd100k/info/100k/{train,val}/<name>.json``, with ``startTime``
(ms since the epoch, the first frame) and ``locations``: the phone's fused fixes at 1 Hz,
each ``timestamp`` (ms), ``latitude``, ``longitude``, ``speed`` (m/s, negative when
unknown) and ``course`` (degrees clockwise from north, negative when unknown); ``gps``,
``gyro`` and ``accelerometer`` are the raw streams. Speed is the fixes' ``speed``; the
yaw rate is the rate of change of ``course`` (unwrapped, sign flipped to counter-clockwise
positive). Fixes with unknown speed or course are dropped; the first fix after the first
frame is held back to it (the import needs odometry from 0 s). Videos are linked, not copied.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from orbis2.data.datasets import DatasetError, write_odometry_csv

SPLITS = ("train", "val")


def info_path(root: Path, split: str, stem: str) -> Path:
    """The info file of a video: ``info/100k/<split>/`` as published, or ``info/<split>/``."""
    for folder in (root / "info" / "100k" / split, root / "info" / split):
        if (folder / f"{stem}.json").is_file():
            return folder / f"{stem}.json"
    return root / "info" / "100k" / split / f"{stem}.json"


def odometry(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(seconds from the first frame, speed, yaw rate) of one info file."""
    try:
        info = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise DatasetError(f"{path}: not a readable JSON info file ({err}); download the info archive again") from err
    if "startTime" not in info or "locations" not in info:
        raise DatasetError(f"{path}: lacks startTime or locations; use the info files of the 100K release")
    fixes = [f for f in info["locations"] if f.get("speed", -1) >= 0 and f.get("course", -1) >= 0]
    t = np.array([f["timestamp"] for f in fixes], np.float64)
    keep = np.concatenate([[True], np.diff(t) > 0]) if len(t) else np.array([], bool)
    if keep.sum() < 3:
        raise DatasetError(f"{path}: {int(keep.sum())} usable location fixes (speed and course known); the video "
                           f"has no odometry, leave it out or import it without a CSV")
    t = (t[keep] - float(info["startTime"])) / 1000.0
    speed = np.array([f["speed"] for f in fixes], np.float64)[keep]
    heading = -np.unwrap(np.radians([f["course"] for f in fixes]))[keep]
    return t, speed, np.gradient(heading, t, edge_order=2)


def from_first_frame(path: Path, t: np.ndarray, speed: np.ndarray, yaw_rate: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drop fixes from before the first frame; the first fix after it is held back to 0 s (the import needs
    odometry from the first frame on), which the 1-Hz fixes allow for at most one period."""
    inside = t >= 0
    t, speed, yaw_rate = t[inside], speed[inside], yaw_rate[inside]
    if len(t) < 2 or t[0] > 1.0:
        raise DatasetError(f"{path}: the first location fix is {t[0] if len(t) else float('nan'):.2f} s after the "
                           f"first frame (at most 1 s can be bridged); leave the video out or import it without a CSV")
    if t[0] > 0:
        t, speed, yaw_rate = (np.concatenate([[v0], v]) for v0, v in ((0.0, t), (speed[0], speed),
                                                                       (yaw_rate[0], yaw_rate)))
    return t, speed, yaw_rate


def convert(root: Path, out: Path, allow_missing_info: bool = False) -> list[Path]:
    """Link every video of ``videos/{train,val}`` into ``out/<split>/`` with its odometry CSV.

    A video without an info file stops the conversion, unless ``allow_missing_info`` (then
    it is linked without a CSV and trains unconditionally).
    """
    written = []
    for split in SPLITS:
        folder = root / "videos" / split
        if not folder.is_dir():
            continue
        for video in sorted(folder.glob("*.mov")):
            info = info_path(root, split, video.stem)
            target = out / split / video.name
            if info.is_file():
                t, speed, yaw_rate = odometry(info)
                t, speed, yaw_rate = from_first_frame(info, t, speed, yaw_rate)
                write_odometry_csv(out / split / f"{video.stem}.csv", t, speed, yaw_rate)
            elif not allow_missing_info:
                raise DatasetError(f"{info}: missing for {video}; download the info archive (bdd100k_info) or pass "
                                   f"--allow-missing-info to import such videos without odometry")
            target.parent.mkdir(parents=True, exist_ok=True)
            target.unlink(missing_ok=True)
            os.symlink(video.resolve(), target)
            written.append(target)
    if not written:
        raise DatasetError(f"{root / 'videos'}: no .mov video in train/ or val/; pass the bdd100k folder holding "
                           f"videos/ and info/")
    return written
