"""Opt-in: the smoke DAG up to the shards through Slurm (profiles/slurm-local), in a fresh project copy, the
town and the shards in two parts each (two Slurm jobs side by side, then the gather).

Skipped unless ``sinfo`` answers (``tools/slurm_local.sh start`` sets up a one-node cluster).
On a multi-node cluster set ``ORBIS2_SLURM_TEST_DIR`` to a folder every node sees.
Checks: every job ran as a Slurm job and its MLflow run nests under the invocation's one parent; the two parts'
shards hold the samples one part writes, in the same order.
"""

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from test_shard_parts import samples

from orbis2.config.params import load_config
from orbis2.data.shards import load_manifest, write_shards

from conftest import ROOT, project_copy, slurm_answers

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not slurm_answers(), reason="no Slurm cluster answers `sinfo`")]


def test_smoke_dag_through_slurm():
    from mlflow.tracking import MlflowClient

    with tempfile.TemporaryDirectory(dir=os.environ.get("ORBIS2_SLURM_TEST_DIR")) as tmp:
        root = project_copy(Path(tmp))
        env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "MLFLOW_TRACKING_URI": f"sqlite:///{root / 'mlflow.db'}"}
        env.pop("ORBIS2_PIPELINE_ID", None)
        proc = subprocess.run([sys.executable, "-m", "snakemake", "--profile", str(ROOT / "profiles/slurm-local"),
                               "data/shards", "--config", "profile=smoke", "parts=2"], cwd=root, env=env,
                              capture_output=True,
                              text=True, timeout=1800)
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        assert "submitted with SLURM jobid" in proc.stdout + proc.stderr

        client = MlflowClient(tracking_uri=env["MLFLOW_TRACKING_URI"])
        runs = client.search_runs([client.get_experiment_by_name("orbis2").experiment_id])
        parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
        children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
        assert len(parents) == 1 and parents[0].info.status == "FINISHED"
        assert sorted(r.info.run_name for r in children) == [
            "shards", "shards_part_0000-of-0002", "shards_part_0001-of-0002", "town", "town_part_0000-of-0002",
            "town_part_0001-of-0002"]
        assert all(r.data.tags["mlflow.parentRunId"] == parents[0].info.run_id for r in children)
        assert all(r.data.tags.get("orbis2.slurm_job_id", "").isdigit() for r in children)
        assert len({r.data.tags["orbis2.slurm_job_id"] for r in children}) == 6

        cfg = load_config(root / "params.yaml", "smoke")
        one_part = write_shards(root / "data/raw/town", Path(tmp) / "one", cfg.data, cfg.shards)
        assert samples(root / "data/shards", load_manifest(root / "data/shards")) == samples(Path(tmp) / "one",
                                                                                            one_part)
