"""MLflow runs of killed stages do not stay RUNNING."""

import os
import subprocess
import sys

from conftest import ROOT

VICTIM = """
import os, signal
from orbis2.tracking import stage_run
with stage_run("victim", {"a": 1}) as run:
    print(run.run_id, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_killed_stage_run_is_marked_killed_by_the_next_start(tmp_path, monkeypatch):
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}", "ORBIS2_PIPELINE_ID": "p1",
           "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-c", VICTIM], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert proc.returncode == -9, proc.stderr
    victim = proc.stdout.split()[-1]
    for key in ("MLFLOW_TRACKING_URI", "ORBIS2_PIPELINE_ID"):
        monkeypatch.setenv(key, env[key])
    from mlflow.tracking import MlflowClient

    from orbis2.tracking import mark_killed_runs, stage_run

    client = MlflowClient(env["MLFLOW_TRACKING_URI"])
    assert client.get_run(victim).info.status == "RUNNING"  # nobody could end it
    with stage_run("next", {}) as run:
        assert client.get_run(victim).info.status == "KILLED"
        assert mark_killed_runs(client, client.get_run(run.run_id).info.experiment_id) == []  # live runs stay
        assert client.get_run(run.run_id).info.status == "RUNNING"
    assert client.get_run(run.run_id).info.status == "FINISHED"
