"""The DAG started from an imported release (params.yaml ``official_weights``, :mod:`orbis2.tasks.official`).

A synthetic release in the authors' layout at the smoke geometry (``test_official.smoke_release``) is imported;
the smoke stages that read it run as the DAG runs them (their scripts, a params.yaml with ``official_weights``
set): the tokenizer stages publish the imported tokenizers, the latent cache is made with them, and the predictor
stages fine-tune the imported predictors for 10 steps at the architecture the import recorded.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from test_import import stage_env
from test_official import FIXTURES, smoke_release
from test_shards import make_raw

from orbis2.cli import main
from orbis2.config.params import load_params, parse_config
from orbis2.data.shards import write_shards
from orbis2.data.video import read_video
from orbis2.errors import ConfigError, OrbisError
from orbis2.io import sha256_file
from orbis2.models.files import load_predictor
from orbis2.registry import registry
from orbis2.tasks import official

from conftest import ROOT

STEPS = 10


@pytest.fixture(scope="module")
def imported(tmp_path_factory) -> Path:
    """The synthetic release at the smoke geometry, imported."""
    root = tmp_path_factory.mktemp("official_dag")
    note = json.loads((FIXTURES / "authors_tiny.json").read_text())
    out = root / "official"
    main(["import-weights", str(smoke_release(root / "release", note)), "--out", str(out)])
    return out


def official_params(folder: Path, **sections: dict) -> dict:
    """params.yaml with ``official_weights`` set and ``sections`` merged into their ``smoke`` part."""
    raw = load_params(ROOT / "params.yaml")
    raw["official_weights"] = str(folder)
    for name, values in sections.items():
        raw[name]["smoke"] = {**raw[name]["smoke"], **values}
    return raw


def without_steering(build: dict) -> dict:
    return {k: v for k, v in build.items() if not k.startswith("steering")}


def run_stage(project: Path, script: str, *args: str) -> str:
    proc = subprocess.run([sys.executable, str(ROOT / "stages" / script), *args, "--profile", "smoke"],
                          cwd=project, capture_output=True, text=True, env=stage_env(project))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout


def test_the_smoke_dag_fine_tunes_an_imported_release(imported, tmp_path, smoke_cfg, make_video):
    """tokenizer_detail, tokenizer_abstract, latents, detail, abstract_tf (``init_from: null``: from the import)
    and action (from abstract_tf, its steering embedder its own), 10 steps each; the fine-tuned networks then
    roll out with ``orbis2 rollout``."""
    steps = {"train": {**load_params(ROOT / "params.yaml")["_predictor"]["smoke"]["train"], "steps": STEPS}}
    raw = official_params(imported, detail=steps, abstract_tf={**steps, "init_from": None}, action=steps)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))
    make_raw(tmp_path / "raw", smoke_cfg, episodes=(("train", 3, 64), ("val", 1, 60)))
    write_shards(tmp_path / "raw", tmp_path / "data" / "shards", smoke_cfg.data, smoke_cfg.shards)

    manifest = json.loads((imported / "manifest.json").read_text())
    for name in ("detail", "abstract"):
        assert "published the imported" in run_stage(tmp_path, f"tokenizer_{name}.py")
        ours = tmp_path / "data" / "tokenizers" / name / "tokenizer.pt"
        assert sha256_file(ours) == sha256_file(imported / manifest["written"][f"tokenizers/{name}"])
    run_stage(tmp_path, "latents.py")
    cache = json.loads((tmp_path / "data" / "latents" / "meta.json").read_text())
    assert cache["tokenizers"]["detail"]["shape"] == [8, 9, 16]  # the import's latents, not a smoke tokenizer's

    for stage, source, started in (("detail", "detail", True), ("abstract_tf", "abstract_tf", True),
                                   ("action", "abstract_tf", False)):
        run_stage(tmp_path, "predictor.py", stage)
        tuned = load_predictor(tmp_path / "data" / "predictors" / stage / "predictor.pt")
        theirs = load_predictor(imported / manifest["written"][f"predictors/{source}"])
        report = json.loads((tmp_path / "reports" / f"{stage}.json").read_text())
        assert report["steps"] == STEPS
        assert without_steering(tuned.build) == without_steering(theirs.build)  # the import's architecture
        assert tuned.build["steering"] is (stage == "action")
        assert tuned.meta["imported"]["started_from"] is started
        ours, start = tuned.model.state_dict(), theirs.model.state_dict()
        moved = max((ours[k] - start[k]).abs().max().item() for k in ours if k in start and "steering" not in k)
        # Fine-tuned (moved) from the import (10 Adam steps of lr 1e-3 stay within about 0.01 of it; a network
        # initialised afresh lies ~0.05 away in every weight); action also holds abstract_tf's own steps.
        assert 0 < moved < 0.03 * (2 if stage == "action" else 1), moved
    assert "steering.feature_mlps.0.0.weight" in tuned.model.state_dict()  # action's own steering embedder

    video = make_video("clip.mp4", 60, 10.0, width=128, height=72)  # the fine-tuned networks roll out as ours do
    data = tmp_path / "data"
    main(["rollout", "--video", str(video), "--out", str(tmp_path / "rollout.mp4"), "--seconds", "1",
          "--profile", "smoke", "--params", str(tmp_path / "params.yaml"), "--device", "cpu",
          "--detail-tokenizer", str(data / "tokenizers" / "detail" / "tokenizer.pt"),
          "--abstract-tokenizer", str(data / "tokenizers" / "abstract" / "tokenizer.pt"),
          "--abstract-predictor", str(data / "predictors" / "abstract_tf" / "predictor.pt"),
          "--detail-predictor", str(data / "predictors" / "detail" / "predictor.pt")])
    assert len(read_video(tmp_path / "rollout.mp4", 1, (128, 72))) == 5 + 10


def test_stages_without_the_setting_or_a_counterpart_are_unchanged(imported):
    reg = registry()
    assert official.imported_predictor(None, reg.predictors["detail"]) is None
    assert official.imported_tokenizer(None, "detail") is None
    with_counterpart = {name for name, spec in reg.predictors.items() if official.counterpart(spec)}
    assert with_counterpart == {"abstract_df", "abstract_tf", "abstract_tf_only", "action", "detail", "detail_distill"}
    assert official.imported_tokenizer(str(imported), "abstract_full") is None  # the compression ablation's own
    assert official.imported_tokenizer(str(imported), "abstract") == imported / "tokenizers/abstract/tokenizer.pt"


def test_mismatches_are_refused_in_one_line(imported, smoke_cfg):
    path = imported / "predictors" / "abstract_tf" / "predictor.pt"
    loaded, spec = load_predictor(path), registry().predictors["abstract_tf"]
    shape = [8, 9, 16]
    assert official.stage_build(loaded, path, spec, {}, smoke_cfg, shape)["steering"] is False
    slower = dataclasses.replace(smoke_cfg, data=dataclasses.replace(smoke_cfg.data, abstract_hz=5))
    cases = [(slower, shape, "the authors' config gives frame_rate = 2.0, but profile smoke uses 5"),
             (smoke_cfg, [8, 18, 32], "the imported predictor has latents [8, 9, 16], profile smoke needs the "
                                      "cache's [8, 18, 32]")]
    for cfg, latent_shape, message in cases:
        with pytest.raises(OrbisError, match=message.replace("[", r"\[").replace("]", r"\]")) as err:
            official.stage_build(loaded, path, spec, {}, cfg, latent_shape)
        assert str(path) in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(OrbisError, match="encodes 72x128 frames, profile default 160x256"):
        official.check_tokenizer(path, (72, 128), parse_config(load_params(ROOT / "params.yaml"), "default"))
    with pytest.raises(OrbisError, match="holds no manifest.json; import the release there first"):
        official.imported_tokenizer(str(imported / "missing"), "detail")


def test_the_setting_is_typed():
    raw = load_params(ROOT / "params.yaml")
    assert parse_config(raw, "smoke").official_weights is None
    with pytest.raises(ConfigError, match="official_weights = 3 must be null or the folder"):
        parse_config({**raw, "official_weights": 3}, "smoke")
    without = {k: v for k, v in raw.items() if k != "official_weights"}
    with pytest.raises(ConfigError, match="add `official_weights: null` at the top level"):
        parse_config(without, "smoke")


def test_an_unsteered_stage_starts_without_the_imported_steering_embedder(imported):
    loaded = load_predictor(imported / "predictors" / "abstract_tf" / "predictor.pt")
    state = official.start_state(loaded)
    assert any(k.startswith("steering.") for k in loaded.model.state_dict())
    assert not any(k.startswith("steering.") for k in state)
    assert all(torch.equal(v, loaded.model.state_dict()[k]) for k, v in state.items())
