"""The latent cache: both tokenizers encode every native frame of every clip once.

Training the predictors re-reads the same frames for thousands of steps; decoding
JPEGs and running two ViT encoders per step would cost far more than the predictor
itself. The ``latents`` stage therefore encodes every frame once and stores

    <root>/meta.json                   tokenizer checksums, shards manifest hash, geometry, file checksums
    <root>/normalization.npz           each tokenizer's latent normalisation (shift, scale)
    <root>/<split>/detail.npy          float16 [N_frames, C, h, w]     (unscaled detail latent)
    <root>/<split>/abstract.npy        float16 [N_frames, C', h', w']  (unscaled abstract latent)
    <root>/<split>/odometry.npy        float32 [N_frames, 2]           (speed, yaw rate)
    <root>/<split>/index.json          shard key -> offset, length, has_odometry, episode, start_frame

Why flat memory-mapped ``.npy`` arrays rather than tar shards of latents: a
training item is a strided window of 10 + 6 frames at a random anchor, and with
a memory map that is an O(1) row gather (no archive scan, no decoding, no
per-sample deserialisation), so the dataset can be map-style and indexed at
random, which lets ``DistributedSampler`` and DataLoader workers shard it
exactly. Every worker process maps the same files, so the OS page cache holds
one copy of the cache however many workers and ranks read it. The shard keys
survive in ``index.json``, so every cached frame traces back to its sample in
``data/shards``. fp16 halves the footprint; the latents are L2-normalised
(|x| <= 1), where fp16 keeps about three significant digits. They are stored as the
tokenizers encode them; readers apply the tokenizer's normalisation (``TokenizerFile.normalize``:
per-position mean removed, per-channel unit variance) on the fly.

``meta.json`` records the SHA-256 of every array, index and the normalisation file, and a
reader checks a split's files before it first uses them (once per process, in the process
that opens the cache): a flipped bit in a memory map would otherwise reach every predictor
as a plausible-looking latent.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from orbis2.config.sections import DataConfig
from orbis2.data.shards import MANIFEST, Clip, load_manifest, read_clips
from orbis2.errors import OrbisError
from orbis2.hierarchy import anchor_range, window_indices, window_span
from orbis2.io import atomic_dir, sha256_file, write_json
from orbis2.models.files import TokenizerFile, load_tokenizer

FORMAT = 3  # 3: meta.json records every file's SHA-256
KINDS = ("detail", "abstract")
ARRAYS = (*KINDS, "odometry")
META = "meta.json"
INDEX = "index.json"
NORMALIZATION = "normalization.npz"


class LatentCacheError(OrbisError):
    """The latent cache is missing, incomplete, or was built from other inputs."""


# --------------------------------------------------------------------------- encoding


def to_model_input(frames: np.ndarray) -> torch.Tensor:
    """RGB uint8 ``[N, H, W, 3]`` -> float ``[N, 3, H, W]`` in [-1, 1], the tokenizers' input range."""
    return torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float().div_(127.5).sub_(1.0)


def encode_frames(tokenizer: TokenizerFile, frames: np.ndarray) -> torch.Tensor:
    """The tokenizer's latent (unscaled, float32, on the CPU) of a stack of RGB frames."""
    model = tokenizer.model.eval()
    device = next(model.parameters()).device
    with torch.inference_mode():
        return model.encode(to_model_input(frames).to(device)).float().cpu()


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


# --------------------------------------------------------------------------- building


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


class _SplitWriter:
    """Fills one split's memory-mapped arrays, batching frames across clip boundaries."""

    def __init__(self, folder: Path, frames: int, tokenizers: dict[str, TokenizerFile],
                 shapes: dict[str, tuple[int, ...]], batch_size: int):
        folder.mkdir(parents=True)
        self.tokenizers, self.batch_size = tokenizers, batch_size
        self.arrays = {kind: np.lib.format.open_memmap(folder / f"{kind}.npy", "w+", np.float16,
                                                       (frames, *shapes[kind])) for kind in KINDS}
        self.arrays["odometry"] = np.lib.format.open_memmap(folder / "odometry.npy", "w+", np.float32, (frames, 2))
        self.pending: list[np.ndarray] = []
        self.cursor = 0  # frames written so far

    def add(self, clip: Clip, offset: int) -> None:
        self.arrays["odometry"][offset:offset + len(clip)] = clip.odometry
        for i in range(len(clip)):
            self.pending.append(clip.frames([i])[0])
            if len(self.pending) == self.batch_size:
                self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        frames = np.stack(self.pending)
        end = self.cursor + len(frames)
        for kind in KINDS:
            half = encode_frames(self.tokenizers[kind], frames).numpy().astype(np.float16)
            if not np.isfinite(half).all():
                raise LatentCacheError(f"the {kind} tokenizer produced latents outside the float16 range; "
                                       f"the cache stores float16 and cannot hold them")
            self.arrays[kind][self.cursor:end] = half
        self.cursor, self.pending = end, []

    def close(self) -> None:
        self.flush()
        for array in self.arrays.values():
            array.flush()
        self.arrays.clear()


def build_latent_cache(shards_root: str | Path, out_root: str | Path, detail: TokenizerFile | str | Path,
                       abstract: TokenizerFile | str | Path, batch_size: int, splits: Sequence[str] | None = None,
                       device: str | torch.device | None = None, decode_workers: int = 0) -> dict[str, Any]:
    """Encode every native frame of every clip of ``splits`` (default: all in the manifest); returns the meta.

    ``decode_workers`` > 0 decodes the JPEGs in that many processes ahead of the encoder (clips then
    arrive in the loader's worker-interleaved order; the index is by key, so readers are unaffected).

    ``detail``/``abstract`` are loaded tokenizers (used on their own device) or paths to tokenizer files
    (loaded on ``device``, default CUDA when present; the path is recorded so a stale cache can name it).
    The cache is built in a temporary folder beside ``out_root`` and renamed into place only when complete.
    """
    shards_root, out_root = Path(shards_root), Path(out_root)
    manifest = load_manifest(shards_root)
    splits = list(manifest["splits"]) if splits is None else list(splits)
    tokenizers, files = {}, {}
    for kind, tokenizer in zip(KINDS, (detail, abstract)):
        tokenizers[kind], files[kind] = _resolve(tokenizer, kind, device)
    probe = np.zeros((1, manifest["height"], manifest["width"], 3), np.uint8)
    shapes = {kind: tuple(encode_frames(tokenizers[kind], probe).shape[1:]) for kind in KINDS}
    meta: dict[str, Any] = {
        "format": FORMAT,
        "dtype": "float16",
        "shards": {"root": str(shards_root), "manifest_sha256": sha256_file(shards_root / MANIFEST)},
        "data": {key: manifest[key] for key in ("source", "fps", "width", "height")},
        "tokenizers": {kind: {"checksum": tokenizers[kind].checksum, "file": files[kind],
                              "build": tokenizers[kind].build, "shape": list(shapes[kind])}
                       for kind in KINDS},
        "splits": {},
    }
    with atomic_dir(out_root) as tmp:
        for split in splits:
            frames = manifest["splits"][split]["frames"]
            writer = _SplitWriter(tmp / split, frames, tokenizers, shapes, batch_size)
            index: dict[str, dict[str, Any]] = {}
            offset = 0
            with tqdm(total=frames, desc=f"latents: {split}", unit="frame") as bar:
                for clip in read_clips(shards_root, split, decode_workers):
                    if offset + len(clip) > frames:
                        raise LatentCacheError(f"{shards_root / MANIFEST}: split '{split}' holds more frames than "
                                               f"the manifest's {frames}; re-run the `shards` stage")
                    index[clip.key] = {"offset": offset, "length": len(clip),
                                       "has_odometry": bool(clip.meta["has_odometry"]),
                                       "episode": clip.meta["episode"], "start_frame": clip.meta["start_frame"]}
                    writer.add(clip, offset)
                    offset += len(clip)
                    bar.update(len(clip))
            writer.close()
            if offset != frames:
                raise LatentCacheError(f"{shards_root / MANIFEST}: split '{split}' lists {frames} frames but its "
                                       f"shards hold {offset}; re-run the `shards` stage")
            write_json(tmp / split / INDEX, index)
            meta["splits"][split] = {"frames": frames, "clips": len(index),
                                     "sha256": {name: sha256_file(tmp / split / name)
                                                for name in (*(f"{a}.npy" for a in ARRAYS), INDEX)}}
        np.savez(tmp / NORMALIZATION, **{f"{kind}_{part}": getattr(tokenizers[kind], part).cpu().numpy()
                                         for kind in KINDS for part in ("shift", "scale")})
        meta["normalization_sha256"] = sha256_file(tmp / NORMALIZATION)
        write_json(tmp / META, meta)
    return meta


# --------------------------------------------------------------------------- reading


class LatentCache:
    """An opened cache: its meta, per-split indexes, and per-split arrays mapped on first use.

    The maps are per process and are dropped when the object is pickled (DataLoader workers
    started by spawn/forkserver, DDP), so each process maps the files instead of copying them.
    The record of which splits were verified travels with it, so workers do not hash them again.
    """

    def __init__(self, root: Path, meta: dict[str, Any]):
        self.root, self.meta = root, meta
        self._arrays: dict[str, dict[str, np.ndarray]] = {}
        self._verified: set[str] = set()
        path = root / NORMALIZATION
        _check_file(path, meta["normalization_sha256"])
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

    def verify(self, split: str) -> None:
        """Check a split's arrays and index against the SHA-256 that ``meta.json`` recorded when they were written."""
        if split in self._verified:
            return
        folder = self._folder(split)
        for name, digest in self.meta["splits"][split]["sha256"].items():
            _check_file(folder / name, digest)
        self._verified.add(split)

    def index(self, split: str) -> dict[str, dict[str, Any]]:
        self.verify(split)
        path = self._folder(split) / INDEX
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise LatentCacheError(f"{path}: unreadable ({err}); re-run the `latents` stage") from err

    def arrays(self, split: str) -> dict[str, np.ndarray]:
        """``detail``, ``abstract`` and ``odometry`` of one split as read-only memory maps."""
        if split not in self._arrays:
            self.verify(split)
            folder, frames = self._folder(split), self.meta["splits"][split]["frames"]
            expected = {kind: (frames, *self.meta["tokenizers"][kind]["shape"]) for kind in KINDS}
            expected["odometry"] = (frames, 2)
            arrays = {}
            for name, shape in expected.items():
                path = folder / f"{name}.npy"
                try:
                    arrays[name] = np.load(path, mmap_mode="r")
                except (OSError, ValueError) as err:
                    raise LatentCacheError(f"{path}: unreadable ({err}); re-run the `latents` stage") from err
                if arrays[name].shape != shape:
                    raise LatentCacheError(f"{path}: shape {arrays[name].shape}, meta.json says {shape}; "
                                           f"re-run the `latents` stage")
            self._arrays[split] = arrays
        return self._arrays[split]

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_arrays": {}}


def _check_file(path: Path, digest: str) -> None:
    if not path.is_file():
        raise LatentCacheError(f"{path}: missing from the latent cache; re-run the `latents` stage")
    if sha256_file(path) != digest:
        raise LatentCacheError(f"{path}: content does not match the SHA-256 recorded in meta.json when the cache "
                               f"was written (corrupt or modified); re-run the `latents` stage")


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


class LatentWindowDataset(Dataset):
    """Two-rate latent windows at every valid (clip, anchor) of a split: the windows of ``clip_window``.

    An item holds ``detail`` (10 Hz window) and ``abstract`` (2 Hz window) latents, plus
    ``detail_slow`` and ``abstract_fast``: each latent space at the other rate's frames.

    Map-style, so ``DistributedSampler`` and DataLoader workers partition it exactly. ``anchor_stride``
    keeps every n-th anchor of a clip (neighbouring anchors overlap almost completely).
    """

    def __init__(self, cache: LatentCache | str | Path, split: str, data: DataConfig, anchor_stride: int = 1):
        self.cache = cache if isinstance(cache, LatentCache) else open_cache(cache)
        if self.cache.meta["data"]["fps"] != data.fps:
            raise LatentCacheError(f"{self.cache.root}: cached at {self.cache.meta['data']['fps']} fps but "
                                   f"params.yaml asks for {data.fps} fps; re-run the `shards` and `latents` stages")
        if anchor_stride < 1:
            raise ValueError(f"anchor_stride must be >= 1, got {anchor_stride}")
        self.split, self.data = split, data
        index = self.cache.index(split)
        self.keys = sorted(index, key=lambda k: index[k]["offset"])
        self.clips = [index[k] for k in self.keys]
        pairs = [(c, a) for c, clip in enumerate(self.clips)
                 for a in anchor_range(data, clip["length"])[::anchor_stride]]
        self.items = np.array(pairs, np.int64).reshape(-1, 2)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict[str, Any]:
        c, anchor = (int(v) for v in self.items[i])
        clip, arrays = self.clips[c], self.cache.arrays(self.split)
        detail, abstract = window_indices(self.data, anchor)
        span = window_span(detail, abstract)
        base = clip["offset"]  # row of the clip's first frame

        def latent(kind: str, idx: np.ndarray) -> torch.Tensor:
            return self.cache.normalize(kind, arrays[kind][base + idx])

        odometry = arrays["odometry"]
        item = _item(self.keys[c], anchor, latent("detail", detail), latent("abstract", abstract),
                     odometry[base + detail], odometry[base + abstract], odometry[base + span], clip["has_odometry"])
        # The same frames in the other latent space, for the hierarchy ablations' flat and top predictors.
        item["detail_slow"], item["abstract_fast"] = latent("detail", abstract), latent("abstract", detail)
        return item


def collate(items: list[dict[str, Any]]) -> dict[str, torch.Tensor]:
    """Stack the :class:`LatentWindowDataset` items' tensors the predictors read into one batch."""
    return {**{key: torch.stack([i[key] for i in items])
               for key in ("detail", "abstract", "detail_slow", "abstract_fast")},
            "odometry": torch.stack([i["odometry"] for i in items]),
            "has_odometry": torch.tensor([i["has_odometry"] for i in items])}
