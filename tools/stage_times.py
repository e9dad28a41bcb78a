"""Wall time and peak memory of every stage of the last Snakemake run, as a Markdown table.

    python tools/stage_times.py [logs/benchmarks]

Reads the `benchmark:` files the rules write (`logs/benchmarks/<rule>.tsv`, one row per run of the
rule; the last row is the latest) and lists the stages in the order they finished, with the sum.
The stage-time table of docs/pipeline.md is this script's output.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd


def stage_times(folder: Path) -> pd.DataFrame:
    """One row per rule: its latest wall seconds and peak resident memory (MB), in finishing order."""
    files = sorted(folder.glob("*.tsv"), key=lambda path: path.stat().st_mtime)
    if not files:
        raise SystemExit(f"{folder}: no benchmark files; run the pipeline with Snakemake first")
    rows = [pd.read_csv(path, sep="\t").iloc[-1].rename(path.stem) for path in files]
    table = pd.DataFrame(rows)[["s", "max_rss"]].rename(columns={"s": "wall_s", "max_rss": "peak_rss_mb"})
    return table.rename_axis("stage")


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    table = stage_times(Path(argv[0] if argv else "logs/benchmarks"))
    print(table.to_markdown(floatfmt=".0f"))
    print(f"\ntotal: {table['wall_s'].sum():.0f} s ({table['wall_s'].sum() / 60:.1f} min) over {len(table)} stages")


if __name__ == "__main__":
    main()
