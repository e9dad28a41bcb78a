"""Readers that turn the paper's datasets into the ``import`` layout: ``<split>/<name>.<video>`` at the
native frame rate, and ``<split>/<name>.csv`` with ``timestamp, speed, yaw_rate`` (seconds from the
first frame, m/s, rad/s counter-clockwise positive) where the dataset has ego motion.

One module per dataset (``nuplan``, ``physicalai_av``, ``bdd100k``, ``opendv``), each reading the
dataset's published layout with plain readers (SQLite, zip, Parquet, JSON): no devkit at run time.
Speed and yaw rate are derived from poses (positions and headings) where a dataset has them, the
same way for every dataset (:func:`motion_from_poses`). A tree that lacks a file the reader needs
stops the reader with a :class:`DatasetError` naming the file and the fix; each video and CSV is
written atomically, so an interrupted run leaves no half-written file.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from orbis2.errors import OrbisError
from orbis2.io import atomic_file


class DatasetError(OrbisError):
    """A dataset tree lacks what a reader needs; the message names the file and the fix."""


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


def native_rate(timestamps_s: np.ndarray, where: str) -> int:
    """The integer frame rate of a camera's timestamps (median spacing), refused when not near an integer."""
    rate = 1.0 / float(np.median(np.diff(timestamps_s)))
    if abs(rate - round(rate)) > 0.05 * rate or round(rate) < 1:
        raise DatasetError(f"{where}: the frames are {rate:.3f} Hz apart, not an integer rate; the import layout "
                           f"needs a fixed native rate")
    return round(rate)


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
