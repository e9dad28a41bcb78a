"""Report: evaluation JSON files in, the paper's tables, figures and a checked summary out."""

from __future__ import annotations

import csv
import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from orbis2.config.params import load_config
from orbis2.errors import OrbisError
from orbis2.eval import figures, records
from orbis2.eval.report import claims, report, tables
from orbis2.eval.report.evals import Evals, load_eval, read_evals

from conftest import ROOT

SETUP = {"profile": "smoke", "seed": 7, "fvd_videos": 12}
RECORDS = ROOT / "tests" / "fixtures" / "records"  # the records of a finished smoke run, as its stages wrote them
# What the smoke profile of params.yaml decides about the tables (FVD splits, steering modes, rates).
SETTINGS = tables.TableSettings.from_config(load_config(ROOT / "params.yaml", "smoke"))

FVD = {  # model: (parameters, fvd val, heldout, turns, fvd_long, slope)
    "flat_detail": (20_000_000, 170.5, 200.25, 210.0, 300.0, 101.63),
    "flat_abstract": (21_000_000, 490.04, 500.0, 510.0, 520.0, 60.38),
    "hierarchical": (41_000_000, 98.97, 98.01, 187.53, 209.15, 46.45),
    "top_detail": (40_000_000, 120.0, 130.0, 140.0, 207.71, 81.4),
    "top_abstract_10hz": (40_000_000, 400.0, 410.0, 420.0, 551.38, 137.07),
}
PROBES = {  # target: (miou, val loss, rmse)
    "abstract_tokenizer": (57.19, 0.265, 4.574),
    "teacher": (60.01, 0.284, 3.89),
    "abstract_df": (58.03, 0.254, 4.274),
    "abstract_tf": (58.29, 0.25, 4.157),
    "abstract_tf_only": (55.01, 0.27, 4.355),
    "detail": (31.97, 0.4, 6.396),
    "flat_detail": (32.72, 0.41, 6.107),
    "flat_abstract": (47.88, 0.3, 4.624),
    "top_detail": (41.02, 0.35, 5.256),
    "detail_on_detail": (25.52, 0.45, 6.514),
    "flat_abstract_full": (50.0, 0.3, 4.8),
    "abstract_tokenizer_full": (59.0, 0.26, 4.0),
}


def real(name: str) -> dict:
    """A record a smoke run wrote (tests/fixtures/records): every key its stage writes, values replaced below."""
    return json.loads((RECORDS / f"{name}.json").read_text())


def fvd_doc(model: str) -> dict:
    params, val, heldout, turns, fvd16, slope = FVD[model]
    base = real("fvd_hierarchical")

    # Bootstrap draws: the same resamples for every model and reference, so differences are paired.
    wiggle = np.linspace(-3.0, 3.0, 40)

    def split(v, n):
        return {**base["fvd"]["val"], "fvd": v, "low": v * 0.9, "high": v * 1.1, "videos": n, "clips": 8,
                "seconds": 6.0, "seed": 3, "draws": list(v + wiggle)}

    def reference(v):
        return {**base["references"]["val"]["repeat_last"], "fvd": v, "low": v - 5.0, "high": v + 5.0, "videos": 40,
                "draws": list(v + wiggle)}

    floor = {"fvd": 30.0, "low": 25.0, "high": 35.0, "clips": 8, "videos_per_half": 20, "half_splits": 50, "seed": 3,
             "definition": "FVD between the real continuations of two disjoint random halves of the clips"}
    chunks = [{"start_s": 4.0 * i, "end_s": 4.0 * (i + 1), "fvd": fvd16 / 2 + slope * i, "low": 0.0, "high": 999.0}
              for i in range(4)]
    return {
        **base,
        "model": model,
        "label": model.replace("_", " ").title(),
        "parameters": params,
        "fvd_material": 10.0,
        "fvd": {"val": split(val, 40), "heldout": split(heldout, 41), "turns": split(turns, 42)},
        "references": {s: {"real_floor": floor, "reconstruction": reference(60.0), "repeat_last": reference(900.0)}
                       for s in ("val", "heldout", "turns")},
        "chunked": {
            **base["chunked"],
            "split": "turns",
            "seconds": 16.0,
            "chunk_seconds": 4.0,
            "videos": 43,
            "seed": 3,
            "chunks": chunks,
            "fvd_long": fvd16,
            "fvd_slope": slope,
            "fvd_slope_low": slope - 3.0,
            "fvd_slope_high": slope + 3.0,
            "fvd_slope_draws": list(slope + wiggle),
        },
    }


def probe_doc(target: str) -> dict:
    miou, loss, rmse = PROBES[target]
    base = real("probe_abstract_tf")
    doc = {
        **base,
        "target": target,
        "label": target.replace("_", " "),
        "block": 3,
        "segmentation": {**base["segmentation"], "miou": miou, "val_loss": loss, "test_frames": 50,
                         "train_frames": 200},
        "depth": {**base["depth"], "rmse": rmse, "test_frames": 51},
    }
    if target in ("abstract_df", "abstract_tf_only"):
        doc["per_block"] = [{"block": k, "miou": miou - 3 + k, "rmse": rmse + 1 - 0.2 * k} for k in range(5)]
    return doc


def steering_doc() -> dict:
    base = real("steering")
    ades = {"original": 1.2, "speed_x0.5": 2.18, "speed_x1.5": 0.53, "yaw_rate_x0.5": 1.65, "yaw_rate_x1.5": 0.73}
    modes = {}
    for i, (mode, ade) in enumerate(ades.items()):
        cells = {"ade": ade, "ade_low": ade - 0.1, "ade_high": ade + 0.1, "turn_deg": 10.0 + 10 * i, "turn_low": 0.0,
                 "turn_high": 50.0, "path_length": 20.0}
        modes[mode] = {**cells, "samples": 20 + i, "commanded_turn_deg": 12.0 + 10 * i, "speed_scale": 1.0,
                       "yaw_rate_scale": 1.0, "instruments": {"learned": cells, "opencv": {**cells, "ade": ade + 3.0}}}
    sanity = {"real_ade": 0.4, "real_low": 0.3, "real_high": 0.5, "shuffled_ade": 4.0, "shuffled_low": 3.5,
              "shuffled_high": 4.5, "videos": 30}
    learned = base["responses"]["learned"]
    interval = learned["turn_response_deg"]
    step = learned["turn_steps_deg"]["original - yaw_rate_x0.5"]

    def turns(scale: float, spread: float) -> dict:
        return {**base["latent_turn"], "modes": {m: {"turn_deg": scale * i, "low": scale * i - spread,
                                                     "high": scale * i + spread, "commanded_turn_deg": 12.0}
                                                 for i, m in enumerate(["real", *ades, "real_subgoals"])}}

    return {
        **base,
        "split": "turns",
        "seconds": 6.0,
        "samples": 20,
        "seed": 5,
        "inverse_dynamics": "learned",
        "instruments": ["learned", "opencv"],
        "modes": modes,
        "responses": {"learned": {**learned,
                                  "turn_response_deg": {**interval, "estimate": 9.0, "low": 5.0, "high": 13.0},
                                  "commanded_turn_response_deg": 12.0,
                                  "turn_steps_deg": {
                                      "original - yaw_rate_x0.5": {**step, "estimate": 4.0, "low": 2.0, "high": 6.0},
                                      "yaw_rate_x1.5 - original": {**step, "estimate": 5.0, "low": 3.0, "high": 7.0}},
                                  "path_ratio": {**learned["path_ratio"], "estimate": 2.5, "low": 2.0, "high": 3.0}}},
        "material": {"turn_deg": 2.0, "path_ratio": 1.1},
        "odometry_sanity": sanity,
        "sanity": {"learned": sanity, "opencv": {**sanity, "real_ade": 0.6}},
        "latent_turn": turns(5.0, 1.0),
        "image_turn": turns(2.0, 0.5),
        "truth": truth_doc(list(ades), interval),
    }


def truth_doc(modes: list[str], interval: dict) -> dict:
    """The steering rollouts against the town's true counterfactuals (orbis2.eval.records.TruthReading)."""
    def iv(estimate, low, high):
        return {**interval, "estimate": estimate, "low": low, "high": high}

    fvd = {"fvd": 80.0, "low": 70.0, "high": 90.0, "clips": 10, "videos": 20, "bootstrap_reps": 50,
           "bootstrap_seed": 5, "draws": [80.0] * 5}
    cells = {m: {"samples": 20, "horizons": [{"seconds": h, "frame": round(h * 10) - 1,
                                              "latent_mse": iv(0.25 * (i + 1), 0.05, 0.9),
                                              "psnr": iv(30.0 - i, 28.0, 32.0)} for i, h in enumerate((0.5, 1.0, 2.0))],
                 "fvd": fvd, "instrument": {"turn_deg": iv(20.0, 18.0, 22.0), "commanded_turn_deg": 21.0,
                                            "relative_error": iv(-0.05, -0.1, 0.0)},
                 "collision": 0, "off_road": 1} for m in modes}
    return {"instrument": "learned", "modes": cells,
            "claim": {"material": 0.1, "verdict": "holds",
                      "modes": {m: {"margin": iv(0.5, 0.3, 0.7), "own": 0.2, "others": 0.3, "verdict": "holds"}
                                for m in modes},
                      "pairs": {m: {o: 0.2 if o == m else 0.3 for o in modes} for m in modes}}}


def speed_doc() -> dict:
    base = real("speed")
    models = {"hierarchical": 3.64, "hierarchical_distilled": 9.1, "flat_detail": 0.7, "flat_abstract": 1.5,
              "v1_style": 0.3}
    params = {"hierarchical_distilled": "hierarchical", "v1_style": "flat_detail"}
    run = base["models"]["hierarchical"]
    return {
        **base,
        "device": "cpu",
        "memory_kind": "cpu_peak_rss",
        "models": {
            m: {**run, "fps": fps, "peak_memory_mb": 900.5, "parameters": FVD[params.get(m, m)][0], "frames": 60}
            for m, fps in models.items()
        },
    }


def compression_doc() -> dict:
    rows = [
        {"variant": "compressed (16-d)", "latent_dim": 16, "fvd_long": 200.0, "fvd_slope": 40.0, "miou": 58.3},
        {"variant": "full (teacher dim)", "latent_dim": 768, "fvd_long": 600.0, "fvd_slope": 150.0, "miou": None},
    ]
    for row in rows:
        row["rmse"] = None
    return {"rows": rows}


def conditioning_doc() -> dict:
    def variant(model, variant, error, effect=0.0, low=0.0, high=0.0, verdict="reference"):
        return {"model": model, "metric": "one_step_mse", "variant": variant, "error": error, "effect": effect,
                "low": low, "high": high, "verdict": verdict, "windows": 64, "clips": 16}

    def baseline(model, horizon, low):
        return {"model": model, "horizon_s": horizon, "baseline": "repeat_last", "model_mse": 0.5,
                "baseline_mse": 0.5 * (1 + low + 0.1), "effect": low + 0.1, "low": low, "high": low + 0.2,
                "verdict": "holds", "windows": 64, "clips": 16}

    base = real("conditioning")
    del base["steering_response"]  # written only with a steered predictor in the scope
    return {**base, "threshold": 0.03,
            "variants": [variant("detail", "true", 0.4), variant("detail", "subgoal_other_clip", 0.6, 0.5, 0.3, 0.7,
                                                                  "used")],
            "baselines": [baseline(m, h, 0.2) for m in ("detail", "abstract_tf") for h in (0.5, 1.0)]}


def write_evals(folder: Path, skip: tuple[str, ...] = ()) -> Path:
    docs = {f"fvd_{m}": fvd_doc(m) for m in FVD} | {f"probe_{t}": probe_doc(t) for t in PROBES}
    docs |= {"steering": steering_doc(), "speed": speed_doc(), "conditioning": conditioning_doc()}
    folder.mkdir(parents=True, exist_ok=True)
    for name, doc in docs.items():
        if name not in skip:
            (folder / f"{name}.json").write_text(json.dumps(doc))
    return folder


@pytest.fixture
def evals(tmp_path):
    """Every evaluation, and the compression rows the report stage derives from them."""
    evals = load_eval(write_evals(tmp_path / "eval"))
    evals.compression = records.CompressionRecord.model_validate(compression_doc())
    return evals


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def verdicts(evals: Evals) -> list[str]:
    return [verdict for _, verdict, _ in claims.check_claims(evals, SETTINGS)]


def summary_verdicts(path: Path) -> list[str]:
    return re.findall(r"^\d\. .*?: \*\*(.+?)\*\*", path.read_text(), flags=re.M)


def test_load_eval_reads_every_file(evals):
    assert set(evals.fvd) == set(report.FVD_MODELS)
    assert set(evals.probe) == set(records.PROBE_TARGETS)
    assert evals.has("steering") and evals.has("speed") and evals.has("conditioning")


def test_load_eval_rejects_a_file_under_the_wrong_name(tmp_path):
    folder = write_evals(tmp_path / "eval")
    (folder / "fvd_hierarchical.json").write_text(json.dumps(fvd_doc("flat_detail")))
    with pytest.raises(OrbisError, match="eval_fvd_hierarchical"):
        load_eval(folder)


def test_read_evals_takes_the_files_it_is_given(tmp_path):
    """The report stage gets each record's path from the DAG: only those are read, wherever they are."""
    folder = write_evals(tmp_path / "eval")
    moved = tmp_path / "elsewhere" / "hier.json"
    moved.parent.mkdir()
    (folder / "fvd_hierarchical.json").rename(moved)
    assert set(read_evals({"hierarchical": moved}, {}).fvd) == {"hierarchical"}
    fvd = {m: folder / f"fvd_{m}.json" for m in FVD} | {"hierarchical": moved}
    evals = read_evals(fvd, {t: folder / f"probe_{t}.json" for t in PROBES},
                              steering=folder / "steering.json", speed=tmp_path / "absent.json",
                              conditioning=folder / "conditioning.json")
    assert set(evals.fvd) == set(FVD) and evals.fvd["hierarchical"].model == "hierarchical"
    assert evals.has("steering") and not evals.has("speed")
    with pytest.raises(OrbisError, match=r"absent\.json \(written by stage eval_speed\)"):
        report.write_main_report(evals, tmp_path / "out", SETUP, SETTINGS)
    with pytest.raises(OrbisError, match="fvd_flat_detail.json says model='flat_detail', expected 'hierarchical'"):
        read_evals({"hierarchical": folder / "fvd_flat_detail.json"}, {})


def test_main_report_tables_round_trip(evals, tmp_path):
    out = tmp_path / "reports"
    written = report.write_main_report(evals, out, SETUP, SETTINGS)
    assert sorted(p.name for p in written) == ["conditioning.csv", "main_table.csv", "speed.csv", "steering.csv",
                                               "summary.md"]
    conditioning = read_csv(out / "conditioning.csv")
    assert [(r["model"], r["check"], r["verdict"]) for r in conditioning][:2] == [
        ("detail", "input: subgoal_other_clip", "used"), ("detail", "beats repeat_last at 0.5 s", "holds")]

    main = read_csv(out / "main_table.csv")  # the main table's row and the references of its (detail) decoder
    assert [r["model"] for r in main] == ["hierarchical", "real_floor", "reconstruction_detail", "repeat_last_detail"]
    assert [r["kind"] for r in main] == ["model"] + ["reference"] * 3
    assert list(main[0]) == [
        "model", "kind", "label", "parameters",
        "fvd_val", "fvd_val_low", "fvd_val_high", "fvd_val_n", "fvd_heldout", "fvd_heldout_low",
        "fvd_heldout_high", "fvd_heldout_n", "fvd_turns", "fvd_turns_low", "fvd_turns_high", "fvd_turns_n",
        "fvd_slope_turns", "fvd_slope_turns_low", "fvd_slope_turns_high", "fvd_slope_turns_n",
        "probe_target", "miou", "miou_n", "rmse", "rmse_n",
    ]  # fmt: skip
    floor = main[1]
    assert float(floor["fvd_val"]) == 30.0 and floor["fvd_slope_turns"] == "NA" and floor["miou"] == "NA"

    ours = main[0]
    assert int(ours["parameters"]) == FVD["hierarchical"][0]
    assert [float(ours[f"fvd_{s}"]) for s in ("val", "heldout", "turns")] == list(FVD["hierarchical"][1:4])
    assert [int(ours[f"fvd_{s}_n"]) for s in ("val", "heldout", "turns")] == [40, 41, 42]
    assert float(ours["fvd_slope_turns"]) == FVD["hierarchical"][5] and ours["fvd_slope_turns_n"] == "43"
    # the hierarchy is probed at its abstract predictor
    assert ours["probe_target"] == "abstract_tf" and float(ours["miou"]) == PROBES["abstract_tf"][0]
    assert float(ours["rmse"]) == PROBES["abstract_tf"][2] and ours["rmse_n"] == "51"

    steering = read_csv(out / "steering.csv")
    assert list(steering[0]) == ["mode", "kind", "instrument", "ade", "ade_low", "ade_high", "ade_n", "turn_deg",
                                 "commanded_turn_deg", "ade_opencv", "turn_deg_opencv", "turn_deg_latent",
                                 "turn_deg_latent_low", "turn_deg_latent_high", "turn_deg_image",
                                 "turn_deg_image_low", "turn_deg_image_high", "truth_n", "latent_mse_0.5s",
                                 "latent_mse_0.5s_low", "latent_mse_0.5s_high", "psnr_0.5s", "psnr_0.5s_low",
                                 "psnr_0.5s_high", "latent_mse_1s", "latent_mse_1s_low", "latent_mse_1s_high",
                                 "psnr_1s", "psnr_1s_low", "psnr_1s_high", "latent_mse_2s", "latent_mse_2s_low",
                                 "latent_mse_2s_high", "psnr_2s", "psnr_2s_low", "psnr_2s_high", "truth_fvd",
                                 "truth_fvd_low", "truth_fvd_high", "truth_fvd_n", "truth_turn_deg",
                                 "truth_turn_deg_low", "truth_turn_deg_high", "truth_commanded_turn_deg",
                                 "truth_turn_relative_error", "truth_turn_relative_error_low",
                                 "truth_turn_relative_error_high", "truth_margin", "truth_margin_low",
                                 "truth_margin_high", "truth_verdict", "truth_collisions", "truth_off_road"]
    assert float(steering[0]["latent_mse_2s"]) == 0.75 and steering[0]["truth_n"] == "20"
    assert steering[0]["truth_verdict"] == "holds" and float(steering[1]["truth_turn_deg"]) == 20.0
    assert steering[-1]["truth_fvd"] == "NA" and steering[5]["truth_margin"] == "NA"
    assert [float(r["turn_deg_latent"]) for r in steering[:-1]] == [5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 0.0]
    assert steering[-1]["turn_deg_latent"] == "NA" and float(steering[-2]["turn_deg_latent_high"]) == 1.0
    assert [float(r["turn_deg_image"]) for r in steering[:-1]] == [2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 0.0]
    assert steering[5]["kind"] == "reference" and steering[5]["ade"] == "NA" and steering[5]["ade_n"] == "20"
    assert steering[-1]["turn_deg_image_low"] == "NA" and float(steering[-2]["turn_deg_image_high"]) == 0.5
    assert float(steering[0]["ade_opencv"]) == 4.2 and float(steering[-2]["ade_opencv"]) == 0.6
    assert [r["mode"] for r in steering] == [*SETTINGS.steering_modes, "real_subgoals", "real_videos",
                                             "shuffled_videos"]
    assert float(steering[1]["ade"]) == 2.18 and steering[1]["ade_n"] == "21"
    assert float(steering[-1]["ade"]) == 4.0 and steering[-1]["ade_n"] == "30"

    speed = read_csv(out / "speed.csv")
    assert list(speed[0]) == ["model", "fps", "fps_n", "peak_memory_mb", "memory_kind", "parameters", "device"]
    assert [(r["model"], float(r["fps"])) for r in speed] == [
        ("hierarchical", 3.64),
        ("hierarchical_distilled", 9.1),
        ("flat_detail", 0.7),
        ("flat_abstract", 1.5),
        ("v1_style", 0.3),
    ]
    assert speed[0]["memory_kind"] == "cpu_peak_rss" and speed[0]["device"] == "cpu"

    summary = (out / "summary.md").read_text()
    for heading in ("## Main results", "## Steering", "## Speed", "## Reading", "## Setup"):
        assert heading in summary
    assert "- profile: smoke" in summary and "- fvd_videos: 12" in summary
    assert summary_verdicts(out / "summary.md") == ["holds"] * 9
    assert not (out / "hierarchy_ablation.csv").exists()


def test_main_report_marks_absent_ablations_not_measured(tmp_path):
    folder = write_evals(tmp_path / "eval", skip=("probe_abstract_df",))
    report.write_main_report(load_eval(folder), tmp_path / "out", SETUP, SETTINGS)
    assert summary_verdicts(tmp_path / "out" / "summary.md") == [
        "not measured",
        "holds",
        "not measured",
        "holds",
        "holds",
        "holds",
        "holds",
        "holds",
        "holds",
    ]
    assert "## Training strategy" not in (tmp_path / "out" / "summary.md").read_text()


def test_steering_table_without_opencv_on_the_rollouts_keeps_its_real_video_check():
    doc = steering_doc()
    doc["instruments"] = ["learned"]  # evaluation.opencv_rollouts: false
    for cells in doc["modes"].values():
        del cells["instruments"]["opencv"]
    rows = tables.steering_table(Evals(steering=records.SteeringRecord.model_validate(doc)), SETTINGS)
    assert all(r["ade_opencv"] == tables.NA and r["turn_deg_opencv"] == tables.NA for r in rows[:-2])
    assert rows[-2]["ade_opencv"] == 0.6 and rows[0]["ade"] == 1.2


def test_main_scope_speed_record_leaves_the_flat_comparison_to_the_full_report(evals, tmp_path):
    for name in ("flat_detail", "flat_abstract", "v1_style", "hierarchical_distilled"):  # eval_speed (main)
        del evals.speed.models[name]  # times the main table's hierarchy only
    report.write_main_report(evals, tmp_path, SETUP, SETTINGS)
    assert [r["model"] for r in read_csv(tmp_path / "speed.csv")] == ["hierarchical"]
    assert verdicts(evals)[4] == "not measured" and "eval_speed_all" in claims.claim_speed(evals, SETTINGS)[1]


def test_full_report_ablations_and_figures(evals, tmp_path):
    out = tmp_path / "reports"
    written = report.write_full_report(evals, out, SETUP, SETTINGS)
    names = {p.relative_to(out).as_posix() for p in written}
    assert names == {
        "main_table.csv", "steering.csv", "speed.csv", "summary.md",
        "hierarchy_ablation.csv", "training_ablation.csv", "compression_ablation.csv", "conditioning.csv",
        "fvd_chunked.csv",
        "figures/fvd_chunked.png", "figures/probe_per_block.png", "figures/bubble_params_fvd_miou.png",
    }  # fmt: skip
    # Table 1 with the flat baselines first (probed at themselves) and every decoder's reference rows.
    main = read_csv(out / "main_table.csv")
    assert [r["model"] for r in main] == ["flat_detail", "flat_abstract", "hierarchical",
                                          *(name for name, *_ in tables.FVD_REFERENCES)]
    assert [r["kind"] for r in main] == ["model"] * 3 + ["reference"] * 5
    assert float(main[1]["miou"]) == PROBES["flat_abstract"][0] and main[1]["probe_target"] == "flat_abstract"
    # Fig. 4's numbers, one FVD column per system, one row per window end.
    chunked = read_csv(out / "fvd_chunked.csv")
    for model in report.FVD_MODELS:
        chunks = evals.fvd[model].chunked.chunks
        assert [float(r["end_s"]) for r in chunked] == [c.end_s for c in chunks]
        assert [float(r[model]) for r in chunked] == pytest.approx([c.fvd for c in chunks], rel=1e-5)

    hierarchy = read_csv(out / "hierarchy_ablation.csv")
    assert [(r["exp"], r["branch"], r["abstraction"], float(r["frame_rate_hz"])) for r in hierarchy] == [
        ("1", "single", "detail", 10.0),
        ("2", "single", "abstract", 10.0),
        ("3", "top", "abstract", 2.0),
        ("3", "bottom", "detail", 10.0),
        ("4", "top", "detail", 2.0),
        ("4", "bottom", "detail", 10.0),
        ("5", "top", "abstract", 10.0),
        ("5", "bottom", "detail", 10.0),
    ]
    assert [r["probe_target"] for r in hierarchy] == [row[4] for row in tables.HIERARCHY_LAYOUT]
    exp4_bottom = hierarchy[5]
    assert float(exp4_bottom["miou"]) == PROBES["detail_on_detail"][0]
    assert float(exp4_bottom["fvd_long"]) == FVD["top_detail"][4] and float(exp4_bottom["fvd_slope"]) == 81.4
    assert exp4_bottom["fvd_long_n"] == exp4_bottom["fvd_slope_n"] == "43"
    assert float(hierarchy[6]["fvd_long"]) == FVD["top_abstract_10hz"][4]

    training = read_csv(out / "training_ablation.csv")
    assert list(training[0]) == ["model", "probe_target", "miou", "miou_n", "rmse", "rmse_n", "val_loss"]
    assert [r["probe_target"] for r in training] == [
        "abstract_tokenizer",
        "abstract_tf_only",
        "abstract_df",
        "abstract_tf",
        "teacher",
    ]
    assert float(training[3]["val_loss"]) == 0.25 and training[3]["miou_n"] == "50"

    compression = read_csv(out / "compression_ablation.csv")
    assert [r["latent_dim"] for r in compression] == ["16", "768"]
    assert float(compression[0]["fvd_slope"]) == 40.0
    assert compression[1]["miou"] == "NA"  # the stage reported null: not measured

    for png in sorted((out / "figures").iterdir()):
        with Image.open(png) as image:
            assert image.format == "PNG" and min(image.size) > 50

    summary = (out / "summary.md").read_text()
    for heading in ("## Hierarchy design study", "## Training strategy", "## Latent compression"):
        assert heading in summary
    assert summary_verdicts(out / "summary.md") == ["holds"] * 9


def _set(evals: Evals, path: tuple, value) -> None:
    """Set the value at ``path`` (attributes of the records, keys of their mappings, indices of their lists)."""
    node = evals
    for key in path[:-1]:
        node = node[key] if isinstance(node, (dict, list)) else getattr(node, key)
    if isinstance(node, (dict, list)):
        node[path[-1]] = value
    else:
        setattr(node, path[-1], value)


@pytest.mark.parametrize(
    "claim, path, value",
    [
        (0, ("probe", "abstract_df", "segmentation", "miou"), 60.0),  # DF only better mIoU than DF+TF
        (0, ("probe", "abstract_tf_only", "depth", "rmse"), 4.0),  # TF only better RMSE
        (1, ("fvd", "flat_abstract", "chunked", "fvd_slope_draws"), [40.0] * 40),  # flat abstract more stable
        (2, ("compression", "rows", 0, "fvd_slope"), 200.0),  # compressed less stable than full
        (3, ("steering", "responses", "learned", "turn_response_deg", "high"), 1.0),  # turns do not follow yaw
        (3, ("steering", "responses", "learned", "path_ratio", "high"), 1.05),  # paths do not follow speed
        (3, ("steering", "responses", "learned", "turn_steps_deg", "yaw_rate_x1.5 - original", "high"),
         0.5),  # x1.5 turns no more than the original
        (4, ("speed", "models", "flat_detail", "fps"), 5.0),  # flat detail faster
        (5, ("conditioning", "variants", 1, "high"), 0.02),  # another clip's subgoal: no material change
        (6, ("conditioning", "baselines", 0, "high"), 0.01),  # repeating the last frame is as good
        (7, ("fvd", "hierarchical", "fvd", "heldout", "draws"), [905.0] * 40),  # the held frame scores better
        (8, ("steering", "truth", "claim", "verdict"), "does not hold"),  # a rollout nearer another command's truth
    ],
)
def test_each_claim_flips_with_the_numbers(evals, tmp_path, claim, path, value):
    assert verdicts(evals)[claim] == "holds"
    _set(evals, path, value)
    expected = ["holds"] * 9
    expected[claim] = "does not hold"
    if path[-1] == "high":  # an interval wholly below the material threshold
        _set(evals, path[:-1] + ("low",), -0.05)
    assert verdicts(evals) == expected
    report.write_full_report(evals, tmp_path / "out", SETUP, SETTINGS)
    assert summary_verdicts(tmp_path / "out" / "summary.md") == expected


def test_an_interval_straddling_the_threshold_is_not_resolved(evals):
    _set(evals, ("conditioning", "variants", 1, "low"), 0.01)
    assert verdicts(evals)[5] == "not resolved at this sample size"


def test_steering_without_truth_has_no_truth_columns_and_its_claim_is_not_measured(evals):
    """A real-data source: no true counterfactuals, so the truth claim is not measured and no truth cells appear."""
    evals.steering.truth = None
    assert verdicts(evals)[8] == "not measured" and verdicts(evals)[3] == "holds"
    assert not any(key.startswith(("truth", "truth_fvd")) for key in tables.steering_table(evals, SETTINGS)[0])


def test_null_compression_slope_is_not_measured(evals):
    _set(evals, ("compression", "rows", 1, "fvd_slope"), None)
    assert verdicts(evals)[2] == "not measured"


@pytest.mark.parametrize(
    "missing, stage, writer",
    [
        ("fvd_hierarchical", "eval_fvd_hierarchical", report.write_main_report),
        ("probe_abstract_tf", "eval_probe_abstract_tf", report.write_main_report),
        ("steering", "eval_steering", report.write_main_report),
        ("speed", "eval_speed", report.write_main_report),
        ("fvd_top_detail", "eval_fvd_top_detail", report.write_full_report),
        ("probe_teacher", "eval_probe_teacher", report.write_full_report),
    ],
)
def test_missing_input_names_file_and_stage(tmp_path, missing, stage, writer):
    folder = write_evals(tmp_path / "eval", skip=(missing,))
    evals = load_eval(folder)
    with pytest.raises(OrbisError, match=re.escape(f"{missing}.json (written by stage {stage})")):
        writer(evals, tmp_path / "out", SETUP, SETTINGS)
    assert not (tmp_path / "out").exists()  # checked before anything is written


def test_missing_metric_is_an_error_not_a_blank(evals, tmp_path):
    evals.probe["flat_detail"].depth = None  # a probe without depth labels
    with pytest.raises(OrbisError, match=r"probe_flat_detail\.json .*depth"):
        report.write_main_report(evals, tmp_path / "out", SETUP, SETTINGS)


def test_full_report_without_compression_drops_that_table(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "compression_ablation.csv").write_text("stale\n")
    evals = load_eval(write_evals(tmp_path / "eval"))
    report.write_full_report(evals, out, SETUP, SETTINGS)
    assert not (out / "compression_ablation.csv").exists()
    assert summary_verdicts(out / "summary.md")[2] == "not measured"


def test_rollout_grid_and_steering_strip_are_pngs(tmp_path):
    rng = np.random.default_rng(0)
    times = [0.5, 4.0, 8.0]
    frames = [rng.integers(0, 255, (3, 36, 64, 3), dtype=np.uint8) for _ in range(2)]
    figures.save_rollout_grid(frames, ["Exp. 1", "Exp. 3 (ours)"], times, tmp_path / "grid.png")
    t = np.linspace(0, 6, 13)[:, None]
    modes = SETTINGS.steering_modes
    plans = [np.hstack([5 * t, 0.1 * k * t**2]) for k in range(len(modes))]
    modes_frames = [rng.integers(0, 255, (3, 36, 64, 3), dtype=np.uint8) for _ in modes]
    figures.save_steering_strip(
        modes_frames, modes, times, plans, tmp_path / "strip.png", estimated=[p * 0.9 for p in plans]
    )
    for name in ("grid.png", "strip.png"):
        with Image.open(tmp_path / name) as image:
            assert image.format == "PNG"
    with pytest.raises(ValueError, match="uint8"):
        figures.save_rollout_grid([f.astype(np.float32) for f in frames], ["a", "b"], times, tmp_path / "bad.png")


def test_the_headline_figure_shows_each_row_at_the_times_its_videos_reach(tmp_path, monkeypatch):
    from orbis2.eval.protocols import steering

    drawn = {}
    monkeypatch.setattr(steering, "save_frame_columns",
                        lambda frames, labels, times, path: drawn.update(frames=frames, labels=labels, times=times))
    videos = {"real": np.arange(31, dtype=np.uint8)[:, None, None, None] * np.ones((1, 4, 6, 3), np.uint8),
              "model": np.zeros((21, 4, 6, 3), np.uint8)}  # 2 s: the 3 s column is left out
    steering.save_headline(videos, 10.0, tmp_path / "headline.png")
    assert drawn["labels"] == ["real", "model"] and drawn["times"] == [0.0, 1.0]
    assert [int(f[0, 0, 0]) for f in drawn["frames"][0]] == [0, 10]  # frame 0: the last context frame
    monkeypatch.undo()
    steering.save_headline({k: v[:31] for k, v in videos.items()}, 10.0, tmp_path / "headline.png")
    with Image.open(tmp_path / "headline.png") as image:
        assert image.format == "PNG"


def test_compression_rows_come_from_the_flat_abstract_models(evals):
    """Compressed vs full: each row reads its own flat abstract model's rollouts and probes."""
    full = fvd_doc("flat_abstract") | {"model": "flat_abstract_full", "latent_channels": 768}
    full["chunked"] = {**full["chunked"], "fvd_slope": 99.0}
    evals.fvd["flat_abstract"].latent_channels = 16
    evals.fvd["flat_abstract_full"] = records.FvdRecord.model_validate(full)
    rows = tables.compression_from_evals(evals).rows
    assert [(r.variant, r.latent_dim) for r in rows] == [("compressed", 16), ("full (teacher dim)", 768)]
    assert rows[1].fvd_slope == 99.0 and rows[0].fvd_slope == FVD["flat_abstract"][5]
    assert rows[1].miou == evals.probe["flat_abstract_full"].segmentation.miou
    del evals.fvd["flat_abstract_full"]
    with pytest.raises(OrbisError, match="eval_fvd_flat_abstract_full"):
        tables.compression_from_evals(evals)


def test_write_csv_known_bytes_and_exact_float_round_trip(tmp_path):
    import pandas as pd

    from orbis2.eval.report.report import write_csv

    rows = [{"model": "a, b", "fvd": 12.345678901234567, "n": 3, "note": None, "slope": float("nan")},
            {"model": 'say "x"', "fvd": 1e-09, "n": 4, "note": "ok", "slope": -0.1}]
    write_csv(rows, tmp_path / "t.csv")
    assert (tmp_path / "t.csv").read_bytes() == (b'model,fvd,n,note,slope\r\n"a, b",12.345678901234567,3,None,nan\r\n'
                                                 b'"say ""x""",1e-09,4,ok,-0.1\r\n')
    back = pd.read_csv(tmp_path / "t.csv")
    assert back["fvd"].tolist() == [12.345678901234567, 1e-09] and back["model"].tolist() == ["a, b", 'say "x"']


def test_a_floor_on_too_few_clips_reads_na(evals):
    evals.fvd["hierarchical"].references["val"].real_floor = records.RealFloor(fvd=None, clips=2, reason="few")
    floor = tables.main_table(evals, "main", SETTINGS)[1]
    assert floor["fvd_val"] == floor["fvd_val_n"] == "NA" and floor["fvd_heldout"] == 30.0


def test_fvd_tables_carry_the_protocol_card(evals, tmp_path):
    card = records.ProtocolCard.model_validate({**real("fvd_hierarchical")["protocol"]["turns"], "fps": 10,
                                                 "i3d_sha256": "ab12", "bootstrap_seed": 31})
    for record in evals.fvd.values():  # the card is the same in every system's record
        record.protocol = {"turns": card, "val": card.model_copy(update={"clips": 2})}
    report.write_main_report(evals, tmp_path, SETUP, SETTINGS)
    summary = (tmp_path / "summary.md").read_text()
    main = summary.split("## Main results (Table 1)")[1].split("## ")[0]
    # the card's entries in the order of its record's file (sorted keys), without the source resolution
    assert "- FVD protocol, turns: bootstrap_reps=50, bootstrap_seed=31, chunk_seconds=1.6, clips=2, " \
           "context_frames=5, floor_splits=10, fps=10, frame_selection=" in main
    assert "i3d_sha256=ab12, long_seconds=3.5, protocol=orbis2, resize=" in main
    assert "FVD protocol, val:" in main and "source_resolution" not in main
    steering = summary.split("## Steering (Table 2)")[1].split("## ")[0]
    assert "FVD protocol" not in steering


def test_fvd_splits_and_steering_modes_follow_the_config(evals, tmp_path, smoke_cfg):
    """A split renamed and one added in ``evaluation.fvd_splits``, a steering mode renamed in
    ``evaluation.steering_modes``: the tables and the split-wise claim follow the config, not a fixed list."""
    ev = dataclasses.replace(smoke_cfg.evaluation, fvd_splits=["val", "night", "turns", "dusk"],
                             steering_modes={"original": [1.0, 1.0], "yaw_rate_x2": [1.0, 2.0]})
    settings = tables.TableSettings.from_config(dataclasses.replace(smoke_cfg, evaluation=ev))
    assert settings.fvd_splits == ("val", "night", "turns", "dusk")
    assert settings.steering_modes == ("original", "yaw_rate_x2")
    for record in evals.fvd.values():
        for new, like in (("night", "heldout"), ("dusk", "val")):
            record.fvd[new] = record.fvd[like].model_copy(update={"videos": 7})
            record.references[new] = record.references[like]
    steering = evals.steering
    steering.modes["yaw_rate_x2"] = steering.modes["yaw_rate_x1.5"].model_copy(update={"samples": 9})
    for reading in (steering.latent_turn, steering.image_turn):
        reading.modes["yaw_rate_x2"] = records.TurnCells(turn_deg=99.0, low=98.0, high=100.0, commanded_turn_deg=24.0)
    for cells in (steering.truth.modes, steering.truth.claim.modes):
        cells["yaw_rate_x2"] = cells["yaw_rate_x1.5"]

    report.write_main_report(evals, tmp_path, SETUP, settings)
    main = read_csv(tmp_path / "main_table.csv")
    assert [key for key in main[0] if key.startswith("fvd_") and key.count("_") == 1] == [
        "fvd_val", "fvd_night", "fvd_turns", "fvd_dusk"]
    assert "fvd_heldout" not in main[0] and main[0]["fvd_night_n"] == main[0]["fvd_dusk_n"] == "7"
    rows = read_csv(tmp_path / "steering.csv")
    assert [r["mode"] for r in rows] == ["original", "yaw_rate_x2", "real_subgoals", "real_videos", "shuffled_videos"]
    assert rows[1]["ade_n"] == "9" and float(rows[1]["turn_deg_latent"]) == 99.0
    assert "night" in claims.check_claims(evals, settings)[7][2]  # claim 8 reads every configured split
    evals.fvd["hierarchical"].fvd.pop("dusk")  # a configured split the record lacks: named, not skipped
    with pytest.raises(OrbisError, match=r"fvd_hierarchical\.json .*fvd\.dusk"):
        tables.main_table(evals, "main", settings)


def test_summary_has_the_instrument_calibration_on_the_truth(evals, tmp_path):
    report.write_main_report(evals, tmp_path, SETUP, SETTINGS)
    section = (tmp_path / "summary.md").read_text().split("## The steering instrument on the true counterfactuals")
    assert len(section) == 2 and "| yaw_rate_x1.5 | learned | 21 | 20 | 18 | 22 | -0.05 | -0.1 | 0 | 20 |" in section[1]
    evals.steering.truth = None
    report.write_main_report(evals, tmp_path, SETUP, SETTINGS)
    assert "true counterfactuals" not in (tmp_path / "summary.md").read_text().split("## Reading")[0]
