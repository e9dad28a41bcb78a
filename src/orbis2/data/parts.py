"""Parts: how a data stage splits its items into independent jobs (``parts`` in params.yaml).

Part ``i`` of ``N`` takes the i-th contiguous block of the items in their fixed order, so that the
parts' outputs, concatenated in part order, are in the order one part would write them. Names
are ``0003-of-0064``: a part's folder, its Snakemake wildcard and its part manifest. Kept free of
heavy imports: the Snakefile reads it. The stages run in parts share their options here.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path
from typing import Any

from orbis2.config.params import load_params
from orbis2.io import atomic_file, write_json
from orbis2.registry import layout_path

WORK_KEY = "key.json"
PART_LOG = "done.jsonl"  # a part's progress: one JSON line per item done (PartLog)


def part_name(part: int, parts: int) -> str:
    """``0003-of-0064``."""
    return f"{part:04d}-of-{parts:04d}"


def part_slice(count: int, part: int, parts: int) -> slice:
    """The contiguous block of ``count`` items that part ``part`` of ``parts`` takes (every item in exactly one
    part; blocks differ in size by one at most)."""
    if not 0 <= part < parts:
        raise ValueError(f"part {part} outside 0..{parts - 1}")
    return slice(count * part // parts, count * (part + 1) // parts)


def keyed_work(work: Path, key: dict[str, Any]) -> Path:
    """``work``, a folder of parts made from the inputs and settings ``key`` describes (JSON): one made from
    another key is emptied first, so that no part resumes work made from other inputs."""
    text = json.dumps(key, sort_keys=True)
    if (work / WORK_KEY).is_file() and json.loads((work / WORK_KEY).read_text()) != key:
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    if not (work / WORK_KEY).is_file() or (work / WORK_KEY).read_text() != text:
        with atomic_file(work / WORK_KEY) as tmp:  # parts started together read a whole key, never a torn one
            tmp.write_text(text)
    return work


def files_fingerprint(paths: list[Path]) -> list[int | None]:
    """What says the files an item is made from are the ones a logged outcome was made from: their sizes and
    modification times, None for one that is absent (reading terabytes of video again to hash them would cost as
    much as converting them)."""
    out: list[int | None] = []
    for path in paths:
        stat = path.stat() if path.exists() else None
        out += [stat.st_size, stat.st_mtime_ns] if stat else [None, None]
    return out


class PartLog:
    """A part's progress: ``done.jsonl`` in its folder, one JSON line appended (and synced) per event.

    An item is logged after it is in place, so a kill loses at most the item being written and the
    line being appended: a torn last line is dropped on the next start, and its item done again.
    Subclasses say when the work in the folder cannot be resumed (:meth:`stale`: the folder is
    emptied and the part starts over) and remove what a killed writer left (:meth:`clean`)."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.path = folder / PART_LOG
        self.events: list[dict[str, Any]] = []
        lines = self.path.read_text().splitlines() if self.path.is_file() else []
        for line in lines:
            try:
                self.events.append(json.loads(line))
            except ValueError:
                break  # torn by a kill: this and anything after it is redone
        if self.events and self.stale(self.events):
            shutil.rmtree(folder)
            self.events = []
        folder.mkdir(parents=True, exist_ok=True)
        self.clean()
        if len(self.events) != len(lines):  # drop the torn line, so that appends follow whole ones
            self.path.write_text("".join(json.dumps(e, sort_keys=True) + "\n" for e in self.events))

    def stale(self, events: list[dict[str, Any]]) -> bool:
        """Whether the logged work cannot be resumed (e.g. a gather moved its files out): start the part over."""
        return False

    def clean(self) -> None:
        """Remove what a writer killed mid-item left in the folder."""

    def add(self, event: dict[str, Any]) -> None:
        with open(self.path, "a") as f:
            f.write(json.dumps(event, sort_keys=True) + "\n")
            f.flush()
            os.fsync(f.fileno())
        self.events.append(event)

    @property
    def done(self) -> bool:
        return any(e.get("done") for e in self.events)


def add_part_options(parser: argparse.ArgumentParser, layout: str, prefix: str = "") -> None:
    """``--parts N``, ``--part I`` and ``--part-manifest FILE`` of a data stage run in parts (orbis2.data.parts):
    without ``--part`` the stage does every part not yet done and gathers them; with it, that part only, and
    writes its part manifest (default: the ``layout`` path of ``<prefix><I>-of-<N>``)."""
    parser.add_argument("--parts", type=int, default=None, help="how many parts (default: params.yaml `parts`)")
    parser.add_argument("--part", type=int, default=None, metavar="I",
                        help="do part I (0-based) only, and write its part manifest (--part-manifest)")
    default = layout_path(layout, f"{prefix}<I>-of-<N>")
    parser.add_argument("--part-manifest", type=Path, default=None, metavar="FILE",
                        help=f"where --part writes its manifest (default: {default})")


def parts_of(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """How many parts the run has (``--parts``, else params.yaml's ``parts``), ``--part`` checked against it."""
    parts = args.parts if args.parts is not None else load_params(args.params)["parts"]
    if parts < 1 or (args.part is not None and not 0 <= args.part < parts):
        parser.error(f"--part {args.part} --parts {parts}: parts must be >= 1 and 0 <= part < parts")
    return parts


def write_part_manifest(args: argparse.Namespace, layout: str, parts: int, written: dict, prefix: str = "") -> None:
    """A part's manifest, atomically, at ``--part-manifest`` or the layout's path of ``<prefix><I>-of-<N>``: what
    the DAG's gather waits on."""
    with atomic_file(args.part_manifest or layout_path(layout, prefix + part_name(args.part, parts))) as tmp:
        write_json(tmp, written)
