"""Parts: how a data stage splits its items into independent jobs (``parts`` in params.yaml).

Part ``i`` of ``N`` takes the i-th contiguous block of the items in their fixed order, so that the
parts' outputs, concatenated in part order, are in the order one part would write them. Names
are ``0003-of-0064``: a part's folder, its Snakemake wildcard and its part manifest. Kept free of
heavy imports: the Snakefile reads it.
"""

from __future__ import annotations


def part_name(part: int, parts: int) -> str:
    """``0003-of-0064``."""
    return f"{part:04d}-of-{parts:04d}"


def part_slice(count: int, part: int, parts: int) -> slice:
    """The contiguous block of ``count`` items that part ``part`` of ``parts`` takes (every item in exactly one
    part; blocks differ in size by one at most)."""
    if not 0 <= part < parts:
        raise ValueError(f"part {part} outside 0..{parts - 1}")
    return slice(count * part // parts, count * (part + 1) // parts)
