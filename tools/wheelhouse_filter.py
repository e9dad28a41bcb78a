"""Remove from a wheelhouse the wheels of distributions the GPU machine's image provides, and report its size.

    python tools/wheelhouse_filter.py WHEELHOUSE [--provided tools/gpu_image_packages.txt]

Names compare as pip normalises them (PEP 503: case and runs of ``-_.`` ignored). Standard library only: it
runs where the wheelhouse is built, before anything of the project is installed.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

HERE = Path(__file__).resolve().parent


def normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def provided(path: Path) -> set[str]:
    lines = (line.split("#")[0].strip() for line in path.read_text().splitlines())
    return {normalise(line) for line in lines if line}


def filter_wheelhouse(wheelhouse: Path, have: set[str]) -> tuple[list[str], int]:
    """Delete the wheels whose distribution is in ``have``; return their names and the bytes left."""
    removed = []
    for wheel in sorted(wheelhouse.glob("*.whl")):
        if normalise(wheel.name.split("-")[0]) in have:
            wheel.unlink()
            removed.append(wheel.name)
    return removed, sum(w.stat().st_size for w in wheelhouse.glob("*.whl"))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("wheelhouse", type=Path)
    parser.add_argument("--provided", type=Path, default=HERE / "gpu_image_packages.txt")
    args = parser.parse_args(argv)
    removed, left = filter_wheelhouse(args.wheelhouse, provided(args.provided))
    kept = len(list(args.wheelhouse.glob("*.whl")))
    print(f"{args.wheelhouse}: removed {len(removed)} wheels the machine has; {kept} left, {left / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
