"""The paper's tables, figures and a summary built from the evaluation JSON files.

Over 600 lines on purpose: every table, claim and figure of the paper's results is here, each
a short pure function, so that the report reads as one document (figures of frames, which
evaluation stages draw too, are in :mod:`orbis2.eval.figures`).

Every table is a list of ordered rows built by a pure function from the dict
``load_eval`` returns; the writers only serialise them. A metric cell always
comes with the sample count it was measured on (``<metric>_n``), and a metric
that an input lacks stops the report with an ``OrbisError`` naming the file and
the stage that writes it, so no table is ever padded with guesses. The only
``NA`` cells are compression-ablation values its inputs report as null (not
measured).
"""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import pandas as pd

from orbis2.config.params import PipelineConfig
from orbis2.errors import OrbisError
from orbis2.eval.conditioning import claim_verdict, conditioning_rows
from orbis2.eval.figures import pyplot, save_figure
from orbis2.eval.stats import paired_draws_interval
from orbis2.io import atomic_file
from orbis2.registry import SCOPES, registry

# From registry.yaml: the systems on the paper's compressed latents (the chunked-FVD figure), and every
# probe target (the per-block figure draws those that have per-block curves).
FVD_MODELS = tuple(name for name, system in registry().systems.items() if system.latents == "compressed")
PROBE_TARGETS = tuple(registry().probe_targets)
FVD_SPLITS = ("val", "heldout", "turns")
STEERING_MODES = ("original", "speed_x0.5", "speed_x1.5", "yaw_rate_x0.5", "yaw_rate_x1.5")
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

HOLDS, FAILS, UNMEASURED = "holds", "does not hold", "not measured"
UNRESOLVED = "not resolved at this sample size"

Row = dict[str, Any]


# ---------------------------------------------------------------- loading


def _file_and_stage(kind: str, name: str | None) -> tuple[str, str]:
    if kind in ("fvd", "probe"):
        return f"{kind}_{name}.json", f"eval_{kind}_{name}"
    if kind == "compression":  # built by compression_from_evals, not read from a file
        return "the compression rows (fvd_flat_abstract_full.json)", "eval_fvd_flat_abstract_full"
    return f"{kind}.json", f"eval_{kind}"


EVAL_KINDS = ("steering", "speed", "conditioning")  # one file each, beside the per-system and per-target ones


def read_evals(fvd: Mapping[str, str | Path], probe: Mapping[str, str | Path], steering: str | Path | None = None,
               speed: str | Path | None = None, conditioning: str | Path | None = None) -> dict:
    """The evaluation JSON files given (``fvd``: system -> file, ``probe``: target -> file, and the steering,
    speed and conditioning files), keyed by kind and name; a file that does not exist is simply absent."""
    evals: dict = {"fvd": {}, "probe": {}, "files": {"fvd": {}, "probe": {}}}
    for kind, files, key in (("fvd", fvd, "model"), ("probe", probe, "target")):
        for name, path in files.items():
            path = Path(path)
            evals["files"][kind][name] = path
            if path.exists():
                data = _read_json(path)
                if data.get(key) != name:
                    found = data.get(key)
                    raise OrbisError(f"{path} says {key}={found!r}, expected {name!r}: re-run eval_{kind}_{name}")
                evals[kind][name] = data
    for kind, path in (("steering", steering), ("speed", speed), ("conditioning", conditioning)):
        if path is not None:
            evals["files"][kind] = Path(path)
            if Path(path).exists():
                evals[kind] = _read_json(Path(path))
    return evals


def load_eval(folder: str | Path) -> dict:
    """Every evaluation JSON present in ``folder`` under the names the evaluation stages give them by default
    (``fvd_<system>.json``, ``probe_<target>.json``, ``steering.json``, ...): :func:`read_evals` of that folder."""
    folder = Path(folder)
    evals = read_evals({name: folder / _file_and_stage("fvd", name)[0] for name in registry().systems},
                       {name: folder / _file_and_stage("probe", name)[0] for name in PROBE_TARGETS},
                       **{kind: folder / f"{kind}.json" for kind in EVAL_KINDS})
    return evals | {"folder": str(folder)}


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise OrbisError(f"cannot read {path}: {err}; re-run the stage that writes it") from err
    if not isinstance(data, dict):
        raise OrbisError(f"{path} holds {type(data).__name__}, expected a JSON object; re-run the stage that writes it")
    return data


def _where(evals: Mapping, kind: str, name: str | None = None) -> str:
    file, stage = _file_and_stage(kind, name)
    given = evals.get("files", {}).get(kind)
    given = given.get(name) if isinstance(given, Mapping) else given
    path = given if given is not None else Path(evals.get("folder", "reports/eval")) / file
    if name is None and Path(path).stem == f"{kind}_all":  # the full report's speed and conditioning records
        stage += "_all"
    return f"{path} (written by stage {stage})"


def _doc(evals: Mapping, kind: str, name: str | None = None) -> dict:
    """The parsed file, or an error naming it and the stage that produces it."""
    doc = evals.get(kind, {}).get(name) if name is not None else evals.get(kind)
    if doc is None:
        raise OrbisError(f"missing {_where(evals, kind, name)}: run that stage first")
    return doc


def _has(evals: Mapping, kind: str, name: str | None = None) -> bool:
    return (evals.get(kind, {}).get(name) if name is not None else evals.get(kind)) is not None


def _get(evals: Mapping, kind: str, name: str | None, *keys: str | int) -> Any:
    """A value deep in a file; missing or null is an error (strict: no blank metric cells)."""
    value: Any = _doc(evals, kind, name)
    for i, key in enumerate(keys):
        try:
            value = value[key]
        except (KeyError, IndexError, TypeError):
            value = None
        if value is None:
            path = ".".join(str(k) for k in keys[: i + 1])
            raise OrbisError(f"{_where(evals, kind, name)} has no value for {path}: re-run that stage")
    return value


# ---------------------------------------------------------------- tables


def _probe_cells(evals: Mapping, target: str) -> Row:
    return {
        "probe_target": target,
        "miou": _get(evals, "probe", target, "segmentation", "miou"),
        "miou_n": _get(evals, "probe", target, "segmentation", "test_frames"),
        "rmse": _get(evals, "probe", target, "depth", "rmse"),
        "rmse_n": _get(evals, "probe", target, "depth", "test_frames"),
    }


def _rollout_cells(evals: Mapping, model: str) -> Row:
    if _get(evals, "fvd", model, "chunked", "split") != "turns":
        raise OrbisError(f"{_where(evals, 'fvd', model)}: chunked FVD must be on the turns split; re-run it")
    return {
        "fvd_model": model,
        "fvd_long": _get(evals, "fvd", model, "chunked", "fvd_long"),
        "fvd_long_n": _get(evals, "fvd", model, "chunked", "videos"),
        "fvd_slope": _get(evals, "fvd", model, "chunked", "fvd_slope"),
        "fvd_slope_n": _get(evals, "fvd", model, "chunked", "videos"),
    }


# Reference rows of the FVD table: (row name, system whose record holds it, reference, label).
FVD_REFERENCES = (
    ("real_floor", "hierarchical", "real_floor", "reference: real vs real, disjoint halves of the clips"),
    ("reconstruction_detail", "hierarchical", "reconstruction", "reference: detail tokenizer reconstruction"),
    ("repeat_last_detail", "hierarchical", "repeat_last", "reference: last context frame held (detail decoder)"),
    ("reconstruction_abstract", "flat_abstract", "reconstruction", "reference: abstract tokenizer reconstruction"),
    ("repeat_last_abstract", "flat_abstract", "repeat_last", "reference: last context frame held (abstract decoder)"),
)


def main_table(evals: Mapping, scope: str = "main") -> list[Row]:
    """Table 1: FVD on three splits (clip-bootstrap intervals), FVD-slope on turns and the linear probes per
    model of the scope (``all`` adds the flat baselines), then the reference rows (``kind`` = reference) on the
    same clips and frames, for each decoder one of the scope's models uses."""
    rows = []
    probed = TABLE_PROBE[scope]
    for model in probed:
        row: Row = {
            "model": model,
            "kind": "model",
            "label": _get(evals, "fvd", model, "label"),
            "parameters": _get(evals, "fvd", model, "parameters"),
        }
        for split in FVD_SPLITS:
            for suffix, key in (("", "fvd"), ("_low", "low"), ("_high", "high"), ("_n", "videos")):
                row[f"fvd_{split}{suffix}"] = _get(evals, "fvd", model, "fvd", split, key)
        rollout = _rollout_cells(evals, model)
        row["fvd_slope_turns"] = rollout["fvd_slope"]
        row["fvd_slope_turns_low"] = _get(evals, "fvd", model, "chunked", "fvd_slope_low")
        row["fvd_slope_turns_high"] = _get(evals, "fvd", model, "chunked", "fvd_slope_high")
        row["fvd_slope_turns_n"] = rollout["fvd_slope_n"]
        row.update(_probe_cells(evals, probed[model]))
        rows.append(row)
    for name, model, ref, label in (r for r in FVD_REFERENCES if r[1] in probed):
        row = {"model": name, "kind": "reference", "label": label, "parameters": NA}
        for split in FVD_SPLITS:
            cells = _get(evals, "fvd", model, "references", split, ref)
            if cells.get("fvd") is None:  # e.g. a real-vs-real floor on fewer than 4 clips: not computable
                row.update({f"fvd_{split}{suffix}": NA for suffix in ("", "_low", "_high", "_n")})
                continue
            row.update({f"fvd_{split}": cells["fvd"], f"fvd_{split}_low": cells["low"],
                        f"fvd_{split}_high": cells["high"],
                        f"fvd_{split}_n": cells.get("videos", cells.get("videos_per_half"))})
        row.update({key: NA for key in rows[0] if key not in row})
        rows.append(row)
    return rows


def steering_table(evals: Mapping) -> list[Row]:
    """Table 2: ADE per steering mode (clip-bootstrap interval) by the main instrument, with OpenCV odometry as a
    second column (NA where ``evaluation.opencv_rollouts`` left it off the generated videos); then the bottom
    level alone given the real subgoals (its turn readings only: a reference for what the top's predictions
    cost), and each instrument on real and on shuffled videos as floor and chance."""
    main = _get(evals, "steering", None, "inverse_dynamics")
    measured = "opencv" in _get(evals, "steering", None, "instruments")
    rows: list[Row] = []
    for mode in STEERING_MODES:
        cells = _get(evals, "steering", None, "modes", mode)
        opencv = (_get(evals, "steering", None, "modes", mode, "instruments", "opencv") if measured
                  else {"ade": NA, "turn_deg": NA})
        rows.append({
            "mode": mode,
            "kind": "generated",
            "instrument": main,
            "ade": cells["ade"],
            "ade_low": _get(evals, "steering", None, "modes", mode, "ade_low"),
            "ade_high": _get(evals, "steering", None, "modes", mode, "ade_high"),
            "ade_n": cells["samples"],
            # How far the video turns (end point, degrees, the clip's turn direction positive) next to the
            # command: a scale-free check that counterfactuals move the rollout the right way.
            "turn_deg": cells["turn_deg"],
            "commanded_turn_deg": cells["commanded_turn_deg"],
            "ade_opencv": opencv["ade"],
            "turn_deg_opencv": opencv["turn_deg"],
            **_turn_cells(evals, "latent", mode),
            **_turn_cells(evals, "image", mode),
        })
    rows.append({**{key: NA for key in rows[0]}, "mode": "real_subgoals", "kind": "reference",
                 "instrument": main, "ade_n": _get(evals, "steering", None, "samples"),
                 **_turn_cells(evals, "latent", "real_subgoals"), **_turn_cells(evals, "image", "real_subgoals")})
    videos = _get(evals, "steering", None, "odometry_sanity", "videos")
    for mode, key in (("real_videos", "real"), ("shuffled_videos", "shuffled")):
        rows.append({
            "mode": mode,
            "kind": "odometry_sanity",
            "instrument": main,
            "ade": _get(evals, "steering", None, "odometry_sanity", f"{key}_ade"),
            "ade_low": _get(evals, "steering", None, "odometry_sanity", f"{key}_low"),
            "ade_high": _get(evals, "steering", None, "odometry_sanity", f"{key}_high"),
            "ade_n": videos,
            "turn_deg": NA,
            "commanded_turn_deg": NA,
            "ade_opencv": _get(evals, "steering", None, "sanity", "opencv", f"{key}_ade"),
            "turn_deg_opencv": NA,
            **{k: v if key == "real" else NA for reading in ("latent", "image")
               for k, v in _turn_cells(evals, reading, "real").items()},
        })
    return rows


def _turn_cells(evals: Mapping, reading: str, mode: str) -> Row:
    """The turn of one of ``eval_steering``'s readings (``latent``: the detail latents without decoding;
    ``image``: the decoded frames' sideways motion; "real": the real continuation, the reading's
    calibration), with its clip-bootstrap interval."""
    cell = _get(evals, "steering", None, f"{reading}_turn", "modes", mode)
    return {f"turn_deg_{reading}": cell["turn_deg"], f"turn_deg_{reading}_low": cell["low"],
            f"turn_deg_{reading}_high": cell["high"]}


def speed_table(evals: Mapping) -> list[Row]:
    """Table 5: frames per second and peak memory per model the record holds, on the device that measured them."""
    device = _get(evals, "speed", None, "device")
    kind = _get(evals, "speed", None, "memory_kind")
    return [
        {
            "model": model,
            "fps": _get(evals, "speed", None, "models", model, "fps"),
            "fps_n": _get(evals, "speed", None, "models", model, "frames"),
            "peak_memory_mb": _get(evals, "speed", None, "models", model, "peak_memory_mb"),
            "memory_kind": kind,
            "parameters": _get(evals, "speed", None, "models", model, "parameters"),
            "device": device,
        }
        for model in _get(evals, "speed", None, "models")
    ]


def hierarchy_table(evals: Mapping, detail_hz: float = 10.0, abstract_hz: float = 2.0) -> list[Row]:
    """Table 3 (Exps 1-5): each predictor's probes and its system's long-horizon FVD on turns.

    A two-branch experiment has one FVD, that of its cascaded rollout; both of
    its rows carry it, with ``fvd_model`` naming the rollout it comes from.
    """
    rows = []
    rates = {"detail_hz": detail_hz, "abstract_hz": abstract_hz}
    for exp, branch, abstraction, rate, target, model in HIERARCHY_LAYOUT:
        row: Row = {"exp": exp, "branch": branch, "abstraction": abstraction, "frame_rate_hz": rates[rate]}
        row.update(_probe_cells(evals, target))
        row.update(_rollout_cells(evals, model))
        rows.append(row)
    return rows


def training_table(evals: Mapping) -> list[Row]:
    """Table 4: probes of the abstract branch under each training strategy, against tokenizer and teacher."""
    rows = []
    for name, target in TRAINING_ROWS:
        row: Row = {"model": name}
        row.update(_probe_cells(evals, target))
        row["val_loss"] = _get(evals, "probe", target, "segmentation", "val_loss")
        rows.append(row)
    return rows


def compression_table(evals: Mapping) -> list[Row]:
    """Compressed against full-dimension abstract latents; a null the stage reports stays visible as NA."""
    source = _get(evals, "compression", None, "rows")
    if not isinstance(source, list) or len(source) < 2:
        raise OrbisError(f"{_where(evals, 'compression')} needs at least two rows (compressed and full)")
    rows = []
    for i, entry in enumerate(source):
        row: Row = {}
        for key in ("variant", "latent_dim"):
            row[key] = _get(evals, "compression", None, "rows", i, key)
        for metric in ("fvd_long", "fvd_slope", "miou", "rmse"):
            if metric not in entry:
                raise OrbisError(f"{_where(evals, 'compression')} row {i} has no {metric} (null if not measured)")
            row[metric] = NA if entry[metric] is None else entry[metric]
            row[f"{metric}_n"] = entry.get(f"{metric}_n", NA)
        rows.append(row)
    return rows


def compression_from_evals(evals: Mapping) -> dict:
    """The compression ablation's rows from the flat abstract models on compressed and on full latents.

    Rollout stability is their FVD over the whole long rollout (``long_seconds``) and FVD-slope on the
    long split; representation quality the probes of those predictors. Raises like every table when an input is missing.
    """
    rows = []
    for variant, model in (("compressed", "flat_abstract"), ("full (teacher dim)", "flat_abstract_full")):
        probe = _probe_cells(evals, model)
        rows.append({"variant": variant, "latent_dim": _get(evals, "fvd", model, "latent_channels"),
                     "fvd_long": _get(evals, "fvd", model, "chunked", "fvd_long"),
                     "fvd_long_n": _get(evals, "fvd", model, "chunked", "videos"),
                     "fvd_slope": _get(evals, "fvd", model, "chunked", "fvd_slope"),
                     "fvd_slope_n": _get(evals, "fvd", model, "chunked", "videos"),
                     "miou": probe["miou"], "miou_n": probe["miou_n"], "rmse": probe["rmse"],
                     "rmse_n": probe["rmse_n"]})
    return {"rows": rows}


# ---------------------------------------------------------------- claims


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else str(value)
    return str(value)


def combined_verdict(verdicts: Sequence[str]) -> str:
    """A claim made of several parts: it fails if one part fails, holds if every part holds, else is unresolved."""
    return FAILS if FAILS in verdicts else HOLDS if all(v == HOLDS for v in verdicts) else UNRESOLVED


def claim_training(evals: Mapping) -> tuple[str, str]:
    """(1) DF+TF probes better than TF only and DF only on both segmentation and depth."""
    needed = ("abstract_tf", "abstract_tf_only", "abstract_df")
    if not all(_has(evals, "probe", t) for t in needed):
        return UNMEASURED, "needs " + ", ".join(f"eval_probe_{t}" for t in needed)
    cells = {t: _probe_cells(evals, t) for t in needed}
    best, others = cells["abstract_tf"], [cells["abstract_tf_only"], cells["abstract_df"]]
    ok = all(best["miou"] > o["miou"] and best["rmse"] < o["rmse"] for o in others)
    text = "mIoU / RMSE: " + ", ".join(
        f"{label} {_fmt(cells[t]['miou'])} / {_fmt(cells[t]['rmse'])}"
        for label, t in (("TF only", "abstract_tf_only"), ("DF only", "abstract_df"), ("DF+TF", "abstract_tf"))
    )
    return (HOLDS if ok else FAILS), text + " (DF+TF must have the highest mIoU and the lowest RMSE)"


def claim_hierarchy_slope(evals: Mapping) -> tuple[str, str]:
    """(2) The hierarchy has the lowest FVD-slope on turns among Table 1's models (the flat baselines too):
    for each other model, the clip-bootstrap interval of (its slope - the hierarchy's), paired over the same
    resamples, lies above ``fvd_material``; "does not hold" when one lies wholly below it, otherwise not
    resolved."""
    models = list(TABLE_PROBE["all"])
    if not all(_has(evals, "fvd", m) for m in models):
        return UNMEASURED, "needs " + ", ".join(f"eval_fvd_{m}" for m in models)
    material = _get(evals, "fvd", "hierarchical", "fvd_material")
    slopes = {m: _get(evals, "fvd", m, "chunked", "fvd_slope") for m in models}
    ours = _get(evals, "fvd", "hierarchical", "chunked", "fvd_slope_draws")
    verdicts, parts = [], []
    for model in models:
        if model == "hierarchical":
            continue
        low, high = paired_draws_interval(_get(evals, "fvd", model, "chunked", "fvd_slope_draws"), ours)
        verdicts.append(claim_verdict({"low": low, "high": high}, material))
        parts.append(f"{model} - hierarchical {_fmt(slopes[model] - slopes['hierarchical'])} "
                     f"[{_fmt(low)}, {_fmt(high)}]")
    verdict = combined_verdict(verdicts)
    text = "FVD-slope on turns: " + ", ".join(f"{m} {_fmt(v)}" for m, v in slopes.items())
    return verdict, f"{text}; paired differences {'; '.join(parts)} (material: > {_fmt(material)})"


def claim_compression(evals: Mapping) -> tuple[str, str]:
    """(3) Compressed abstract latents roll out more stably (lower FVD-slope) than full-dimension ones."""
    if not _has(evals, "compression"):
        return UNMEASURED, "needs eval_fvd_flat_abstract_full"
    rows = sorted(compression_table(evals), key=lambda r: r["latent_dim"])
    small, large = rows[0], rows[-1]
    if small["latent_dim"] == large["latent_dim"]:
        raise OrbisError(f"{_where(evals, 'compression')}: the rows must differ in latent_dim")
    if NA in (small["fvd_slope"], large["fvd_slope"]):
        return UNMEASURED, "a compression row has a null FVD-slope"
    ok = small["fvd_slope"] < large["fvd_slope"]
    text = (
        f"FVD-slope with {small['latent_dim']}-d latents {_fmt(small['fvd_slope'])}, "
        f"with {large['latent_dim']}-d latents {_fmt(large['fvd_slope'])}"
    )
    return (HOLDS if ok else FAILS), text


def claim_steering(evals: Mapping) -> tuple[str, str]:
    """(4) Steering follows counterfactual commands, read scale-free by the main instrument: the recovered turn
    under yaw rate x1.5 exceeds that under x0.5, and the path under speed x1.5 is longer than under x0.5, each
    by a material margin (interval lower bounds; paired per start); and the turns are ordered x0.5 < original
    < x1.5, each step by half the material turn (it commands half the change). ADE is reported, not decided
    on: it mixes the instrument's own error with the model's."""
    if not _has(evals, "steering"):
        return UNMEASURED, "needs eval_steering"
    main = _get(evals, "steering", None, "inverse_dynamics")
    turn = _get(evals, "steering", None, "responses", main, "turn_response_deg")
    ratio = _get(evals, "steering", None, "responses", main, "path_ratio")
    material = _get(evals, "steering", None, "material")
    steps = _get(evals, "steering", None, "responses", main, "turn_steps_deg")
    verdicts = [claim_verdict(turn, material["turn_deg"]), claim_verdict(ratio, material["path_ratio"]),
                *(claim_verdict(step, material["turn_deg"] / 2) for step in steps.values())]
    verdict = combined_verdict(verdicts)
    floor = _get(evals, "steering", None, "odometry_sanity")
    text = (f"{main} instrument: turn under yaw rate x1.5 minus x0.5 {_fmt(turn['estimate'])} deg "
            f"[{_fmt(turn['low'])}, {_fmt(turn['high'])}] (material > {_fmt(material['turn_deg'])}; commanded "
            f"{_fmt(_get(evals, 'steering', None, 'responses', main, 'commanded_turn_response_deg'))}); steps "
            + ", ".join(f"{name} {_fmt(step['estimate'])} [{_fmt(step['low'])}, {_fmt(step['high'])}]"
                        for name, step in steps.items())
            + f" (material > {_fmt(material['turn_deg'] / 2)}); path length "
            f"speed x1.5 / x0.5 {_fmt(ratio['estimate'])} [{_fmt(ratio['low'])}, {_fmt(ratio['high'])}] "
            f"(material > {_fmt(material['path_ratio'])}; commanded 3); instrument ADE on real videos "
            f"{_fmt(floor['real_ade'])} m, shuffled {_fmt(floor['shuffled_ade'])} m")
    return verdict, text


def claim_speed(evals: Mapping) -> tuple[str, str]:
    """(5) The hierarchy generates frames faster than the flat detail-level model."""
    if not _has(evals, "speed") or "flat_detail" not in _get(evals, "speed", None, "models"):
        return UNMEASURED, "needs eval_speed_all (the flat baselines timed beside the hierarchy)"
    ours = _get(evals, "speed", None, "models", "hierarchical", "fps")
    flat = _get(evals, "speed", None, "models", "flat_detail", "fps")
    device = _get(evals, "speed", None, "device")
    return (HOLDS if ours > flat else FAILS), f"fps on {device}: hierarchical {_fmt(ours)}, flat_detail {_fmt(flat)}"


def _conditioning_row(evals: Mapping, model: str, variant: str) -> dict:
    for row in _get(evals, "conditioning", None, "variants"):
        if row["model"] == model and row["variant"] == variant and row["metric"] == "one_step_mse":
            return row
    raise OrbisError(f"{_where(evals, 'conditioning')} has no {model}/{variant} row: re-run that stage")


def claim_subgoal(evals: Mapping) -> tuple[str, str]:
    """(6) The detail predictor follows its abstract subgoal: one from another clip raises its one-step
    conditional-mean error by more than the material threshold (the interval's lower bound decides)."""
    if not _has(evals, "conditioning"):
        return UNMEASURED, "needs eval_conditioning"
    threshold = _get(evals, "conditioning", None, "threshold")
    row = _conditioning_row(evals, "detail", "subgoal_other_clip")
    verdict = claim_verdict(row, threshold)
    return verdict, (f"one-step error +{_fmt(100 * row['effect'])} % [{_fmt(100 * row['low'])}, "
                     f"{_fmt(100 * row['high'])}] with another clip's subgoal (material: > {_fmt(100 * threshold)} %;"
                     f" {row['windows']} windows, {row['clips']} clips)")


def claim_beats_repeat(evals: Mapping) -> tuple[str, str]:
    """(7) Every main predictor's one-step conditional mean beats repeating the last context frame at 0.5 s
    by a material margin (an unbiased comparison: a sample would pay twice the conditional variance)."""
    if not _has(evals, "conditioning"):
        return UNMEASURED, "needs eval_conditioning"
    threshold = _get(evals, "conditioning", None, "threshold")
    rows = [r for r in _get(evals, "conditioning", None, "baselines")
            if r["baseline"] == "repeat_last" and r["horizon_s"] == 0.5]
    verdicts = [claim_verdict(r, threshold) for r in rows]
    verdict = combined_verdict(verdicts)
    return verdict, "repeat-last error over model error - 1: " + ", ".join(
        f"{r['model']} {_fmt(100 * r['effect'])} % [{_fmt(100 * r['low'])}, {_fmt(100 * r['high'])}]" for r in rows)


def claim_fvd_below_repeat(evals: Mapping) -> tuple[str, str]:
    """(8) The hierarchy's FVD lies below the repeat-last reference's on every FVD split: per split, the interval
    of (repeat-last - hierarchical) from their bootstrap draws on the same clip resamples lies above
    ``fvd_material``; "does not hold" when one lies wholly below it, otherwise not resolved."""
    if not _has(evals, "fvd", "hierarchical"):
        return UNMEASURED, "needs eval_fvd_hierarchical"
    material = _get(evals, "fvd", "hierarchical", "fvd_material")
    verdicts, parts = [], []
    for split in FVD_SPLITS:
        ours = _get(evals, "fvd", "hierarchical", "fvd", split)
        still = _get(evals, "fvd", "hierarchical", "references", split, "repeat_last")
        low, high = paired_draws_interval(still["draws"], ours["draws"])
        verdicts.append(claim_verdict({"low": low, "high": high}, material))
        parts.append(f"{split} {_fmt(still['fvd'] - ours['fvd'])} [{_fmt(low)}, {_fmt(high)}]")
    verdict = combined_verdict(verdicts)
    return verdict, (f"repeat-last FVD minus the hierarchy's, paired over the same clip resamples: {'; '.join(parts)}"
                     f" (material: > {_fmt(material)})")


CLAIMS: tuple[tuple[str, Callable[[Mapping], tuple[str, str]]], ...] = (
    ("DF+TF gives the best representations among TF only, DF only and DF+TF", claim_training),
    ("the hierarchy has the lowest FVD-slope among the main-table models", claim_hierarchy_slope),
    ("compression stabilises abstract rollouts (lower FVD-slope than full latents)", claim_compression),
    ("steering follows counterfactual commands", claim_steering),
    ("the hierarchy is faster than the flat detail baseline", claim_speed),
    ("the detail predictor follows its abstract subgoal", claim_subgoal),
    ("every main predictor beats repeating the last frame at 0.5 s", claim_beats_repeat),
    ("the hierarchy's FVD is below repeating the last frame's on every split", claim_fvd_below_repeat),
)


def check_claims(evals: Mapping) -> list[tuple[str, str, str]]:
    """(claim, verdict, evidence) for each of the paper's claims, in the paper's order."""
    return [(claim, *fn(evals)) for claim, fn in CLAIMS]


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
    lines += ["| " + " | ".join(_fmt(row[key]) for key in header) + " |" for row in rows]
    return "\n".join(lines)


def protocol_lines(evals: Mapping) -> list[str]:
    """The FVD protocol card of each split, from the FVD records that carry one (identical across systems but for
    their I3D inputs' source resolution), so that a table's FVDs can be reproduced from what is printed beside it."""
    cards: dict[str, dict] = {}
    for record in (evals.get("fvd") or {}).values():
        for split, card in (record or {}).get("protocol", {}).items():
            cards.setdefault(split, {k: v for k, v in card.items() if k != "source_resolution"})
    lines = [f"FVD protocol, {split}: " + ", ".join(f"{k}={v}" for k, v in card.items()) for split, card in
             sorted(cards.items())]
    return [*(f"- {line}" for line in lines), ""] if lines else []


def summary_markdown(tables: Sequence[tuple[str, Sequence[Row]]], evals: Mapping, setup: Mapping) -> str:
    """The tables, the claims checked against them, then the setup that produced them."""
    parts = ["# Orbis 2 evaluation summary", ""]
    for title, rows in tables:
        parts += [f"## {title}", "", markdown_table(rows), ""]
        if any(key.startswith("fvd") for row in rows for key in row):
            parts += protocol_lines(evals)
    parts += ["## Reading", ""]
    for i, (claim, verdict, evidence) in enumerate(check_claims(evals), start=1):
        parts.append(f"{i}. {claim}: **{verdict}**. {evidence}.")
    parts += ["", "## Setup", ""]
    for key, value in setup.items():
        shown = json.dumps(value, sort_keys=True) if isinstance(value, (dict, list, tuple)) else _fmt(value)
        parts.append(f"- {key}: {shown}")
    return "\n".join(parts) + "\n"


def _tables(evals: Mapping, full: bool, detail_hz: float, abstract_hz: float) -> list[tuple[str, str, list[Row]]]:
    """(title, file name, rows) of every table; ``full`` adds the flat baselines to Table 1 and makes the ablations
    required, else they join when present."""
    tables = [
        ("Main results (Table 1)", MAIN_CSV, main_table(evals, "all" if full else "main")),
        ("Steering (Table 2)", STEERING_CSV, steering_table(evals)),
        ("Speed and memory (Table 5)", SPEED_CSV, speed_table(evals)),
    ]
    hierarchy_ready = all(_has(evals, "fvd", e[5]) and _has(evals, "probe", e[4]) for e in HIERARCHY_LAYOUT)
    if full or hierarchy_ready:
        rows = hierarchy_table(evals, detail_hz, abstract_hz)
        tables.append(("Hierarchy design study (Table 3)", HIERARCHY_CSV, rows))
    if full or all(_has(evals, "probe", t) for _, t in TRAINING_ROWS):
        tables.append(("Training strategy (Table 4)", TRAINING_CSV, training_table(evals)))
    if _has(evals, "compression"):
        tables.append(("Latent compression", COMPRESSION_CSV, compression_table(evals)))
    if _has(evals, "conditioning"):
        tables.append(("Conditioning use and one-step baselines", CONDITIONING_CSV,
                       conditioning_rows(_doc(evals, "conditioning"))))
    return tables


def _write_tables(
    csv_tables: Sequence[tuple[str, str, list[Row]]],
    summary_tables: Sequence[tuple[str, str, list[Row]]],
    evals: Mapping,
    out_dir: Path,
    setup: Mapping,
) -> list[Path]:
    summary = summary_markdown([(title, rows) for title, _, rows in summary_tables], evals, setup)
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
                                                                       "action", "flat_detail", "flat_abstract")}}


def write_main_report(
    evals: Mapping, out_dir: str | Path, setup: Mapping, detail_hz: float = 10.0, abstract_hz: float = 2.0
) -> list[Path]:
    """main_table.csv, steering.csv, speed.csv (conditioning.csv when its record exists) and a summary.md
    of what is available; returns the paths.

    Only the three main tables are written as CSV; ablation tables whose inputs
    all exist are shown in the summary too, and claims without inputs read
    "not measured".
    """
    tables = _tables(evals, False, detail_hz, abstract_hz)
    csv_tables = tables[:3] + [t for t in tables if t[1] == CONDITIONING_CSV]
    return _write_tables(csv_tables, tables, evals, Path(out_dir), setup)


def write_full_report(
    evals: Mapping, out_dir: str | Path, setup: Mapping, detail_hz: float = 10.0, abstract_hz: float = 2.0
) -> list[Path]:
    """Every table, the ablations and the JSON-driven figures, with a summary covering all of them.

    ``evals["compression"]`` (from :func:`compression_from_evals`) is optional: without it
    compression_ablation.csv is not written (a stale one is removed) and the summary marks
    claim 3 not measured.
    Everything is checked before the first file is written.
    """
    out_dir = Path(out_dir)
    tables = _tables(evals, True, detail_hz, abstract_hz)
    _per_block_targets(evals)
    written = _write_tables(tables, tables, evals, out_dir, setup)
    if not _has(evals, "compression"):
        (out_dir / COMPRESSION_CSV).unlink(missing_ok=True)
    figures = out_dir / FIGURES
    plot_chunked_fvd(evals, figures / FIG_CHUNKED)
    write_chunked_fvd(evals, out_dir / CHUNKED_CSV)
    plot_probe_blocks(evals, figures / FIG_BLOCKS)
    plot_bubble(evals, figures / FIG_BUBBLE)
    return written + [out_dir / CHUNKED_CSV, figures / FIG_CHUNKED, figures / FIG_BLOCKS, figures / FIG_BUBBLE]


# Columns that describe a row rather than name it or measure it (left out of headline names).
DESCRIPTIVE = ("label", "kind", "instrument", "device", "seed_verdicts")


def headline(tables: Sequence[str | Path], columns: Mapping[str, Sequence[str]] | None = None
             ) -> tuple[dict[str, float], dict[str, str]]:
    """The report tables' numbers as metrics ``<table>/<row>/<column>`` and their verdicts as
    tags ``verdict/<table>/<row>``: what the pipeline's parent run shows a reviewer.

    A row is named by its text cells outside :data:`DESCRIPTIVE` (``main_table/hierarchical``,
    ``conditioning/hierarchical/ade/no_actions``); NA cells are left out. ``columns`` keeps,
    for the tables it names (by file stem), only those numeric columns.
    """
    columns = columns or {}
    metrics: dict[str, float] = {}
    tags: dict[str, str] = {}
    for path in map(Path, tables):
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        for row in rows:
            numbers = {k: _number(v) for k, v in row.items()}
            name = "/".join(_key(v) for k, v in row.items()
                            if numbers[k] is None and v != NA and k not in DESCRIPTIVE and k != "verdict")
            prefix = f"{path.stem}/{name}" if name else path.stem
            kept = columns.get(path.stem)
            for column, value in numbers.items():
                if value is not None and column not in DESCRIPTIVE and (kept is None or column in kept):
                    metrics[f"{prefix}/{_key(column)}"] = value
            if row.get("verdict"):
                tags[f"verdict/{prefix}"] = row["verdict"]
    return metrics, tags


def _number(text: str | None) -> float | None:
    try:
        value = float(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def _key(text: str) -> str:
    """Text as part of an MLflow metric name (letters, digits, ``_-. /`` only)."""
    return re.sub(r"[^A-Za-z0-9_.\- ]+", "_", str(text)).strip("_") or "_"


# ---------------------------------------------------------------- figures


def plot_chunked_fvd(evals: Mapping, path: str | Path, models: Sequence[str] = FVD_MODELS) -> None:
    """Fig. 4: FVD of each consecutive window of the long turns rollouts, one line per model."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for model in models:
        chunks = _get(evals, "fvd", model, "chunked", "chunks")
        ends = [_get(evals, "fvd", model, "chunked", "chunks", i, "end_s") for i in range(len(chunks))]
        fvds = [_get(evals, "fvd", model, "chunked", "chunks", i, "fvd") for i in range(len(chunks))]
        ax.plot(ends, fvds, marker="o", label=_get(evals, "fvd", model, "label"))
    ax.set_xlabel("end of window (s)")
    ax.set_ylabel("FVD")
    ax.set_title("FVD over consecutive windows (turns)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, path)


def write_chunked_fvd(evals: Mapping, path: str | Path, models: Sequence[str] = FVD_MODELS) -> None:
    """Fig. 4's numbers as a table: the end of each window (s) and one FVD column per system."""
    rows = [{"system": model, "end_s": chunk["end_s"], "fvd": chunk["fvd"]}
            for model in models for chunk in _get(evals, "fvd", model, "chunked", "chunks")]
    table = pd.DataFrame(rows).pivot(index="end_s", columns="system", values="fvd")[list(models)]
    with atomic_file(Path(path)) as tmp:
        table.reset_index().to_csv(tmp, index=False, lineterminator="\n", float_format="%.6g")


def _per_block_targets(evals: Mapping) -> list[str]:
    targets = [t for t in PROBE_TARGETS if _has(evals, "probe", t) and _doc(evals, "probe", t).get("per_block")]
    if not targets:
        raise OrbisError(
            f"no probe file {'in ' + evals['folder'] if 'folder' in evals else 'given'} has per_block results: "
            "run an eval_probe_<target> stage with per-block probing"
        )
    return targets


def plot_probe_blocks(evals: Mapping, path: str | Path) -> None:
    """Fig. 5: segmentation mIoU and depth RMSE of a probe on every block, one line per probed model."""
    targets = _per_block_targets(evals)
    plt = pyplot()
    fig, (ax_miou, ax_rmse) = plt.subplots(1, 2, figsize=(9, 3.6))
    for target in targets:
        blocks = _get(evals, "probe", target, "per_block")
        cells = [
            tuple(_get(evals, "probe", target, "per_block", i, key) for key in ("block", "miou", "rmse"))
            for i in range(len(blocks))
        ]
        cells.sort()
        label = _get(evals, "probe", target, "label")
        ax_miou.plot([c[0] for c in cells], [c[1] for c in cells], marker="o", label=label)
        ax_rmse.plot([c[0] for c in cells], [c[2] for c in cells], marker="o", label=label)
    for ax, name in ((ax_miou, "segmentation mIoU (higher is better)"), (ax_rmse, "depth RMSE (lower is better)")):
        ax.set_xlabel("predictor block")
        ax.set_title(name)
        ax.grid(alpha=0.3)
    ax_miou.legend(fontsize=8)
    save_figure(fig, path)


def plot_bubble(evals: Mapping, path: str | Path, x_metric: str = "fvd_slope") -> None:
    """Fig. 2: long-horizon FVD against segmentation mIoU, bubble area proportional to parameters.

    ``x_metric`` is ``fvd_slope`` (turns) or one of ``fvd_val``, ``fvd_heldout``, ``fvd_turns``.
    """
    rows = [r for r in main_table(evals, "all") if r["kind"] == "model"]
    key = "fvd_slope_turns" if x_metric == "fvd_slope" else x_metric
    if key not in rows[0] or not key.startswith("fvd"):
        raise ValueError(f"x_metric must be fvd_slope, fvd_val, fvd_heldout or fvd_turns, got {x_metric!r}")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    largest = max(r["parameters"] for r in rows)
    for row in rows:
        ax.scatter(row[key], row["miou"], s=2000.0 * row["parameters"] / largest, alpha=0.5)
        ax.annotate(f"{row['label']}\n{row['parameters'] / 1e6:.1f}M", (row[key], row["miou"]), ha="center", fontsize=8)
    ax.set_xlabel("FVD-slope on turns" if x_metric == "fvd_slope" else x_metric.replace("_", " "))
    ax.set_ylabel("segmentation mIoU")
    ax.set_title("bubble area: parameters")
    ax.grid(alpha=0.3)
    ax.margins(0.25)
    save_figure(fig, path)
