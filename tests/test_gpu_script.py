"""The GPU measurement script rehearsed on the CPU (REHEARSE=1: every part, smoke preset, compiled through dynamo
and AOTAutograd but not inductor's CPU code, which is not what runs on a GPU), so the first minutes on a GPU measure
instead of debugging; and what it carries there fits what the machine accepts."""

import json
import os
import subprocess
import sys
import tarfile

import pytest
import yaml

from orbis2.config.params import load_config

from conftest import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
from gpu_suite import carried_files, scaled_params  # noqa: E402

sys.path.insert(0, str(ROOT / "tools"))
from wheelhouse_filter import filter_wheelhouse, provided  # noqa: E402

PARTS = ("peak", "forwards", "rollouts", "train", "graphs", "rollouts_eager", "toggles", "rollouts_v1", "dag")


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


def test_the_wheelhouse_keeps_only_what_the_gpu_image_lacks(tmp_path):
    have = provided(ROOT / "tools" / "gpu_image_packages.txt")
    assert {"torch", "numpy", "opencv-python-headless", "pyyaml", "pillow"} <= have
    for name in ("torch-2.11.0-cp312-cp312-linux_x86_64.whl", "PyYAML-6.0-cp312-cp312-manylinux2014_x86_64.whl",
                 "typing_extensions-4.16.0-py3-none-any.whl", "mlflow_skinny-3.17.2-py3-none-any.whl",
                 "snakemake-9.27.1-py3-none-any.whl"):
        (tmp_path / name).write_bytes(b"x" * 1000)
    removed, left = filter_wheelhouse(tmp_path, have)
    assert sorted(removed) == ["PyYAML-6.0-cp312-cp312-manylinux2014_x86_64.whl",
                               "torch-2.11.0-cp312-cp312-linux_x86_64.whl", "typing_extensions-4.16.0-py3-none-any.whl"]
    assert left == 2000 and sorted(p.name for p in tmp_path.iterdir()) == [
        "mlflow_skinny-3.17.2-py3-none-any.whl", "snakemake-9.27.1-py3-none-any.whl"]


def test_the_repository_carried_to_the_gpu_machine_leaves_room_for_the_wheelhouse():
    """The machine accepts 64 MiB; the script's limit is 60; the DAG part's wheelhouse measured 21.5 MiB
    (tools/build_wheelhouse.sh), so the repository must stay under 60 - 22 MiB."""
    repository, _ = carried_files(ROOT)
    assert repository / 2**20 < 38, repository / 2**20


@pytest.mark.slow
def test_the_gpu_script_rehearses_every_part_on_the_cpu(tmp_path):
    out = tmp_path / "out"
    env = {**os.environ, "REHEARSE": "1", "OUT": str(out), "PYTHON": sys.executable,
           "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "inductor")}
    done = subprocess.run(["bash", "tools/gpu_run.sh"], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=1500)
    assert done.returncode == 0, done.stderr[-2000:]
    # Exactly two files under $OUT, all the machine needs to return: the summary and one archive of everything.
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == ["results.tar.gz", "summary.json"]
    with tarfile.open(out / "results.tar.gz") as archive:
        names = set(archive.getnames())
        archive.extractall(tmp_path / "back", filter="data")
    assert {f"work/{part}.json" for part in PARTS} <= names and "work/gpu_run.log" in names
    summary = json.loads((out / "summary.json").read_text())
    parts = summary["parts"]
    assert set(PARTS) | {"carried"} == set(parts)
    failed = {name: (tmp_path / "back" / "work" / f"{name}.txt").read_text()[-1500:] for name, part in parts.items()
              if name != "carried" and part.get("exit") != 0}
    assert not failed, failed
    assert parts["carried"]["carried_mib"] < parts["carried"]["limit_mib"] == 60
    assert parts["peak"]["matmul_tflops_measured"] > 0
    for name in ("detail", "abstract", "cached", "flat"):
        assert parts["forwards"]["forwards"][name]["median_ms"] > 0 and parts["forwards"]["forwards"][name]["kernels"]
    hierarchy = {"hierarchical", "distilled"}
    for part, systems in (("rollouts", hierarchy), ("rollouts_eager", hierarchy),
                          ("rollouts_v1", {"flat_detail", "v1_style"})):
        assert set(parts[part]["systems"]) == systems
        assert all(run["fps"] > 0 for run in parts[part]["systems"].values()), parts[part]
    assert all(run["compile_s"] > 0 for run in parts["rollouts"]["systems"].values())  # compiled
    assert json.loads((tmp_path / "back" / "work" / "rollouts.json").read_text())["compile"] == "eager"
    assert {run["model"] for run in parts["train"]["runs"]} == {"abstract", "detail"}
    assert all(run["mfu_measured_matmul"] > 0 for run in parts["train"]["runs"])
    assert parts["graphs"]["host_syncs"] == []  # nothing in the detail forward would stop a CUDA-graph capture
    toggles = parts["toggles"]
    assert toggles["kv_cache"]["max_abs_diff"] < 1e-4 and toggles["bf16"]["equal"]  # bf16 is CUDA-only
    assert toggles["compile"] == {"skipped": "--no-compile"}  # rehearsed by the rollouts part
    assert parts["dag"]["exit"] == 0
