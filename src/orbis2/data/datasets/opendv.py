"""OpenDV-YouTube: the driving videos without odometry -> the import layout, marked unconditional.

The published layout: the meta file ``meta/OpenDV-YouTube.json`` lists each video with
``videoid``, ``youtuber``, ``split`` (``Train`` / ``Val``), ``start_discard`` and
``end_discard`` (seconds of intro and outro to drop); the download script saves each
video as ``<root>/<youtuber with spaces as _>/<videoid>.{mp4,webm,mkv}``. Each video is
written without its discarded head and tail at its native rate and without a CSV: the
import marks it unconditional (no odometry), for pre-training.

Real downloads: a blank discard cell (empty, null or NaN once the CSV meta is turned into
JSON) drops nothing and is noted in the report; YouTube's AV1 and VP9 webm files are decoded
through PyAV where OpenCV cannot (:mod:`orbis2.data.video`); a container that reports no or a
nonsensical frame count (a webm without a duration) is counted by decoding. A video that is
not downloaded, cannot be decoded or has nothing left after the discards is skipped and
reported; a meta entry that lacks a field or names another split, too.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from orbis2.data.datasets import DatasetError, Item, Report, convert_items, reader_key
from orbis2.data.video import VideoError, count_frames, iter_frames, probe, write_video
from orbis2.io import atomic_file

EXTENSIONS = ("mp4", "webm", "mkv")  # what the download script may save
SPLITS = {"train": "train", "val": "val"}


def video_of(videos: Path, entry: dict) -> Path | None:
    folder = videos / str(entry["youtuber"]).replace(" ", "_")
    return next((folder / f"{entry['videoid']}.{ext}" for ext in EXTENSIONS
                 if (folder / f"{entry['videoid']}.{ext}").is_file()), None)


def read_meta(meta: Path) -> list[dict]:
    try:
        entries = json.loads(meta.read_text())
    except (OSError, ValueError) as err:
        raise DatasetError(f"{meta}: not a readable meta file ({err}); download OpenDV-YouTube.json (or convert "
                           f"the meta CSV with the dataset's meta_preprocess.py)") from err
    if not isinstance(entries, list):
        raise DatasetError(f"{meta}: not a list of video entries; use the published meta file")
    return entries


def check_entry(meta: Path, n: int, entry: dict) -> None:
    missing = {"videoid", "youtuber", "split"} - set(entry)
    if missing:
        raise DatasetError(f"{meta}: entry {n} lacks {sorted(missing)}; use the published meta file",
                           reason="bad meta entry")
    if str(entry["split"]).lower() not in SPLITS:
        raise DatasetError(f"{meta}: entry {n} has split {entry['split']!r}, expected Train or Val",
                           reason="bad meta entry")


def seconds(value) -> float | None:
    """A discard cell in seconds; None when blank (empty, null or NaN)."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    number = float(value)
    return None if math.isnan(number) else number


def convert_video(path: Path, entry: dict, target: Path) -> dict:
    """Write one video without its discarded ends; returns the report's details."""
    info = probe(path)
    cells = {key: seconds(entry.get(key)) for key in ("start_discard", "end_discard")}
    start = round((cells["start_discard"] or 0.0) * info.fps)
    total = info.frames or count_frames(path)
    stop = total - round((cells["end_discard"] or 0.0) * info.fps)
    with atomic_file(target) as tmp:
        frames = (f for i, f in enumerate(iter_frames(path)) if start <= i < stop)
        if write_video(tmp, frames, info.fps) == 0:
            raise DatasetError(f"{path}: nothing is left of its {total} frames after dropping "
                               f"{entry.get('start_discard')} s and {entry.get('end_discard')} s; check the file or "
                               f"its meta entry", reason="nothing left after the discards")
    details = {"codec": info.codec, "fps": round(info.fps, 3), "frames": max(0, min(stop, total) - start)}
    if not info.frames:
        details["frames_counted_by_decoding"] = total
    blank = [key for key, value in cells.items() if value is None]
    if blank:
        details["blank_cells"] = blank  # nothing dropped there
    return details


def convert(meta: Path, videos: Path, out: Path, limit: int | None = None, strict: bool = False, parts: int = 1,
            part: int | None = None) -> Report:
    """Write the listed videos that are present, at most ``limit``; the absent ones are reported. One item per meta
    entry, in parts (:func:`orbis2.data.datasets.convert_items`)."""
    entries = read_meta(meta)
    items = [Item(f"entry {n} ({entry.get('videoid')})", tuple(filter(None, [_present(videos, entry)])),
                  lambda report, n=n, entry=entry: convert_entry(meta, videos, out, n, entry, report),
                  json.dumps(entry, sort_keys=True))
             for n, entry in enumerate(entries)]
    key = reader_key(__file__, meta=meta, videos=videos, strict=strict)
    return convert_items(Report("opendv", out, strict), items, key, parts, part, limit)


def _present(videos: Path, entry: dict) -> Path | None:
    """The entry's downloaded video, if its entry names one."""
    return video_of(videos, entry) if {"videoid", "youtuber"} <= set(entry) else None


def convert_entry(meta: Path, videos: Path, out: Path, n: int, entry: dict, report: Report) -> None:
    """Convert meta entry ``n`` into ``report``: its video written, or why it was left out."""
    try:
        check_entry(meta, n, entry)
        path = video_of(videos, entry)
        if path is None:
            raise DatasetError(f"{videos / str(entry['youtuber']).replace(' ', '_') / str(entry['videoid'])}.mp4: "
                               f"missing (nor .webm, .mkv); rerun the dataset's download script (YouTube removes "
                               f"some videos)", reason="not downloaded")
        target = out / SPLITS[str(entry["split"]).lower()] / f"{entry['videoid']}.mp4"
        details = convert_video(path, entry, target)
    except (DatasetError, VideoError) as err:
        report.skip(str(entry.get("videoid", f"entry {n}")), err)
        return
    except ValueError as err:  # a discard cell that is not a number
        report.skip(str(entry.get("videoid")), DatasetError(
            f"{meta}: entry {n} ({entry.get('videoid')}): a discard cell is not a number ({err}); fix the meta "
            f"file", reason="bad meta entry"))
        return
    report.add(target, **details)
