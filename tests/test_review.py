"""Reviewing a run with DVC: no lock update from a run whose config DVC cannot see, loss curves, and a
`dvc plots show` page that needs no network. That a Snakemake run leaves dvc.lock in step is tested on the
smoke project (tests/test_pipeline.py)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import yaml

from orbis2 import dag
from orbis2.config.params import load_params
from orbis2.stage import draw_loss_curves

from conftest import ROOT


def test_config_drift_names_what_dvc_cannot_see():
    params = load_params(ROOT / "params.yaml")
    assert dag.config_drift({**params, "train_launcher": "torchrun --nproc_per_node 8"}, ROOT / "params.yaml") == []
    other = "paper" if params["profile"] != "paper" else "smoke"
    changed = {**params, "profile": other, "action": {**params["action"], "all": {}}}
    assert dag.config_drift(changed, ROOT / "params.yaml") == ["action", "profile"]


def test_no_commit_when_the_run_differs_from_params_yaml(tmp_path, capfd, monkeypatch):
    (tmp_path / ".dvc").mkdir()
    params = load_params(ROOT / "params.yaml")
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({**params, "profile": "paper"}))
    assert not dag.commit_to_dvc(["town", "shards"], [], tmp_path)  # terabytes: not hashed on the submit host
    assert "at the paper profile the outputs are terabytes" in capfd.readouterr().err
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    assert not dag.commit_to_dvc(["town", "shards"], ["profile"], tmp_path)
    assert "dvc.lock not updated" in capfd.readouterr().err and not (tmp_path / "dvc.lock").exists()
    monkeypatch.setenv(dag.COMMIT_ENV, "0")
    assert not dag.commit_to_dvc(["town", "shards"], [], tmp_path)
    assert capfd.readouterr().err == ""


def test_a_run_of_another_profile_writes_it_into_params_yaml(tmp_path, capfd, monkeypatch):
    """`snakemake --config profile=smoke` with params.yaml saying default: DVC then reads the run's profile."""
    params = tmp_path / "params.yaml"
    text = re.sub(r"^profile: \S+", "profile: default", (ROOT / "params.yaml").read_text(), count=1,
                  flags=re.MULTILINE)
    params.write_text(text)
    assert not dag.follows_profile(["profile"], params)  # not a DVC project
    (tmp_path / ".dvc").mkdir()
    assert dag.follows_profile(["profile"], params) and not dag.follows_profile(["action", "profile"], params)
    dag.adopt_profile("smoke", params)
    assert "params.yaml: profile default -> smoke" in capfd.readouterr().err
    assert load_params(params)["profile"] == "smoke"
    assert params.read_text().replace("profile: smoke", "profile: default", 1) == text  # only that line changed
    monkeypatch.setenv(dag.COMMIT_ENV, "0")
    assert not dag.follows_profile(["profile"], params)


def test_a_run_is_committed_through_its_sinks_with_their_dependencies():
    """One `dvc commit --with-deps` of the run's last stages records exactly the run: DVC rewrites dvc.lock once
    per target, so naming all 45 smoke stages took 2.5 CPU minutes."""
    stages = list(yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"])
    assert dag.commit_sinks(stages, ROOT) == ["report_main", "report_all"]
    upstream = ["town", "assets", "shards", "tokenizer_detail", "tokenizer_abstract", "latents", "abstract_df",
                "abstract_tf", "action"]  # `snakemake --until action`
    assert dag.commit_sinks(upstream, ROOT) == ["action"]
    assert dag.commit_sinks(["town", "action"], ROOT) is None  # not a whole run: each is committed by name
    assert dag.commit_sinks([s for s in stages if s != "report_all"], ROOT) is not None


def curves(folder: Path, evaluated: bool = True) -> Path:
    folder.mkdir(parents=True)
    pd.DataFrame({"step": [1, 2, 3], "loss": [400.0, 380.0, 350.0]}).to_csv(folder / "train.csv", index=False)
    if evaluated:
        pd.DataFrame({"step": [3], "val_loss": [1.5]}).to_csv(folder / "eval.csv", index=False)
    return folder


def test_each_loss_is_drawn_on_its_own(tmp_path):
    drawn = draw_loss_curves(curves(tmp_path / "predictor/curves"), "predictor")
    assert [p.name for p in drawn] == ["loss.png", "val_loss.png"]
    assert all(p.read_bytes().startswith(b"\x89PNG") for p in drawn)
    assert [p.name for p in draw_loss_curves(curves(tmp_path / "tokenizer/curves", False), "tokenizer")] == [
        "loss.png"]


def test_plots_page_needs_no_network(tmp_path):
    """dvc.yaml's plots are images only: DVC copies them beside its page, which then loads no script."""
    plots = yaml.safe_load((ROOT / "dvc.yaml").read_text())["plots"]
    assert all(isinstance(p, str) and p.endswith(".png") for p in plots)
    assert "data/predictors/action/curves/val_loss.png" in plots and "data/tokenizers/detail/curves/loss.png" in plots
    (tmp_path / "dvc.yaml").write_text(yaml.safe_dump({"plots": plots}))
    draw_loss_curves(curves(tmp_path / "data/predictors/action/curves"), "action")
    draw_loss_curves(curves(tmp_path / "data/tokenizers/detail/curves", False), "tokenizer_detail")
    for cmd in (["init", "--no-scm", "-q"], ["plots", "show"]):
        proc = subprocess.run([sys.executable, "-m", "dvc", *cmd], cwd=tmp_path, capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
    page = (tmp_path / "dvc_plots/index.html").read_text()
    assert "<script" not in page and not re.search(r"(src|href)=[\"']?https?:", page)
    images = re.findall(r"<img src=\"([^\"]+)\"", page)
    assert len(images) == 3 and all((tmp_path / "dvc_plots" / src).is_file() for src in images)
