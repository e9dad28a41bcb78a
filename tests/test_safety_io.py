"""Atomic outputs: the swap never loses the old output, leftovers of a kill are cleaned, symlinks are followed."""

import os
import subprocess
import sys

import pytest

from orbis2 import io as orbis_io
from orbis2.io import atomic_dir, atomic_file


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_failed_swap_keeps_the_old_output(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old")
    real_replace = os.replace
    calls = []

    def flaky_replace(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:  # the rename that brings the new directory in
            raise OSError("simulated crash between the renames")
        real_replace(src, dst)

    monkeypatch.setattr(orbis_io.os, "replace", flaky_replace)
    with pytest.raises(OSError, match="simulated"):
        with atomic_dir(out) as tmp:
            (tmp / "a.txt").write_text("new")
    assert (out / "a.txt").read_text() == "old"
    monkeypatch.setattr(orbis_io.os, "replace", real_replace)
    with atomic_dir(out) as tmp:
        (tmp / "a.txt").write_text("new")
    assert (out / "a.txt").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_leftovers_of_a_killed_writer_are_cleaned_or_restored(tmp_path):
    pid = dead_pid()
    stale_new = tmp_path / f".out.new-{pid}-abc"
    stale_new.mkdir()
    (stale_new / "half.bin").write_bytes(b"x")
    # Killed between "rename old aside" and "rename new in": the old output is only aside.
    orphan = tmp_path / f".out.old-{pid}-def"
    orphan.mkdir()
    (orphan / "a.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_dir(tmp_path / "out"):
            assert (tmp_path / "out" / "a.txt").read_text() == "old"  # restored before the new build
            raise RuntimeError("the stage fails")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    # A live writer's temporary (this test's parent process) is left alone.
    live = tmp_path / f".out.new-{os.getppid()}-ghi"
    live.mkdir()
    with atomic_dir(tmp_path / "out") as tmp:
        (tmp / "b.txt").write_text("b")
    assert live.is_dir() and sorted(p.name for p in (tmp_path / "out").iterdir()) == ["b.txt"]


def test_symlinked_output_is_written_at_its_destination(tmp_path):
    big_disk = tmp_path / "big" / "raw"
    big_disk.mkdir(parents=True)
    (big_disk / "old.txt").write_text("old")
    (tmp_path / "data").mkdir()
    link = tmp_path / "data" / "raw"
    link.symlink_to(big_disk)
    with atomic_dir(link) as tmp:
        (tmp / "new.txt").write_text("new")
    assert link.is_symlink() and os.readlink(link) == str(big_disk)
    assert sorted(p.name for p in link.iterdir()) == ["new.txt"]
    assert sorted(p.name for p in (tmp_path / "big").iterdir()) == ["raw"]


def test_atomic_file_removes_a_dead_writers_temporary(tmp_path):
    stale = tmp_path / f".last.pt.new-{dead_pid()}-xyz.pt"
    stale.write_bytes(b"half a checkpoint")
    with atomic_file(tmp_path / "last.pt") as tmp:
        tmp.write_bytes(b"whole")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.pt"]
