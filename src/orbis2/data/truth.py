"""True counterfactuals as data: the town re-rendered along commanded paths from clips' starts (the ``truth`` stage).

For each evaluated start of a town clip (a shard clip and the native index of its last context frame) and
each command (a steering mode: the clip's own speed and yaw rate from that frame on, each scaled), the
town re-renders the episode the clip was cut from along the commanded path
(:func:`orbis2.sim.counterfactual.render_path`): the start frame, then one frame per commanded step.
The episode comes back from the clip's metadata (its town style and seeds, the split's episode length in
``town.episode_seconds``), simulated again, and is checked against the clip's recorded poses bit for bit,
so a town changed since the shards were written stops here instead of rendering another world.

Storage mirrors the shards (:mod:`orbis2.data.shards`): WebDataset tars with fixed headers, one sample
per start and command, keyed ``<clip key>_<start:04d>_<mode>`` (:func:`truth_key`), members ``0000.jpg``... (JPEG at the
shards' quality: the truth passes through the same lossy step as the real frames a model learned from),
``odometry.npy`` (float32 [T, 2]: speed and yaw rate driven from each frame), ``pose.npy`` (float64
[T, 3]), ``events.npy`` (uint8 [T, 2]: collision, off road) and ``json``; ``manifest.json`` lists the
shards with their SHA-256. A source other than the town has no truth: its manifest says so and holds
no shards.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable

import cv2
import numpy as np

from orbis2.config.sections import DataConfig, TownConfig
from orbis2.data.shards import Clip, ShardError, ShardWriter, _jpeg, iter_samples, load_manifest
from orbis2.errors import OrbisError
from orbis2.io import load_npy, npy_bytes, sha256_file, write_json
from orbis2.sim import Camera, EgoTrack, Town, simulate_ego
from orbis2.sim.counterfactual import render_path

MANIFEST = "manifest.json"
_ORIGIN = re.compile(r"town style=(\S+) town_seed=(\d+) ego_seed=(\d+)")


class TruthError(OrbisError):
    """The truth cache is missing, stale or does not cover what the evaluation asks for."""


@dataclass(frozen=True)
class Command:
    """One start and command: which clip, its last context frame, the steering mode and its scales."""

    clip: str
    start: int  # clip-relative native index of the last context frame
    mode: str
    speed_scale: float
    yaw_rate_scale: float

    @property
    def key(self) -> str:
        return truth_key(self.clip, self.start, self.mode)


def truth_key(clip: str, start: int, mode: str) -> str:
    """A sample key: WebDataset splits a member name at its first dot, so the mode's dots ("x0.5") become "-"."""
    return f"{clip}_{start:04d}_{re.sub(r'[^A-Za-z0-9_-]', '-', mode)}"


def single_thread_renderer() -> None:
    """A rendering worker process's initializer: one numba thread each, as clips are the unit of parallelism."""
    os.environ["NUMBA_NUM_THREADS"] = "1"


@lru_cache(maxsize=4)
def _town(style: str, seed: int) -> Town:
    return Town.generate(style, seed)


def recorded_episode(clip: Clip, town_cfg: TownConfig) -> tuple[Town, EgoTrack]:
    """The town and the recorded ego track of the episode a town clip was cut from, checked against the clip."""
    meta = clip.meta
    found = _ORIGIN.fullmatch(str(meta.get("origin", "")))
    if meta.get("source") != "town" or found is None:
        raise TruthError(f"clip '{clip.key}' does not come from the town (origin {meta.get('origin')!r}); only "
                         f"town clips have a true counterfactual")
    style, town_seed, ego_seed = found.group(1), int(found.group(2)), int(found.group(3))
    town = _town(style, town_seed)
    track = simulate_ego(town, ego_seed, town_cfg.episode_seconds[meta["split"]], int(meta["fps"]))
    span = slice(meta["start_frame"], meta["start_frame"] + meta["frames"])
    poses = np.stack([track.x[span], track.y[span], track.yaw[span]], 1)
    if poses.shape != clip.pose.shape or not np.array_equal(poses, clip.pose):
        raise TruthError(f"clip '{clip.key}': the town, simulated again from params.yaml, does not drive the "
                         f"clip's recorded poses (town or town section changed since the shards were written); "
                         f"re-run the `town` and `shards` stages")
    return town, track


def render_commands(clip: Clip, commands: list[Command], steps: int, data: DataConfig, town_cfg: TownConfig,
                    jpeg_quality: int) -> list[tuple[str, dict[str, bytes], dict[str, Any]]]:
    """Render one clip's commands: per command its key, tar members and a summary (events). ``steps`` commanded
    native steps each, from the recorded controls (float64, as driven) times the command's scales."""
    town, track = recorded_episode(clip, town_cfg)
    camera = Camera(data.width, data.height, town_cfg.hfov_deg, town_cfg.mount_height_m)
    encode = [int(cv2.IMWRITE_JPEG_QUALITY), jpeg_quality]
    out = []
    for c in commands:
        first = clip.meta["start_frame"] + c.start
        if first + steps > len(track.t):
            raise TruthError(f"clip '{clip.key}': start {c.start} + {steps} steps runs past its episode")
        controls = slice(first, first + steps)
        path = render_path(town, camera, track, first, track.speed[controls] * c.speed_scale,
                           track.yaw_rate[controls] * c.yaw_rate_scale)
        members = {f"{i:04d}.jpg": _jpeg(frame, encode) for i, frame in enumerate(path.rgb)}
        members["odometry.npy"] = npy_bytes(np.stack([path.speed, path.yaw_rate], 1).astype(np.float32))
        members["pose.npy"] = npy_bytes(np.stack([path.x, path.y, path.yaw], 1))
        members["events.npy"] = npy_bytes(np.stack([path.collision, path.off_road], 1).astype(np.uint8))
        summary = {"clip": c.clip, "start": c.start, "mode": c.mode, "speed_scale": c.speed_scale,
                   "yaw_rate_scale": c.yaw_rate_scale, "episode_frame": first, "frames": len(path.rgb),
                   "collision": bool(path.collision.any()), "off_road": bool(path.off_road.any())}
        members["json"] = json.dumps({**clip.meta, **summary, "truth": True}, sort_keys=True).encode()
        out.append((c.key, members, summary))
    return out


def counterfactual_clip(clip: Clip, speed_scale: float, yaw_rate_scale: float, data: DataConfig,
                        town_cfg: TownConfig, jpeg_quality: int) -> tuple[np.ndarray, np.ndarray]:
    """A whole town clip driven again from its first frame with its recorded controls scaled: the frames as the
    shards would hold them (rendered, JPEG at the shards' quality, decoded) [T, H, W, 3] uint8 and the speed and
    yaw rate driven from each frame [T, 2] (what the inverse-dynamics instrument learns to read off the road)."""
    town, track = recorded_episode(clip, town_cfg)
    camera = Camera(data.width, data.height, town_cfg.hfov_deg, town_cfg.mount_height_m)
    first = clip.meta["start_frame"]
    controls = slice(first, first + clip.meta["frames"] - 1)
    path = render_path(town, camera, track, first, track.speed[controls] * speed_scale,
                       track.yaw_rate[controls] * yaw_rate_scale)
    encode = [int(cv2.IMWRITE_JPEG_QUALITY), jpeg_quality]
    frames = np.stack([cv2.cvtColor(cv2.imdecode(np.frombuffer(_jpeg(f, encode), np.uint8), cv2.IMREAD_COLOR),
                                    cv2.COLOR_BGR2RGB) for f in path.rgb])
    return frames, np.stack([path.speed, path.yaw_rate], 1)


def write_truth(out: Path, rendered: Iterable[tuple[str, dict[str, bytes], dict[str, Any]]],
                header: dict[str, Any], max_shard_mb: float) -> dict[str, Any]:
    """Write rendered commands (:func:`render_commands`, in order) as shards plus ``manifest.json``."""
    writer = ShardWriter(out, "truth", int(max_shard_mb * 2**20))
    seen: set[str] = set()
    events: dict[str, dict[str, int]] = {}
    samples = 0
    for key, members, summary in rendered:
        if key in seen:
            raise TruthError(f"two commands share the key {key!r}: give the steering modes names that differ in "
                             f"more than their punctuation")
        seen.add(key)
        writer.write(key, members)
        counts = events.setdefault(summary["mode"], {"samples": 0, "collision": 0, "off_road": 0})
        counts["samples"] += 1
        counts["collision"] += summary["collision"]
        counts["off_road"] += summary["off_road"]
        samples += 1
    writer.close()
    shards = [{"path": str(s["path"].relative_to(out)), **{k: s[k] for k in ("samples", "bytes", "sha256")}}
              for s in writer.shards]  # the writer hashed each shard as it wrote it
    manifest = {**header, "available": True, "samples": samples, "events": events, "shards": shards}
    write_json(out / MANIFEST, manifest)
    return manifest


def write_unavailable(out: Path, header: dict[str, Any], reason: str) -> dict[str, Any]:
    """The manifest of a source without truth (no shards)."""
    manifest = {**header, "available": False, "reason": reason, "samples": 0, "events": {}, "shards": []}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / MANIFEST, manifest)
    return manifest


@dataclass
class TruthVideo:
    """One start and command's true frames [T, H, W, 3] uint8 and what the ego drove: the speed and yaw rate from
    each frame [T], the poses [T, 3] (x, y, yaw) and per frame the collision and off-road flags
    (:class:`orbis2.sim.counterfactual.PathFrames`)."""

    frames: np.ndarray
    speed: np.ndarray
    yaw_rate: np.ndarray
    pose: np.ndarray
    collision: np.ndarray
    off_road: np.ndarray


def read_manifest(root: Path) -> dict[str, Any]:
    return load_manifest(root, "truth", TruthError)


def read_truth(root: Path, wanted: Iterable[str] | None = None) -> dict[str, TruthVideo]:
    """The truth cache's videos by key (``wanted``: only these), each shard checked against the manifest's hash."""
    root = Path(root)
    manifest = read_manifest(root)
    wanted = None if wanted is None else set(wanted)
    out = {}
    for shard in manifest["shards"]:
        path = root / shard["path"]
        if not path.is_file() or sha256_file(path) != shard["sha256"]:
            raise TruthError(f"{path}: missing or does not match {root / MANIFEST}'s hash; re-run the `truth` stage")
        for sample in iter_samples(path):
            if wanted is not None and sample["__key__"] not in wanted:
                continue
            try:
                clip = Clip.from_sample(sample, str(path))
                events = load_npy(sample["events.npy"])
            except (ShardError, KeyError, ValueError) as err:
                raise TruthError(f"{path}: sample '{sample['__key__']}' unreadable ({err}); re-run the `truth` "
                                 f"stage") from err
            out[clip.key] = TruthVideo(clip.frames(range(len(clip))), clip.odometry[:, 0], clip.odometry[:, 1],
                                       clip.pose, events[:, 0].astype(bool), events[:, 1].astype(bool))
    if wanted is not None and wanted - set(out):
        missing = sorted(wanted - set(out))
        raise TruthError(f"{root}: no true counterfactual for {len(missing)} of the evaluated starts and commands "
                         f"(first: {missing[0]}); re-run the `truth` stage with the evaluation's settings")
    return out
