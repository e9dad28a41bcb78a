"""Render the embedded town into the raw episode layout (the ``town`` stage).

Splits (all from one ``town.seed``):

- ``train``, ``val``, ``probe``: ego drives in the default-style town, disjoint ego seeds;
- ``turns``: the ``episodes.turns`` episodes with the largest total |yaw| among
  ``turns_candidates`` simulated val-town drives (like the paper's nuPlan-turns);
- ``heldout``: a different town (heldout style: layout, palette, textures, seed),
  the unseen-domain split (like the paper's Waymo evaluation).

Every episode is a pure function of (seed, split, index), so the result does not
depend on how many worker processes render it.
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from orbis2.config.sections import SPLITS, DataConfig, TownConfig
from orbis2.data.episodes import EpisodeRecord, RawIndex, read_odometry, write_labels, write_odometry
from orbis2.data.motion import motion_statistics
from orbis2.data.parts import PartLog, keyed_work, part_name, part_slice
from orbis2.data.video import write_video
from orbis2.io import atomic_file, move_into
from orbis2.sim import Camera, Town, render_episode, simulate_ego

SPLIT_CODES = {split: code for code, split in enumerate(SPLITS)}

# Cityscapes colours for the train ids (the official palette), black for ignore.
CITYSCAPES_PALETTE = np.zeros((256, 3), np.uint8)
for _tid, _rgb in {0: (128, 64, 128), 1: (244, 35, 232), 2: (70, 70, 70), 3: (102, 102, 156),
                   4: (190, 153, 153), 5: (153, 153, 153), 6: (250, 170, 30), 7: (220, 220, 0),
                   8: (107, 142, 35), 9: (152, 251, 152), 10: (70, 130, 180), 11: (220, 20, 60),
                   12: (255, 0, 0), 13: (0, 0, 142), 14: (0, 0, 70), 15: (0, 60, 100),
                   16: (0, 80, 100), 17: (0, 0, 230), 18: (119, 11, 32)}.items():
    CITYSCAPES_PALETTE[_tid] = _rgb


@dataclass(frozen=True)
class EpisodePlan:
    split: str
    index: int
    style: str
    town_seed: int
    ego_seed: int
    seconds: float

    @property
    def stem(self) -> str:
        return f"town_{self.split}_{self.index:05d}"


def derive_seed(*parts: int) -> int:
    return int(np.random.SeedSequence(list(parts)).generate_state(1)[0])


@lru_cache(maxsize=4)
def cached_town(style: str, seed: int) -> Town:
    """Towns are deterministic and costly to build; each worker builds each once."""
    return Town.generate(style, seed)


def split_town(cfg: TownConfig, split: str) -> tuple[str, int]:
    """(style, town seed) a split drives in: the heldout split has its own town and style."""
    return ("heldout", derive_seed(cfg.seed, 1)) if split == "heldout" else ("default", derive_seed(cfg.seed, 0))


def plan_episodes(cfg: TownConfig, fps: int) -> list[EpisodePlan]:
    plans = []
    for split in ("train", "val", "probe", "heldout"):
        style, town_seed = split_town(cfg, split)
        plans += [EpisodePlan(split, i, style, town_seed, derive_seed(cfg.seed, SPLIT_CODES[split], i),
                              cfg.episode_seconds[split]) for i in range(cfg.episodes[split])]
    style, main_town = split_town(cfg, "turns")
    town = cached_town(style, main_town)
    seconds = cfg.episode_seconds["turns"]
    candidates = [derive_seed(cfg.seed, SPLIT_CODES["turns"], i) for i in range(cfg.turns_candidates)]
    yaw = [simulate_ego(town, s, seconds, fps).total_abs_yaw() for s in candidates]
    chosen = sorted(np.argsort(yaw, kind="stable")[::-1][: cfg.episodes["turns"]])
    plans += [EpisodePlan("turns", i, style, main_town, candidates[c], seconds) for i, c in enumerate(chosen)]
    return plans


def render_and_write(plan: EpisodePlan, root: Path, data: DataConfig, cfg: TownConfig) -> EpisodeRecord:
    """Simulate, render and write one episode (video, odometry, labels)."""
    town = cached_town(plan.style, plan.town_seed)
    camera = Camera(data.width, data.height, cfg.hfov_deg, cfg.mount_height_m)
    track = simulate_ego(town, plan.ego_seed, plan.seconds, data.fps)
    with_labels = plan.split in cfg.label_splits
    label_frames, depths, semantics = [], [], []

    def frames():
        for k, (rgb, depth, labels) in enumerate(render_episode(town, camera, track)):
            if with_labels and k % cfg.label_stride == 0:
                label_frames.append(k)
                depths.append(depth)
                semantics.append(labels)
            yield rgb

    folder = root / plan.split
    folder.mkdir(parents=True, exist_ok=True)
    n = write_video(folder / f"{plan.stem}.mp4", frames(), data.fps)
    write_odometry(folder / f"{plan.stem}.parquet", data.fps, track.speed, track.yaw_rate,
                   (track.x, track.y, track.yaw))
    if with_labels:
        write_labels(folder / f"{plan.stem}.labels.npz", label_frames, np.stack(depths), np.stack(semantics))
    return EpisodeRecord(plan.split, plan.stem, n, has_odometry=True, has_pose=True, label_frames=label_frames,
                         origin=f"town style={plan.style} town_seed={plan.town_seed} ego_seed={plan.ego_seed}")


def _init_worker() -> None:
    # One numba thread per process: episodes are the unit of parallelism.
    os.environ["NUMBA_NUM_THREADS"] = "1"


class _TownLog(PartLog):
    """A town part's ``done.jsonl``: one ``{"record": ...}`` line per episode rendered and in place."""

    def records(self) -> dict[str, EpisodeRecord]:
        return {e["record"]["stem"]: EpisodeRecord(**e["record"]) for e in self.events if "record" in e}

    def stale(self, events: list[dict[str, Any]]) -> bool:
        """A logged episode whose video is gone was moved out by a gather: the part is rendered again."""
        return any(not EpisodeRecord(**e["record"]).video(self.folder).is_file() for e in events if "record" in e)

    def clean(self) -> None:
        """Remove the files of an episode a kill stopped half-way (not logged, so rendered again)."""
        logged = self.records()
        for path in self.folder.glob("*/town_*"):
            if path.name.split(".")[0] not in logged:
                path.unlink()


def render_part(work: Path, data: DataConfig, cfg: TownConfig, part: int = 0, parts: int = 1) -> dict[str, Any]:
    """Render part ``part`` of ``parts`` (a contiguous block of :func:`plan_episodes`' episodes) into
    ``work/<part_name>/<split>/``; return the part's manifest (its folder and its episodes' records, in plan
    order).

    Each episode is logged (``done.jsonl``) once its files are in place, so a killed part started again renders
    only the episodes that were in flight (one per worker process). ``work`` must belong to these settings
    (:func:`town_key`). Episodes are pure functions of their plan: the part's files do not depend on ``parts``.
    """
    plans = plan_episodes(cfg, data.fps)
    plans = plans[part_slice(len(plans), part, parts)]
    folder = work / part_name(part, parts)
    log = _TownLog(folder)
    done = log.records()
    todo = [plan for plan in plans if plan.stem not in done]
    # 0: one process per core the job may use (a Slurm job's cores, not the node's)
    workers = min(cfg.workers or len(os.sched_getaffinity(0)), max(len(todo), 1))
    with tqdm(total=len(plans), initial=len(plans) - len(todo), desc=f"town {part_name(part, parts)}",
              unit="ep") as bar:
        if workers == 1:
            for plan in todo:
                log.add({"record": asdict(render_and_write(plan, folder, data, cfg))})
                bar.update()
        else:
            with ProcessPoolExecutor(workers, initializer=_init_worker) as pool:
                futures = [pool.submit(render_and_write, plan, folder, data, cfg) for plan in todo]
                for future in as_completed(futures):
                    log.add({"record": asdict(future.result())})
                    bar.update()
    done = log.records()
    return {"folder": str(folder), "records": [asdict(done[plan.stem]) for plan in plans]}


def town_key(data: DataConfig, cfg: TownConfig) -> dict[str, Any]:
    """What a part's episodes are made from (the settings); a work folder made from another key is not resumed."""
    return {"data": asdict(data), "town": asdict(cfg)}


def gather_town(parts_written: list[dict[str, Any]], root: Path, data: DataConfig, cfg: TownConfig) -> RawIndex:
    """The parts' episodes, in part order (the plan's), moved into ``root/<split>/`` (see
    :func:`orbis2.data.shards.gather_parts` for why moved) with ``index.json``."""
    records = []
    for written in parts_written:
        for record in (EpisodeRecord(**r) for r in written["records"]):
            (root / record.split).mkdir(parents=True, exist_ok=True)
            sources = [record.video, record.odometry] + ([record.labels] if record.label_frames else [])
            for source in (path(Path(written["folder"])) for path in sources):
                move_into(source, root / record.split / source.name)
            records.append(record)
    camera = Camera(data.width, data.height, cfg.hfov_deg, cfg.mount_height_m)
    index = RawIndex("town", data.fps, data.width, data.height,
                     {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
                      "mount_height_m": cfg.mount_height_m}, records)
    index.write(root)
    return index


def build_town_dataset(root: Path, data: DataConfig, cfg: TownConfig, parts: int = 1,
                       work: Path | None = None) -> RawIndex:
    """Render every episode into ``root``: each of ``parts`` parts is rendered (or resumed, or found finished) in
    ``work`` (default: ``<root>.parts`` beside it), then gathered. The episodes and their order do not depend on
    ``parts``."""
    work = keyed_work(Path(work) if work is not None else root.with_name(root.name + ".parts"), town_key(data, cfg))
    written = [render_part(work, data, cfg, part, parts) for part in range(parts)]
    return gather_town(written, root, data, cfg)


def split_motion_statistics(root: Path, index: RawIndex, cfg: TownConfig) -> dict[str, dict[str, float]]:
    """`motion_statistics` of every split's odometry (the world's speeds and turns, per split),
    with the frames on the town's corner bends (from the ego poses)."""
    stats = {}
    for split in sorted({e.split for e in index.episodes}):
        odo = [read_odometry(root / split / f"{e.stem}.parquet") for e in index.split(split)]
        town = cached_town(*split_town(cfg, split))
        x, y = np.concatenate([o["x"] for o in odo]), np.concatenate([o["y"] for o in odo])
        stats[split] = motion_statistics(np.concatenate([o["speed"] for o in odo]),
                                         np.concatenate([o["yaw_rate"] for o in odo]),
                                         on_bend=~np.isnan(town.bend_offset(x, y)))
    return stats


# --------------------------------------------------------------------------- previews


def colorize_depth(depth: np.ndarray, max_depth: float = 80.0) -> np.ndarray:
    finite = np.where(np.isfinite(depth), depth, max_depth)
    inv = 1.0 - np.clip(finite / max_depth, 0, 1) ** 0.5
    bgr = cv2.applyColorMap((inv * 255).astype(np.uint8), cv2.COLORMAP_MAGMA)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def colorize_labels(labels: np.ndarray) -> np.ndarray:
    return CITYSCAPES_PALETTE[labels]


def write_previews(sheet_path: Path, video_path: Path, data: DataConfig, cfg: TownConfig) -> None:
    """A contact sheet (RGB | depth | labels rows, both town styles) and a short preview video."""
    plans = [p for p in plan_episodes(cfg, data.fps) if p.split in ("turns", "heldout") and p.index == 0]
    camera = Camera(data.width, data.height, cfg.hfov_deg, cfg.mount_height_m)
    rows, video_frames = [], []
    for plan in plans:
        town = cached_town(plan.style, plan.town_seed)
        track = simulate_ego(town, plan.ego_seed, min(plan.seconds, cfg.preview_seconds), data.fps)
        frames = list(render_episode(town, camera, track))
        picks = np.linspace(0, len(frames) - 1, 4).round().astype(int)
        for k in picks:
            rgb, depth, labels = frames[k]
            rows.append(np.concatenate([rgb, colorize_depth(depth), colorize_labels(labels)], axis=1))
        video_frames += [np.concatenate([rgb, colorize_labels(labels)], axis=1) for rgb, _, labels in frames]
    with atomic_file(sheet_path) as tmp:
        cv2.imwrite(str(tmp), cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR))
    with atomic_file(video_path) as tmp:
        write_video(tmp, video_frames, data.fps, playable=True)

