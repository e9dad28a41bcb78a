"""nuPlan: the front camera and the ego poses of each log database -> the import layout.

nuPlan ships one SQLite database per log (``nuplan-v1.1/splits/<split>/<log>.db``) and
the camera frames as JPEGs under ``nuplan-v1.1/sensor_blobs/<log>/CAM_F0/``. The tables
read here follow the devkit's schema (docs/nuplan_schema.md): ``camera`` (``token``,
``channel``: ``CAM_F0`` is the front camera), ``image`` (``camera_token``,
``filename_jpg`` relative to the sensor-blob root, ``timestamp`` in microseconds) and
``ego_pose`` (``timestamp`` in microseconds, global ``x``, ``y`` and quaternion
``qw, qx, qy, qz``). Speed and yaw rate come from the poses, which nuPlan logs at about
100 Hz, and are interpolated at the image times (``lidar_pc``, the point clouds, is not
needed for this).

Camera blobs exist for about a tenth of the logs and ship as separate archives, which users
unpack into separate folders: every ``--sensor-root`` given is searched for a log's
``<log>/<channel>/`` folder. A log whose database lists no images of the channel, or whose
images are in none of the roots (not downloaded), is skipped and reported, and so is a clip
with an image missing; the other logs convert.

Each run of consecutive front images (a gap over 1.5 frame periods ends a run) is cut into
``clip_seconds`` clips. ``turns_deg`` keeps only clips whose heading changes by at least
that many degrees: our stand-in for the paper's nuPlan-turns, whose selection rule the
paper does not give (it cites its source benchmark).
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

import cv2
import numpy as np

from orbis2.data.datasets import (
    DatasetError,
    Item,
    Report,
    convert_items,
    heading_change_deg,
    motion_from_poses,
    native_rate,
    reader_key,
    write_odometry_csv,
    yaw_of_quaternion,
)
from orbis2.data.video import write_video
from orbis2.io import atomic_file

TABLES = {"camera": {"token", "channel"}, "image": {"camera_token", "filename_jpg", "timestamp"},
          "ego_pose": {"timestamp", "x", "y", "qw", "qx", "qy", "qz"}}


def check_schema(con: sqlite3.Connection, db: Path) -> None:
    for table, columns in TABLES.items():
        present = {row[1] for row in con.execute(f"PRAGMA table_info({table})")}
        if not present:
            raise DatasetError(f"{db}: has no table {table!r}, so it is not a nuPlan log database; pass the .db files "
                               f"of nuplan-v1.1/splits/<split>/", reason="not a log database")
        if columns - present:
            raise DatasetError(f"{db}: table {table} lacks column(s) {sorted(columns - present)}; use the nuPlan v1.1 "
                               f"log databases", reason="not a log database")


def read_log(db: Path, channel: str) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """(image files, image times s, speed, yaw rate at the image times) of one log, times from its first image."""
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
        check_schema(con, db)
    except sqlite3.DatabaseError as err:
        raise DatasetError(f"{db}: not a readable SQLite database ({err}); download the log again",
                           reason="unreadable log") from err
    with con:
        images = con.execute("SELECT image.filename_jpg, image.timestamp FROM image JOIN camera "
                             "ON image.camera_token = camera.token WHERE camera.channel = ? "
                             "ORDER BY image.timestamp", (channel,)).fetchall()
        poses = np.array(con.execute("SELECT timestamp, x, y, qw, qx, qy, qz FROM ego_pose ORDER BY timestamp")
                         .fetchall(), np.float64)
    con.close()
    if len(images) < 2:
        raise DatasetError(f"{db}: its table image lists {len(images)} {channel} image(s): a log without camera "
                           f"data (most logs have none); nothing to do, or pick another --channel",
                           reason="no images in the log")
    if len(poses) < 3:
        raise DatasetError(f"{db}: table ego_pose holds {len(poses)} rows; the log is incomplete, download it again",
                           reason="unreadable log")
    t_img = np.array([ts for _, ts in images], np.float64) / 1e6
    t_pose = poses[:, 0] / 1e6
    keep = np.concatenate([[True], np.diff(t_pose) > 0])
    speed, yaw_rate = motion_from_poses(t_pose[keep], poses[keep, 1], poses[keep, 2],
                                        yaw_of_quaternion(*poses[keep, 3:7].T))
    inside = (t_img >= t_pose[0]) & (t_img <= t_pose[-1])
    if not inside.any():
        raise DatasetError(f"{db}: no {channel} image lies within the span of its ego poses; the log is incomplete",
                           reason="unreadable log")
    files = [name for (name, _), ok in zip(images, inside) if ok]
    t_img = t_img[inside]
    return (files, t_img, np.interp(t_img, t_pose[keep], speed), np.interp(t_img, t_pose[keep], yaw_rate))


def clips_of(t: np.ndarray, fps: float, clip_seconds: float) -> list[slice]:
    """Consecutive runs of frames (a gap over 1.5 periods ends one), cut into ``clip_seconds`` clips; a shorter
    piece is kept when it lasts half a clip or 5 s, whichever is less."""
    breaks = np.flatnonzero(np.diff(t) > 1.5 / fps) + 1
    length = max(2, round(clip_seconds * fps))
    shortest = max(2, min(length // 2, round(5 * fps)))
    clips = []
    for start, stop in zip(np.concatenate([[0], breaks]), np.concatenate([breaks, [len(t)]])):
        for a in range(start, stop, length):
            b = min(a + length, stop)
            if b - a >= shortest:
                clips.append(slice(int(a), int(b)))
    return clips


def blob_root(files: list[str], roots: list[Path], db: Path, channel: str) -> Path:
    """The sensor root holding this log's images (the first that has its ``<log>/<channel>/`` folder)."""
    for root in roots:
        if (root / files[0]).parent.is_dir():
            return root
    raise DatasetError(f"{db}: none of its {len(files)} {channel} images ({files[0]}, ...) is under "
                       f"{', '.join(str(r) for r in roots)}: the log's camera archive is not downloaded; download it "
                       f"and pass the folder it unpacks to with --sensor-root (several may be given)",
                       reason="images not downloaded")


def read_clip(paths: list[Path], db: Path) -> list[np.ndarray]:
    frames = []
    for path in paths:
        image = cv2.imread(str(path))
        if image is None:
            raise DatasetError(f"{path}: missing or unreadable, listed in {db} (table image); download the camera "
                               f"archive holding log {db.stem} again", reason="missing images")
        frames.append(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
    return frames


def convert(databases: Path, sensor_roots: list[Path], out: Path, split: str, channel: str = "CAM_F0",
            clip_seconds: float = 20.0, turns_deg: float | None = None, strict: bool = False, parts: int = 1,
            part: int | None = None) -> Report:
    """Convert every log database in ``databases`` (a .db file or a folder of them) whose images are present. One
    item per log, in parts (:func:`orbis2.data.datasets.convert_items`)."""
    dbs = [databases] if databases.is_file() else sorted(databases.glob("*.db")) if databases.is_dir() else []
    if not dbs:
        raise DatasetError(f"{databases}: no nuPlan log database (*.db); pass nuplan-v1.1/splits/<split>/ or one .db")
    for root in sensor_roots:
        if not root.is_dir():
            raise DatasetError(f"{root}: no such folder; pass the sensor-blob root (nuplan-v1.1/sensor_blobs)")
    items = [Item(db.name, (db,), lambda report, db=db: convert_log(db, sensor_roots, out, split, channel,
                                                                    clip_seconds, turns_deg, report))
             for db in dbs]
    key = reader_key(__file__, databases=databases, sensor_roots=sensor_roots, split=split, channel=channel,
                     clip_seconds=clip_seconds, turns_deg=turns_deg, strict=strict)
    return convert_items(Report("nuplan", out, strict), items, key, parts, part)


def convert_log(db: Path, sensor_roots: list[Path], out: Path, split: str, channel: str, clip_seconds: float,
                turns_deg: float | None, report: Report) -> None:
    """Convert the clips of one log into ``report``: each written, or why it (or the whole log) was left out."""
    try:
        files, t, speed, yaw_rate = read_log(db, channel)
        root = blob_root(files, sensor_roots, db, channel)
        fps = native_rate(t, f"{db} ({channel})")
    except DatasetError as err:
        report.skip(str(db), err)
        return
    for n, clip in enumerate(clips_of(t, fps, clip_seconds)):
        if turns_deg is not None and heading_change_deg(yaw_rate[clip], t[clip]) < turns_deg:
            continue
        stem = f"{db.stem}_{n:03d}"
        try:
            frames = read_clip([root / name for name in files[clip]], db)
        except DatasetError as err:
            report.skip(stem, err)
            continue
        video = out / split / f"{stem}.mp4"
        with atomic_file(video) as tmp:
            write_video(tmp, frames, fps)
        write_odometry_csv(out / split / f"{stem}.csv", t[clip] - t[clip][0], speed[clip], yaw_rate[clip])
        report.add(video, log=db.stem, fps=round(fps, 3))
