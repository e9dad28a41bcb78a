"""The resume key of a training stage covers params, input files and code, and nothing else."""

import dataclasses

import pytest

from orbis2 import stage
from orbis2.errors import OrbisError
from orbis2.stage import code_version, work_dir


def with_train(cfg, section, **changes):
    sec = cfg.section(section)
    changed = dataclasses.replace(sec, train=dataclasses.replace(sec.train, **changes))
    return cfg.with_section(section, changed)


def test_key_ignores_bookkeeping_but_not_the_trajectory(smoke_cfg, tmp_path):
    manifest = tmp_path / "manifest.json"
    manifest.write_text('{"train": "abc"}')
    inputs = {"shards": manifest}
    base = work_dir("tokenizer_detail", smoke_cfg, ["data", "tokenizer_detail"], inputs)
    cadence = with_train(smoke_cfg, "tokenizer_detail", checkpoint_every=3, log_every=1, eval_every=0)
    assert work_dir("tokenizer_detail", cadence, ["data", "tokenizer_detail"], inputs) == base
    other_lr = with_train(smoke_cfg, "tokenizer_detail", lr=0.5)
    assert work_dir("tokenizer_detail", other_lr, ["data", "tokenizer_detail"], inputs) != base


def test_key_follows_input_files_and_code(smoke_cfg, tmp_path, monkeypatch):
    manifest = tmp_path / "manifest.json"
    manifest.write_text('{"train": "abc"}')
    key = lambda: work_dir("abstract_df", smoke_cfg, ["data", "abstract_df"], {"latents": manifest})  # noqa: E731
    before = key()
    manifest.write_text('{"train": "new data"}')
    after_data = key()
    assert after_data != before
    monkeypatch.setattr(stage, "code_version", lambda: "a bug fix")
    assert key() != after_data
    with pytest.raises(OrbisError, match="missing.json: not found"):
        work_dir("abstract_df", smoke_cfg, ["data"], {"latents": tmp_path / "missing.json"})


def test_code_version_hashes_every_module(tmp_path):
    (tmp_path / "pkg" / "sub").mkdir(parents=True)
    (tmp_path / "pkg" / "a.py").write_text("x = 1\n")
    (tmp_path / "pkg" / "sub" / "b.py").write_text("y = 2\n")
    first = code_version(tmp_path / "pkg")
    (tmp_path / "pkg" / "sub" / "b.py").write_text("y = 3\n")
    assert code_version.__wrapped__(tmp_path / "pkg") != first
    assert len(code_version()) == 64
