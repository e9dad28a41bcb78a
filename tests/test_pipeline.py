"""The smoke profile through the real DAG, with Snakemake and with DVC, in a fresh copy of the project.

Checks: outputs exist and are read by the next stage; one MLflow parent run per
invocation with one nested run per stage; a second run does no work; changing
one stage's params re-runs that stage (and its dependents) only.
"""

import csv
import json
import math
import re
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from test_dag import dvc_stages

from orbis2.config.params import load_config
from orbis2.data.parts import part_name
from orbis2.data.shards import Clip, iter_samples, load_manifest, shard_paths, verify_shards
from orbis2.latents import LatentWindowDataset, open_cache
from orbis2.models.files import load_predictor, load_tokenizer
from orbis2.tasks.predictors import STAGES as STAGE_SPECS

from conftest import project_copy, project_env, run

pytestmark = pytest.mark.slow


def mlflow_runs(db: Path) -> list[tuple[str, str, str | None]]:
    """(run id, run name, parent run id) of every run in the store."""
    with sqlite3.connect(db) as con:
        names = dict(con.execute("select run_uuid, name from runs"))
        parents = dict(con.execute("select run_uuid, value from tags where key = 'mlflow.parentRunId'"))
    return [(r, n, parents.get(r)) for r, n in names.items()]


PREDICTORS = sorted(STAGE_SPECS)
STAGES = sorted(name for name in dvc_stages() if name != "import")  # the whole DAG on the embedded town
# The MLflow runs of a Snakemake build: every stage, and the one part of the shards and of each latent cache (jobs
# of Snakemake's own).
RUNS = sorted([*STAGES, *(f"{stage}_part_{part_name(0, 1)}" for stage in ("town", "shards", "latents",
                                                                                   "latents_full"))])
TARGETS = ["reports/main_table.csv", "reports/all"]


def upstream(target: str, stages: dict[str, dict]) -> set[str]:
    """``target`` and every stage whose outputs it reads, directly or not (from dvc.yaml's deps and outs)."""
    producer = {out: name for name, stage in stages.items() for out in stage["outs"]}
    found, todo = set(), [target]
    while todo:
        name = todo.pop()
        if name not in found:
            found.add(name)
            todo += [producer[d] for d in stages[name]["deps"] if d in producer]
    return found


def downstream(source: str, stages: dict[str, dict]) -> set[str]:
    """``source`` and every stage that reads its outputs, directly or not."""
    return {name for name in stages if source in upstream(name, stages)}


MAIN_STAGES = sorted(upstream("report_main", dvc_stages()) & set(STAGES))  # what reports/main_table.csv needs
ACTION_STAGES = sorted(upstream("action", dvc_stages()) & set(STAGES))  # what the steered predictor needs


def check_outputs(root: Path, full: bool = True, stages: list[str] = MAIN_STAGES) -> None:
    """Every output of ``stages`` (all stages when ``full``) exists and the next stage could read it."""
    verify_shards(root / "data/shards")
    manifest = load_manifest(root / "data/shards")
    assert set(manifest["splits"]) == {"train", "val", "turns", "heldout", "probe"}
    clip = Clip.from_sample(next(iter_samples(shard_paths(root / "data/shards", "probe")[0])))
    assert clip.frames([0]).shape == (1, 72, 128, 3) and clip.labels is not None
    assert (root / "reports/town_contact_sheet.png").stat().st_size > 10_000
    detail = load_tokenizer(root / "data/tokenizers/detail/tokenizer.pt")
    abstract = load_tokenizer(root / "data/tokenizers/abstract/tokenizer.pt")
    cache = open_cache(root / "data/latents", detail.checksum, abstract.checksum)
    window = LatentWindowDataset(cache, "train", load_config(root / "params.yaml").data)[0]
    assert window["detail"].shape[:2] == (10, 16) and window["abstract"].shape[:2] == (6, 16)
    for name in ("tokenizer_detail", "tokenizer_abstract"):
        assert json.loads((root / f"reports/{name}.json").read_text())["steps"] == 30
    smoke = load_config(root / "params.yaml")
    full_abstract = load_tokenizer(root / "data/tokenizers/abstract_full/tokenizer.pt") if full else None
    for name in PREDICTORS if full else sorted(set(PREDICTORS) & set(stages)):
        predictor = load_predictor(root / f"data/predictors/{name}/predictor.pt")
        expected = full_abstract if STAGE_SPECS[name].latents == "full" else abstract
        assert predictor.meta["stage"] == name and predictor.meta["tokenizers"]["abstract"]["checksum"] == \
            expected.checksum
        report = json.loads((root / f"reports/{name}.json").read_text())
        assert report["steps"] == smoke.section(name).train.steps and math.isfinite(report["val_loss"])
        assert report["val_loss_init"] > 0
    assert load_predictor(root / "data/predictors/action/predictor.pt").model.steering is not None
    if full or "report_main" in stages:
        check_reports(root, full)


def check_reports(root: Path, full: bool) -> None:
    """The report stages read every evaluation and wrote the paper's tables with finite figures."""
    tables = {"reports/main_table.csv": ["hierarchical"]}
    if full:  # reports/all's Table 1 puts the flat baselines before the main table's row
        tables["reports/all/main_table.csv"] = ["flat_detail", "flat_abstract", "hierarchical"]
    rows = []
    for table, models in tables.items():
        with open(root / table) as handle:
            rows += [r for r in csv.DictReader(handle) if r["kind"] == "model"]
        assert [r["model"] for r in rows[-len(models):]] == models, table
    for row in rows:
        for column in ("fvd_val", "fvd_heldout", "fvd_turns", "fvd_slope_turns", "miou", "rmse"):
            assert math.isfinite(float(row[column])) and int(row[f"{column}_n"]) >= 2, (row["model"], column)
    for name in ("steering.csv", "speed.csv", "summary.md", "headline.png"):
        assert (root / "reports" / name).stat().st_size > 100
    for name in ("hierarchy_ablation.csv", "training_ablation.csv", "compression_ablation.csv", "summary.md",
                 "figures/fvd_chunked.png", "figures/probe_per_block.png", "figures/bubble_params_fvd_miou.png",
                 "figures/rollout_grid.png", "figures/steering_strip.png"):
        assert not full or (root / "reports/all" / name).stat().st_size > 100, name
    fvd = json.loads((root / "reports/eval/fvd_hierarchical.json").read_text())
    val = fvd["fvd"]["val"]
    assert len(fvd["chunked"]["chunks"]) == 2 and (val["videos"], val["clips"]) == (2, 2)  # a start per clip
    assert val["low"] <= val["fvd"] <= val["high"] and set(fvd["references"]["val"]) >= {"reconstruction",
                                                                                           "repeat_last"}
    conditioning = json.loads((root / "reports/eval/conditioning.json").read_text())
    assert conditioning["seeds"] == [0, 1] and {r["model"] for r in conditioning["baselines"]} == {
        "abstract_tf", "detail", "action"}
    if full:
        conditioning = json.loads((root / "reports/eval/conditioning_all.json").read_text())
        assert {r["model"] for r in conditioning["baselines"]} == {
            "abstract_tf", "detail", "action", "flat_detail", "flat_abstract"}
        speed = json.loads((root / "reports/eval/speed_all.json").read_text())
        assert set(speed["models"]) == {"hierarchical", "hierarchical_distilled", "flat_detail", "flat_abstract",
                                        "v1_style"}
    assert (root / "reports/conditioning.csv").stat().st_size > 100
    steering = json.loads((root / "reports/eval/steering.json").read_text())
    assert set(steering["modes"]) == {"original", "speed_x0.5", "speed_x1.5", "yaw_rate_x0.5", "yaw_rate_x1.5"}


def set_param(root: Path, section: str, key: str, value) -> None:
    params = yaml.safe_load((root / "params.yaml").read_text())
    params[section]["all"][key] = value
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))


def test_snakemake_smoke_dag(smoke_project, tmp_path):
    """The session's smoke project: the README's main job (`snakemake --cores 2`, the default target),
    then `reports/all`. Each invocation is one MLflow parent run; every stage ran once, under one of them.
    Then, in a copy, a param edit: the main job's plan is the edited stage and what reads it, nothing else,
    and running the stage is one more invocation. (The stages that read it ran in the build; running them
    again would only show the same code working twice.)"""
    check_outputs(smoke_project)
    root = Path(shutil.copytree(smoke_project, tmp_path / "project", symlinks=True))
    runs = mlflow_runs(root / "mlflow.db")
    parents = {r for r, _, p in runs if p is None}
    assert len(parents) == 2 and sorted(n for _, n, p in runs if p in parents) == RUNS

    assert "Nothing to be done" in run(["snakemake", "--cores", "2", *TARGETS], root)

    set_param(root, "action", "steering_dropout", 0.2)
    plan = run(["snakemake", "--cores", "2", "--dry-run"], root)  # the main job
    assert "threads:" not in plan  # the session's profile gives every job one thread (conftest)
    assert set(re.findall(r"^(?:local)?rule (\w+):", plan, re.MULTILINE)) == {"all"} | (
        downstream("action", dvc_stages()) & set(MAIN_STAGES))
    out = run(["snakemake", "--cores", "2", "--until", "action"], root)
    assert re.findall(r"^(?:local)?rule (\w+):", out, re.MULTILINE) == ["action"]
    assert f"dvc.lock records this run ({len(ACTION_STAGES)} stages)" in out  # test_dvc_repro_smoke_dag: DVC agrees
    assert len([r for r in mlflow_runs(root / "mlflow.db") if r[2] is None]) == 3  # one parent per invocation


def test_tokenizer_levers_measure_a_change_against_a_baseline(smoke_main, tmp_path):
    """tools/tokenizer_levers.py: short trainings on the smoke shards (outside the shared project), one with pixel
    MSE and the perceptual term and its paired PSNR gain over the base; an unknown setting, or a folder's name
    reused with other settings, stops with a line."""
    shutil.copy(smoke_main / "params.yaml", tmp_path / "params.yaml")
    tool = [sys.executable, str(Path(__file__).parents[1] / "tools" / "tokenizer_levers.py")]
    common = ["--profile", "smoke", "--shards", str(smoke_main / "data/shards"), "--assets",
              str(smoke_main / "data/assets"), "--set", "train.steps=6", "--set", "fid_images=8"]
    run([*tool, "base", *common], tmp_path)
    out = run([*tool, "levers", *common, "--set", "mse_weight=1.0", "--perceptual", "1.0", "--perceptual-taps",
               "conv_1,conv_2", "--against", "base"], tmp_path)
    rows = [json.loads(line) for line in (tmp_path / "reports/tokenizer_levers.jsonl").read_text().splitlines()]
    assert [r["name"] for r in rows] == ["base", "levers"] and rows[1]["set"] == {
        "train.steps": 6, "fid_images": 8, "mse_weight": 1.0}
    assert rows[1]["perceptual"] == 1.0 and rows[1]["perceptual_taps"] == ["conv_1", "conv_2"]
    assert rows[0]["steps"] == 6 and rows[0]["frames"] == 8 and rows[0]["clips"] >= 2
    assert rows[0]["psnr_per_frame"] != rows[1]["psnr_per_frame"]  # the levers changed the training
    gain = rows[1]["psnr_gain_db"]
    assert gain["low"] <= gain["estimate"] <= gain["high"] and "vs base" in out
    assert gain["estimate"] == pytest.approx(sum(rows[1]["psnr_per_frame"]) / 8 - sum(rows[0]["psnr_per_frame"]) / 8)
    bad = subprocess.run([*tool, "bad", *common, "--set", "no_such_key=1"], cwd=tmp_path, capture_output=True,
                         text=True, env=project_env(tmp_path))
    assert bad.returncode != 0 and "no_such_key" in bad.stderr
    other = subprocess.run([*tool, "levers", *common], cwd=tmp_path, capture_output=True, text=True,
                           env=project_env(tmp_path))  # the folder holds a training with other settings
    assert other.returncode != 0 and "started with" in other.stderr


def test_sampler_sweep_pairs_settings_on_the_same_starts_and_noise(smoke_main, tmp_path):
    """tools/sampler_sweep.py on the smoke run: a setting equal to the base reproduces its frames (a paired
    difference of exactly zero), fewer Euler steps change them; every figure carries its interval."""
    out = tmp_path / "sweep.jsonl"
    run([sys.executable, str(Path(__file__).parents[1] / "tools" / "sampler_sweep.py"), "--profile", "smoke",
         "--seconds", "1", "--horizons", "0.1", "0.5", "--setting", "same:", "--setting", "one:bottom_nfe=1",
         "--out", str(out)], smoke_main)
    base, same, one = [json.loads(line) for line in out.read_text().splitlines()]
    assert [base["setting"], one["bottom_nfe"], base["bottom_nfe"]] == ["base", 1, 2] and base["rollouts"] >= 2
    assert set(base["horizons"]) == {"0.1", "0.5"} and "vs_base_db" not in base["horizons"]["0.1"]
    for h in ("0.1", "0.5"):
        same_h = same["horizons"][h]
        assert same_h["vs_base_db"]["estimate"] == same_h["vs_base_sharpness"]["estimate"] == 0
        assert one["horizons"][h]["vs_base_db"]["estimate"] != 0.0
        assert 0 < base["horizons"][h]["reconstruction_sharpness"]["estimate"] < 2
        e = one["horizons"][h]["generated_psnr"]
        assert e["low"] <= e["estimate"] <= e["high"]


def test_guidance_selection_starts_from_the_trained_models(smoke_main, tmp_path):
    """The guidance scale chosen on val, in a copy of the session's smoke project: one eval_steering per scale."""
    root = Path(shutil.copytree(smoke_main, tmp_path / "project", symlinks=True))
    run([sys.executable, "tools/select_guidance.py", "--guidance", "1", "2", "--out", "selection"], root)
    chosen = json.loads((root / "selection/selection.json").read_text())
    assert chosen["split"] == "val" and chosen["chosen"] in (1.0, 2.0) and set(chosen["smaller_step_low_deg"]) == {
        "1.0", "2.0"}
    assert all(json.loads((root / f"selection/steering_g{w}.json").read_text())["split"] == "val" for w in (1, 2))


def test_dvc_repro_smoke_dag(smoke_main, tmp_path):
    """DVC takes over a Snakemake run: in a copy of the session's smoke project, `dvc status` of the main job
    is clean (each Snakemake run recorded its jobs' outputs in dvc.lock), and a param edit makes
    `dvc repro action` run the steered predictor alone, nothing upstream. test_dag proves that both DAGs
    issue the same commands."""
    root = Path(shutil.copytree(smoke_main, tmp_path / "project", symlinks=True))
    assert "Data and pipelines are up to date." in run(["dvc", "status", "--with-deps", "report_main"], root)
    assert "Running stage" not in run(["dvc", "repro", "action"], root)

    known = {run_id for run_id, _, _ in mlflow_runs(root / "mlflow.db")}
    dropout = yaml.safe_load((root / "params.yaml").read_text())["action"]["all"]["steering_dropout"]
    set_param(root, "action", "steering_dropout", round(dropout + 0.05, 2))
    out = run(["dvc", "repro", "action"], root)
    assert re.findall(r"Running stage '([^']+)'", out) == ["action"]
    check_outputs(root, full=False, stages=ACTION_STAGES)
    added = [(name, parent) for run_id, name, parent in mlflow_runs(root / "mlflow.db") if run_id not in known]
    assert len([name for name, p in added if p is None]) == 1  # one new invocation, with one stage
    assert [name for name, p in added if p is not None] == ["action"]
    with sqlite3.connect(root / "mlflow.db") as con:  # the copied store writes into the copy, not the original
        uris = [uri for (uri,) in con.execute("select artifact_uri from runs")]
    assert all(uri.startswith((f"{root}/", f"{root.as_uri()}/")) for uri in uris)  # MLflow keeps a path or a URI
    assert "Data and pipelines are up to date." in run(["dvc", "status", "--with-deps", "action"], root)


def test_import_source_feeds_the_shards(tmp_path, make_video):
    """With data.all.source = import, both tools build the shards from your videos, not the town."""
    root = project_copy(tmp_path / "project")
    videos = root / "data" / "videos"
    for split, frames in (("train", 80), ("val", 140)):  # the import needs both splits
        make_video(f"drive_{split}.mp4", frames, fps=20, folder=videos / split)  # one 3 s / 6 s smoke clip each
    params = yaml.safe_load((root / "params.yaml").read_text())
    params["data"]["all"]["source"] = "import"
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))

    out = run(["dvc", "repro", "shards"], root)
    assert "Running stage 'pipelines/import/dvc.yaml:import'" in out and "stage 'town'" not in out
    manifest = load_manifest(root / "data/shards")
    assert manifest["source"] == "import" and manifest["splits"]["train"]["samples"] == 1
    assert manifest["splits"]["val"]["samples"] == 1

    shutil.rmtree(root / "data/shards")
    out = run(["snakemake", "--cores", "2", "data/shards"], root)
    assert "checkpoint shards:" in out and "rule town:" not in out  # shards is a checkpoint (its files are inputs)
