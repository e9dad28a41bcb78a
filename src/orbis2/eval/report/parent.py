"""What the pipeline's parent MLflow run shows: a one-minute read of the main report.

* :func:`parent_metrics`: at most :data:`MAX_METRICS` headline numbers, named
  ``<table>/<row>/<column>`` as docs/tracking.md names them (``main_table/hierarchical/fvd_heldout``);
  every other number stays in the tables (``tables/`` on the parent, ``reports/`` on disk).
* :func:`intervals`: every interval of the main tables as one table (value, bounds, sample count,
  verdict), and :func:`plot_intervals` the same as one forest plot, a panel per measure, so that no
  interval is read off four separate metric charts.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import pandas as pd

from orbis2.eval.figures import pyplot, save_figure
from orbis2.io import atomic_file

MAX_METRICS = 20
INTERVALS_CSV, FOREST_PNG, STAGE_TIMES_CSV = "intervals.csv", "intervals.png", "stage_times.csv"
# table (file stem) -> (the column naming a row, {row: columns}); "*": every other row.
HEADLINE: dict[str, tuple[str, dict[str, tuple[str, ...]]]] = {
    "main_table": ("model", {"hierarchical": ("fvd_val", "fvd_heldout", "fvd_turns", "fvd_slope_turns", "miou",
                                              "rmse"),
                             "*": ("fvd_heldout",)}),  # the reference rows: what the hierarchy is measured against
    "steering": ("mode", {"original": ("ade", "turn_deg", "commanded_turn_deg")}),
    "speed": ("model", {"*": ("fps", "peak_memory_mb")}),
}
# table -> (the columns naming a row, [(measure, value, low, high, count)]): where the report's intervals are.
INTERVALS: dict[str, tuple[tuple[str, ...], list[tuple[str, str, str, str, str | None]]]] = {
    "main_table": (("model",), [(c, c, f"{c}_low", f"{c}_high", f"{c}_n")
                                for c in ("fvd_val", "fvd_heldout", "fvd_turns", "fvd_slope_turns")]),
    "steering": (("mode",), [("ade", "ade", "ade_low", "ade_high", "ade_n"),
                             ("turn_deg_latent", "turn_deg_latent", "turn_deg_latent_low", "turn_deg_latent_high",
                              None)]),
    "conditioning": (("model", "check"), [("effect", "effect", "low", "high", "clips")]),
}
INTERVAL_COLUMNS = ["table", "row", "measure", "value", "low", "high", "n", "verdict"]


def _read(paths: Sequence[Path]) -> dict[str, pd.DataFrame]:
    return {Path(p).stem: pd.read_csv(p) for p in paths if Path(p).suffix == ".csv"}


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def parent_metrics(tables: Sequence[Path]) -> dict[str, float]:
    """The headline: :data:`HEADLINE`'s cells of the tables given (NA cells left out), at most 20, to 4 significant
    digits (MLflow's runs table and DVC print every digit they get; the tables and records keep them all)."""
    frames, metrics = _read(tables), {}
    for stem, (key, wanted) in HEADLINE.items():
        if stem not in frames:
            continue
        for _, row in frames[stem].iterrows():
            columns = wanted.get(str(row[key]), wanted.get("*", ()))
            for column in columns:
                if column in row and _finite(row[column]):
                    metrics[f"{stem}/{row[key]}/{column}"] = float(f"{float(row[column]):.4g}")
    if len(metrics) > MAX_METRICS:
        raise ValueError(f"{len(metrics)} headline metrics, more than {MAX_METRICS}: trim HEADLINE")
    return metrics


def intervals(tables: Sequence[Path]) -> pd.DataFrame:
    """Every interval of the tables given, one row each (:data:`INTERVAL_COLUMNS`); rows without one left out."""
    frames, rows = _read(tables), []
    for stem, (keys, measures) in INTERVALS.items():
        if stem not in frames:
            continue
        frame = frames[stem]
        for _, row in frame.iterrows():
            for measure, value, low, high, count in measures:
                if not all(c in frame.columns and _finite(row[c]) for c in (value, low, high)):
                    continue
                if "metric" in frame.columns:  # conditioning: one panel per metric, each on its own scale
                    measure = f"{measure} on {row['metric']}"
                rows.append({"table": stem, "row": " ".join(str(row[k]) for k in keys), "measure": measure,
                             "value": float(row[value]), "low": float(row[low]), "high": float(row[high]),
                             "n": int(row[count]) if count in frame.columns and _finite(row[count]) else None,
                             "verdict": row["verdict"] if "verdict" in frame.columns else None})
    frame = pd.DataFrame(rows, columns=INTERVAL_COLUMNS)
    frame["n"] = frame["n"].astype("Int64")
    return frame


def write_intervals(frame: pd.DataFrame, path: Path) -> Path:
    with atomic_file(Path(path)) as tmp:
        frame.to_csv(tmp, index=False, lineterminator="\n", float_format="%.6g")
    return Path(path)


def plot_intervals(frame: pd.DataFrame, path: Path) -> Path:
    """A forest plot: one panel per (table, measure), a point and its 95 % interval per row, n in the label;
    the conditioning effects with their zero line (no effect) and verdicts."""
    groups = [(key, group) for key, group in frame.groupby(["table", "measure"], sort=False)]
    plt = pyplot()
    heights = [len(group) + 1.2 for _, group in groups] or [1]
    fig, axes = plt.subplots(len(heights), 1, figsize=(8, 0.32 * sum(heights) + 0.6),
                             gridspec_kw={"height_ratios": heights}, squeeze=False)
    for ax, ((table, measure), group) in zip(axes[:, 0], groups):
        y = range(len(group))[::-1]
        ax.errorbar(group["value"], list(y), xerr=[group["value"] - group["low"], group["high"] - group["value"]],
                    fmt="o", color="tab:blue", ecolor="tab:gray", capsize=3, markersize=4)
        labels = [f"{r.row}" + (f"  (n={r.n})" if pd.notna(r.n) else "")
                  + (f"  [{r.verdict}]" if isinstance(r.verdict, str) else "") for r in group.itertuples()]
        ax.set_yticks(list(y), labels, fontsize=7)
        ax.set_ylim(-0.8, len(group) - 0.2)
        if table in ("conditioning", "steering") or (group["low"] < 0).any():
            ax.axvline(0, color="tab:red", lw=0.8, alpha=0.6)
        ax.set_title(f"{table}: {measure}", fontsize=8, loc="left")
        ax.tick_params(axis="x", labelsize=7)
        ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)
    return Path(path)


def write_stage_times(seconds: dict[str, float], path: Path) -> Path:
    """Each stage's wall time of this run, slowest first (the parent's table; each stage run has its own)."""
    frame = pd.DataFrame(sorted(seconds.items(), key=lambda kv: -kv[1]), columns=["stage", "seconds"])
    with atomic_file(Path(path)) as tmp:
        frame.to_csv(tmp, index=False, lineterminator="\n", float_format="%.1f")
    return Path(path)
