"""Labelled frames for the linear probes: the town's ground truth, Cityscapes and KITTI (Eigen split).

Every source yields :class:`ProbeFrame` objects at one resolution ``size=(W, H)``
(the profile's), so one probe routine serves all of them. Images are
cover-resized and centre-cropped exactly like the videos (``resize_cover``);
labels go through the same geometry with nearest-neighbour sampling, so a
label never blends two classes or two depths. A missing task is marked by
its invalid value everywhere: semantic 255 (Cityscapes' ignore id), depth NaN.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from orbis2.data.shards import iter_clips
from orbis2.data.video import resize_cover
from orbis2.errors import OrbisError

IGNORE = 255
NUM_CLASSES = 19

# Cityscapes label id -> train id (cityscapesScripts' labels.py); every id not listed is ignored.
CITYSCAPES_TRAIN_IDS = {7: 0, 8: 1, 11: 2, 12: 3, 13: 4, 17: 5, 19: 6, 20: 7, 21: 8, 22: 9, 23: 10,
                        24: 11, 25: 12, 26: 13, 27: 14, 28: 15, 31: 16, 32: 17, 33: 18}
_CITYSCAPES_LUT = np.full(256, IGNORE, np.uint8)
for _label_id, _train_id in CITYSCAPES_TRAIN_IDS.items():
    _CITYSCAPES_LUT[_label_id] = _train_id

KITTI_DEPTH_SCALE = 256.0  # KITTI depth PNGs hold uint16 metres * 256; 0 marks a pixel without a measurement


class ProbeDataError(OrbisError):
    """A probe data set is missing or not in the expected layout; the message names the path."""


@dataclass(frozen=True)
class ProbeFrame:
    """One labelled frame: ``image`` uint8 [H, W, 3] RGB, ``semantic`` uint8 [H, W] train ids
    (255 = ignore), ``depth`` float32 [H, W] metres (0 or NaN = invalid), ``source`` a unique id,
    ``episode`` the group that must stay on one side of a train/test division."""

    image: np.ndarray
    semantic: np.ndarray
    depth: np.ndarray
    source: str
    episode: str


def resize_label(label: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour version of ``resize_cover``: the same scale and centre crop, no blending."""
    return resize_cover(label, size, nearest=True)


def _frame(image: np.ndarray, semantic: np.ndarray | None, depth: np.ndarray | None, size: tuple[int, int] | None,
           source: str, episode: str) -> ProbeFrame:
    h, w = image.shape[:2]
    semantic = np.full((h, w), IGNORE, np.uint8) if semantic is None else semantic.astype(np.uint8)
    depth = np.full((h, w), np.nan, np.float32) if depth is None else depth.astype(np.float32)
    if size is not None:
        image, semantic, depth = resize_cover(image, size), resize_label(semantic, size), resize_label(depth, size)
    return ProbeFrame(image, semantic, depth, source, episode)


def _read_rgb(path: Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ProbeDataError(f"{path}: OpenCV cannot read this image (missing, unreadable or not an image)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _read_raw(path: Path, what: str, layout: str) -> np.ndarray:
    if not path.is_file():
        raise ProbeDataError(f"{path}: {what} not found; expected layout: {layout}")
    array = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if array is None or array.ndim != 2:
        raise ProbeDataError(f"{path}: {what} must be a single-channel PNG; expected layout: {layout}")
    return array


def _pick(items: list, limit: int | None) -> list:
    """``limit`` items spread evenly over the sorted list (every city or drive is represented)."""
    if limit is None or limit >= len(items):
        return items
    return [items[int(i)] for i in np.linspace(0, len(items) - 1, limit).round().astype(int)]


# --------------------------------------------------------------------------- town


def town_probe_frames(shards_root: str | Path, split: str = "probe",
                      size: tuple[int, int] | None = None) -> list[ProbeFrame]:
    """Every labelled frame of a shards split (depth: z-depth in metres, sky = inf, i.e. invalid).

    ``episode`` is the clip's episode (the key before its last ``_``), so
    :func:`split_by_episode` keeps all clips of one drive together.
    """
    frames = []
    for clip in iter_clips(Path(shards_root), split):
        if clip.labels is None:
            continue
        labels = clip.labels
        for i, index in enumerate(labels["frames"].tolist()):
            frames.append(_frame(clip.frames([index])[0], labels["semantic"][i], labels["depth"][i], size,
                                 f"{clip.key}/{index:04d}", clip.key.rsplit("_", 1)[0]))
    if not frames:
        raise ProbeDataError(f"{shards_root}: split '{split}' holds no labelled frames; the town stage writes "
                             f"labels for data.label_splits, re-run it and the shards stage")
    return frames


def split_by_episode(frames: Sequence[ProbeFrame], test_fraction: float = 0.25,
                     seed: int = 0) -> tuple[list[ProbeFrame], list[ProbeFrame]]:
    """(train, test) with whole episodes on one side, so test frames come from drives the probe never saw.

    The episodes are shuffled with ``seed`` and ``round(test_fraction * episodes)`` of
    them (at least one, never all) go to the test side: the same input, the same division.
    """
    episodes = sorted({f.episode for f in frames})
    if len(episodes) < 2:
        raise ProbeDataError(f"a train/test division by episode needs at least 2 episodes, got {episodes}; "
                             f"add probe episodes (town.episodes.probe in params.yaml)")
    n_test = min(max(1, round(test_fraction * len(episodes))), len(episodes) - 1)
    order = np.random.default_rng(seed).permutation(len(episodes))
    test = {episodes[i] for i in order[:n_test]}
    return [f for f in frames if f.episode not in test], [f for f in frames if f.episode in test]


# --------------------------------------------------------------------------- Cityscapes

CITYSCAPES_LAYOUT = ("<root>/leftImg8bit/<split>/<city>/<name>_leftImg8bit.png with labels "
                     "<root>/gtFine/<split>/<city>/<name>_gtFine_labelIds.png (leftImg8bit_trainvaltest.zip "
                     "and gtFine_trainvaltest.zip extracted into one root)")


def cityscapes_train_ids(label_ids: np.ndarray) -> np.ndarray:
    """Cityscapes label ids -> the 19 train ids (official table), everything else 255."""
    return _CITYSCAPES_LUT[label_ids.astype(np.uint8)]


def cityscapes_frames(root: str | Path, split: str, size: tuple[int, int],
                      limit: int | None = None) -> list[ProbeFrame]:
    """Cityscapes fine annotations of ``split`` ("train" or "val"); no depth.

    Layout: ``<root>/leftImg8bit/<split>/<city>/<name>_leftImg8bit.png`` and
    ``<root>/gtFine/<split>/<city>/<name>_gtFine_labelIds.png``. ``limit`` keeps that
    many images spread evenly over the sorted list. ``episode`` is the city.
    """
    root = Path(root)
    image_dir = root / "leftImg8bit" / split
    if not image_dir.is_dir():
        raise ProbeDataError(f"{image_dir}: not found; expected layout: {CITYSCAPES_LAYOUT}")
    images = sorted(image_dir.glob("*/*_leftImg8bit.png"))
    if not images:
        raise ProbeDataError(f"{image_dir}: no <city>/*_leftImg8bit.png images; expected layout: {CITYSCAPES_LAYOUT}")
    frames = []
    for path in _pick(images, limit):
        city, name = path.parent.name, path.name[: -len("_leftImg8bit.png")]
        label_path = root / "gtFine" / split / city / f"{name}_gtFine_labelIds.png"
        label = cityscapes_train_ids(_read_raw(label_path, "Cityscapes label for " + path.name, CITYSCAPES_LAYOUT))
        frames.append(_frame(_read_rgb(path), label, None, size, f"cityscapes/{split}/{city}/{name}", city))
    return frames


# --------------------------------------------------------------------------- KITTI

KITTI_LAYOUT = ("raw images <root>/<date>/<drive>/image_02/data/<frame:010d>.png (image_03 for 'r'); depth "
                "either merged into the raw tree as <root>/<date>/<drive>/proj_depth/groundtruth/image_02/"
                "<frame:010d>.png, or, with depth_root, data_depth_annotated.zip extracted as "
                "<depth_root>/{train,val}/<drive>/proj_depth/groundtruth/image_02/<frame:010d>.png")


def read_eigen_split(path: str | Path) -> list[tuple[str, int, str]]:
    """Lines ``<date>/<drive> <frame> <l|r>`` (monodepth2's split files) -> (folder, frame, camera)."""
    path = Path(path)
    if not path.is_file():
        raise ProbeDataError(f"{path}: Eigen split file not found; expected lines such as "
                             f"'2011_09_26/2011_09_26_drive_0002_sync 69 l' (monodepth2's splits/eigen*/)")
    entries = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 3 or not parts[1].isdigit() or parts[2] not in ("l", "r") or parts[0].count("/") != 1:
            raise ProbeDataError(f"{path}:{number}: {line!r} is not '<date>/<drive> <frame> <l|r>'")
        entries.append((parts[0], int(parts[1]), "image_02" if parts[2] == "l" else "image_03"))
    if not entries:
        raise ProbeDataError(f"{path}: the Eigen split file lists no frames")
    return entries


def read_kitti_depth(path: Path) -> np.ndarray:
    """A KITTI depth PNG (uint16, metres * 256) -> float32 metres, 0 where there is no measurement."""
    raw = _read_raw(path, "KITTI depth map", KITTI_LAYOUT)
    if raw.dtype != np.uint16:
        raise ProbeDataError(f"{path}: KITTI depth maps are 16-bit PNGs, this one is {raw.dtype}")
    return raw.astype(np.float32) / KITTI_DEPTH_SCALE


def kitti_eigen_frames(root: str | Path, split_file: str | Path, size: tuple[int, int],
                       depth_root: str | Path | None = None, limit: int | None = None) -> list[ProbeFrame]:
    """KITTI frames listed in an Eigen split file, with the annotated (projected, densified) depth; no semantics.

    Images: ``<root>/<date>/<drive>/image_02/data/<frame:010d>.png`` (``image_03`` for
    ``r``). Depth, ``depth_root`` None: merged into the raw tree,
    ``<root>/<date>/<drive>/proj_depth/groundtruth/image_02/<frame:010d>.png``; with
    ``depth_root``: ``data_depth_annotated.zip`` as extracted,
    ``<depth_root>/{train,val}/<drive>/proj_depth/groundtruth/image_02/<frame:010d>.png``.
    Not every Eigen test frame has an annotation: list only annotated ones (monodepth2's
    ``eigen_benchmark``), a missing depth map is an error. ``episode`` is the drive.
    """
    root = Path(root)
    if not root.is_dir():
        raise ProbeDataError(f"{root}: KITTI root not found; expected layout: {KITTI_LAYOUT}")
    if depth_root is not None and not Path(depth_root).is_dir():
        raise ProbeDataError(f"{depth_root}: KITTI depth root not found; expected layout: {KITTI_LAYOUT}")
    frames = []
    for folder, index, camera in _pick(read_eigen_split(split_file), limit):
        drive = folder.split("/")[1]
        name = f"{index:010d}.png"
        image_path = root / folder / camera / "data" / name
        if not image_path.is_file():
            raise ProbeDataError(f"{image_path}: KITTI image listed in {split_file} not found; "
                                 f"expected layout: {KITTI_LAYOUT}")
        tail = Path(drive) / "proj_depth" / "groundtruth" / camera / name
        if depth_root is None:
            depth_path = root / folder.split("/")[0] / tail
        else:
            candidates = [Path(depth_root) / part / tail for part in ("train", "val")]
            depth_path = next((p for p in candidates if p.is_file()), None)
            if depth_path is None:
                raise ProbeDataError(f"{candidates[0]} (or {candidates[1]}): KITTI depth map for {image_path} not "
                                     f"found; expected layout: {KITTI_LAYOUT}")
        frames.append(_frame(_read_rgb(image_path), None, read_kitti_depth(depth_path), size,
                             f"kitti/{folder}/{camera}/{index:010d}", drive))
    return frames
