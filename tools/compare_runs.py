"""Two published runs side by side: their headline figures with intervals, their verdicts, their stage times.

    python tools/compare_runs.py docs/results/default docs/results/default-32x20 --out comparison.md

Each folder is one ``tools/publish_results.py`` wrote; the figures are read from its tables and from its
``summary.md`` (the report stage's; its tables share one format). The runs are not paired: each interval is
its own run's clip bootstrap, so the table marks a difference as clear only where the two intervals do not
overlap. Two runs of one profile share their evaluation clips, seeds and noise draws, so their figures differ
by the models; their stage times also by the machines, which each folder's README names.
"""

from __future__ import annotations

import argparse
import io
import json
import re
from pathlib import Path

import pandas as pd

SPLITS = ("val", "heldout", "turns")
READING = re.compile(r"^(\d+)\. (.+?): \*\*(.+?)\*\*")


def summary_tables(path: Path) -> dict[str, pd.DataFrame]:
    """The first pipe table under each ``## heading`` of a run's summary.md, numbers as numbers."""
    tables: dict[str, pd.DataFrame] = {}
    heading, rows = None, []
    for line in [*path.read_text().splitlines(), ""]:
        if line.startswith("|"):
            rows.append([cell.strip() for cell in line.strip().strip("|").split("|")])
            continue
        if rows and heading and heading not in tables:
            text = "\n".join("\t".join(row) for i, row in enumerate(rows) if i != 1)  # rows[1]: the |---| rule
            tables[heading] = pd.read_csv(io.StringIO(text), sep="\t")
        rows = []
        if line.startswith("## "):
            heading = line[3:].strip()
    return tables


class Run:
    """One published folder's figures, as (value, low, high) triples under a readable name."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.record = json.loads((folder / "run.json").read_text())
        self.figures: dict[str, tuple[float, float, float]] = {}
        self.verdicts: dict[str, str] = {}
        main = pd.read_csv(folder / "main_table.csv").set_index("model")
        for model, row in main.iterrows():
            for split in SPLITS:
                self._add(f"FVD {split}: {model}", row, f"fvd_{split}")
            self._add(f"FVD-slope turns: {model}", row, "fvd_slope_turns")
            if pd.notna(row.get("miou")):
                self.figures[f"probe mIoU: {model} ({row['probe_target']})"] = (row["miou"],) * 3
                self.figures[f"probe depth RMSE: {model} ({row['probe_target']})"] = (row["rmse"],) * 3
        tables = summary_tables(folder / "summary.md")
        first = tables.get("The first generated frame")
        for _, row in (first if first is not None else pd.DataFrame()).iterrows():
            for name, column in (("generated", "generated_psnr"), ("reconstruction", "reconstruction_psnr"),
                                 ("gap", "gap_db")):
                self._add(f"first frame PSNR, {name} (dB): {row['model']} {row['split']}", row, column)
        steering = folder / "steering.csv"
        for _, row in (pd.read_csv(steering) if steering.is_file() else pd.DataFrame()).iterrows():
            if row["kind"] != "generated":
                continue
            self.figures[f"steering turn, commanded (deg): {row['mode']}"] = (row["commanded_turn_deg"],) * 3
            self.figures[f"steering turn, instrument (deg): {row['mode']}"] = (row["turn_deg"],) * 3
            self._add(f"steering turn, latents (deg): {row['mode']}", row, "turn_deg_latent")
        conditioning = folder / "conditioning.csv"
        for _, row in (pd.read_csv(conditioning) if conditioning.is_file() else pd.DataFrame()).iterrows():
            name = f"conditioning {row['model']}, {row['check']} ({row['metric']})"
            self.figures[name] = (row["effect"], row["low"], row["high"])
            self.verdicts[name] = row["verdict"]
        for line in (folder / "summary.md").read_text().splitlines():
            found = READING.match(line)
            if found:
                self.verdicts[f"claim {found[1]}: {found[2]}"] = found[3]
        self.times = pd.read_csv(folder / "stage_times.csv").set_index("stage")["wall_s"]

    def _add(self, name: str, row: pd.Series, column: str) -> None:
        if column in row and pd.notna(row[column]):
            low, high = row.get(f"{column}_low"), row.get(f"{column}_high")
            self.figures[name] = (row[column], low if pd.notna(low) else row[column],
                                  high if pd.notna(high) else row[column])

    def title(self) -> str:
        r, m = self.record, self.record["machine"]
        return (f"`{self.folder}`: commit `{(r['commit'] or 'none')[:7]}`, finished {r['finished']}, "
                f"{m['cpu']}{' (AVX-512)' if m['avx512'] else ''}")


def _cell(value: tuple[float, float, float]) -> str:
    v, low, high = value
    return f"{v:.4g}" if low == v == high else f"{v:.4g} [{low:.4g}, {high:.4g}]"


def comparison(a: Run, b: Run) -> str:
    """The markdown page: figures, verdicts, stage times; only what both runs measured."""
    lines = [f"# {b.folder.name} against {a.folder.name}", "", f"- A: {a.title()}", f"- B: {b.title()}", "",
             "Each interval is its own run's (95 %, clips resampled); the runs are not paired. *apart*: the "
             "two intervals do not overlap.", "", "## Figures", "",
             "| figure | A | B | B - A | |", "|---|---|---|---|---|"]
    for name, fa in a.figures.items():
        fb = b.figures.get(name)
        if fb is None:
            continue
        intervals = fa[1] != fa[2] and fb[1] != fb[2]
        apart = intervals and (fb[1] > fa[2] or fb[2] < fa[1])
        lines.append(f"| {name} | {_cell(fa)} | {_cell(fb)} | {fb[0] - fa[0]:+.4g} | {'apart' if apart else ''} |")
    lines += ["", "## Verdicts", "", "| check | A | B |", "|---|---|---|"]
    lines += [f"| {name} | {verdict} | {b.verdicts[name]} |" for name, verdict in a.verdicts.items()
              if name in b.verdicts]
    common = [stage for stage in b.times.index if stage in a.times.index]
    lines += ["", "## Stage times (s)", "", "| stage | A | B | B / A |", "|---|---|---|---|"]
    lines += [f"| {stage} | {a.times[stage]:.0f} | {b.times[stage]:.0f} | {b.times[stage] / a.times[stage]:.2f} |"
              for stage in common]
    total_a, total_b = a.times[common].sum(), b.times[common].sum()
    lines += [f"| **all {len(common)}** | **{total_a:.0f}** | **{total_b:.0f}** | **{total_b / total_a:.2f}** |", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", type=Path, help="a published folder (docs/results/<name>)")
    parser.add_argument("b", type=Path, help="the folder compared with it")
    parser.add_argument("--out", type=Path, default=None, help="write the page here (default: print it)")
    args = parser.parse_args(argv)
    for folder in (args.a, args.b):
        if not (folder / "run.json").is_file():
            raise SystemExit(f"{folder}: no run.json; give a folder tools/publish_results.py wrote")
    page = comparison(Run(args.a), Run(args.b))
    if args.out:
        args.out.write_text(page)
        print(f"wrote {args.out}")
    else:
        print(page)


if __name__ == "__main__":
    main()
