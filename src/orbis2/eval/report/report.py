"""The report: the paper's tables as CSV, a summary with the claims, the headline metrics and the figures.

The rows come from :mod:`orbis2.eval.report.tables` and the verdicts from :mod:`orbis2.eval.report.claims`, both
pure functions of the records :mod:`orbis2.eval.records` reads; this module only serialises and
draws them (figures of frames, which evaluation stages draw too, are in :mod:`orbis2.eval.figures`).
Everything a writer needs is checked before its first file is written.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping, Sequence

import pandas as pd

from orbis2.config.params import PipelineConfig
from orbis2.errors import OrbisError
from orbis2.eval.figures import pyplot, save_figure
from orbis2.eval.protocols.conditioning import conditioning_rows
from orbis2.eval.records import PROBE_TARGETS
from orbis2.eval.report.claims import check_claims, fmt
from orbis2.eval.report.evals import Evals
from orbis2.eval.report.tables import (
    HIERARCHY_LAYOUT,
    TRAINING_ROWS,
    Row,
    TableSettings,
    calibration_table,
    chunked,
    compression_table,
    hierarchy_table,
    main_table,
    speed_table,
    steering_table,
    training_table,
)
from orbis2.io import atomic_file
from orbis2.registry import registry

# From registry.yaml: the systems on the paper's compressed latents (the chunked-FVD figure).
FVD_MODELS = tuple(name for name, system in registry().systems.items() if system.latents == "compressed")

MAIN_CSV = "main_table.csv"
HEADLINE_JSON = "headline.json"  # Table 1 as flat metrics (headline): what `dvc metrics show` reads
STEERING_CSV = "steering.csv"
SPEED_CSV = "speed.csv"
HIERARCHY_CSV = "hierarchy_ablation.csv"
TRAINING_CSV = "training_ablation.csv"
COMPRESSION_CSV = "compression_ablation.csv"
CONDITIONING_CSV = "conditioning.csv"
CHUNKED_CSV = "fvd_chunked.csv"  # Fig. 4's data: end_s, one FVD column per system (`dvc plots show`)
SUMMARY_MD = "summary.md"
FIGURES = "figures"
FIG_CHUNKED = "fvd_chunked.png"
FIG_BLOCKS = "probe_per_block.png"
FIG_BUBBLE = "bubble_params_fvd_miou.png"

# ---------------------------------------------------------------- writers


def _cell(value: Any) -> str:
    return repr(value) if isinstance(value, float) else str(value)


def write_csv(rows: Sequence[Row], path: str | Path) -> None:
    """Header row plus one line per row (CRLF, as the ``csv`` module writes); floats are written
    with ``repr`` so they read back exactly."""
    if not rows:
        raise ValueError(f"no rows to write to {path}")
    table = pd.DataFrame(list(rows), columns=list(rows[0]), dtype=object).map(_cell)
    with atomic_file(Path(path)) as tmp:
        table.to_csv(tmp, index=False, lineterminator="\r\n")


def markdown_table(rows: Sequence[Row]) -> str:
    header = list(rows[0])
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(row[key]) for key in header) + " |" for row in rows]
    return "\n".join(lines)


def protocol_lines(evals: Evals) -> list[str]:
    """The FVD protocol card of each split, from the FVD records (identical across systems but for their I3D
    inputs' source resolution), so that a table's FVDs can be reproduced from what is printed beside it. Its
    entries in the order of the record's file (sorted keys, as every record is written)."""
    cards: dict[str, dict] = {}
    for record in evals.fvd.values():
        for split, card in record.protocol.items():
            cards.setdefault(split, dict(sorted(card.model_dump(exclude={"source_resolution"}).items())))
    lines = [f"FVD protocol, {split}: " + ", ".join(f"{k}={v}" for k, v in card.items()) for split, card in
             sorted(cards.items())]
    return [*(f"- {line}" for line in lines), ""] if lines else []


def first_frame_table(evals: Evals) -> list[Row]:
    """One row per system and split with a first-frame measurement (FVD records that have one)."""
    rows = []
    for name, record in evals.fvd.items():
        for split, cell in (record.first_frame or {}).items():
            row: Row = {"model": name, "split": split, "n": cell.gap_db.units}
            for key in ("generated_psnr", "reconstruction_psnr", "gap_db"):
                iv = getattr(cell, key)
                row.update({key: iv.estimate, f"{key}_low": iv.low, f"{key}_high": iv.high})
            rows.append(row)
    return rows


def summary_markdown(tables: Sequence[tuple[str, Sequence[Row]]], evals: Evals, setup: Mapping,
                     settings: TableSettings) -> str:
    """The tables, the claims checked against them, then the setup that produced them."""
    parts = ["# Orbis 2 evaluation summary", ""]
    for title, rows in tables:
        parts += [f"## {title}", "", markdown_table(rows), ""]
        if any(key.startswith("fvd") for row in rows for key in row):
            parts += protocol_lines(evals)
    calibration = calibration_table(evals)
    if calibration:  # docs/evaluation.md, "The instrument on the truth"
        parts += ["## The steering instrument on the true counterfactuals", "",
                  "The turn the instrument reads from the town's true videos under each command, against the "
                  "commanded turn (degrees, each start's turn direction positive; relative error = read / "
                  "commanded - 1, clip-bootstrap intervals).", "", markdown_table(calibration), ""]
    first = first_frame_table(evals)
    if first:
        parts += ["## The first generated frame", "",
                  "PSNR (dB) against the real frame of each rollout's first generated frame and of the detail "
                  "tokenizer's reconstruction of that real frame; gap = reconstruction - generated, paired per "
                  "rollout: the blur the predictor adds to the tokenizer's (clip-bootstrap intervals).", "",
                  markdown_table(first), ""]
    parts += ["## Reading", ""]
    for i, (claim, verdict, evidence) in enumerate(check_claims(evals, settings), start=1):
        parts.append(f"{i}. {claim}: **{verdict}**. {evidence}.")
    parts += ["", "## Setup", ""]
    for key, value in setup.items():
        shown = json.dumps(value, sort_keys=True) if isinstance(value, (dict, list, tuple)) else fmt(value)
        parts.append(f"- {key}: {shown}")
    return "\n".join(parts) + "\n"


def _tables(evals: Evals, full: bool, settings: TableSettings) -> list[tuple[str, str, list[Row]]]:
    """(title, file name, rows) of every table; ``full`` adds the flat baselines to Table 1 and makes the ablations
    required, else they join when present."""
    tables = [
        ("Main results (Table 1)", MAIN_CSV, main_table(evals, "all" if full else "main", settings)),
        ("Steering (Table 2)", STEERING_CSV, steering_table(evals, settings)),
        ("Speed and memory (Table 5)", SPEED_CSV, speed_table(evals)),
    ]
    hierarchy_ready = all(evals.has("fvd", e[5]) and evals.has("probe", e[4]) for e in HIERARCHY_LAYOUT)
    if full or hierarchy_ready:
        tables.append(("Hierarchy design study (Table 3)", HIERARCHY_CSV, hierarchy_table(evals, settings)))
    if full or all(evals.has("probe", t) for _, t in TRAINING_ROWS):
        tables.append(("Training strategy (Table 4)", TRAINING_CSV, training_table(evals)))
    if evals.has("compression"):
        tables.append(("Latent compression", COMPRESSION_CSV, compression_table(evals)))
    if evals.has("conditioning"):
        tables.append(("Conditioning use and one-step baselines", CONDITIONING_CSV,
                       conditioning_rows(evals.conditioning_record())))
    return tables


def _write_tables(
    csv_tables: Sequence[tuple[str, str, list[Row]]],
    summary_tables: Sequence[tuple[str, str, list[Row]]],
    evals: Evals,
    out_dir: Path,
    setup: Mapping,
    settings: TableSettings,
) -> list[Path]:
    summary = summary_markdown([(title, rows) for title, _, rows in summary_tables], evals, setup, settings)
    written = []
    for _, name, rows in csv_tables:
        write_csv(rows, out_dir / name)
        written.append(out_dir / name)
    with atomic_file(out_dir / SUMMARY_MD) as tmp:
        tmp.write_text(summary)
    return written + [out_dir / SUMMARY_MD]


def report_setup(cfg: PipelineConfig) -> dict[str, Any]:
    """What the summary states about how the numbers were made."""
    ev = cfg.evaluation
    return {"profile": cfg.profile, "resolution": f"{cfg.data.width}x{cfg.data.height}",
            "evaluation seed": ev.seed, "NFE (top / bottom)": f"{ev.top_nfe} / {ev.bottom_nfe}",
            "FVD rollouts": f"{ev.seconds} s on {', '.join(ev.fvd_splits)}; chunked {ev.long_seconds} s on "
                            f"{ev.long_split} in {ev.chunk_seconds} s chunks",
            "starts per clip": ev.starts_per_clip, "steering": f"{ev.steering_seconds} s on {ev.steering_split}",
            "probe": f"town probe split, {ev.probe.seg_epochs} / {ev.probe.depth_epochs} epochs, "
                     f"seed {ev.probe.seed}",
            "training seeds": {s: cfg.section(s).train.seed for s in ("abstract_df", "abstract_tf", "detail",
                                                                       registry().steered, "flat_detail",
                                                                       "flat_abstract")}}


def write_main_report(
    evals: Evals, out_dir: str | Path, setup: Mapping, settings: TableSettings
) -> list[Path]:
    """main_table.csv, steering.csv, speed.csv (conditioning.csv when its record exists) and a summary.md
    of what is available; returns the paths.

    Only the three main tables are written as CSV; ablation tables whose inputs
    all exist are shown in the summary too, and claims without inputs read
    "not measured".
    """
    tables = _tables(evals, False, settings)
    csv_tables = tables[:3] + [t for t in tables if t[1] == CONDITIONING_CSV]
    return _write_tables(csv_tables, tables, evals, Path(out_dir), setup, settings)


def write_full_report(
    evals: Evals, out_dir: str | Path, setup: Mapping, settings: TableSettings
) -> list[Path]:
    """Every table, the ablations and the JSON-driven figures, with a summary covering all of them.

    ``evals.compression`` (from :func:`compression_from_evals`) is optional: without it
    compression_ablation.csv is not written (a stale one is removed) and the summary marks
    claim 3 not measured.
    Everything is checked before the first file is written.
    """
    out_dir = Path(out_dir)
    tables = _tables(evals, True, settings)
    _per_block_targets(evals)
    written = _write_tables(tables, tables, evals, out_dir, setup, settings)
    if not evals.has("compression"):
        (out_dir / COMPRESSION_CSV).unlink(missing_ok=True)
    figures = out_dir / FIGURES
    plot_chunked_fvd(evals, figures / FIG_CHUNKED, settings.long_split)
    write_chunked_fvd(evals, out_dir / CHUNKED_CSV)
    plot_probe_blocks(evals, figures / FIG_BLOCKS)
    plot_bubble(evals, figures / FIG_BUBBLE, settings=settings)
    return written + [out_dir / CHUNKED_CSV, figures / FIG_CHUNKED, figures / FIG_BLOCKS, figures / FIG_BUBBLE]


# ---------------------------------------------------------------- figures


def plot_chunked_fvd(evals: Evals, path: str | Path, split: str, models: Sequence[str] = FVD_MODELS) -> None:
    """Fig. 4: FVD of each consecutive window of the long rollouts on ``split``, one line per model."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for model in models:
        chunks = chunked(evals, model).chunks
        ax.plot([c.end_s for c in chunks], [c.fvd for c in chunks], marker="o", label=evals.fvd_record(model).label)
    ax.set_xlabel("end of window (s)")
    ax.set_ylabel("FVD")
    ax.set_title(f"FVD over consecutive windows ({split})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, path)


def write_chunked_fvd(evals: Evals, path: str | Path, models: Sequence[str] = FVD_MODELS) -> None:
    """Fig. 4's numbers as a table: the end of each window (s) and one FVD column per system."""
    rows = [{"system": model, "end_s": chunk.end_s, "fvd": chunk.fvd}
            for model in models for chunk in chunked(evals, model).chunks]
    table = pd.DataFrame(rows).pivot(index="end_s", columns="system", values="fvd")[list(models)]
    with atomic_file(Path(path)) as tmp:
        table.reset_index().to_csv(tmp, index=False, lineterminator="\n", float_format="%.6g")


def _per_block_targets(evals: Evals) -> list[str]:
    targets = [t for t in PROBE_TARGETS if t in evals.probe and evals.probe[t].per_block]
    if not targets:
        raise OrbisError(
            f"no probe file {f'in {evals.folder}' if evals.folder else 'given'} has per_block results: "
            "run an eval_probe_<target> stage with per-block probing"
        )
    return targets


def plot_probe_blocks(evals: Evals, path: str | Path) -> None:
    """Fig. 5: segmentation mIoU and depth RMSE of a probe on every block, one line per probed model."""
    targets = _per_block_targets(evals)
    plt = pyplot()
    fig, (ax_miou, ax_rmse) = plt.subplots(1, 2, figsize=(9, 3.6))
    for target in targets:
        record = evals.probe_record(target)
        cells = sorted((b.block, b.miou, b.rmse) for b in record.per_block or ())
        label = record.label
        ax_miou.plot([c[0] for c in cells], [c[1] for c in cells], marker="o", label=label)
        ax_rmse.plot([c[0] for c in cells], [c[2] for c in cells], marker="o", label=label)
    for ax, name in ((ax_miou, "segmentation mIoU (higher is better)"), (ax_rmse, "depth RMSE (lower is better)")):
        ax.set_xlabel("predictor block")
        ax.set_title(name)
        ax.grid(alpha=0.3)
    ax_miou.legend(fontsize=8)
    save_figure(fig, path)


def plot_bubble(evals: Evals, path: str | Path, settings: TableSettings, x_metric: str = "fvd_slope") -> None:
    """Fig. 2: long-horizon FVD against segmentation mIoU, bubble area proportional to parameters.

    ``x_metric`` is ``fvd_slope`` (on the long split) or ``fvd_<split>`` for one of the FVD splits.
    """
    rows = [r for r in main_table(evals, "all", settings) if r["kind"] == "model"]
    key = f"fvd_slope_{settings.long_split}" if x_metric == "fvd_slope" else x_metric
    if key not in rows[0] or not key.startswith("fvd"):
        known = ", ".join(["fvd_slope", *(f"fvd_{split}" for split in settings.fvd_splits)])
        raise ValueError(f"x_metric must be one of {known}, got {x_metric!r}")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    largest = max(r["parameters"] for r in rows)
    for row in rows:
        ax.scatter(row[key], row["miou"], s=2000.0 * row["parameters"] / largest, alpha=0.5)
        ax.annotate(f"{row['label']}\n{row['parameters'] / 1e6:.1f}M", (row[key], row["miou"]), ha="center", fontsize=8)
    ax.set_xlabel(f"FVD-slope on {settings.long_split}" if x_metric == "fvd_slope" else x_metric.replace("_", " "))
    ax.set_ylabel("segmentation mIoU")
    ax.set_title("bubble area: parameters")
    ax.grid(alpha=0.3)
    ax.margins(0.25)
    save_figure(fig, path)

