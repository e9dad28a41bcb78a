"""OpenDV-YouTube: the driving videos without odometry -> the import layout, marked unconditional.

The published layout: the meta file ``meta/OpenDV-YouTube.json`` lists each video with
``videoid``, ``youtuber``, ``split`` (``Train`` / ``Val``), ``start_discard`` and
``end_discard`` (seconds of intro and outro to drop); the download script saves each
video as ``<root>/<youtuber with spaces as _>/<videoid>.{mp4,webm,mkv}``. Each video is
written without its discarded head and tail at its native rate and without a CSV: the
import marks it unconditional (no odometry), for pre-training.
"""

from __future__ import annotations

import json
from pathlib import Path

from orbis2.data.datasets import DatasetError
from orbis2.data.video import iter_frames, probe, write_video
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
    for n, entry in enumerate(entries):
        missing = {"videoid", "youtuber", "split"} - set(entry)
        if missing:
            raise DatasetError(f"{meta}: entry {n} lacks {sorted(missing)}; use the published meta file")
        if str(entry["split"]).lower() not in SPLITS:
            raise DatasetError(f"{meta}: entry {n} has split {entry['split']!r}, expected Train or Val")
    return entries


def convert(meta: Path, videos: Path, out: Path, allow_missing: bool = False, limit: int | None = None) -> list[Path]:
    """Write the listed videos that are present (all must be, unless ``allow_missing``), at most ``limit``."""
    entries = read_meta(meta)
    found = [(entry, video_of(videos, entry)) for entry in entries]
    absent = [entry for entry, path in found if path is None]
    if absent and not allow_missing:
        first = absent[0]
        raise DatasetError(f"{videos / str(first['youtuber']).replace(' ', '_') / first['videoid']}.mp4: missing "
                           f"({len(absent)} of {len(entries)} listed videos are); rerun the dataset's download "
                           f"script or pass --allow-missing to convert the present ones")
    written = []
    for entry, path in [(e, p) for e, p in found if p is not None][:limit]:
        fps = probe(path).fps
        start = round(float(entry.get("start_discard", 0) or 0) * fps)
        total = probe(path).frames
        stop = total - round(float(entry.get("end_discard", 0) or 0) * fps) if total else None
        target = out / SPLITS[str(entry["split"]).lower()] / f"{entry['videoid']}.mp4"
        with atomic_file(target) as tmp:
            frames = (f for i, f in enumerate(iter_frames(path)) if i >= start and (stop is None or i < stop))
            if write_video(tmp, frames, fps) == 0:
                raise DatasetError(f"{path}: nothing is left after dropping {entry.get('start_discard')} s and "
                                   f"{entry.get('end_discard')} s; check the file or its meta entry")
        written.append(target)
    return written
