"""MLflow tracking across processes: one parent per invocation, a race-free fresh store,
a parent that stays FAILED, inputs, models and provenance tags."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from orbis2.tracking import StageRun, dataset_context, invocation_key, store_lock

SRC = Path(__file__).resolve().parents[1] / "src"

STAGE = """
import sys
from pathlib import Path
from orbis2.stage import freeze_imports
from orbis2.tracking import stage_run
stage, fail = sys.argv[1], sys.argv[2] == "fail"
with stage_run(stage, {"profile": "smoke", "data": {"fps": 10}},
               {"profile": "smoke", "data": {"fps": 10}, "evaluation": {"seed": 3}}) as run:
    freeze_imports()  # as a stage does (orbis2.stage.open_stage): the process's exit walks less
    run.log_metrics({"x": 1.0})
    if Path("model").is_dir():
        run.log_model(Path("model"), {"val_loss": 0.25})
    if Path("summary.md").is_file():
        run.publish(Path("summary.md"))
        run.publish(Path("summary.md"), "gallery", "renamed.md")
        run.publish_metrics({"main_table/hierarchical/fvd_heldout": 12.5})
        run.publish_tags({"claim 1": "holds: x"})
    if fail:
        raise RuntimeError("stage failed on purpose")
"""


def start(cwd: Path, stage: str, invocation: str, fail: bool = False) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(SRC), "ORBIS2_PIPELINE_ID": invocation, "ORBIS2_SYSTEM_METRICS": "0",
           "MLFLOW_TRACKING_URI": f"sqlite:///{cwd / 'mlflow.db'}"}
    env.pop("SLURM_JOB_ID", None)
    return subprocess.Popen([sys.executable, "-c", STAGE, stage, "fail" if fail else "ok"], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(proc: subprocess.Popen, ok: bool = True) -> None:
    out, err = proc.communicate(timeout=600)
    assert (proc.returncode == 0) == ok, err[-3000:]


def runs(cwd: Path) -> list:
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{cwd / 'mlflow.db'}")
    experiment = client.get_experiment_by_name("orbis2")
    return client.search_runs([experiment.experiment_id], max_results=100)


def test_stages_started_together_on_a_fresh_store_share_one_parent(tmp_path):
    (tmp_path / "data/shards").mkdir(parents=True)
    (tmp_path / "data/shards/manifest.json").write_text(json.dumps({"splits": {}}))
    procs = [start(tmp_path, f"stage{i}", "inv-a") for i in range(4)]
    for proc in procs:
        finish(proc)
    found = runs(tmp_path)
    parents = [r for r in found if "mlflow.parentRunId" not in r.data.tags]
    children = [r for r in found if "mlflow.parentRunId" in r.data.tags]
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    assert sorted(r.info.run_name for r in children) == [f"stage{i}" for i in range(4)]
    assert {r.data.tags["mlflow.parentRunId"] for r in children} == {parents[0].info.run_id}
    tags = children[0].data.tags
    assert tags["orbis2.profile"] == "smoke" and len(tags["orbis2.params_sha256"]) == 64
    assert len(tags["orbis2.shards_sha256"]) == 64 and "orbis2.slurm_job_id" not in tags
    assert children[0].inputs.dataset_inputs[0].dataset.digest == tags["orbis2.shards_sha256"][:36]

    finish(start(tmp_path, "other", "inv-b"))  # another invocation: another parent
    assert len([r for r in runs(tmp_path) if "mlflow.parentRunId" not in r.data.tags]) == 2


def test_parent_stays_failed_after_a_later_success(tmp_path):
    finish(start(tmp_path, "broken", "inv", fail=True), ok=False)
    finish(start(tmp_path, "fine", "inv"))
    parent = [r for r in runs(tmp_path) if "mlflow.parentRunId" not in r.data.tags]
    assert [r.info.status for r in parent] == ["FAILED"]


def test_trained_model_is_logged_with_its_config(tmp_path):
    (tmp_path / "data/shards").mkdir(parents=True)
    (tmp_path / "data/shards/manifest.json").write_text(json.dumps({"splits": {}}))
    (tmp_path / "model").mkdir()
    (tmp_path / "model/weights.pt").write_bytes(b"\x00" * 64)
    finish(start(tmp_path, "trainer", "inv"))
    from mlflow.artifacts import download_artifacts
    from mlflow.tracking import MlflowClient

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    models = client.search_logged_models([client.get_experiment_by_name("orbis2").experiment_id])
    assert [m.name for m in models] == ["trainer"] and models[0].params["data.fps"] == "10"
    [stage] = [r for r in runs(tmp_path) if "mlflow.parentRunId" in r.data.tags]
    assert models[0].source_run_id == stage.info.run_id
    local = Path(download_artifacts(models[0].artifact_location, dst_path=str(tmp_path / "dl"), tracking_uri=uri))
    assert (local / "weights.pt").stat().st_size == 64
    assert json.loads((local / "config.json").read_text())["data"] == {"fps": 10}
    run = client.get_run(stage.info.run_id)  # listed on its run, with its metrics and training data
    assert [o.model_id for o in run.outputs.model_outputs] == [models[0].model_id]
    [metric] = client.get_logged_model(models[0].model_id).metrics
    digest = stage.data.tags["orbis2.shards_sha256"][:36]
    assert (metric.key, metric.value, metric.dataset_digest) == ("val_loss", 0.25, digest)


def test_invocation_key_under_dvc_names_the_call(tmp_path, monkeypatch):
    monkeypatch.delenv("ORBIS2_PIPELINE_ID", raising=False)
    monkeypatch.setenv("DVC_ROOT", str(tmp_path))
    lock = tmp_path / ".dvc/tmp/lock"
    lock.parent.mkdir(parents=True)
    lock.write_text(f" {os.getpid()}\n")  # DVC's own pid, as zc.lockfile writes it
    first = invocation_key()
    lock.write_text(f" {os.getpid()}\n")  # DVC rewrites the lock between stages of one call
    assert first == invocation_key() and f":{os.getpid()}:" in first
    lock.write_text(f" {os.getppid()}\n")  # another call
    assert invocation_key() != first
    monkeypatch.setenv("ORBIS2_PIPELINE_ID", "given")
    assert invocation_key() == "given"


@pytest.mark.parametrize("uri, lock", [("sqlite:///mlflow.db", "mlflow.db.lock"),
                                       ("sqlite:////abs/store.db", "/abs/store.db.lock")])
def test_sqlite_store_lock_sits_next_to_the_database(uri, lock):
    assert store_lock(uri).lock_file == str(Path(lock).absolute())


def test_parent_run_carries_the_headline(tmp_path):
    """The parent is what a reviewer opens: profile, params digest, commit, stage times, what stages publish."""
    (tmp_path / "summary.md").write_text("# Summary\n")
    finish(start(tmp_path, "report_main", "inv"))
    from mlflow.artifacts import download_artifacts
    from mlflow.tracking import MlflowClient

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name("orbis2")
    assert experiment.tags["mlflow.experimentKind"] == "custom_model_development"  # opens on runs, not GenAI
    [parent] = [r for r in runs(tmp_path) if "mlflow.parentRunId" not in r.data.tags]
    assert parent.info.run_name.startswith("pipeline smoke ")
    assert parent.data.params["profile"] == "smoke" and parent.data.params["git_commit"] == "unknown"
    assert len(parent.data.params["params_sha256"]) == 12 and "orbis2.params_sha256" not in parent.data.tags
    assert parent.data.metrics["main_table/hierarchical/fvd_heldout"] == 12.5
    assert parent.data.tags["claim 1"] == "holds: x"
    names = {f.path for f in client.list_artifacts(parent.info.run_id)}
    assert names == {"summary.md", "gallery", "params.json"}
    assert [f.path for f in client.list_artifacts(parent.info.run_id, "gallery")] == ["gallery/renamed.md"]
    config = json.loads(Path(download_artifacts(run_id=parent.info.run_id, artifact_path="params.json",
                                                dst_path=str(tmp_path / "dl"), tracking_uri=uri)).read_text())
    assert config["evaluation"] == {"seed": 3}  # the whole config, not only the first stage's sections


def test_stage_times_are_collected_for_the_parent(tmp_path):
    import subprocess as sp
    from types import SimpleNamespace

    from mlflow.tracking import MlflowClient

    env = {**os.environ, "PYTHONPATH": str(SRC), "ORBIS2_PIPELINE_ID": "inv", "ORBIS2_SYSTEM_METRICS": "0",
           "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}
    (tmp_path / "params.yaml").write_text((Path(__file__).resolve().parents[1] / "params.yaml").read_text())
    code = ("import argparse\nfrom orbis2.interfaces import INTERFACES\nfrom orbis2.stage import open_stage\n"
            "with open_stage('timed', argparse.Namespace(params='params.yaml', profile='smoke'), "
            "INTERFACES['shards']) as s:\n"
            "    s.summary = 'ok'\n")
    proc = sp.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    [parent] = [r for r in runs(tmp_path) if "mlflow.parentRunId" not in r.data.tags]
    [child] = [r for r in runs(tmp_path) if "mlflow.parentRunId" in r.data.tags]
    assert not parent.data.metrics  # the parent's metrics are the report's headline only
    assert child.data.metrics["wall_seconds"] > 0
    store = SimpleNamespace(MlflowClient=lambda: MlflowClient(tracking_uri=env["MLFLOW_TRACKING_URI"]))
    logger = StageRun(store, child.info.run_id, "report_main", parent_id=parent.info.run_id)
    assert logger.stage_times() == {"timed": child.data.metrics["wall_seconds"]}


@pytest.mark.parametrize("stage, context", [("tokenizer_detail", "training"), ("predictor_top", "training"),
                                            ("inverse_dynamics", "training"), ("eval_fvd_hierarchical", "evaluation"),
                                            ("eval_steering", "evaluation"), ("latents_compressed", "inference")])
def test_dataset_context_says_what_a_stage_does_with_the_shards(stage, context):
    assert dataset_context(stage) == context


def test_a_moved_store_finds_its_artifacts(tmp_path):
    """MLflow records absolute artifact paths; `python -m orbis2.tracking relocate` re-points a moved store."""
    from mlflow.artifacts import download_artifacts
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    old, new = tmp_path / "project", tmp_path / "moved" / "project"
    old.mkdir()
    (old / "summary.md").write_text("# Summary\n")
    (old / "model").mkdir()
    (old / "model/weights.pt").write_bytes(b"\x01" * 32)
    finish(start(old, "report_main", "inv"))
    new.parent.mkdir()
    old.rename(new)
    assert not old.exists()

    uri = f"sqlite:///{new / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    [parent] = [r for r in runs(new) if "mlflow.parentRunId" not in r.data.tags]
    with pytest.raises((OSError, MlflowException)):  # the store still names the old folder
        download_artifacts(run_id=parent.info.run_id, artifact_path="summary.md", dst_path=str(tmp_path / "dl0"),
                           tracking_uri=uri)

    env = {**os.environ, "PYTHONPATH": str(SRC)}
    env.pop("MLFLOW_TRACKING_URI", None)
    proc = subprocess.run([sys.executable, "-m", "orbis2.tracking", "relocate"], cwd=new, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and f"re-pointed from {old} to {new}" in proc.stdout, proc.stderr[-2000:]
    summary = download_artifacts(run_id=parent.info.run_id, artifact_path="summary.md",
                                 dst_path=str(tmp_path / "dl1"), tracking_uri=uri)
    assert Path(summary).read_text() == "# Summary\n"
    [model] = client.search_logged_models([client.get_experiment_by_name("orbis2").experiment_id])
    weights = Path(download_artifacts(model.artifact_location, dst_path=str(tmp_path / "dl2"), tracking_uri=uri))
    assert (weights / "weights.pt").read_bytes() == b"\x01" * 32
    assert all(str(new) in r.info.artifact_uri for r in runs(new))
    assert not old.exists()  # nothing was written at the old place

    proc = subprocess.run([sys.executable, "-m", "orbis2.tracking", "relocate"], cwd=new, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and "already point here" in proc.stdout


def test_relocate_names_a_missing_store(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    proc = subprocess.run([sys.executable, "-m", "orbis2.tracking", "relocate", "--store",
                           f"sqlite:///{tmp_path / 'nowhere.db'}"], env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 2 and "nowhere.db: no such store" in proc.stderr


def test_a_stage_in_a_moved_project_repoints_the_store(tmp_path):
    """A stage started in a moved project writes into it, not into the old folder, and finds the old runs too."""
    from mlflow.artifacts import download_artifacts

    old, new = tmp_path / "project", tmp_path / "elsewhere"
    old.mkdir()
    (old / "summary.md").write_text("# Summary\n")
    finish(start(old, "report_main", "inv"))
    old.rename(new)
    finish(start(new, "next", "inv-2"))
    assert not old.exists()
    assert all(r.info.artifact_uri.startswith((f"{new}/", f"{new.as_uri()}/")) for r in runs(new))  # path or URI
    first = next(r for r in runs(new) if r.info.run_name == "report_main")
    assert Path(download_artifacts(run_id=first.data.tags["mlflow.parentRunId"], artifact_path="summary.md",
                                   dst_path=str(tmp_path / "dl"), tracking_uri=f"sqlite:///{new / 'mlflow.db'}")
                ).read_text() == "# Summary\n"


def test_a_stage_run_does_not_import_ipython(tmp_path):
    """MLflow asks IPython whether a run starts in a notebook, importing it (0.4 s of every stage) where it is
    installed; a stage's process is not in one (orbis2.tracking._not_a_notebook)."""
    pytest.importorskip("IPython")
    probe = ("import sys\nfrom orbis2.tracking import stage_run\nwith stage_run('probe', {'profile': 'smoke'}):\n"
             "    pass\nprint('IPython' in sys.modules)\n")
    env = {**os.environ, "PYTHONPATH": str(SRC), "ORBIS2_PIPELINE_ID": "inv-ipython", "ORBIS2_SYSTEM_METRICS": "0",
           "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}
    done = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "False"
    assert [r.info.status for r in runs(tmp_path) if r.info.run_name == "probe"] == ["FINISHED"]
