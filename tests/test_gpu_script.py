"""The GPU measurement script runs its every part on the CPU (DRY=1, smoke preset), so it cannot rot unseen."""

import json
import os
import subprocess
import sys

import pytest
import yaml

from orbis2.config.params import load_config

from conftest import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
from gpu_suite import scaled_params  # noqa: E402

PARTS = ("peak", "forwards", "toggles", "graphs", "rollouts", "train", "dag")


def test_the_scaled_gpu_profile_is_valid_and_short(tmp_path):
    params = scaled_params(yaml.safe_load((ROOT / "params.yaml").read_text()), "gpu", 3)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    scaled, full = load_config(tmp_path / "params.yaml", "gpu"), load_config(ROOT / "params.yaml", "gpu")
    for stage in ("abstract_df", "detail", "action", "detail_distill", "tokenizer_detail"):
        train = scaled.section(stage).train
        assert train.steps == 3 and train.eval_every == 3 and train.batch_size <= 8
        assert scaled.section(stage).preset == full.section(stage).preset  # the gpu profile's networks
    assert scaled.data == full.data  # its resolution
    assert scaled.section("town").episodes == load_config(ROOT / "params.yaml", "smoke").section("town").episodes


@pytest.mark.slow
def test_the_gpu_script_runs_every_part_on_the_cpu(tmp_path):
    out = tmp_path / "out"
    env = {**os.environ, "DRY": "1", "OUT": str(out), "PYTHON": sys.executable}
    done = subprocess.run(["bash", "tools/gpu_run.sh"], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=900)
    assert done.returncode == 0, done.stderr[-2000:]
    steps = {row["step"]: row for row in map(json.loads, (out / "steps.jsonl").read_text().splitlines())}
    assert set(steps) == set(PARTS)
    failed = {name: (out / f"{name}.txt").read_text()[-1500:] for name, row in steps.items() if row["exit"] != 0}
    assert not failed, failed
    forwards = json.loads((out / "forwards.json").read_text())
    for name in ("detail", "abstract", "cached", "flat"):
        assert forwards[name]["median_ms"] > 0 and forwards[name]["kernels"]["count"] > 0
    toggles = json.loads((out / "toggles.json").read_text())
    assert toggles["kv_cache"]["max_abs_diff"] < 1e-4 and toggles["bf16"]["equal"]  # bf16 is CUDA-only
    train = json.loads((out / "train.json").read_text())
    assert {run["model"] for run in train["runs"]} == {"abstract", "detail"}
    assert all(run["mfu_measured_matmul"] > 0 for run in train["runs"])
    assert json.loads((out / "rollouts.json").read_text())
    assert json.loads((out / "dag.json").read_text())["exit"] == 0
