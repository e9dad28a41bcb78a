"""WebDataset shards of clips, and the two-rate clip windows the predictors train on.

One sample per clip (a fixed-length piece of an episode). Members of sample ``key``:

- ``key.0000.jpg`` ... one JPEG per native frame. JPEG rather than mp4 bytes: any
  frame decodes alone straight from memory, so a 10 Hz or 2 Hz window costs only
  the frames it uses, and no temporary file or codec state is needed;
- ``key.odometry.npy``: float32 ``[n, 2]`` (speed m/s, yaw rate rad/s; NaN if unknown);
- ``key.pose.npy``: float64 ``[n, 3]`` (x, y, yaw of the camera; NaN if unknown);
- ``key.json``: source, split, episode, fps, start frame and time, resolution, camera;
- ``key.labels.npz`` (labelled splits): ``frames`` (indices within the clip),
  ``depth`` (float16 m), ``semantic`` (Cityscapes train ids).

Keys are ``<episode stem>_<clip index>`` with zero padding, unique across the dataset.
Tar headers carry fixed owners and times, so the same clips give the same bytes
and hashes on every run. ``manifest.json`` lists shards, sample counts and SHA-256.

A *window* is read from a clip around an anchor ``a``, the native index of the
last detail context frame: detail frames every ``fps/detail_hz`` frames
(``detail_context`` up to and including ``a``, then the predicted ones), abstract
frames every ``fps/abstract_hz`` frames (``abstract_context`` ending on ``a``,
then the predicted ones, the first of which lands on the last predicted detail
frame with the default 10 Hz / 2 Hz / 5-frame settings).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import itertools
import json
import os
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Collection, Iterable, Iterator

import cv2
import numpy as np
import webdataset as wds
from torch.utils.data import IterableDataset, get_worker_info
from tqdm import tqdm

from orbis2.config.sections import SPLITS, DataConfig, ShardsConfig
from orbis2.data.episodes import EpisodeRecord, RawIndex, read_odometry
from orbis2.data.parts import PART_LOG, PartLog, keyed_work, part_name, part_slice  # noqa: F401 (PART_LOG)
from orbis2.data.video import iter_frames
from orbis2.errors import OrbisError
from orbis2.hierarchy import anchor_range, window_indices, window_span
from orbis2.io import HashingFile, load_npy, load_npz, move_into, npy_bytes, npz_bytes, sha256_file, write_json

MANIFEST = "manifest.json"


class ShardError(OrbisError):
    """A shard or manifest is missing, truncated or corrupt; the message names the file."""


# --------------------------------------------------------------------------- writing


class ShardWriter:
    """WebDataset shards ``<prefix>-000000.tar``... in ``folder``, rolling over once a shard holds ``max_bytes``
    of payload (``webdataset.ShardWriter``'s rule), with fixed headers (mtime 0, uid/gid 0, owner ``orbis2``,
    mode 0644, USTAR) so that the same samples give the same bytes.

    Each shard is written as ``<name>.partial`` and hashed as it is written, then flushed to disk and renamed:
    a ``.tar`` that exists is whole, and its SHA-256 costs no second read. ``on_shard(record)`` is called once a
    shard is in place; ``shards`` lists the records (``path``, ``samples``, ``bytes``, ``sha256``, ``frames``
    and the ``last`` tag written, see :meth:`write`). Numbering starts at ``start`` (a resumed writer).
    """

    def __init__(self, folder: Path, prefix: str, max_bytes: int, start: int = 0,
                 on_shard: Callable[[dict[str, Any]], None] | None = None):
        self.folder, self.prefix, self.max_bytes = Path(folder), prefix, max_bytes
        self.next, self.on_shard = start, on_shard
        self.shards: list[dict[str, Any]] = []
        self._tar: wds.TarWriter | None = None
        self._file: HashingFile | None = None
        self._open: dict[str, Any] = {}

    def write(self, key: str, members: dict[str, bytes], frames: int = 0, tag: Any = None) -> None:
        """Add one sample; ``frames`` and ``tag`` (e.g. where in the input it came from) go into its shard's record."""
        if self._tar is not None and self._open["size"] >= self.max_bytes:
            self._close_shard()
        if self._tar is None:  # opened lazily: a split without clips leaves no empty shard
            path = self.folder / f"{self.prefix}-{self.next:06d}.tar"
            self.folder.mkdir(parents=True, exist_ok=True)
            self._file = HashingFile(path.with_name(path.name + PARTIAL))
            self._tar = wds.TarWriter(self._file, encoder=False, mtime=0, user="orbis2", group="orbis2",
                                      mode=0o644)
            self._open = {"path": path, "samples": 0, "size": 0, "frames": 0}
            self.next += 1
        self._open["size"] += self._tar.write({"__key__": key, **members})
        self._open["samples"] += 1
        self._open["frames"] += frames
        self._open["last"] = tag

    def close(self) -> None:
        if self._tar is not None:
            self._close_shard()

    def _close_shard(self) -> None:
        assert self._tar is not None and self._file is not None
        self._tar.close()
        size, digest = self._file.finish()
        path = self._open["path"]
        os.replace(self._file.path, path)
        record = {"path": path, "samples": self._open["samples"], "bytes": size, "sha256": digest,
                  "frames": self._open["frames"], "last": self._open.get("last")}
        self._tar = self._file = None
        self.shards.append(record)
        if self.on_shard is not None:
            self.on_shard(record)


PARTIAL = ".partial"  # a shard still being written (removed when a part resumes)


def clip_starts(n_frames: int, clip_frames: int, min_frames: int) -> list[tuple[int, int]]:
    """Non-overlapping (start, length) clips; a short episode becomes one shorter clip."""
    if n_frames >= clip_frames:
        return [(s, clip_frames) for s in range(0, n_frames - clip_frames + 1, clip_frames)]
    return [(0, n_frames)] if n_frames >= min_frames else []


# --------------------------------------------------------------------------- parts


class _PartLog(PartLog):
    """A shards part's progress (``done.jsonl``): one line per shard in place, one per split finished, one when
    the part is done.

    A shard is logged after it is renamed into place, so a kill loses at most the shard being
    written (its ``.partial`` file is removed on the next start) and the line being appended
    (a torn last line is ignored: its shard is written again, to the same bytes)."""

    def stale(self, events: list[dict[str, Any]]) -> bool:
        # gathered already (the gather moves the shards out): written again
        return any(not (self.folder / e["path"]).is_file() for e in events if e.get("shard"))

    def clean(self) -> None:
        for stale in self.folder.rglob(f"*{PARTIAL}"):
            stale.unlink()

    def shards(self, split: str) -> list[dict[str, Any]]:
        return [e for e in self.events if e.get("shard") and e["split"] == split]

    def finished(self, split: str) -> bool:
        return any(e.get("finished") == split for e in self.events)


def _checked_index(raw_root: Path, data: DataConfig) -> RawIndex:
    index = RawIndex.read(raw_root)
    if (index.fps, index.width, index.height) != (data.fps, data.width, data.height):
        raise ShardError(f"{raw_root / 'index.json'}: episodes are {index.width}x{index.height} at {index.fps} fps "
                         f"but params.yaml asks for {data.width}x{data.height} at {data.fps} fps; "
                         f"re-run the town/import stage")
    return index


def write_part(raw_root: Path, work: Path, data: DataConfig, cfg: ShardsConfig, part: int = 0,
               parts: int = 1) -> dict[str, Any]:
    """Write part ``part`` of ``parts`` (a contiguous block of every split's episodes) as shards in
    ``work/<part_name>/<split>/``; return the part's manifest (its splits' shards, in order).

    Resumes where it stopped: shards already in place (``done.jsonl``) are kept, and writing
    restarts at the clip after the last one they hold, which gives the same shards, byte for byte,
    as a run that was never stopped. ``work`` must belong to these inputs (see :func:`write_shards`).
    Frames stream from the decoder: a part holds one clip's frames at a time, whatever the
    length of the video.
    """
    with one_core():
        return _write_part(raw_root, work, data, cfg, part, parts)


@contextlib.contextmanager
def one_core() -> Iterator[None]:
    """OpenCV on one thread for the block: a part is one core's work (parts, not threads, use the others). With
    OpenCV's own threads a part kept 1.5 cores busy at no more frames/s, and two parts side by side reached
    1.6x one part instead of 1.9x (512x288, 2 cores; benchmarks/bench_shards.py)."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(threads)


def _write_part(raw_root: Path, work: Path, data: DataConfig, cfg: ShardsConfig, part: int,
                parts: int) -> dict[str, Any]:
    index = _checked_index(raw_root, data)
    folder = work / part_name(part, parts)
    log = _PartLog(folder)
    encode = [int(cv2.IMWRITE_JPEG_QUALITY), cfg.jpeg_quality]
    for split in SPLITS:
        episodes = index.split(split)
        if not episodes or log.finished(split) or log.done:
            continue
        episodes = episodes[part_slice(len(episodes), part, parts)]
        done = log.shards(split)
        after = tuple(done[-1]["last"]) if done else (-1, -1)  # (episode, clip) of the last clip in place
        writer = ShardWriter(folder / split, split, int(cfg.max_shard_mb * 2**20), start=len(done),
                             on_shard=lambda r, split=split: log.add(
                                 {"shard": True, "split": split, "path": str(r["path"].relative_to(folder)),
                                  **{k: r[k] for k in ("samples", "bytes", "sha256", "frames", "last")}}))
        for e, ep in enumerate(tqdm(episodes, desc=f"shards {part_name(part, parts)}: {split}", unit="ep")):
            if e < after[0]:
                continue
            skip = after[1] if e == after[0] else -1
            for c, length, members in episode_clips(raw_root, ep, index, data, cfg, encode, skip):
                writer.write(f"{ep.stem}_{c:04d}", members, frames=length, tag=[e, c])
        writer.close()
        log.add({"finished": split})
    if not log.done:
        log.add({"done": True})
    return part_manifest(log, index)


def part_manifest(log: _PartLog, index: RawIndex) -> dict[str, Any]:
    """A finished part's splits and shards (paths relative to the part's folder)."""
    splits = {}
    for split in SPLITS:
        if not index.split(split):
            continue
        splits[split] = [{k: e[k] for k in ("path", "samples", "bytes", "sha256", "frames")} for e in log.shards(split)]
    return {"folder": str(log.folder), "splits": splits}


def episode_clips(raw_root: Path, ep: EpisodeRecord, index: RawIndex, data: DataConfig, cfg: ShardsConfig,
                  encode: list[int], skip: int = -1) -> Iterator[tuple[int, int, dict[str, bytes]]]:
    """``(clip index, frames, members)`` of one episode's clips after clip ``skip``.

    Frames stream from the decoder and are encoded clip by clip; the frames after the last clip
    are not decoded, nor are any when every clip is at or before ``skip``."""
    odo = read_odometry(ep.odometry(raw_root))
    n = min(ep.frames, len(odo["frame"]))
    clip_frames = round(cfg.clip_seconds[ep.split] * data.fps)
    clips = clip_starts(n, clip_frames, data.window_span_frames)
    if len(clips) <= skip + 1:
        return
    labels = load_npz(ep.labels(raw_root).read_bytes()) if ep.label_frames else None
    video = ep.video(raw_root)
    frames = iter_frames(video)
    for c, (start, length) in enumerate(clips):
        pixels = list(itertools.islice(frames, length))
        if len(pixels) < length:
            raise ShardError(f"{video}: decoded {start + len(pixels)} frames, but {raw_root / 'index.json'} says "
                             f"{ep.frames}; the video is truncated or the index is stale: re-run the town/import stage")
        if c <= skip:
            continue
        members = {f"{i:04d}.jpg": _jpeg(frame, encode) for i, frame in enumerate(pixels)}
        sl = slice(start, start + length)
        members["odometry.npy"] = npy_bytes(np.stack([odo["speed"][sl], odo["yaw_rate"][sl]], 1).astype(np.float32))
        members["pose.npy"] = npy_bytes(np.stack([odo["x"][sl], odo["y"][sl], odo["yaw"][sl]], 1))
        if labels is not None:
            keep = (labels["frames"] >= start) & (labels["frames"] < start + length)
            members["labels.npz"] = npz_bytes(frames=labels["frames"][keep] - start,
                                              depth=labels["depth"][keep], semantic=labels["semantic"][keep])
        members["json"] = json.dumps({
            "source": index.source, "split": ep.split, "episode": ep.stem, "origin": ep.origin,
            "fps": data.fps, "start_frame": start, "start_time": start / data.fps, "frames": length,
            "width": data.width, "height": data.height, "camera": index.camera,
            "has_odometry": ep.has_odometry, "has_pose": ep.has_pose}, sort_keys=True).encode()
        yield c, length, members


def gather_parts(raw_root: Path, parts_written: list[dict[str, Any]], out_root: Path) -> dict[str, Any]:
    """The shards of every part, in part order, moved into ``out_root/<split>/<split>-NNNNNN.tar`` (numbered
    across parts), and ``manifest.json``. Moved, not copied or linked: no second copy, and the files stay the
    ones the parts wrote (a hard link would let a tool that replaces one name, as ``dvc commit`` does, give
    the other a new time). A part whose shards were gathered is written again if it is asked for again."""
    index = RawIndex.read(raw_root)
    manifest: dict[str, Any] = {"source": index.source, "fps": index.fps, "width": index.width,
                                "height": index.height, "camera": index.camera, "splits": {}}
    for split in SPLITS:
        if not index.split(split):
            continue
        (out_root / split).mkdir(parents=True, exist_ok=True)
        shards = []
        for written in parts_written:
            for shard in written["splits"][split]:
                name = f"{split}/{split}-{len(shards):06d}.tar"
                move_into(Path(written["folder"]) / shard["path"], out_root / name)
                shards.append({"path": name, **{k: shard[k] for k in ("samples", "bytes", "sha256")}})
        manifest["splits"][split] = {"samples": sum(s["samples"] for s in shards),
                                     "frames": sum(s["frames"] for w in parts_written for s in w["splits"][split]),
                                     "shards": shards}
    write_json(out_root / MANIFEST, manifest)
    return manifest


def shards_key(raw_root: Path, data: DataConfig, cfg: ShardsConfig) -> dict[str, Any]:
    """What a part's shards are made from: the raw index (the town and import stages write it with the videos,
    atomically) and the settings. A work folder made from another key is not resumed."""
    return {"index": sha256_file(Path(raw_root) / "index.json"), "data": dataclasses.asdict(data),
            "shards": dataclasses.asdict(cfg)}


def write_shards(raw_root: Path, out_root: Path, data: DataConfig, cfg: ShardsConfig, parts: int = 1,
                 work: Path | None = None) -> dict[str, Any]:
    """Cut every raw episode into clips and write per-split shards plus the manifest into ``out_root``.

    Each of ``parts`` parts is written (or resumed, or found finished) in ``work`` (default:
    ``<out_root>.parts`` beside it), then gathered. ``work`` holds a key of its inputs; one made
    from other inputs is emptied first. The samples and their order do not depend on ``parts``;
    where shards end does.
    """
    work = keyed_work(Path(work) if work is not None else out_root.with_name(out_root.name + ".parts"),
                      shards_key(raw_root, data, cfg))
    written = [write_part(raw_root, work, data, cfg, part, parts) for part in range(parts)]
    return gather_parts(raw_root, written, out_root)


def _jpeg(frame: np.ndarray, params: list[int]) -> bytes:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), params)
    assert ok, "OpenCV failed to encode a JPEG frame"
    return buf.tobytes()


# --------------------------------------------------------------------------- reading


def load_manifest(root: Path, stage: str = "shards", error: type[OrbisError] = ShardError) -> dict[str, Any]:
    """The manifest of a folder of checked shards, written by ``stage`` (missing or unreadable: ``error``)."""
    path = Path(root) / MANIFEST
    if not path.is_file():
        raise error(f"{path}: missing; run the `{stage}` stage first")
    try:
        return json.loads(path.read_text())
    except ValueError as err:
        raise error(f"{path}: not valid JSON ({err}); re-run the `{stage}` stage") from err


def shard_paths(root: Path, split: str) -> list[Path]:
    manifest = load_manifest(root)
    if split not in manifest["splits"]:
        raise ShardError(f"{Path(root) / MANIFEST}: no split '{split}' (have {sorted(manifest['splits'])})")
    return [Path(root) / s["path"] for s in manifest["splits"][split]["shards"]]


@dataclass(frozen=True)
class ShardRef:
    """Where a shard is read from, and its size and SHA-256 as the manifest recorded them when it was written."""

    url: str
    bytes: int
    sha256: str


def shard_refs(root: Path, split: str, base: str | None = None) -> list[ShardRef]:
    """A split's shards in manifest order: where each is read from (:func:`shard_urls`) and what it must hash to."""
    urls = shard_urls(root, split, base)  # names a split the manifest lacks
    entries = load_manifest(root)["splits"][split]["shards"]
    return [ShardRef(url, int(e["bytes"]), str(e["sha256"])) for url, e in zip(urls, entries, strict=True)]


def verify_shards(root: Path, splits: Iterable[str] | None = None, base: str | None = None) -> int:
    """Stream every shard of ``splits`` (default: all) and compare its size and SHA-256 with the manifest; the
    bytes checked.

    The full check, by hand or before copying a dataset: readers do not call it. Each reader checks a shard
    just before it reads it (:func:`shard_dataset`, :func:`iter_clips`), so a process hashes only the shards it
    reads, and a job of many ranks does not hash every split on every rank before its first step.
    """
    manifest = load_manifest(root)
    splits = list(manifest["splits"]) if splits is None else list(splits)
    refs = [ref for split in splits for ref in shard_refs(root, split, base)]
    with tqdm(total=sum(r.bytes for r in refs), desc="verify shards", unit="B", unit_scale=True, leave=False) as bar:
        for ref in refs:
            verify_shard(ref, bar)
    return sum(r.bytes for r in refs)


def verify_shard(ref: ShardRef, bar: tqdm | None = None) -> None:
    """Stream one shard and compare its size and SHA-256 with the manifest's.

    Reading alone would not notice damage: a flipped byte in a JPEG payload still decodes (to wrong pixels), and
    a damaged tar header mid-shard ends the archive early without an error in ``tarfile``. So a reader streams
    the shard through the hash first and reads its samples only if it matches (a second read, from the page
    cache for a local file; a shard behind a URL is fetched twice)."""
    size, digest = _stream_digest(ref.url, bar)
    if size != ref.bytes:
        raise ShardError(f"{ref.url}: {size} bytes, the manifest says {ref.bytes} (truncated or "
                         f"modified); re-run the `shards` stage")
    if digest != ref.sha256:
        raise ShardError(f"{ref.url}: content does not match the manifest's hash (corrupt or modified); "
                         f"re-run the `shards` stage")


def _stream_digest(url: str, bar: tqdm | None = None) -> tuple[int, str]:
    """Size and SHA-256 of one shard, read in 1 MiB blocks through ``webdataset.gopen`` (files, pipes, URLs)."""
    digest, size = hashlib.sha256(), 0
    try:
        with wds.gopen(url, "rb") as stream:
            while block := stream.read(1 << 20):
                digest.update(block)
                size += len(block)
                if bar is not None:
                    bar.update(len(block))
    except FileNotFoundError as err:
        raise ShardError(f"{url}: listed in the manifest but missing; re-run the `shards` stage") from err
    except OSError as err:
        raise ShardError(f"{url}: unreadable ({err}); re-run the `shards` stage, or check the shards' URL") from err
    return size, digest.hexdigest()


def shard_urls(root: Path, split: str, base: str | None = None) -> list[str]:
    """Where a split's shards are read from: local paths under ``root``, or the manifest's
    relative paths placed into ``base`` (default ``$ORBIS2_SHARDS_URL``) when the shards live
    elsewhere. ``base`` is a prefix (``https://host/shards``) or a template with ``{}``
    (``pipe:aws s3 cp s3://bucket/shards/{} -``); ``webdataset`` opens files, ``pipe:`` commands
    and HTTP(S) URLs. The manifest itself is always read from ``root``."""
    base = base if base is not None else os.environ.get("ORBIS2_SHARDS_URL")
    paths = [str(p.relative_to(root)) for p in shard_paths(root, split)]
    if not base:
        return [str(Path(root) / p) for p in paths]
    return [base.format(p) if "{}" in base else f"{base.rstrip('/')}/{p}" for p in paths]


def _raise_shard_error(exn: Exception) -> bool:
    """``webdataset`` error handler: a broken shard stops the read with a message naming it.

    webdataset appends the stream and URL to ``exn.args`` as the error leaves the shard;
    before that (no URL yet) the error is passed on unchanged so that it gets one.
    """
    if isinstance(exn, ShardError):
        raise exn
    url = getattr(exn, "filename", None) or (exn.args[-1] if len(exn.args) >= 3 else None)
    if not isinstance(url, str):
        raise exn
    raise ShardError(f"{url}: truncated, corrupt or unreadable shard ({exn.args[0]}); "
                     f"re-run the `shards` stage") from exn


def shard_dataset(shards: list[ShardRef]) -> wds.WebDataset:
    """The raw samples (members grouped by key) of ``shards`` in order, through ``webdataset``; each shard is
    checked (:func:`verify_shard`) just before it is opened."""
    refs = {ref.url: ref for ref in shards}

    def checked(urls: Iterator[dict[str, str]]) -> Iterator[dict[str, str]]:
        for shard in urls:
            verify_shard(refs[shard["url"]])
            yield shard

    return _tar_samples(list(refs), checked)


def interleave(streams: Iterable[Iterator[Any]], lanes: int) -> Iterator[Any]:
    """The items of ``streams`` read ``lanes`` streams at a time, an item from each in turn; a stream that ends
    gives its place to the next one. A stream is started only when its turn first comes (a shard is opened,
    and checked, only then). ``lanes=1`` gives the streams one after another."""
    pending = iter(streams)
    open_ = list(itertools.islice(pending, lanes))
    turn = 0
    while open_:
        turn %= len(open_)
        try:
            item = next(open_[turn])
        except StopIteration:
            following = next(pending, None)
            if following is None:
                del open_[turn]
            else:
                open_[turn] = following
            continue
        yield item
        turn += 1


def iter_samples(path: Path | str) -> Iterator[dict[str, Any]]:
    """Yield the samples of one shard (a path or URL) as they are, unchecked: for shards whose reader checks
    them itself (the truth shards; :func:`iter_clips` for the dataset's)."""
    yield from _tar_samples([str(path)])


def _tar_samples(urls: list[str], opening: Callable[[Iterator[dict[str, str]]], Iterator[dict[str, str]]] | None = None
                 ) -> wds.WebDataset:
    """The samples of ``urls`` in order (no shuffling or splitting: readers choose their shards themselves);
    ``opening`` sees each shard just before it is opened. A broken shard raises :class:`ShardError`."""
    return wds.WebDataset(urls, shardshuffle=False, nodesplitter=None, workersplitter=opening,
                          handler=_raise_shard_error, empty_check=False)


def iter_clips(root: Path, split: str, sources: Collection[str] | None = None) -> Iterator[Clip]:
    """Every clip of a split in manifest order, or of its shards named in ``sources`` (``<split>/<shard>.tar``, as
    the latent cache's chunk table names them), each shard checked just before it is read."""
    refs = shard_refs(root, split)
    if sources is not None:
        names = tuple(f"/{source}" for source in sources)
        refs = [ref for ref in refs if ref.url.endswith(names)]
    for ref in refs:
        for sample in shard_dataset([ref]):
            yield Clip.from_sample(sample, ref.url)


@dataclass
class Clip:
    """A decoded-on-demand clip: JPEG bytes stay compressed until a frame is asked for."""

    key: str
    meta: dict[str, Any]
    jpegs: list[bytes]
    odometry: np.ndarray  # [n, 2] speed, yaw rate
    pose: np.ndarray      # [n, 3]
    labels: dict[str, np.ndarray] | None
    pixels: np.ndarray | None = None  # every frame decoded ahead (see read_clips), else None

    @classmethod
    def from_sample(cls, sample: dict[str, Any], source: str = "") -> "Clip":
        key, source = sample["__key__"], source or sample.get("__url__", "")
        try:
            meta = json.loads(sample["json"])
            jpegs = [sample[f"{i:04d}.jpg"] for i in range(meta["frames"])]
            labels = load_npz(sample["labels.npz"]) if "labels.npz" in sample else None
            return cls(key, meta, jpegs, load_npy(sample["odometry.npy"]), load_npy(sample["pose.npy"]), labels)
        except (KeyError, ValueError) as err:
            raise ShardError(f"{source}: sample '{key}' is incomplete or malformed ({err!r}); "
                             f"re-run the `shards` stage") from err

    def frames(self, indices: np.ndarray | list[int]) -> np.ndarray:
        """RGB uint8 ``[len(indices), H, W, 3]``."""
        if self.pixels is not None:
            return self.pixels[np.asarray(indices, dtype=np.int64)]
        out = []
        for i in indices:
            bgr = cv2.imdecode(np.frombuffer(self.jpegs[i], np.uint8), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ShardError(f"clip '{self.key}': frame {i} is not a decodable JPEG; re-run the `shards` stage")
            out.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        return np.stack(out)

    def decoded(self) -> "Clip":
        """This clip with every frame decoded (and its JPEG bytes dropped)."""
        return Clip(self.key, self.meta, [], self.odometry, self.pose, self.labels, self.frames(range(len(self))))

    def __len__(self) -> int:
        return len(self.pixels) if self.pixels is not None else len(self.jpegs)


def split_clips(root: Path, split: str, keys: Collection[str] | None = None,
                sources: Collection[str] | None = None) -> dict[str, Clip]:
    """The clips of a split's shards by key, every one or those of ``keys``, read from every shard of the split or
    those named in ``sources`` (:func:`iter_clips`); JPEGs stay compressed until frames are asked for."""
    return {clip.key: clip for clip in iter_clips(root, split, sources) if keys is None or clip.key in keys}


def split_digest(root: Path, split: str) -> str:
    """A digest of a split's shards (their SHA-256 from the manifest), e.g. to key statistics cached from them."""
    shards = load_manifest(root)["splits"][split]["shards"]
    return hashlib.sha256("".join(s["sha256"] for s in shards).encode()).hexdigest()[:16]


def clip_window(clip: Clip, data: DataConfig, anchor: int) -> dict[str, Any]:
    """The two windows (frames and odometry) of one clip at one anchor."""
    detail, abstract = window_indices(data, anchor)
    valid = anchor_range(data, len(clip))
    if anchor not in valid:
        raise ValueError(f"anchor {anchor} outside {valid} for clip '{clip.key}' of {len(clip)} frames")
    span = window_span(detail, abstract)
    return {
        "key": clip.key,
        "anchor": anchor,
        "detail_frames": clip.frames(detail),
        "abstract_frames": clip.frames(abstract),
        "detail_odometry": clip.odometry[detail],
        "abstract_odometry": clip.odometry[abstract],
        "odometry": clip.odometry[span],
        "has_odometry": bool(clip.meta["has_odometry"]),
    }


def assign(items: int, rank: int, world: int, worker: int, workers: int) -> tuple[str, int, int]:
    """How one reader (rank, worker) takes its part: whole shards if there are enough, else every n-th sample.

    Slots go rank-fastest (slot = worker * world + rank), so each rank holds every ``world``-th item,
    as ``split_by_node`` then ``split_by_worker`` would give it, and ranks differ by one item at most."""
    slot, slots = worker * world + rank, world * workers
    return ("shards" if items >= slots else "samples"), slot, slots


class ClipStream(IterableDataset):
    """Clips of a split's shards, read by ``webdataset`` and partitioned across ranks and workers.

    Ranks come from ``rank``/``world`` or, like ``wds.split_by_node``, from ``RANK``/``WORLD_SIZE``
    or ``torch.distributed``; DataLoader workers split a rank's shards like ``wds.split_by_worker``.
    With fewer shards than (ranks x workers) every reader keeps every n-th sample instead, so
    all ranks still get the same number of clips (give or take one) and none waits at a barrier.

    ``interleave`` shards are read side by side, a clip from each in turn (:func:`interleave`): a shard
    holds minutes of one video, so a reader that took its shards one at a time would fill a shuffle buffer
    with one street. 1 reads them one after another. Each shard is checked just before it is read.
    Iterating yields the clips themselves; subclasses turn each clip into training items
    (``items``). ``seed`` and ``epoch`` make every random choice reproducible.
    """

    def __init__(self, root: Path, split: str, seed: int = 0, epoch: int = 0,
                 rank: int | None = None, world: int | None = None, base_url: str | None = None,
                 interleave: int = 1):
        if interleave < 1:
            raise ValueError(f"interleave must be >= 1, got {interleave}")
        self.shards = shard_refs(root, split, base_url)
        self.seed, self.epoch, self.interleave = seed, epoch, interleave
        node_rank, node_world, _, _ = wds.utils.pytorch_worker_info()
        self.rank = rank if rank is not None else node_rank
        self.world = world if world is not None else node_world

    def clips(self) -> Iterator[Clip]:
        info = get_worker_info()
        worker, workers = (info.id, info.num_workers) if info else (0, 1)
        mode, slot, slots = assign(len(self.shards), self.rank, self.world, worker, workers)
        # whole shards: every world-th from the rank on, then every workers-th of those from the worker on
        mine = self.shards[self.rank::self.world][worker::workers] if mode == "shards" else self.shards
        samples = interleave((iter(shard_dataset([ref])) for ref in mine), self.interleave)
        if mode == "samples":
            samples = (s for i, s in enumerate(samples) if i % slots == slot)
        for sample in samples:
            yield Clip.from_sample(sample)

    def rng(self, clip: Clip) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.epoch, zlib.crc32(clip.key.encode())])

    def items(self, clip: Clip) -> Iterator[Any]:
        yield clip

    def __iter__(self) -> Iterator[Any]:
        for clip in self.clips():
            yield from self.items(clip)


class _DecodedClips(ClipStream):
    def items(self, clip: Clip) -> Iterator[Clip]:
        yield clip.decoded()


def read_clips(root: Path, split: str, workers: int = 0) -> Iterator[Clip]:
    """Every clip of a split exactly once, frames decoded in ``workers`` processes (``wds.WebLoader``).

    The order is fixed for a given ``workers`` (the loader takes one clip from each worker in
    turn), not the manifest's: index clips by key. A broken shard raises :class:`ShardError`.
    """
    dataset = _DecodedClips(root, split, rank=0, world=1)
    if workers == 0:
        yield from dataset
        return
    yield from wds.WebLoader(dataset, batch_size=None, num_workers=workers, collate_fn=_identity)


def _identity(item: Any) -> Any:
    return item


class WindowDataset(ClipStream):
    """Two-rate windows: ``anchors="random"`` draws one anchor per clip per epoch (training),
    ``anchors="first"`` takes the earliest (deterministic evaluation)."""

    def __init__(self, root: Path, split: str, data: DataConfig, anchors: str = "random", **kwargs: Any):
        if anchors not in ("random", "first"):
            raise ValueError(f"anchors must be 'random' or 'first', got {anchors!r}")
        super().__init__(root, split, **kwargs)
        self.data, self.anchors = data, anchors

    def items(self, clip: Clip) -> Iterator[dict[str, Any]]:
        valid = anchor_range(self.data, len(clip))
        if len(valid) == 0:
            return
        anchor = valid[0] if self.anchors == "first" else int(self.rng(clip).integers(valid.start, valid.stop))
        yield clip_window(clip, self.data, anchor)


class FrameDataset(ClipStream):
    """Single RGB frames (``uint8 [H, W, 3]``) for the tokenizers: ``per_clip`` random frames per clip."""

    def __init__(self, root: Path, split: str, per_clip: int = 4, **kwargs: Any):
        super().__init__(root, split, **kwargs)
        self.per_clip = per_clip

    def items(self, clip: Clip) -> Iterator[np.ndarray]:
        picks = self.rng(clip).choice(len(clip), size=min(self.per_clip, len(clip)), replace=False)
        yield from clip.frames(np.sort(picks))
