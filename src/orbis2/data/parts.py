"""Parts: how a data stage splits its items into independent jobs (``parts`` in params.yaml).

Part ``i`` of ``N`` takes the i-th contiguous block of the items in their fixed order, so that the
parts' outputs, concatenated in part order, are in the order one part would write them. Names
are ``0003-of-0064``: a part's folder, its Snakemake wildcard and its part manifest. Kept free of
heavy imports: the Snakefile reads it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

WORK_KEY = "key.json"


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
    if (work / WORK_KEY).is_file() and json.loads((work / WORK_KEY).read_text()) != key:
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    (work / WORK_KEY).write_text(json.dumps(key, sort_keys=True))
    return work
