"""The paper's tables as rows: pure functions of the evaluation records (:mod:`orbis2.eval.records`).

Every table is a list of ordered rows; the writers (:mod:`orbis2.eval.report.report`) only serialise
them. A metric cell always comes with the sample count it was measured on (``<metric>_n``), and a
metric that an input lacks stops the report with an ``OrbisError`` naming the file and the stage
that writes it. The only ``NA`` cells are values no stage measures for that row (a reference row's
probes, a compression-ablation value its inputs report as null). Which systems and probe targets
fill the rows comes from registry.yaml; which FVD splits, steering modes and frame rates from the
configuration (:class:`TableSettings`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from orbis2.config.params import PipelineConfig
from orbis2.errors import OrbisError
from orbis2.eval.records import Chunked, CompressionRecord, CompressionRow, Interval, RealFloor, SteeringRecord
from orbis2.eval.report.evals import Evals
from orbis2.registry import SCOPES, registry

# Table 1's rows and the predictor probed for each (the hierarchy at its top one): registry.yaml's main_table,
# after its flat baselines in the full report.
TABLE_PROBE = {scope: registry().table(scope) for scope in SCOPES}
TRAINING_ROWS = (
    ("abstract tokenizer", "abstract_tokenizer"),
    ("TF only", "abstract_tf_only"),
    ("DF only", "abstract_df"),
    ("DF + TF", "abstract_tf"),
    ("teacher", "teacher"),
)
# Table 3: (exp, branch, abstraction, frame rate, probed target, model whose rollout gives the FVD).
HIERARCHY_LAYOUT = (
    (1, "single", "detail", "detail_hz", "flat_detail", "flat_detail"),
    (2, "single", "abstract", "detail_hz", "flat_abstract", "flat_abstract"),
    (3, "top", "abstract", "abstract_hz", "abstract_tf", "hierarchical"),
    (3, "bottom", "detail", "detail_hz", "detail", "hierarchical"),
    (4, "top", "detail", "abstract_hz", "top_detail", "top_detail"),
    (4, "bottom", "detail", "detail_hz", "detail_on_detail", "top_detail"),
    (5, "top", "abstract", "detail_hz", "flat_abstract", "top_abstract_10hz"),
    (5, "bottom", "detail", "detail_hz", "detail", "top_abstract_10hz"),
)
NA = "NA"

Row = dict[str, Any]


@dataclass(frozen=True)
class TableSettings:
    """What the configuration decides about the tables: Table 1's FVD splits (``evaluation.fvd_splits``) and
    the split of its FVD-slope (``evaluation.long_split``), Table 2's steering modes (the keys of
    ``evaluation.steering_modes``, in order) and Table 3's frame rates (``data.detail_hz``, ``abstract_hz``)."""

    fvd_splits: tuple[str, ...]
    long_split: str
    steering_modes: tuple[str, ...]
    detail_hz: int
    abstract_hz: int

    @classmethod
    def from_config(cls, cfg: PipelineConfig) -> TableSettings:
        ev = cfg.evaluation
        return cls(tuple(ev.fvd_splits), ev.long_split, tuple(ev.steering_modes), cfg.data.detail_hz,
                   cfg.data.abstract_hz)


def probe_cells(evals: Evals, target: str) -> Row:
    """A probe target's segmentation mIoU and depth RMSE with their test-frame counts."""
    record = evals.probe_record(target)
    seg = evals.value(record.segmentation, "probe", target, "segmentation")
    depth = evals.value(record.depth, "probe", target, "depth")
    return {"probe_target": target, "miou": seg.miou, "miou_n": seg.test_frames, "rmse": depth.rmse,
            "rmse_n": depth.test_frames}


def chunked(evals: Evals, model: str) -> Chunked:
    """A system's chunked FVD (its record has one when ``evaluation.long_split`` was among its splits)."""
    return evals.value(evals.fvd_record(model).chunked, "fvd", model, "chunked")


def _rollout_cells(evals: Evals, model: str, long_split: str) -> Row:
    rollout = chunked(evals, model)
    if rollout.split != long_split:
        raise OrbisError(f"{evals.where('fvd', model)}: chunked FVD must be on the {long_split} split "
                         f"(evaluation.long_split); re-run it")
    return {"fvd_model": model, "fvd_long": rollout.fvd_long, "fvd_long_n": rollout.videos,
            "fvd_slope": rollout.fvd_slope, "fvd_slope_n": rollout.videos}


# Reference rows of the FVD table: (row name, system whose record holds it, reference, label); the reference is
# a field of :class:`References`.
FVD_REFERENCES = (
    ("real_floor", "hierarchical", "real_floor", "reference: real vs real, disjoint halves of the clips"),
    ("reconstruction_detail", "hierarchical", "reconstruction", "reference: detail tokenizer reconstruction"),
    ("repeat_last_detail", "hierarchical", "repeat_last", "reference: last context frame held (detail decoder)"),
    ("reconstruction_abstract", "flat_abstract", "reconstruction", "reference: abstract tokenizer reconstruction"),
    ("repeat_last_abstract", "flat_abstract", "repeat_last", "reference: last context frame held (abstract decoder)"),
)


def main_table(evals: Evals, scope: str, settings: TableSettings) -> list[Row]:
    """Table 1: FVD on each of ``evaluation.fvd_splits`` (clip-bootstrap intervals), FVD-slope on the long split
    and the linear probes per model of the scope (``all`` adds the flat baselines), then the reference rows
    (``kind`` = reference) on the same clips and frames, for each decoder one of the scope's models uses."""
    slope = f"fvd_slope_{settings.long_split}"
    rows = []
    probed = TABLE_PROBE[scope]
    for model in probed:
        record = evals.fvd_record(model)
        row: Row = {"model": model, "kind": "model", "label": record.label, "parameters": record.parameters}
        for split in settings.fvd_splits:
            cells = evals.entry(record.fvd, split, "fvd", model, "fvd")
            row.update({f"fvd_{split}": cells.fvd, f"fvd_{split}_low": cells.low, f"fvd_{split}_high": cells.high,
                        f"fvd_{split}_n": cells.videos})
        rollout = _rollout_cells(evals, model, settings.long_split)
        row[slope] = rollout["fvd_slope"]
        row[f"{slope}_low"] = chunked(evals, model).fvd_slope_low
        row[f"{slope}_high"] = chunked(evals, model).fvd_slope_high
        row[f"{slope}_n"] = rollout["fvd_slope_n"]
        row.update(probe_cells(evals, probed[model]))
        rows.append(row)
    for name, model, ref, label in (r for r in FVD_REFERENCES if r[1] in probed):
        row = {"model": name, "kind": "reference", "label": label, "parameters": NA}
        for split in settings.fvd_splits:
            refs = evals.entry(evals.fvd_record(model).references, split, "fvd", model, "references")
            cells = evals.value(getattr(refs, ref), "fvd", model, f"references.{split}.{ref}")
            if cells.fvd is None:  # e.g. a real-vs-real floor on fewer than 4 clips: not computable
                row.update({f"fvd_{split}{suffix}": NA for suffix in ("", "_low", "_high", "_n")})
                continue
            row.update({f"fvd_{split}": cells.fvd, f"fvd_{split}_low": cells.low, f"fvd_{split}_high": cells.high,
                        f"fvd_{split}_n": cells.videos_per_half if isinstance(cells, RealFloor) else cells.videos})
        row.update({key: NA for key in rows[0] if key not in row})
        rows.append(row)
    return rows


def steering_table(evals: Evals, settings: TableSettings) -> list[Row]:
    """Table 2: ADE per steering mode of ``evaluation.steering_modes`` (clip-bootstrap interval) by the main
    instrument, with OpenCV odometry as a second column (NA where ``evaluation.opencv_rollouts`` left it off the
    generated videos); then the bottom level alone given the real subgoals (its turn readings only: a
    reference for what the top's predictions cost), and each instrument on real and on shuffled videos as
    floor and chance. Where the record has the town's true counterfactuals, each mode's row also scores it
    against them (:func:`_truth_cells`); a cell a row does not measure is NA."""
    record = evals.steering_record()
    main = record.inverse_dynamics
    measured = "opencv" in record.instruments
    rows: list[Row] = []
    for mode in settings.steering_modes:
        cells = evals.entry(record.modes, mode, "steering", None, "modes")
        opencv = (evals.entry(cells.instruments, "opencv", "steering", None, f"modes.{mode}.instruments")
                  if measured else None)
        rows.append({
            "mode": mode,
            "kind": "generated",
            "instrument": main,
            "ade": cells.ade,
            "ade_low": cells.ade_low,
            "ade_high": cells.ade_high,
            "ade_n": cells.samples,
            # How far the video turns (end point, degrees, the clip's turn direction positive) next to the
            # command: a scale-free check that counterfactuals move the rollout the right way.
            "turn_deg": cells.turn_deg,
            "commanded_turn_deg": cells.commanded_turn_deg,
            "ade_opencv": opencv.ade if opencv else NA,
            "turn_deg_opencv": opencv.turn_deg if opencv else NA,
            **_turn_cells(evals, "latent", mode),
            **_turn_cells(evals, "image", mode),
            **_truth_cells(evals, record, mode),
        })
    rows.append({**{key: NA for key in rows[0]}, "mode": "real_subgoals", "kind": "reference",
                 "instrument": main, "ade_n": record.samples,
                 **_turn_cells(evals, "latent", "real_subgoals"), **_turn_cells(evals, "image", "real_subgoals")})
    floor = record.odometry_sanity
    opencv_floor = evals.entry(record.sanity, "opencv", "steering", None, "sanity")
    for mode, (ade, low, high, ade_opencv) in (
            ("real_videos", (floor.real_ade, floor.real_low, floor.real_high, opencv_floor.real_ade)),
            ("shuffled_videos", (floor.shuffled_ade, floor.shuffled_low, floor.shuffled_high,
                                 opencv_floor.shuffled_ade))):
        rows.append({
            "mode": mode,
            "kind": "odometry_sanity",
            "instrument": main,
            "ade": ade,
            "ade_low": low,
            "ade_high": high,
            "ade_n": floor.videos,
            "turn_deg": NA,
            "commanded_turn_deg": NA,
            "ade_opencv": ade_opencv,
            "turn_deg_opencv": NA,
            **{k: v if mode == "real_videos" else NA for reading in ("latent", "image")
               for k, v in _turn_cells(evals, reading, "real").items()},
        })
    return [{**{key: NA for key in rows[0]}, **row} for row in rows]


def _interval_cells(name: str, iv: Interval | None) -> Row:
    return {name: NA, f"{name}_low": NA, f"{name}_high": NA} if iv is None else {
        name: iv.estimate, f"{name}_low": iv.low, f"{name}_high": iv.high}


def _truth_cells(evals: Evals, record: SteeringRecord, mode: str) -> Row:
    """One mode's rollouts against the town's true counterfactuals (none without them): per horizon the latent
    MSE and PSNR of generated against true frames, FVD of generated against true videos, the instrument's turn
    read from the true videos beside the commanded one (its calibration: the true video follows the command),
    the truth-based claim's margin (closer to its own command's truth than to the others', relative) and how
    many true paths met traffic or left the road; every figure with its interval and sample count."""
    truth = record.truth
    if truth is None:
        return {}
    cells = evals.entry(truth.modes, mode, "steering", None, "truth.modes")
    margin = evals.entry(truth.claim.modes, mode, "steering", None, "truth.claim.modes")
    row: Row = {"truth_n": cells.samples}
    for horizon in cells.horizons:
        at = f"{horizon.seconds:g}s"
        row |= _interval_cells(f"latent_mse_{at}", horizon.latent_mse) | _interval_cells(f"psnr_{at}", horizon.psnr)
    row |= {"truth_fvd": cells.fvd.fvd, "truth_fvd_low": cells.fvd.low, "truth_fvd_high": cells.fvd.high,
            "truth_fvd_n": cells.fvd.videos}
    row |= _interval_cells("truth_turn_deg", cells.instrument.turn_deg)
    row |= {"truth_commanded_turn_deg": cells.instrument.commanded_turn_deg}
    row |= _interval_cells("truth_turn_relative_error", cells.instrument.relative_error)
    row |= _interval_cells("truth_margin", margin.margin) | {"truth_verdict": margin.verdict}
    return row | {"truth_collisions": cells.collision, "truth_off_road": cells.off_road}


def _turn_cells(evals: Evals, reading: str, mode: str) -> Row:
    """The turn of one of ``eval_steering``'s readings (``latent``: the detail latents without decoding;
    ``image``: the decoded frames' sideways motion; "real": the real continuation, the reading's
    calibration), with its clip-bootstrap interval."""
    record = evals.steering_record()
    turns = record.latent_turn if reading == "latent" else record.image_turn
    cell = evals.entry(turns.modes, mode, "steering", None, f"{reading}_turn.modes")
    return {f"turn_deg_{reading}": cell.turn_deg, f"turn_deg_{reading}_low": cell.low,
            f"turn_deg_{reading}_high": cell.high}


def calibration_table(evals: Evals) -> list[Row]:
    """The steering instrument on the town's true counterfactuals, per mode: the turn it reads from the true videos
    against the commanded one (the true video follows the command exactly), and its relative error with an
    interval; empty without a steering record with truth."""
    truth = evals.steering_record().truth if evals.has("steering") else None
    if truth is None:
        return []
    rows = []
    for mode, cells in truth.modes.items():
        reading, relative = cells.instrument.turn_deg, cells.instrument.relative_error
        rows.append({"mode": mode, "instrument": truth.instrument,
                     "commanded_turn_deg": cells.instrument.commanded_turn_deg,
                     **_interval_cells("read_turn_deg", reading), **_interval_cells("relative_error", relative),
                     "n": cells.samples})
    return rows


def speed_table(evals: Evals) -> list[Row]:
    """Table 5: frames per second and peak memory per model the record holds, on the device that measured them."""
    record = evals.speed_record()
    return [{"model": model, "fps": run.fps, "fps_n": run.frames, "peak_memory_mb": run.peak_memory_mb,
             "memory_kind": record.memory_kind, "parameters": run.parameters, "device": record.device}
            for model, run in record.models.items()]


def hierarchy_table(evals: Evals, settings: TableSettings) -> list[Row]:
    """Table 3 (Exps 1-5): each predictor's probes and its system's long-horizon FVD on turns.

    A two-branch experiment has one FVD, that of its cascaded rollout; both of
    its rows carry it, with ``fvd_model`` naming the rollout it comes from.
    """
    rows = []
    rates = {"detail_hz": settings.detail_hz, "abstract_hz": settings.abstract_hz}
    for exp, branch, abstraction, rate, target, model in HIERARCHY_LAYOUT:
        row: Row = {"exp": exp, "branch": branch, "abstraction": abstraction, "frame_rate_hz": rates[rate]}
        row.update(probe_cells(evals, target))
        row.update(_rollout_cells(evals, model, settings.long_split))
        rows.append(row)
    return rows


def training_table(evals: Evals) -> list[Row]:
    """Table 4: probes of the abstract branch under each training strategy, against tokenizer and teacher."""
    rows = []
    for name, target in TRAINING_ROWS:
        row: Row = {"model": name}
        row.update(probe_cells(evals, target))
        row["val_loss"] = evals.value(evals.probe_record(target).segmentation, "probe", target,
                                      "segmentation").val_loss
        rows.append(row)
    return rows


def compression_table(evals: Evals) -> list[Row]:
    """Compressed against full-dimension abstract latents; a null the stage reports stays visible as NA."""
    source = evals.compression_record().rows
    if len(source) < 2:
        raise OrbisError(f"{evals.where('compression')} needs at least two rows (compressed and full)")
    rows = []
    for entry in source:
        row: Row = {"variant": entry.variant, "latent_dim": entry.latent_dim}
        for metric in ("fvd_long", "fvd_slope", "miou", "rmse"):
            value, n = getattr(entry, metric), getattr(entry, f"{metric}_n")
            row[metric] = NA if value is None else value
            row[f"{metric}_n"] = NA if n is None else n
        rows.append(row)
    return rows


def compression_from_evals(evals: Evals) -> CompressionRecord:
    """The compression ablation's rows from the flat abstract models on compressed and on full latents.

    Rollout stability is their FVD over the whole long rollout (``long_seconds``) and FVD-slope on the
    long split; representation quality the probes of those predictors. Raises like every table when an input is missing.
    """
    rows = []
    for variant, model in (("compressed", "flat_abstract"), ("full (teacher dim)", "flat_abstract_full")):
        probe = probe_cells(evals, model)
        rollout = chunked(evals, model)
        rows.append(CompressionRow(variant=variant, latent_dim=evals.fvd_record(model).latent_channels,
                                   fvd_long=rollout.fvd_long, fvd_long_n=rollout.videos,
                                   fvd_slope=rollout.fvd_slope, fvd_slope_n=rollout.videos,
                                   miou=probe["miou"], miou_n=probe["miou_n"], rmse=probe["rmse"],
                                   rmse_n=probe["rmse_n"]))
    return CompressionRecord(rows=rows)
