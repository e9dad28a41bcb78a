"""A run's profile travels with its outputs: commands find it in the files they read (orbis2.run_profile)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch
import yaml

from orbis2.cli import main
from orbis2.config.params import load_config
from orbis2.errors import OrbisError
from orbis2.run_profile import resolve_profile

from conftest import ROOT

GPU_SIZES = {"hidden_size": 384, "depth": 8, "num_heads": 6, "cond_dim": 192}


@pytest.fixture
def params(tmp_path):
    """params.yaml saying `default`, whatever the checkout's says."""
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({**raw, "profile": "default"}, sort_keys=False))
    return path


def tokenizer(path, preset, sizes=None, **extra):
    torch.save({"kind": "detail", "build": {"preset": preset, **(sizes or {})}, "extra": extra, "state_dict": {}},
               path)
    return path


def predictor(path, preset, stage="abstract_tf", **build):
    torch.save({"build": {"preset": preset, "latent_channels": 8, **build}, "meta": {"stage": stage},
                "state_dict": {}}, path)
    return path


def manifest(path, width, height, fps=10):
    path.write_text(json.dumps({"width": width, "height": height, "fps": fps, "splits": {}}))
    return path


def test_the_files_profile_wins_over_params_yaml(params, tmp_path):
    cfg, which = resolve_profile(params, None, [tokenizer(tmp_path / "t.pt", "smoke"), None,
                                                manifest(tmp_path / "manifest.json", 128, 72)])
    assert cfg.profile == "smoke" and cfg.data.width == 128
    assert which == f"profile smoke (as {tmp_path / 't.pt'} says; {params} says default)"


def test_params_yaml_decides_between_profiles_the_files_fit(params, tmp_path):
    cfg, which = resolve_profile(params, None, [manifest(tmp_path / "manifest.json", 256, 160),
                                                tokenizer(tmp_path / "t.pt", "default")])
    assert cfg.profile == "default" and "as" in which
    # A tokenizer's sizes tell them apart too, where the default profile moves its latent grid (`_tokenizer.model`)
    raw = yaml.safe_load(params.read_text())
    raw["_tokenizer"]["default"]["model"] = grid = {"patch_size": 8, "decoder_mult": [1, 1, 2, 4],
                                                    "abstract_decoder_mult": [1, 1, 2, 2]}
    params.write_text(yaml.safe_dump(raw, sort_keys=False))
    assert resolve_profile(params, None, [tokenizer(tmp_path / "g.pt", "default")])[0].profile == "gpu"
    sizes = load_config(params, "default").tokenizer_detail.model
    assert sizes == {**grid, "decoder_mult": (1, 1, 2, 4), "abstract_decoder_mult": (1, 1, 2, 2)}
    assert resolve_profile(params, None, [tokenizer(tmp_path / "d.pt", "default", sizes)])[0].profile == "default"
    # The predictor's sizes tell the gpu profile from the default one (same frames, same tokenizers).
    gpu = predictor(tmp_path / "p.pt", "default", **GPU_SIZES)
    assert resolve_profile(params, None, [tmp_path / "manifest.json", gpu])[0].profile == "gpu"


def test_a_recorded_profile_is_taken_as_recorded(params, tmp_path):
    path = tokenizer(tmp_path / "t.pt", "default", profile="gpu")
    assert resolve_profile(params, None, [path])[0].profile == "gpu"


def test_files_of_two_runs_are_an_error_naming_both(params, tmp_path):
    small, large = tokenizer(tmp_path / "small.pt", "smoke"), predictor(tmp_path / "large.pt", "paper")
    with pytest.raises(OrbisError) as err:
        resolve_profile(params, None, [small, large])
    message = str(err.value)
    assert str(small) in message and str(large) in message and "profile smoke" in message
    assert "profile paper" in message and "--profile" in message


def test_files_that_fit_several_profiles_but_not_params_yaml_ask_for_profile(params, tmp_path):
    raw = yaml.safe_load(params.read_text())
    params.write_text(yaml.safe_dump({**raw, "profile": "smoke"}, sort_keys=False))
    with pytest.raises(OrbisError, match="fits profile default or gpu, not .*smoke; pass --profile"):
        resolve_profile(params, None, [manifest(tmp_path / "manifest.json", 256, 160)])


def test_profile_given_overrides_and_no_files_keep_params_yaml(params, tmp_path):
    small = tokenizer(tmp_path / "t.pt", "smoke")
    assert resolve_profile(params, "paper", [small])[0].profile == "paper"
    other = tmp_path / "notes.txt"
    other.write_text("not an artifact")
    cfg, which = resolve_profile(params, None, [other, tmp_path / "missing.pt"])
    assert cfg.profile == "default" and which == f"profile default ({params})"


def test_a_video_of_no_profiles_size_says_nothing(params, tmp_path, make_video):
    foreign = make_video("mine.mp4", 3, 10.0, width=160, height=96)
    smoke = make_video("smoke.mp4", 3, 10.0, width=128, height=72)
    assert resolve_profile(params, None, [foreign])[0].profile == "default"
    assert resolve_profile(params, None, [foreign, smoke])[0].profile == "smoke"


def test_rollout_says_which_profile_it_found(params, tmp_path, capsys):
    """The README's `orbis2 rollout` after a smoke run, params.yaml saying default: the checkpoints decide."""
    tok = tokenizer(tmp_path / "t.pt", "smoke")
    with pytest.raises(SystemExit) as end:
        main(["rollout", "--video", str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "o.mp4"),
              "--params", str(params), "--detail-tokenizer", str(tok), "--abstract-tokenizer", str(tok),
              "--abstract-predictor", str(predictor(tmp_path / "a.pt", "smoke")),
              "--detail-predictor", str(predictor(tmp_path / "d.pt", "smoke", "detail", subgoal_shift=True))])
    err = capsys.readouterr().err
    assert end.value.code == 2 and f"orbis2 rollout: profile smoke (as {tok} says; {params} says default)" in err
    assert "missing.mp4" in err  # then the video, read at the smoke profile's size


def test_a_stage_run_by_hand_takes_the_profile_of_its_shards(params, tmp_path):
    """`python stages/<stage>.py` without --profile in a smoke project whose params.yaml says default."""
    shards = tmp_path / "shards"
    shards.mkdir()
    manifest(shards / "manifest.json", 128, 72)
    code = ("import argparse, sys\nfrom orbis2.interfaces import INTERFACES\nfrom orbis2.stage import open_stage\n"
            f"args = argparse.Namespace(params={str(params)!r}, profile=None, shards={str(shards)!r})\n"
            "with open_stage('latents', args, INTERFACES['latents']) as s:\n"
            "    s.summary = s.cfg.profile\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "ORBIS2_SYSTEM_METRICS": "0",
           "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f"[latents] profile smoke (as {shards / 'manifest.json'} says; {params} says default)" in proc.stderr
    assert "[latents] smoke (" in proc.stdout
