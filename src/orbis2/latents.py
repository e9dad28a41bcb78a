"""The latent cache: both tokenizers encode every native frame of every clip once, in parts, one chunk per shard.

Training the predictors re-reads the same frames for thousands of steps; decoding
JPEGs and running two ViT encoders per step would cost far more than the predictor
itself. The ``latents`` stage therefore encodes every frame once and stores

    <root>/meta.json                        tokenizer checksums, shards manifest hash, geometry, index checksums
    <root>/normalization.npz                each tokenizer's latent normalisation (shift, scale)
    <root>/<split>/chunks.npy               one row per chunk: name, source shard, frames, clips, first row,
                                            the SHA-256 of each of its files (blocks.npy's too)
    <root>/<split>/clips.npy                one row per clip, in split order: key, chunk, row in the chunk,
                                            row in the split, length, has_odometry, episode, start_frame
    <root>/<split>/<chunk>/detail.npy       float16 [n, C, h, w]     (unscaled detail latent)
    <root>/<split>/<chunk>/abstract.npy     float16 [n, C', h', w']  (unscaled abstract latent)
    <root>/<split>/<chunk>/odometry.npy     float32 [n, 2]           (speed, yaw rate)
    <root>/<split>/<chunk>/clips.npy        the chunk's own rows of the clip table (what the gather reads)
    <root>/<split>/<chunk>/blocks.npy       per block of ``BLOCK_ROWS`` rows: the SHA-256 of that block of each
                                            of detail, abstract and odometry (what a reader checks)

One chunk per source shard, named after it (``train/train-000003.tar`` -> ``train/train-000003/``),
its clips in the shard's order: the chunks of a split, in the manifest's order, hold the split's frames
in the order of its samples (rows numbered across chunks give each frame one row in the split).

**Parts.** Part ``i`` of ``parts`` (params.yaml ``parts``, the shards' setting) encodes the ``i``-th
contiguous block of each split's shards into a work folder (:func:`encode_part`); each shard is
checked against the shards manifest just before it is read, encoded in batches of
``latents.batch_size`` frames counted from the shard's first frame, written as one chunk
(``.partial`` folder, synced, renamed) and then recorded in the part's ``done.jsonl``. A killed
part, started again, keeps every recorded chunk and starts at the shard in flight (with decode
workers, one shard per worker is in flight: on CUDA a part decodes shards in every core of its job
but one, :func:`decode_workers`). Batches never cross a shard, so which part, worker or restart
encodes a shard does not change its latents: ``parts=N`` gives the latents of ``parts=1`` bit for
bit. A work folder made from other inputs (shards manifest, tokenizer
checksums, settings; the stage's folder also the code) is never resumed, nor is a part's work
encoded on another kind of device. The gather (:func:`gather_parts`) moves every part's chunks
into the cache and writes the split tables and ``meta.json``.

**Memory.** A part holds the clips of the shards in flight and their latents (one shard's each),
whatever the corpus; the gather writes the clip table through a memory map; a reader holds numpy
arrays, one row per clip and per chunk (no Python object per clip or window, no JSON index).

**Precision.** The encoders run in float32 on the CPU and under bfloat16 autocast on CUDA; the
cache stores float16, which already halves the footprint of float32. The latents are
L2-normalised (|x| <= 1), where float16 keeps about three significant digits. They are stored as
the tokenizers encode them; readers apply the tokenizer's normalisation (``TokenizerFile.normalize``:
per-position mean removed, per-channel unit variance) on the fly.

Why memory-mapped ``.npy`` arrays rather than tar shards of latents: a training item is a strided
window of 10 + 6 frames of one clip at a random anchor, and with a memory map that is an O(1) row
gather (no archive scan, no decoding, no per-sample deserialisation), so the dataset can be
map-style and indexed at random, which lets ``DistributedSampler`` and DataLoader workers shard it
exactly. Every worker process maps the same files, so the OS page cache holds one copy of the
cache however many workers and ranks read it. The clip keys survive in ``clips.npy``, so every
cached frame traces back to its sample in ``data/shards``.

**Integrity.** ``meta.json`` records the SHA-256 of each split's two tables and of the
normalisation file; ``chunks.npy`` that of every chunk file; a chunk's ``blocks.npy`` that of
every block of ``BLOCK_ROWS`` rows of each of its arrays. A reader checks a split's tables when
it opens the split; when it maps a chunk's array, the file's header and size against the tables;
and before it returns rows, the blocks that hold them (``blocks.npy`` itself, small, hashed whole
against ``chunks.npy`` when first needed). Each block is hashed once per process, and DataLoader
workers and DDP ranks started from a process carry the record of what it checked. So a reader
hashes what it reads and at most a block more at each end of a read (a predictor's random
windows: 2-3x the rows they read, as they skip frames; never whole chunks), and a reader of the
odometry alone hashes no latents. :meth:`LatentCache.verify` (the check by hand) hashes whole
files. A flipped bit in a memory map would otherwise reach every predictor as a
plausible-looking latent.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, IterableDataset, get_worker_info
from tqdm import tqdm

from orbis2.config.sections import DataConfig
from orbis2.data.parts import PART_LOG, PartLog, keyed_work, part_name, part_slice
from orbis2.data.shards import MANIFEST, Clip, ShardRef, load_manifest, shard_dataset, shard_refs
from orbis2.errors import OrbisError
from orbis2.hierarchy import anchor_range, window_indices, window_span
from orbis2.io import HashingFile, atomic_dir, move_into, npz_bytes, sha256_file, write_json
from orbis2.models.files import TokenizerFile, load_tokenizer

# 4: one chunk per source shard, written in parts, each chunk checked when first read;
# 5: each chunk's blocks.npy (a SHA-256 per BLOCK_ROWS rows of each array), the rows checked as they are read
FORMAT = 5
KINDS = ("detail", "abstract")
ARRAYS = (*KINDS, "odometry")
META = "meta.json"
CHUNKS = "chunks.npy"
CLIPS = "clips.npy"
BLOCKS = "blocks.npy"
CHUNK_FILES = (*(f"{name}.npy" for name in ARRAYS), CLIPS, BLOCKS)
# Rows (frames) per checked block. A predictor's window spans about 16-30 native frames (26 in every
# profile), and a read hashes the blocks that hold its rows: at most its span plus a block at each end.
# A 26-frame window lies in at most 3 blocks of 16 (48 rows, 1.8x its span); blocks of 32 would hash up
# to 64 rows (2.5x). Smaller blocks cost more digests (32 bytes a block and array: 6 bytes a frame at 16,
# next to 36.9 kB of latents a frame at the paper's scale) and one more hash call a block (about 0.5 us).
BLOCK_ROWS = 16
# blocks.npy: one row per block, a 32-byte SHA-256 per array (uint8, not a bytes dtype: numpy's fixed-width
# bytes drop trailing zero bytes when read).
BLOCK_DTYPE = np.dtype([(name, "u1", (32,)) for name in ARRAYS])
NORMALIZATION = "normalization.npz"
PARTIAL = ".partial"  # a chunk being written (``.<chunk>.partial``, removed when a part starts again)


class LatentCacheError(OrbisError):
    """The latent cache is missing, incomplete, or was built from other inputs."""


# --------------------------------------------------------------------------- encoding


def to_model_input(frames: np.ndarray, device: str | torch.device | None = None) -> torch.Tensor:
    """RGB uint8 ``[N, H, W, 3]`` -> float ``[N, 3, H, W]`` in [-1, 1], the tokenizers' input range, on ``device``
    (the frames travel as bytes and are converted there: the same values on every device)."""
    x = torch.from_numpy(np.ascontiguousarray(frames))
    if device is not None:
        x = x.to(device)
    return x.permute(0, 3, 1, 2).float().div_(127.5).sub_(1.0)


def encode_frames(tokenizer: TokenizerFile, frames: np.ndarray, autocast: bool = False) -> torch.Tensor:
    """The tokenizer's latent (unscaled, float32, on the CPU) of a stack of RGB frames.

    ``autocast``: under bfloat16 autocast where the tokenizer is on CUDA (what the latent cache does); on
    the CPU the encoder runs in float32 either way."""
    model = tokenizer.model.eval()
    device = next(model.parameters()).device
    with torch.inference_mode(), torch.autocast(device.type, dtype=torch.bfloat16,
                                                enabled=autocast and device.type == "cuda"):
        return model.encode(to_model_input(frames, device)).float().cpu()


def encoder_mode(tokenizers: dict[str, TokenizerFile]) -> str:
    """How the cache's encoders run: ``cuda bfloat16 autocast`` or ``cpu float32`` (recorded in the meta; a
    part's work is never resumed on another kind of device)."""
    devices = sorted({next(t.model.parameters()).device.type for t in tokenizers.values()})
    return ", ".join(f"{d} bfloat16 autocast" if d == "cuda" else f"{d} float32" for d in devices)


MAX_DECODE_WORKERS = 8


def decode_workers(tokenizers: dict[str, TokenizerFile]) -> int:
    """How many processes read and decode shards beside the encoder by default: none on the CPU (the encoder's
    threads use the cores), on CUDA every core this process may run on but its own (a part job's: its Slurm
    ``cpus_per_task``, from the rule's threads), at most ``MAX_DECODE_WORKERS``. The latents do not depend on it."""
    if all(next(t.model.parameters()).device.type == "cpu" for t in tokenizers.values()):
        return 0
    return max(0, min(MAX_DECODE_WORKERS, len(os.sched_getaffinity(0)) - 1))


def encode_window(window: dict[str, Any], detail: TokenizerFile, abstract: TokenizerFile) -> dict[str, Any]:
    """Encode one ``clip_window`` on the fly into the item ``LatentWindowDataset`` serves from the cache."""
    return _item(window["key"], window["anchor"],
                 detail.normalize(encode_frames(detail, window["detail_frames"])),
                 abstract.normalize(encode_frames(abstract, window["abstract_frames"])),
                 window["detail_odometry"], window["abstract_odometry"], window["odometry"],
                 window["has_odometry"])


def _item(key: str, anchor: int, detail: torch.Tensor, abstract: torch.Tensor, detail_odometry: np.ndarray,
          abstract_odometry: np.ndarray, odometry: np.ndarray, has_odometry: bool) -> dict[str, Any]:
    def odo(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.asarray(a, np.float32))

    return {"key": key, "anchor": int(anchor), "detail": detail, "abstract": abstract,
            "detail_odometry": odo(detail_odometry), "abstract_odometry": odo(abstract_odometry),
            "odometry": odo(odometry), "has_odometry": bool(has_odometry)}


# --------------------------------------------------------------------------- tokenizers


def _resolve(tokenizer: TokenizerFile | str | Path, kind: str,
             device: str | torch.device | None) -> tuple[TokenizerFile, str | None]:
    """A loaded tokenizer and, when it was given as a path, that path (recorded for error messages)."""
    if isinstance(tokenizer, TokenizerFile):
        loaded, path = tokenizer, None
    else:
        path = str(tokenizer)
        loaded = load_tokenizer(Path(path), device or ("cuda" if torch.cuda.is_available() else "cpu"))
    if loaded.kind != kind:
        raise LatentCacheError(f"{path or 'the given tokenizer'}: is a {loaded.kind} tokenizer, "
                               f"expected the {kind} one")
    return loaded, path


def load_encoders(detail: TokenizerFile | str | Path, abstract: TokenizerFile | str | Path,
                  device: str | torch.device | None = None) -> tuple[dict[str, TokenizerFile], dict[str, str | None]]:
    """Both tokenizers (loaded ones are used on their own device; paths are loaded on ``device``, default CUDA
    when present) and the paths they came from (None for loaded ones)."""
    tokenizers, files = {}, {}
    for kind, tokenizer in zip(KINDS, (detail, abstract)):
        tokenizers[kind], files[kind] = _resolve(tokenizer, kind, device)
    return tokenizers, files


def latent_shapes(tokenizers: dict[str, TokenizerFile], height: int, width: int) -> dict[str, tuple[int, ...]]:
    """Each tokenizer's latent shape ``(C, h, w)`` for frames of ``height`` x ``width``."""
    probe = np.zeros((1, height, width, 3), np.uint8)
    return {kind: tuple(encode_frames(tokenizers[kind], probe).shape[1:]) for kind in KINDS}


# --------------------------------------------------------------------------- parts


def chunk_name(shard: dict[str, Any]) -> str:
    """A chunk's name: its source shard's file name without ``.tar`` (``train/train-000003.tar``: ``train-000003``)."""
    return Path(shard["path"]).name.removesuffix(".tar")


def _splits(manifest: dict[str, Any], splits: Sequence[str] | None) -> list[str]:
    splits = list(manifest["splits"]) if splits is None else list(splits)
    missing = [s for s in splits if s not in manifest["splits"]]
    if missing:
        raise LatentCacheError(f"the shards have no split {', '.join(missing)} (have {list(manifest['splits'])}); "
                               f"re-run the `shards` stage")
    return splits


def latent_work(work: Path, shards_root: Path, tokenizers: dict[str, TokenizerFile], batch_size: int,
                splits: Sequence[str] | None = None) -> Path:
    """``work`` as the parts' folder of these inputs (:func:`~orbis2.data.parts.keyed_work`): the shards manifest,
    the tokenizers (by checksum), the batch size, the splits and the cache format. One made from others is emptied."""
    manifest = load_manifest(shards_root)
    return keyed_work(Path(work), {"format": FORMAT, "manifest": sha256_file(Path(shards_root) / MANIFEST),
                                   "tokenizers": {kind: t.checksum for kind, t in tokenizers.items()},
                                   "batch_size": batch_size, "splits": _splits(manifest, splits)})


class _ChunkLog(PartLog):
    """A latents part's progress (``done.jsonl``): one line per chunk in place, with its clips' count, frames, the
    device that encoded it and its files' SHA-256. Work whose chunks a gather moved out starts over."""

    def stale(self, events: list[dict[str, Any]]) -> bool:
        return any(not (self.folder / e["split"] / e["chunk"]).is_dir() for e in events)

    def clean(self) -> None:
        for partial in self.folder.glob(f"*/.*{PARTIAL}"):
            shutil.rmtree(partial)


def encode_part(shards_root: str | Path, work: str | Path, tokenizers: dict[str, TokenizerFile], batch_size: int,
                part: int = 0, parts: int = 1, splits: Sequence[str] | None = None, workers: int | None = None,
                base_url: str | None = None) -> dict[str, Any]:
    """Encode part ``part`` of ``parts`` (the contiguous block of each split's shards, :func:`part_slice`) into
    ``work/<part_name>/<split>/<chunk>/``; return the part's manifest (its chunks per split, in shard order).

    Resumes where it stopped: chunks recorded in ``done.jsonl`` are kept and the others encoded, unless
    those were encoded on another kind of device (CUDA under bfloat16 autocast, or the CPU in float32):
    then the part starts over, so that a cache never mixes the two. A part found finished is returned
    as it is, whatever this process's device (a gather on a CPU node). ``workers`` > 0 processes read and
    decode shards (one shard each at a time) while this one encodes (default: :func:`decode_workers`).
    ``work`` must belong to these inputs (:func:`latent_work`).
    """
    shards_root = Path(shards_root)
    manifest = load_manifest(shards_root)
    splits = _splits(manifest, splits)
    encoder = encoder_mode(tokenizers)
    folder = Path(work) / part_name(part, parts)
    log = _ChunkLog(folder)
    todo = _todo(shards_root, manifest, splits, log, part, parts, base_url)
    if todo and any(e["encoder"] != encoder for e in log.events):
        shutil.rmtree(folder)
        log = _ChunkLog(folder)
        todo = _todo(shards_root, manifest, splits, log, part, parts, base_url)
    with tqdm(total=len(todo), desc=f"latents {part_name(part, parts)}", unit="chunk") as bar:
        workers = decode_workers(tokenizers) if workers is None else workers
        for (split, i), arrays, clips in _encoded_shards(todo, tokenizers, batch_size, workers):
            shard = manifest["splits"][split]["shards"][i]
            name = chunk_name(shard)
            digests = write_chunk(folder / split / name, arrays, clips)
            log.add({"split": split, "chunk": name, "index": i, "source": shard["path"], "encoder": encoder,
                     "frames": len(arrays["odometry"]), "clips": len(clips), "sha256": digests})
            bar.update(1)
    return {"folder": str(folder), "encoder": log.events[0]["encoder"] if log.events else encoder,
            "splits": {split: sorted((e for e in log.events if e["split"] == split), key=lambda e: e["index"])
                       for split in splits}}


def _todo(shards_root: Path, manifest: dict[str, Any], splits: list[str], log: _ChunkLog, part: int, parts: int,
          base_url: str | None) -> list[tuple[tuple[str, int], ShardRef]]:
    """``((split, shard index), shard)`` of the part's shards not yet recorded in its log."""
    done = {(e["split"], e["chunk"]) for e in log.events}
    todo = []
    for split in splits:
        shards = manifest["splits"][split]["shards"]
        refs = shard_refs(shards_root, split, base_url)
        todo += [((split, i), refs[i]) for i in range(len(shards))[part_slice(len(shards), part, parts)]
                 if (split, chunk_name(shards[i])) not in done]
    return todo


class _ShardClips(IterableDataset):
    """The decoded clips of a list of shards, as ``(task, clip)`` items and a ``(task, None)`` when a shard ends; in
    DataLoader worker processes each takes every n-th shard. Each shard is checked against the manifest just
    before it is read; a damaged one yields its error, which the encoding process raises as it is."""

    def __init__(self, todo: list[tuple[Any, ShardRef]]):
        self.todo = todo

    def __iter__(self) -> Iterator[tuple[Any, Any]]:
        info = get_worker_info()
        mine = self.todo if info is None else self.todo[info.id::info.num_workers]
        for task, ref in mine:
            try:
                for sample in shard_dataset([ref]):  # checked against the manifest before it is read
                    clip = Clip.from_sample(sample, ref.url)
                    # a tensor, so that a worker hands the frames over in shared memory
                    yield task, (clip.key, clip.meta, torch.from_numpy(clip.frames(range(len(clip)))), clip.odometry)
            except OrbisError as err:
                yield task, err
                return
            yield task, None


def _one_thread(worker: int) -> None:
    cv2.setNumThreads(1)  # a decode worker is one core's work: the workers, not threads, use the others


def _identity(item: Any) -> Any:
    return item


class _Chunk:
    """One shard's clips as they arrive, encoded in batches of ``batch_size`` frames counted from the shard's first
    frame, so that the latents do not depend on which part, worker or restart encodes the shard."""

    def __init__(self, tokenizers: dict[str, TokenizerFile], batch_size: int):
        self.tokenizers, self.batch_size = tokenizers, batch_size
        self.latents: dict[str, list[np.ndarray]] = {kind: [] for kind in KINDS}
        self.odometry: list[np.ndarray] = []
        self.clips: list[tuple[str, int, bool, str, int]] = []
        self.pending: list[np.ndarray] = []

    def add(self, key: str, meta: dict[str, Any], pixels: torch.Tensor | np.ndarray, odometry: np.ndarray) -> None:
        pixels = pixels.numpy() if isinstance(pixels, torch.Tensor) else pixels
        self.clips.append((key, len(pixels), bool(meta["has_odometry"]), str(meta["episode"]),
                           int(meta["start_frame"])))
        self.odometry.append(np.asarray(odometry, np.float32))
        for frame in pixels:
            self.pending.append(frame)
            if len(self.pending) == self.batch_size:
                self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        frames = np.stack(self.pending)
        for kind in KINDS:
            half = encode_frames(self.tokenizers[kind], frames, autocast=True).numpy().astype(np.float16)
            if not np.isfinite(half).all():
                raise LatentCacheError(f"the {kind} tokenizer produced latents outside the float16 range; "
                                       f"the cache stores float16 and cannot hold them")
            self.latents[kind].append(half)
        self.pending = []

    def finish(self) -> tuple[dict[str, np.ndarray], np.ndarray]:
        self.flush()
        arrays = {kind: np.concatenate(self.latents[kind]) for kind in KINDS}
        arrays["odometry"] = np.concatenate(self.odometry)
        return arrays, clip_table(self.clips)


def _encoded_shards(todo: list[tuple[Any, ShardRef]], tokenizers: dict[str, TokenizerFile],
                    batch_size: int, workers: int) -> Iterator[tuple[Any, dict[str, np.ndarray], np.ndarray]]:
    """``(task, arrays, clip table)`` of each shard of ``todo``, as each is finished (in order without workers)."""
    dataset = _ShardClips(todo)
    workers = min(workers, len(todo))
    stream = iter(dataset) if workers == 0 else iter(DataLoader(
        dataset, batch_size=None, num_workers=workers, collate_fn=_identity, worker_init_fn=_one_thread))
    building: dict[Any, _Chunk] = {}
    for task, item in stream:
        if isinstance(item, BaseException):
            raise item
        if item is None:
            yield (task, *building.pop(task, _Chunk(tokenizers, batch_size)).finish())
        else:
            building.setdefault(task, _Chunk(tokenizers, batch_size)).add(*item)


def clip_table(clips: Sequence[tuple[str, int, bool, str, int]]) -> np.ndarray:
    """A chunk's clip table: ``(key, length, has_odometry, episode, start_frame)`` per clip -> structured rows
    with each clip's first ``row`` in the chunk."""
    width = lambda values: max([1, *map(len, values)])  # noqa: E731
    table = np.zeros(len(clips), [("key", f"U{width([c[0] for c in clips])}"), ("row", "i8"), ("length", "i8"),
                                  ("has_odometry", "?"), ("episode", f"U{width([c[3] for c in clips])}"),
                                  ("start_frame", "i8")])
    for field, column in zip(("key", "length", "has_odometry", "episode", "start_frame"), zip(*clips)):
        table[field] = column
    table["row"] = np.cumsum(table["length"]) - table["length"]
    return table


def _save(path: Path, array: np.ndarray) -> str:
    """``array`` as ``.npy`` (the bytes ``np.save`` writes), synced; its SHA-256, computed as it is written."""
    file = HashingFile(path)
    np.lib.format.write_array(file, np.ascontiguousarray(array), allow_pickle=False)
    return file.finish()[1]


def block_digest(rows: np.ndarray) -> bytes:
    """The SHA-256 of rows' raw bytes (C order: the bytes a ``.npy`` file holds after its header).

    SHA-256 rather than BLAKE2: with the CPUs' SHA extensions hashlib's SHA-256 ran at about 1.6 GiB/s
    here, ``blake2b(digest_size=16)`` at about 0.8 GiB/s, and it is the hash every other check uses."""
    return hashlib.sha256(np.ascontiguousarray(rows)).digest()


def chunk_blocks(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """A chunk's ``blocks.npy``: for each block of ``BLOCK_ROWS`` rows (the last one may be shorter), the
    :func:`block_digest` of those rows of each of ``ARRAYS`` (which have one row per frame each)."""
    frames = len(arrays[ARRAYS[0]])
    table = np.zeros(-(-frames // BLOCK_ROWS), BLOCK_DTYPE)
    for name in ARRAYS:
        array = np.ascontiguousarray(arrays[name])
        if len(array) != frames:
            raise ValueError(f"{name}: {len(array)} rows, {ARRAYS[0]} has {frames}")
        for b in range(len(table)):
            table[name][b] = np.frombuffer(block_digest(array[b * BLOCK_ROWS:(b + 1) * BLOCK_ROWS]), np.uint8)
    return table


def write_chunk(folder: Path, arrays: dict[str, np.ndarray], clips: np.ndarray) -> dict[str, str]:
    """One chunk's files (``arrays``: detail, abstract, odometry; ``clips``: its :func:`clip_table`; ``blocks.npy``:
    the arrays' :func:`chunk_blocks`) into ``folder``, atomically (a ``.partial`` folder beside it, synced,
    renamed); their SHA-256, computed as they are written."""
    partial = folder.with_name(f".{folder.name}{PARTIAL}")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    digests = {f"{name}.npy": _save(partial / f"{name}.npy", arrays[name]) for name in ARRAYS}
    digests[CLIPS] = _save(partial / CLIPS, clips)
    digests[BLOCKS] = _save(partial / BLOCKS, chunk_blocks(arrays))
    shutil.rmtree(folder, ignore_errors=True)  # written but not recorded when a part was killed: written again
    os.replace(partial, folder)
    return digests


# --------------------------------------------------------------------------- gathering


def gather_parts(shards_root: str | Path, written: list[dict[str, Any]], out_root: str | Path,
                 tokenizers: dict[str, TokenizerFile], files: dict[str, str | None],
                 splits: Sequence[str] | None = None) -> dict[str, Any]:
    """Every part's chunks, in part order, moved into ``out_root/<split>/<chunk>/``, each split's tables
    (``chunks.npy``, ``clips.npy``), the normalisation and ``meta.json``; returns the meta.

    Moved, not copied: no second copy, and the files stay the ones the parts wrote and hashed. A part whose
    chunks were gathered is encoded again if it is asked for again."""
    shards_root, out_root = Path(shards_root), Path(out_root)
    manifest = load_manifest(shards_root)
    splits = _splits(manifest, splits)
    encoders = sorted({w["encoder"] for w in written})
    if len(encoders) > 1:
        raise LatentCacheError(f"the parts were encoded on different kinds of device ({' and '.join(encoders)}): "
                               f"their latents differ; run every part on one kind (delete the others' work folders)")
    meta = cache_meta(shards_root, tokenizers, files, encoders[0] if encoders else encoder_mode(tokenizers))
    for split in splits:
        entries = [(Path(w["folder"]) / split / c["chunk"], c) for w in written for c in w["splits"][split]]
        shards = manifest["splits"][split]["shards"]
        if [c["index"] for _, c in entries] != list(range(len(shards))):
            raise LatentCacheError(f"{shards_root / MANIFEST}: the parts hold chunks of shards "
                                   f"{[c['index'] for _, c in entries]} of split '{split}', not each of its "
                                   f"{len(shards)} once; re-run the `latents` stage")
        (out_root / split).mkdir(parents=True)
        for path, chunk in entries:
            move_into(path, out_root / split / chunk["chunk"])
        meta["splits"][split] = write_split(out_root / split, [c for _, c in entries])
        if meta["splits"][split]["frames"] != manifest["splits"][split]["frames"]:
            raise LatentCacheError(f"{shards_root / MANIFEST}: split '{split}' lists "
                                   f"{manifest['splits'][split]['frames']} frames but its shards hold "
                                   f"{meta['splits'][split]['frames']}; re-run the `shards` stage")
    write_meta(out_root, meta, tokenizers)
    return meta


def cache_meta(shards_root: Path, tokenizers: dict[str, TokenizerFile], files: dict[str, str | None],
               encoder: str) -> dict[str, Any]:
    """``meta.json`` of a cache of ``shards_root`` by ``tokenizers``, without its splits yet."""
    manifest = load_manifest(shards_root)
    shapes = latent_shapes(tokenizers, manifest["height"], manifest["width"])
    return {"format": FORMAT, "dtype": "float16", "encoder": encoder,
            "shards": {"root": str(shards_root), "manifest_sha256": sha256_file(shards_root / MANIFEST)},
            "data": {key: manifest[key] for key in ("source", "fps", "width", "height")},
            "tokenizers": {kind: {"checksum": tokenizers[kind].checksum, "file": files[kind],
                                  "build": tokenizers[kind].build, "shape": list(shapes[kind])} for kind in KINDS},
            "splits": {}}


def write_meta(root: Path, meta: dict[str, Any], tokenizers: dict[str, TokenizerFile] | None = None,
               normalization: dict[str, np.ndarray] | None = None) -> None:
    """``normalization.npz`` (each tokenizer's ``shift`` and ``scale``, or ``normalization``'s arrays) and
    ``meta.json`` (with the former's SHA-256), the last files a cache gets."""
    if normalization is None:
        normalization = {f"{kind}_{part}": getattr(tokenizers[kind], part).cpu().numpy()
                         for kind in KINDS for part in ("shift", "scale")}
    (root / NORMALIZATION).write_bytes(npz_bytes(**normalization))
    write_json(root / META, {**meta, "normalization_sha256": sha256_file(root / NORMALIZATION)})


def write_split(folder: Path, chunks: list[dict[str, Any]]) -> dict[str, Any]:
    """A split's tables from its chunks, in split order, each in ``folder/<chunk>/`` and described by its part's
    record (``chunk``, ``source``, ``frames``, ``clips``, ``sha256`` of its files): ``chunks.npy`` and
    ``clips.npy`` (written through a memory map, so the table is never held whole); the split's meta entry.
    Each chunk's own clip table is checked against its part's record before it is read."""
    widths = {"key": 1, "episode": 1}
    for chunk in chunks:
        table = folder / chunk["chunk"] / CLIPS
        _check_file(table, chunk["sha256"][CLIPS], f"its part's {PART_LOG}")
        dtype = np.load(table, mmap_mode="r", allow_pickle=False).dtype
        widths = {field: max(width, dtype[field].itemsize // 4) for field, width in widths.items()}
    width = lambda values: max([1, *map(len, values)])  # noqa: E731
    table = np.zeros(len(chunks), [("name", f"U{width([c['chunk'] for c in chunks])}"),
                                   ("source", f"U{width([c['source'] for c in chunks])}"),
                                   ("frames", "i8"), ("clips", "i8"), ("first_row", "i8"), ("first_clip", "i8"),
                                   *((f"{file.removesuffix('.npy')}_sha256", "U64") for file in CHUNK_FILES)])
    clips = np.lib.format.open_memmap(folder / CLIPS, "w+", np.dtype([
        ("key", f"U{widths['key']}"), ("chunk", "i8"), ("row", "i8"), ("offset", "i8"), ("length", "i8"),
        ("has_odometry", "?"), ("episode", f"U{widths['episode']}"), ("start_frame", "i8")]),
        (sum(c["clips"] for c in chunks),))
    rows = first = 0
    for k, chunk in enumerate(chunks):
        own = np.load(folder / chunk["chunk"] / CLIPS, allow_pickle=False)
        if len(own) != chunk["clips"] or int(own["length"].sum()) != chunk["frames"]:
            raise LatentCacheError(f"{folder / chunk['chunk'] / CLIPS}: {len(own)} clips, {own['length'].sum()} "
                                   f"frames; its part recorded {chunk['clips']}, {chunk['frames']}; "
                                   f"re-run the `latents` stage")
        table[k] = (chunk["chunk"], chunk["source"], chunk["frames"], chunk["clips"], rows, first,
                    *(chunk["sha256"][file] for file in CHUNK_FILES))
        block = clips[first:first + len(own)]
        for field in ("key", "row", "length", "has_odometry", "episode", "start_frame"):
            block[field] = own[field]
        block["chunk"], block["offset"] = k, rows + own["row"]
        rows, first = rows + chunk["frames"], first + len(own)
    clips.flush()
    del clips
    return {"frames": rows, "clips": first, "chunks": len(chunks),
            "sha256": {CHUNKS: _save(folder / CHUNKS, table), CLIPS: sha256_file(folder / CLIPS)}}


def build_latent_cache(shards_root: str | Path, out_root: str | Path, detail: TokenizerFile | str | Path,
                       abstract: TokenizerFile | str | Path, batch_size: int, splits: Sequence[str] | None = None,
                       device: str | torch.device | None = None, workers: int | None = None, parts: int = 1,
                       work: str | Path | None = None, base_url: str | None = None) -> dict[str, Any]:
    """Encode every native frame of every clip of ``splits`` (default: all in the manifest); returns the meta.

    Each of ``parts`` parts is encoded (or resumed, or found finished) in ``work`` (default:
    ``<out_root>.parts`` beside it; see :func:`latent_work`), then gathered into ``out_root``, which is
    built beside it and renamed into place only when complete. The latents do not depend on ``parts``
    or ``workers`` (the processes decoding shards, default :func:`decode_workers`; see :func:`encode_part`).

    ``detail``/``abstract`` are loaded tokenizers (used on their own device) or paths to tokenizer files
    (loaded on ``device``, default CUDA when present; the path is recorded so a stale cache can name it).
    """
    shards_root, out_root = Path(shards_root), Path(out_root)
    tokenizers, files = load_encoders(detail, abstract, device)
    work = latent_work(Path(work) if work is not None else out_root.with_name(out_root.name + ".parts"),
                       shards_root, tokenizers, batch_size, splits)
    written = [encode_part(shards_root, work, tokenizers, batch_size, part, parts, splits, workers, base_url)
               for part in range(parts)]
    with atomic_dir(out_root) as tmp:
        return gather_parts(shards_root, written, tmp, tokenizers, files, splits)


# --------------------------------------------------------------------------- reading


class SplitIndex:
    """A split's tables as numpy arrays: ``chunks`` (one row per chunk) and ``clips`` (one row per clip, in split
    order), the structured rows ``chunks.npy`` and ``clips.npy`` hold (see the module's layout)."""

    def __init__(self, chunks: np.ndarray, clips: np.ndarray):
        self.chunks, self.clips = chunks, clips
        self._order: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.clips)

    @property
    def keys(self) -> np.ndarray:
        return self.clips["key"]

    def find(self, keys: Sequence[str]) -> np.ndarray:
        """The clip table's rows of ``keys`` (vectorised: the keys sorted once, then binary search)."""
        if self._order is None:
            self._order = np.argsort(self.keys, kind="stable")
        ordered, wanted = self.keys[self._order], np.asarray(list(keys), dtype=str)
        at = np.searchsorted(ordered, wanted)
        found = np.zeros(len(wanted), bool)
        if len(ordered):
            found = (at < len(ordered)) & (ordered[np.minimum(at, len(ordered) - 1)] == wanted)
        if not found.all():
            raise KeyError(f"no clip {', '.join(map(str, wanted[~found][:5]))} in the split")
        return self._order[at]


def _row_blocks(rows: Any, n: int) -> np.ndarray | None:
    """The blocks (of ``BLOCK_ROWS`` rows) that indexing an array of ``n`` rows with ``rows`` reads, or None for
    an index it does not resolve (the caller checks every block). Rows outside the array are left to the
    array's own indexing to refuse."""
    if isinstance(rows, (int, np.integer)):
        r = int(rows) + (n if rows < 0 else 0)
        return np.array([r // BLOCK_ROWS] if 0 <= r < n else [], np.int64)
    if isinstance(rows, slice):
        start, stop, step = rows.indices(n)
        if step == 1:
            return np.arange(start // BLOCK_ROWS, (stop - 1) // BLOCK_ROWS + 1) if stop > start else np.zeros(0, int)
        rows = np.arange(start, stop, step)
    if rows is None or rows is Ellipsis:
        return None
    rows = np.asarray(rows)
    if rows.dtype == bool:
        if rows.ndim != 1:
            return None
        rows = np.flatnonzero(rows)
    if not np.issubdtype(rows.dtype, np.integer):
        return None
    flat = rows.ravel().astype(np.int64)
    flat = np.where(flat < 0, flat + n, flat)
    return np.unique(flat[(flat >= 0) & (flat < n)] // BLOCK_ROWS)


class ChunkArray:
    """One array file of a chunk (``detail``, ``abstract`` or ``odometry``), memory-mapped and indexed like it
    (``array[rows]``, ``array[rows, ...]``, ``np.asarray(array)``): before rows are returned, the blocks of
    ``BLOCK_ROWS`` rows that hold them are checked against the chunk's ``blocks.npy``, each block once per
    process (:meth:`LatentCache.check_blocks`). What the index returns is the map's (a view for a slice)."""

    def __init__(self, cache: LatentCache, split: str, c: int, name: str, path: Path, array: np.ndarray):
        self.cache, self.split, self.c, self.name, self.path, self.array = cache, split, c, name, path, array

    @property
    def shape(self) -> tuple[int, ...]:
        return self.array.shape

    @property
    def dtype(self) -> np.dtype:
        return self.array.dtype

    @property
    def ndim(self) -> int:
        return self.array.ndim

    def __len__(self) -> int:
        return len(self.array)

    def __getitem__(self, key: Any) -> np.ndarray:
        rows = (key[0] if key else Ellipsis) if isinstance(key, tuple) else key
        self.cache.check_blocks(self, _row_blocks(rows, len(self)))
        return self.array[key]

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> np.ndarray:
        self.cache.check_blocks(self, None)
        return np.array(self.array, dtype, copy=True) if copy else np.asarray(self.array, dtype)


class SplitArray:
    """One array (``detail``, ``abstract`` or ``odometry``) of a split, its chunks' rows numbered as one array.

    Indexed like the array it stands for (a row, a slice, an array of rows, optionally more axes after the
    rows: ``odometry[rows, 1]``); each chunk read is mapped (:meth:`LatentCache.chunk`), and the blocks holding
    the rows read are checked before they are returned (:class:`ChunkArray`). Returns numpy arrays."""

    def __init__(self, cache: LatentCache, split: str, name: str):
        index = cache.index(split)
        self.cache, self.split, self.name = cache, split, name
        frames = cache.meta["splits"][split]["frames"]
        self._starts = np.append(index.chunks["first_row"], frames).astype(np.int64)
        row = tuple(cache.meta["tokenizers"][name]["shape"]) if name in KINDS else (2,)
        self.shape = (frames, *row)
        self.dtype = np.dtype(np.float16 if name in KINDS else np.float32)

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def _rows(self, c: int) -> ChunkArray:
        return self.cache.chunk(self.split, c, (self.name,))[self.name]

    def _range(self, start: int, stop: int) -> np.ndarray:
        if stop <= start:
            return np.zeros((0, *self.shape[1:]), self.dtype)
        first, last = (int(np.searchsorted(self._starts, r, "right")) - 1 for r in (start, stop - 1))
        pieces = [self._rows(c)[max(start, self._starts[c]) - self._starts[c]:min(stop, self._starts[c + 1])
                                - self._starts[c]] for c in range(first, last + 1)]
        return pieces[0] if len(pieces) == 1 else np.concatenate(pieces)

    def __getitem__(self, key: Any) -> np.ndarray:
        rows, rest = (key[0], key[1:]) if isinstance(key, tuple) else (key, ())
        n = len(self)
        if isinstance(rows, slice):
            start, stop, step = rows.indices(n)
            if step == 1:
                out = self._range(start, stop)
                return out[(slice(None), *rest)] if rest else out
            rows = np.arange(start, stop, step)
        if isinstance(rows, (int, np.integer)):
            r = int(rows) + (n if rows < 0 else 0)
            if not 0 <= r < n:
                raise IndexError(f"row {rows} outside the {n} rows of {self.split}/{self.name}")
            c = int(np.searchsorted(self._starts, r, "right")) - 1
            out = self._rows(c)[r - self._starts[c]]
            return out[rest] if rest else out
        rows = np.asarray(rows)
        if rows.size == 0:
            rows = rows.astype(np.int64)
        if not np.issubdtype(rows.dtype, np.integer):
            raise TypeError(f"{self.split}/{self.name}: index rows with integers or a slice, not {rows.dtype}")
        flat = rows.ravel().astype(np.int64)
        flat = np.where(flat < 0, flat + n, flat)
        if flat.size and (flat.min() < 0 or flat.max() >= n):
            raise IndexError(f"rows outside the {n} rows of {self.split}/{self.name}")
        chunks = np.searchsorted(self._starts, flat, "right") - 1
        if flat.size and (chunks == chunks[0]).all():
            out = self._rows(int(chunks[0]))[flat - self._starts[chunks[0]]]
        else:
            out = np.empty((flat.size, *self.shape[1:]), self.dtype)
            for c in np.unique(chunks):
                at = chunks == c
                out[at] = self._rows(int(c))[flat[at] - self._starts[c]]
        out = out.reshape(*rows.shape, *self.shape[1:])
        return out[(slice(None),) * rows.ndim + rest] if rest else out


class LatentCache:
    """An opened cache: its meta, per-split tables, and each chunk's arrays mapped on first use.

    The rows read are checked block by block (:class:`ChunkArray`), each block the first time this process
    reads it: a reader hashes about what it reads, not whole chunks. The record of what was checked (the
    files hashed whole, a bit per block of each array read) travels with the object when it is pickled
    (DataLoader workers started by spawn/forkserver, DDP), as it does into forked workers, so no process
    hashes a block twice. The maps and the loaded ``blocks.npy`` are per process (dropped when pickled: each
    process maps the files instead of copying them), at most ``MAPPED`` chunks at a time (the least recently
    read unmapped first: a process may hold only so many maps).
    """

    MAPPED = 256

    def __init__(self, root: Path, meta: dict[str, Any]):
        self.root, self.meta = root, meta
        self._verified: set[str] = set()  # files checked by this process (or the one it was started from)
        self._checked: dict[str, np.ndarray] = {}  # per array file read: which of its blocks were checked (bools)
        self._indexes: dict[str, SplitIndex] = {}
        self._maps: OrderedDict[tuple[str, int], dict[str, ChunkArray]] = OrderedDict()
        self._digests: dict[tuple[str, int], np.ndarray] = {}  # the chunks' blocks.npy, as loaded
        path = root / NORMALIZATION
        self._check(path, meta["normalization_sha256"], META)
        try:
            with np.load(path) as norm:
                self.norm = {key: torch.from_numpy(norm[key]) for key in norm.files}
        except (OSError, ValueError) as err:
            raise LatentCacheError(f"{path}: unreadable ({err}); re-run the `latents` stage") from err

    def normalize(self, kind: str, z: np.ndarray | torch.Tensor) -> torch.Tensor:
        """Cached latents ``[..., C, h, w]`` as the predictors see them (the tokenizer's normalisation)."""
        z = torch.as_tensor(np.asarray(z, np.float32) if isinstance(z, np.ndarray) else z, dtype=torch.float32)
        return (z - self.norm[f"{kind}_shift"]) * self.norm[f"{kind}_scale"]

    @property
    def splits(self) -> list[str]:
        return list(self.meta["splits"])

    def _folder(self, split: str) -> Path:
        if split not in self.meta["splits"]:
            raise LatentCacheError(f"{self.root}: no split '{split}' in the latent cache (have {self.splits}); "
                                   f"re-run the `latents` stage")
        return self.root / split

    def _check(self, path: Path, digest: str, recorded_in: str) -> None:
        """``path`` against its recorded SHA-256, once per process (and the processes started from it)."""
        name = str(path.relative_to(self.root))
        if name not in self._verified:
            _check_file(path, digest, recorded_in)
            self._verified.add(name)

    def index(self, split: str) -> SplitIndex:
        """A split's chunk and clip tables, checked against ``meta.json`` when this process first opens them."""
        if split not in self._indexes:
            folder, info = self._folder(split), self.meta["splits"][split]
            tables = []
            for name, rows in ((CHUNKS, info["chunks"]), (CLIPS, info["clips"])):
                path = folder / name
                self._check(path, info["sha256"][name], META)
                try:
                    tables.append(np.load(path, allow_pickle=False))
                except (OSError, ValueError) as err:
                    raise LatentCacheError(f"{path}: unreadable ({err}); re-run the `latents` stage") from err
                if len(tables[-1]) != rows:
                    raise LatentCacheError(f"{path}: {len(tables[-1])} rows, meta.json says {rows}; "
                                           f"re-run the `latents` stage")
            self._indexes[split] = SplitIndex(*tables)
        return self._indexes[split]

    def chunk(self, split: str, c: int, names: Sequence[str] = ARRAYS) -> dict[str, ChunkArray]:
        """``names`` (default ``detail``, ``abstract`` and ``odometry``) of chunk ``c`` of a split as read-only memory
        maps (:class:`ChunkArray`: the rows read are checked as they are read). Mapping hashes nothing: it checks
        each file's header (shape, dtype, C order) against the cache's tables and its size against the header,
        so a truncated or replaced file is named here. A reader of the odometry alone (the turn repeats, the
        steering evaluation) hashes no latents."""
        key = (split, int(c))
        maps = self._maps.get(key)
        if maps is None:
            maps = self._maps[key] = {}
            if len(self._maps) > self.MAPPED:
                self._digests.pop(self._maps.popitem(last=False)[0], None)
        else:
            self._maps.move_to_end(key)
        missing = [name for name in names if name not in maps]
        if missing:
            row = self.index(split).chunks[c]
            folder = self._folder(split) / str(row["name"])
        for name in missing:
            path = folder / f"{name}.npy"
            if not path.is_file():
                raise LatentCacheError(f"{path}: missing from the latent cache; re-run the `latents` stage")
            try:
                array = np.load(path, mmap_mode="r")
            except (OSError, ValueError) as err:
                raise LatentCacheError(f"{path}: unreadable ({err}); re-run the `latents` stage") from err
            shape = (int(row["frames"]), *(self.meta["tokenizers"][name]["shape"] if name in KINDS else (2,)))
            dtype = np.dtype(np.float16 if name in KINDS else np.float32)
            if array.shape != shape:
                raise LatentCacheError(f"{path}: shape {array.shape}, the cache's tables say {shape}; "
                                       f"re-run the `latents` stage")
            if array.dtype != dtype or not array.flags.c_contiguous:
                raise LatentCacheError(f"{path}: a {array.dtype} array in {'C' if array.flags.c_contiguous else 'F'} "
                                       f"order, the cache's tables say {dtype} in C order; re-run the `latents` stage")
            size = path.stat().st_size
            if size != array.offset + array.nbytes:
                raise LatentCacheError(f"{path}: {size} bytes, its header says {array.offset + array.nbytes}; "
                                       f"re-run the `latents` stage")
            self._checked.setdefault(str(path.relative_to(self.root)), np.zeros(-(-len(array) // BLOCK_ROWS), bool))
            maps[name] = ChunkArray(self, split, int(c), name, path, array)
        return maps

    def block_digests(self, split: str, c: int) -> np.ndarray:
        """Chunk ``c``'s ``blocks.npy`` (:func:`chunk_blocks`), hashed whole against ``chunks.npy`` the first time
        this process (or the one it came from) needs it, loaded once per process."""
        key = (split, int(c))
        if key not in self._digests:
            row = self.index(split).chunks[c]
            path = self._folder(split) / str(row["name"]) / BLOCKS
            self._check(path, str(row["blocks_sha256"]), f"{split}/{CHUNKS}")
            try:
                table = np.load(path, allow_pickle=False)
            except (OSError, ValueError) as err:
                raise LatentCacheError(f"{path}: unreadable ({err}); re-run the `latents` stage") from err
            if table.dtype != BLOCK_DTYPE or table.shape != (-(-int(row["frames"]) // BLOCK_ROWS),):
                raise LatentCacheError(f"{path}: {table.shape} rows of {table.dtype}, not the blocks of "
                                       f"{int(row['frames'])} frames; re-run the `latents` stage")
            self._digests[key] = table
        return self._digests[key]

    def check_blocks(self, array: ChunkArray, blocks: np.ndarray | None) -> None:
        """Check ``blocks`` (None: all) of a chunk's array against their SHA-256 in its ``blocks.npy`` (recorded
        in ``chunks.npy`` through that file's own SHA-256), those this process has not checked yet; a file hashed
        whole (:meth:`verify`) is not checked again."""
        name = str(array.path.relative_to(self.root))
        if name in self._verified:
            return
        checked = self._checked[name]
        todo = np.flatnonzero(~checked) if blocks is None else blocks[~checked[blocks]]
        if not todo.size:
            return
        digests = self.block_digests(array.split, array.c)[array.name]
        for b in todo.tolist():
            if block_digest(array.array[b * BLOCK_ROWS:(b + 1) * BLOCK_ROWS]) != digests[b].tobytes():
                raise LatentCacheError(
                    f"{array.path}: content does not match the SHA-256 recorded in {array.split}/{CHUNKS} when the "
                    f"cache was written (corrupt or modified); re-run the `latents` stage")
            checked[b] = True

    def verify(self, split: str) -> int:
        """Check every file of a split (its tables and each chunk's files, ``blocks.npy`` included) against the
        SHA-256 recorded when they were written, whole (a reader checks the blocks it reads); the number of files
        checked."""
        index, folder = self.index(split), self._folder(split)
        for row in index.chunks:
            for file in CHUNK_FILES:
                self._check(folder / str(row["name"]) / file, str(row[f"{file.removesuffix('.npy')}_sha256"]),
                            f"{split}/{CHUNKS}")
        return 2 + len(CHUNK_FILES) * len(index.chunks)

    def arrays(self, split: str) -> dict[str, SplitArray]:
        """``detail``, ``abstract`` and ``odometry`` of one split, rows numbered across chunks (:class:`SplitArray`)."""
        self.index(split)
        return {name: SplitArray(self, split, name) for name in ARRAYS}

    def __getstate__(self) -> dict[str, Any]:
        # the record of checked blocks travels as bits (one a block: 1/128 byte a frame and array)
        checked = {name: (len(bits), np.packbits(bits)) for name, bits in self._checked.items()}
        return {**self.__dict__, "_maps": OrderedDict(), "_indexes": {}, "_digests": {}, "_checked": checked}

    def __setstate__(self, state: dict[str, Any]) -> None:
        state["_checked"] = {name: np.unpackbits(bits, count=n).astype(bool)
                             for name, (n, bits) in state["_checked"].items()}
        self.__dict__.update(state)


def _check_file(path: Path, digest: str, recorded_in: str, stage: str = "latents") -> None:
    if not path.is_file():
        raise LatentCacheError(f"{path}: missing from the latent cache; re-run the `{stage}` stage")
    if sha256_file(path) != digest:
        raise LatentCacheError(f"{path}: content does not match the SHA-256 recorded in {recorded_in} when the cache "
                               f"was written (corrupt or modified); re-run the `{stage}` stage")


def open_cache(root: str | Path, detail_checksum: str | None = None,
               abstract_checksum: str | None = None) -> LatentCache:
    """Open a cache, refusing one that another tokenizer checkpoint (by SHA-256) produced."""
    root = Path(root)
    path = root / META
    if not path.is_file():
        raise LatentCacheError(f"{path}: missing; run the `latents` stage first")
    try:
        meta = json.loads(path.read_text())
    except ValueError as err:
        raise LatentCacheError(f"{path}: not valid JSON ({err}); re-run the `latents` stage") from err
    if meta.get("format") != FORMAT:
        raise LatentCacheError(f"{path}: cache format {meta.get('format')}, this code reads {FORMAT}; "
                               f"re-run the `latents` stage")
    for kind, checksum in zip(KINDS, (detail_checksum, abstract_checksum)):
        recorded = meta["tokenizers"][kind]
        if checksum is not None and checksum != recorded["checksum"]:
            source = recorded["file"] or "a tokenizer file"
            raise LatentCacheError(
                f"{root}: the cached {kind} latents were encoded by {source} (sha256 {recorded['checksum'][:12]}), "
                f"but the {kind} tokenizer in use has sha256 {checksum[:12]}: the tokenizer was retrained or "
                f"replaced since; re-run the `latents` stage to re-encode")
    return LatentCache(root, meta)


def window_counts(data: DataConfig, lengths: np.ndarray, anchor_stride: int = 1) -> tuple[np.ndarray, int]:
    """How many windows each clip of ``lengths`` frames gives (every ``anchor_stride``-th anchor of
    :func:`anchor_range`), and the first anchor; vectorised over the clips."""
    empty = anchor_range(data, 0)  # anchor_range(data, n) is range(first, n + empty.stop)
    span = np.asarray(lengths, np.int64) + empty.stop - empty.start
    return np.maximum(0, -(-span // anchor_stride)), empty.start


class LatentWindowDataset(Dataset):
    """Two-rate latent windows at every valid (clip, anchor) of a split: the windows of ``clip_window``.

    An item holds ``detail`` (10 Hz window) and ``abstract`` (2 Hz window) latents, plus
    ``detail_slow`` and ``abstract_fast``: each latent space at the other rate's frames. Items are in
    split order: the clips in order, each clip's anchors in increasing order.

    Map-style, so ``DistributedSampler`` and DataLoader workers partition it exactly. ``anchor_stride``
    keeps every n-th anchor of a clip (neighbouring anchors overlap almost completely). Holds the
    split's clip table and one int64 per clip (where its windows start): an item's clip is found by
    binary search, so no array or object per window exists unless :attr:`items` is asked for.
    """

    def __init__(self, cache: LatentCache | str | Path, split: str, data: DataConfig, anchor_stride: int = 1):
        self.cache = cache if isinstance(cache, LatentCache) else open_cache(cache)
        if self.cache.meta["data"]["fps"] != data.fps:
            raise LatentCacheError(f"{self.cache.root}: cached at {self.cache.meta['data']['fps']} fps but "
                                   f"params.yaml asks for {data.fps} fps; re-run the `shards` and `latents` stages")
        if anchor_stride < 1:
            raise ValueError(f"anchor_stride must be >= 1, got {anchor_stride}")
        self.split, self.data, self.anchor_stride = split, data, anchor_stride
        self.clips = self.cache.index(split).clips  # structured rows: key, chunk, row, offset, length, ...
        self.keys = self.clips["key"]
        counts, self._first_anchor = window_counts(data, self.clips["length"], anchor_stride)
        self._starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)  # clip c: windows starts[c]..

    def __len__(self) -> int:
        return int(self._starts[-1])

    def windows(self, start: int = 0, stop: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(clip, anchor)`` of windows ``start``..``stop`` (default: to the end), as two int64 arrays."""
        stop = len(self) if stop is None else stop
        i = np.arange(start, stop, dtype=np.int64)
        clip = np.searchsorted(self._starts, i, "right") - 1
        return clip, self._first_anchor + self.anchor_stride * (i - self._starts[clip])

    @property
    def items(self) -> np.ndarray:
        """Every window's ``(clip, anchor)``, ``[len, 2]`` int64, made when asked for (16 bytes a window)."""
        return np.stack(self.windows(), 1)

    def __getitem__(self, i: int) -> dict[str, Any]:
        n = len(self)
        i = int(i) + (n if i < 0 else 0)
        if not 0 <= i < n:
            raise IndexError(f"window {i} outside the {n} windows of {self.split}")
        c = int(np.searchsorted(self._starts, i, "right")) - 1
        anchor = self._first_anchor + self.anchor_stride * (i - int(self._starts[c]))
        clip = self.clips[c]
        arrays = self.cache.chunk(self.split, int(clip["chunk"]))
        detail, abstract = window_indices(self.data, anchor)
        span = window_span(detail, abstract)
        base = int(clip["row"])  # the clip's first frame in its chunk

        def latent(kind: str, idx: np.ndarray) -> torch.Tensor:
            return self.cache.normalize(kind, arrays[kind][base + idx])

        odometry = arrays["odometry"]
        item = _item(str(clip["key"]), anchor, latent("detail", detail), latent("abstract", abstract),
                     odometry[base + detail], odometry[base + abstract], odometry[base + span],
                     bool(clip["has_odometry"]))
        # The same frames in the other latent space, for the hierarchy ablations' flat and top predictors.
        item["detail_slow"], item["abstract_fast"] = latent("detail", abstract), latent("abstract", detail)
        return item


def collate(items: list[dict[str, Any]]) -> dict[str, torch.Tensor]:
    """Stack the :class:`LatentWindowDataset` items' tensors the predictors read into one batch."""
    return {**{key: torch.stack([i[key] for i in items])
               for key in ("detail", "abstract", "detail_slow", "abstract_fast")},
            "odometry": torch.stack([i["odometry"] for i in items]),
            "has_odometry": torch.tensor([i["has_odometry"] for i in items])}

