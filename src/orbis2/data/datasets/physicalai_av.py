"""PhysicalAI-Autonomous-Vehicles: the front camera and the ego-motion labels -> the import layout.

The dataset is published in chunks: per feature one zip per chunk, its path given by the
``chunk_path`` template in the root's ``features.csv`` (e.g.
``camera/camera_front_wide_120fov/camera_front_wide_120fov.chunk_{chunk_id:04d}.zip``) and
its members per clip by the ``clip_files_in_zip`` JSON templates there (the camera's
``video`` mp4 and ``frame_timestamps`` Parquet with a ``timestamp`` column in
microseconds; the ``egomotion`` Parquet with ``timestamp``, ``x``, ``y``, ``qx``, ``qy``,
``qz``, ``qw``). ``clip_index.parquet`` (index ``clip_id``) gives each clip's ``chunk``, its
``split`` (``train``, ``val``, ``test``) and ``clip_is_valid``, which users of the dataset
filter on. These are the files the dataset's own interface (``physical_ai_av``) reads; this
reader uses the same templates, so a partial download (some chunks) converts the clips it holds.

Clips go to the import split named by their ``split`` (``test`` to ``heldout``, the import's
split for data no model trains on) unless ``split`` is given, which puts every clip there;
invalid clips are skipped and reported unless ``include_invalid``. A clip whose members are
missing, or whose ego motion does not cover its frames, is skipped and reported; a chunk whose egomotion
zip is missing is reported once, for all its clips. Each clip is an item of the conversion in parts, so a
part killed in the middle of a chunk converts again only the clip it was on.

The paper fine-tunes on the dataset's IMU-derived ego motion; the egomotion table is that
motion, and speed and yaw rate are derived from its poses as for every dataset here.
Videos are copied as published (their native rate); CSV times are seconds from a clip's
first frame.
"""

from __future__ import annotations

import io
import json
import zipfile
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd

from orbis2.data.datasets import (
    DatasetError,
    Item,
    Report,
    convert_items,
    motion_from_poses,
    reader_key,
    write_odometry_csv,
    yaw_of_quaternion,
)
from orbis2.io import atomic_file

CAMERA = "camera_front_wide_120fov"
EGOMOTION = "egomotion"
# The dataset's splits -> the import's split folders (the import has no `test`; `heldout` is its unseen data).
SPLITS = {"train": "train", "val": "val", "test": "heldout"}


def read_features(root: Path) -> pd.DataFrame:
    path = root / "features.csv"
    if not path.is_file():
        raise DatasetError(f"{path}: missing; download features.csv and clip_index.parquet from the dataset's root "
                           f"with the chunks")
    features = pd.read_csv(path, index_col="feature")
    missing = {"chunk_path", "clip_files_in_zip"} - set(features.columns)
    if missing:
        raise DatasetError(f"{path}: lacks column(s) {sorted(missing)}; download the current features.csv")
    return features


def templates(features: pd.DataFrame, feature: str, root: Path) -> tuple[str, dict[str, str]]:
    if feature not in features.index:
        raise DatasetError(f"{root / 'features.csv'}: lists no feature {feature!r}; pass one of "
                           f"{sorted(features.index)}")
    return features.at[feature, "chunk_path"], json.loads(features.at[feature, "clip_files_in_zip"])


def read_parquet(archive: zipfile.ZipFile, member: str, zip_path: Path, columns: list[str]) -> pd.DataFrame:
    try:
        table = pd.read_parquet(io.BytesIO(archive.read(member)))
    except KeyError:
        raise DatasetError(f"{zip_path}: has no member {member}; the chunk is incomplete, download it "
                           f"again", reason="incomplete chunk") from None
    if set(columns) - set(table.columns):
        raise DatasetError(f"{zip_path}: {member} lacks column(s) {sorted(set(columns) - set(table.columns))}",
                           reason="incomplete chunk")
    return table


def read_index(root: Path, split: str | None) -> pd.DataFrame:
    """``clip_index.parquet``, checked for the columns this run needs."""
    path = root / "clip_index.parquet"
    if not path.is_file():
        raise DatasetError(f"{path}: missing; download clip_index.parquet from the dataset's root")
    index = pd.read_parquet(path)
    needed = {"chunk"} | ({"split"} if split is None else set())
    if needed - set(index.columns):
        raise DatasetError(f"{path}: lacks column(s) {sorted(needed - set(index.columns))}; download the current "
                           f"clip_index.parquet (without a split column: pass --split NAME to put every clip into "
                           f"one import split)")
    unknown = set(index["split"]) - set(SPLITS) if split is None else set()
    if unknown:
        raise DatasetError(f"{path}: split value(s) {sorted(unknown)} are not {sorted(SPLITS)}; pass --split NAME to "
                           f"put every clip into one import split")
    return index


def convert_clip(clip_id: str, cams: zipfile.ZipFile, egos: zipfile.ZipFile, cam_zip: Path, ego_zip: Path,
                 cam_files: dict[str, str], ego_member: str, folder: Path) -> Path:
    """One clip's mp4 (copied) and odometry CSV (its ego motion at the frame timestamps)."""
    names = {k: v.format(clip_id=clip_id) for k, v in cam_files.items()}
    frame_t = read_parquet(cams, names["frame_timestamps"], cam_zip, ["timestamp"])["timestamp"]
    ego = read_parquet(egos, ego_member.format(clip_id=clip_id), ego_zip,
                       ["timestamp", "x", "y", "qx", "qy", "qz", "qw"]).sort_values("timestamp")
    t_pose = ego["timestamp"].to_numpy(np.float64) / 1e6
    try:
        speed, yaw_rate = motion_from_poses(t_pose, ego["x"], ego["y"],
                                            yaw_of_quaternion(ego["qw"], ego["qx"], ego["qy"], ego["qz"]))
    except ValueError as err:
        raise DatasetError(f"{ego_zip}: the ego motion of clip {clip_id}: {err}; the chunk is incomplete, download "
                           f"it again", reason="incomplete chunk") from None
    t = frame_t.to_numpy(np.float64) / 1e6
    covered = (t >= t_pose[0]) & (t <= t_pose[-1])
    if not covered[0] or covered.sum() < 2:
        raise DatasetError(f"{ego_zip}: the ego motion of clip {clip_id} does not cover its first frames; the chunk "
                           f"is incomplete, download it again", reason="ego motion does not cover the frames")
    video = folder / f"{clip_id}.mp4"
    with atomic_file(video) as tmp:
        try:
            tmp.write_bytes(cams.read(names["video"]))
        except KeyError:
            raise DatasetError(f"{cam_zip}: has no member {names['video']}; the chunk is incomplete, download it "
                               f"again", reason="incomplete chunk") from None
    write_odometry_csv(folder / f"{clip_id}.csv", t[covered] - t[0], np.interp(t[covered], t_pose, speed),
                       np.interp(t[covered], t_pose, yaw_rate))
    return video


def convert(root: Path, out: Path, split: str | None = None, camera: str = CAMERA, include_invalid: bool = False,
            strict: bool = False, parts: int = 1, part: int | None = None) -> Report:
    """Convert every clip whose camera and egomotion chunks are present, in parts
    (:func:`orbis2.data.datasets.convert_items`).

    One item per clip of a downloaded chunk (chunks in order, clips in the index's order within a chunk), named
    by its ``clip_id`` and made from its chunk's two zip files and the index: a part killed mid-chunk converts
    again only the clip it was on, and every clip of a chunk whose zip changed is converted again. A clip opens
    its chunk's zips itself (reading their central directories, a small cost beside copying its mp4), so no
    clip's work depends on another's. What goes wrong with a whole chunk (its egomotion zip missing) is reported
    once, as ``chunk N (K clips)``, by the chunk's first clip; its other clips report nothing."""
    features = read_features(root)
    index = read_index(root, split)
    cam_path, cam_files = templates(features, camera, root)
    ego_path, ego_files = templates(features, EGOMOTION, root)
    report = Report("physicalai-av", out, strict)
    chunks = sorted(set(int(c) for c in index["chunk"]))
    present = [c for c in chunks if (root / cam_path.format(chunk_id=c)).is_file()]
    if not present:
        raise DatasetError(f"{root / cam_path.format(chunk_id=chunks[0])}: no {camera} chunk is present; download "
                           f"at least one chunk of {camera} and of {EGOMOTION}")
    absent = int(index["chunk"].isin(set(chunks) - set(present)).sum())
    if absent:
        report.notes["clips in chunks not downloaded"] = absent
    valid = index["clip_is_valid"].astype(bool) if "clip_is_valid" in index.columns else pd.Series(True, index.index)

    def convert_one(clip_id: str, chunk: int, clips: int, first: bool, report: Report) -> None:
        cam_zip, ego_zip = root / cam_path.format(chunk_id=chunk), root / ego_path.format(chunk_id=chunk)
        if not ego_zip.is_file():
            if first or strict:  # the chunk's skip, once; under strict whichever clip a part starts at stops it
                report.skip(f"chunk {chunk} ({clips} clips)", DatasetError(
                    f"{ego_zip}: missing, but {cam_zip} is present; download the {EGOMOTION} chunk {chunk} too",
                    reason="egomotion chunk missing"))
            return
        if not valid[clip_id] and not include_invalid:
            report.skip(clip_id, DatasetError(
                f"{root / 'clip_index.parquet'}: clip {clip_id} has clip_is_valid false; pass "
                f"--include-invalid to convert such clips too", reason="clip_is_valid false"))
            return
        target = split or SPLITS[index.at[clip_id, "split"]]
        try:
            with zipfile.ZipFile(cam_zip) as cams, zipfile.ZipFile(ego_zip) as egos:
                video = convert_clip(clip_id, cams, egos, cam_zip, ego_zip, cam_files, ego_files[EGOMOTION],
                                     out / target)
        except DatasetError as err:
            report.skip(clip_id, err)
            return
        report.add(video, split=target, clip_is_valid=bool(valid[clip_id]))

    in_chunk: dict[int, list] = {chunk: [] for chunk in present}  # each chunk's clips, in the index's order
    for clip_id, chunk in zip(index.index, index["chunk"]):
        in_chunk.get(int(chunk), []).append(clip_id)
    items = []
    for chunk, clips in in_chunk.items():
        sources = (root / cam_path.format(chunk_id=chunk), root / ego_path.format(chunk_id=chunk),
                   root / "clip_index.parquet")
        items += [Item(str(clip_id), sources, partial(convert_one, clip_id, chunk, len(clips), i == 0))
                  for i, clip_id in enumerate(clips)]
    key = reader_key(__file__, root=root, split=split, camera=camera, include_invalid=include_invalid, strict=strict)
    return convert_items(report, items, key, parts, part)
