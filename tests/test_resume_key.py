"""The resume key of a training stage covers params, input files and code, and nothing else."""

import dataclasses

import pytest

from orbis2 import stage
from orbis2.errors import OrbisError
from orbis2.sources import code_version, module_closure, source_digest
from orbis2.stage import work_dir

from conftest import ROOT

SCRIPT = "stages/predictor.py"


def with_train(cfg, section, **changes):
    sec = cfg.section(section)
    changed = dataclasses.replace(sec, train=dataclasses.replace(sec.train, **changes))
    return cfg.with_section(section, changed)


def test_key_ignores_bookkeeping_but_not_the_trajectory(smoke_cfg, tmp_path):
    manifest = tmp_path / "manifest.json"
    manifest.write_text('{"train": "abc"}')
    inputs = {"shards": manifest}
    base = work_dir("tokenizer_detail", smoke_cfg, ["data", "tokenizer_detail"], inputs, SCRIPT)
    cadence = with_train(smoke_cfg, "tokenizer_detail", checkpoint_every=3, log_every=1, eval_every=0)
    assert work_dir("tokenizer_detail", cadence, ["data", "tokenizer_detail"], inputs, SCRIPT) == base
    other_lr = with_train(smoke_cfg, "tokenizer_detail", lr=0.5)
    assert work_dir("tokenizer_detail", other_lr, ["data", "tokenizer_detail"], inputs, SCRIPT) != base


def test_key_follows_input_files_and_code(smoke_cfg, tmp_path, monkeypatch):
    manifest = tmp_path / "manifest.json"
    manifest.write_text('{"train": "abc"}')
    key = lambda: work_dir("abstract_df", smoke_cfg, ["data", "abstract_df"], {"latents": manifest},  # noqa: E731
                           SCRIPT)
    before = key()
    manifest.write_text('{"train": "new data"}')
    after_data = key()
    assert after_data != before
    monkeypatch.setattr(stage, "code_version", lambda script: "a bug fix")
    assert key() != after_data
    with pytest.raises(OrbisError, match="missing.json: not found"):
        work_dir("abstract_df", smoke_cfg, ["data"], {"latents": tmp_path / "missing.json"}, SCRIPT)


MODEL = '''"""A model."""

import torch


class Net(torch.nn.Module):
    """Two layers."""

    def forward(self, x):
        if x.isnan().any():
            raise ValueError(f"NaN input of shape {x.shape}")
        print(f"forward {x.shape}", flush=True)
        return torch.tanh(x) * 2.0
'''


def files(tmp_path, model: str) -> list:
    (tmp_path / "pkg" / "sub").mkdir(parents=True, exist_ok=True)
    (tmp_path / "pkg" / "sub" / "net.py").write_text(model)
    (tmp_path / "pkg" / "a.py").write_text("x = 1\n")
    return [tmp_path / "pkg" / "sub" / "net.py", tmp_path / "pkg" / "a.py"]


def key_of(tmp_path, model: str) -> str:
    return source_digest(files(tmp_path, model))


@pytest.mark.parametrize("change", [
    ('"""Two layers."""', '"""Two layers, documented better."""'),  # a docstring
    ('"""A model."""\n', ""),  # the module's docstring, gone
    ("return torch.tanh(x) * 2.0", "return torch.tanh(x) * 2.0  # scaled, as the paper does"),  # a comment
    ('print(f"forward {x.shape}", flush=True)', 'print(f"forward pass on {x.shape}",\n              flush=True)'),
    ('f"NaN input of shape {x.shape}"', 'f"the input holds NaN (shape {x.shape}); check the data"'),  # a message
])
def test_a_change_to_docs_comments_or_messages_keeps_the_key(tmp_path, change):
    before = key_of(tmp_path, MODEL)
    assert MODEL.count(change[0]) == 1
    assert key_of(tmp_path, MODEL.replace(*change)) == before


@pytest.mark.parametrize("change", [
    ("* 2.0", "* 3.0"),  # a constant
    ("torch.tanh(x)", "torch.sigmoid(x)"),  # the model
    ("x.isnan().any()", "x.isinf().any()"),  # a condition, even one that only raises
    ("{x.shape}\", flush", "{x.sum().item()}\", flush"),  # an expression inside a message is code
])
def test_a_change_to_what_the_code_computes_changes_the_key(tmp_path, change):
    before = key_of(tmp_path, MODEL)
    assert MODEL.count(change[0]) == 1
    assert key_of(tmp_path, MODEL.replace(*change)) != before

def test_a_change_to_any_of_the_files_changes_the_key(tmp_path):
    paths = files(tmp_path, MODEL)
    before = source_digest(paths)
    (tmp_path / "pkg" / "a.py").write_text("x = 2\n")
    assert source_digest(paths) != before


def test_the_code_key_covers_the_modules_a_stage_imports_and_no_other():
    """A training stage's key follows its script's import graph (the DAG's): the model, the loop, the losses,
    but not the evaluations or the reports, whose fixes must not restart a training run."""
    closure = module_closure(ROOT / SCRIPT)
    names = {str(f.relative_to(ROOT)) for f in closure}
    assert {SCRIPT, "src/orbis2/train.py", "src/orbis2/tasks/predictors.py", "src/orbis2/models/stdit.py",
            "src/orbis2/flow.py", "src/orbis2/latents.py"} <= names
    assert not [name for name in names if name.startswith(("src/orbis2/eval/", "src/orbis2/rollout.py"))]
    assert code_version(SCRIPT) == code_version(ROOT / SCRIPT) == source_digest(closure)
    assert len(code_version(SCRIPT)) == 64
