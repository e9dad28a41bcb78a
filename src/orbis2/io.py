"""Atomic writes and deterministic archives: no half-written output, same bytes every run."""

from __future__ import annotations

import contextlib
import glob
import hashlib
import io
import json
import os
import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np


@contextlib.contextmanager
def atomic_dir(target: Path) -> Iterator[Path]:
    """Build a directory beside ``target`` and swap it in only if the block succeeds.

    The swap never leaves the target missing: the old directory is renamed aside, the
    new one renamed in, and only then is the old one deleted (if the second rename
    fails the old one is put back). Temporaries left by a killed process are removed,
    or an orphaned old directory restored, on the next call for the same target. A
    ``target`` that is a symlink (e.g. data on a bigger disk) is followed: the new
    directory is built beside the link's destination and replaces that.
    """
    target = _follow_link(Path(target))
    target.parent.mkdir(parents=True, exist_ok=True)
    _recover_stale(target)
    tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(target, "new"), dir=target.parent))
    tmp.chmod(0o755)  # mkdtemp makes it private; outputs are shared data
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if not target.exists():
        os.replace(tmp, target)
        return
    old = Path(tempfile.mkdtemp(prefix=_temp_prefix(target, "old"), dir=target.parent))
    os.replace(target, old)  # a directory target replaces the empty placeholder
    try:
        os.replace(tmp, target)
    except BaseException:
        os.replace(old, target)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    shutil.rmtree(old)


def _follow_link(target: Path) -> Path:
    """The path a symlinked output points to (made absolute); other paths unchanged."""
    if target.is_symlink():
        return target.resolve()
    return target


def _temp_prefix(target: Path, kind: str) -> str:
    """``.<name>.<kind>-<pid>-``: the pid lets a later run tell a dead writer's leftovers from a live one's."""
    return f".{target.name}.{kind}-{os.getpid()}-"


def _recover_stale(target: Path) -> None:
    """Delete temporaries of ``target`` (files or folders) whose writer is dead; restore an old directory
    orphaned mid-swap."""
    for path in sorted(target.parent.glob(f".{glob.escape(target.name)}.*-*-*")):
        kind, _, rest = path.name[len(target.name) + 2:].partition("-")
        pid = rest.split("-", 1)[0]
        if kind not in ("new", "old") or not pid.isdigit() or _alive(int(pid)):
            continue
        if kind == "old" and not target.exists():
            os.replace(path, target)  # killed between the two renames: the old output is still valid
        elif path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    """Whether another process with this pid runs (our own pid: a leftover of an earlier process that had it)."""
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def atomic_file(target: Path) -> Iterator[Path]:
    """Yield a temporary path in the same folder; renamed onto ``target`` on success.

    A temporary left by a killed writer of the same target is deleted first.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    _recover_stale(target)
    fd, name = tempfile.mkstemp(prefix=_temp_prefix(target, "new"), suffix=target.suffix, dir=target.parent)
    os.close(fd)
    tmp = Path(name)
    tmp.chmod(0o644)  # mkstemp makes it private; outputs are shared data
    try:
        yield tmp
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, target)


def move_into(source: Path, target: Path) -> None:
    """Move a part's finished file into the output being gathered, replacing what was there: a rename (no copy,
    a new inode for no one: DVC and Snakemake see the file the part wrote), a copy across file systems."""
    try:
        os.replace(source, target)
    except OSError:
        shutil.move(source, target)


class HashingFile:
    """A binary file that hashes and counts what is written to it; ``finish`` syncs it to disk and closes it, so
    that a writer has the file's SHA-256 without reading it again."""

    def __init__(self, path: Path):
        self.path = path
        self._file = open(path, "wb")  # noqa: SIM115 (closed by finish)
        self._digest, self._size = hashlib.sha256(), 0

    def write(self, data: bytes) -> int:
        self._digest.update(data)
        self._size += len(data)
        return self._file.write(data)

    def flush(self) -> None:
        self._file.flush()

    def finish(self) -> tuple[int, str]:
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        return self._size, self._digest.hexdigest()


def sha256_file(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_json(path: Path, obj: Any) -> None:
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True) + "\n")


def npz_bytes(**arrays: np.ndarray) -> bytes:
    """A compressed ``.npz`` whose bytes depend only on the arrays (fixed zip timestamps)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            member = io.BytesIO()
            np.save(member, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, member.getvalue())
    return buf.getvalue()


def npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def load_npy(data: bytes) -> np.ndarray:
    return np.load(io.BytesIO(data), allow_pickle=False)


def load_npz(data: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}
