"""MLflow tracking: one run per stage, nested under one parent run per pipeline invocation.

The store is ``sqlite:///mlflow.db`` unless ``MLFLOW_TRACKING_URI`` says otherwise;
the experiment is ``orbis2`` unless ``MLFLOW_EXPERIMENT_NAME`` says otherwise.

A *pipeline invocation* is one ``snakemake`` or ``dvc repro`` call. Stages are
separate processes started by it, so they find their common parent through an
invocation key (:func:`invocation_key`). The first stage of an invocation
creates the parent; later ones reuse it.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import socket
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

from orbis2.config import flatten

DEFAULT_TRACKING_URI = "sqlite:///mlflow.db"
INVOCATION_TAG = "orbis2.invocation"
OWNER_TAG = "orbis2.process"  # the process that set the run RUNNING (see process_key)


PIPELINE_TOOLS = ("snakemake", "dvc")


def invocation_key() -> str:
    """Identify the pipeline invocation this stage belongs to.

    ``ORBIS2_PIPELINE_ID`` if set; else the nearest ancestor process that is
    ``snakemake`` or ``dvc`` (pid and start time, so a reused pid is a new key);
    else this process's group (a stage run by hand is its own pipeline).
    """
    explicit = os.environ.get("ORBIS2_PIPELINE_ID")
    if explicit:
        return explicit
    pid = os.getppid()
    while pid > 1:
        stat = _proc_stat(pid)
        if stat is None:
            break
        if set(PIPELINE_TOOLS) & _proc_programs(pid):
            return f"{socket.gethostname()}:{pid}:{stat[19]}"
        pid = int(stat[1])
    pgid = os.getpgid(0)
    stat = _proc_stat(pgid)
    return f"{socket.gethostname()}:pg{pgid}:{stat[19] if stat else ''}"


def _proc_stat(pid: int) -> list[str] | None:
    """Fields of /proc/<pid>/stat after the command name (state, ppid, ..., starttime at 19)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _proc_programs(pid: int) -> set[str]:
    """Base names of a process's program and first argument (``python .../snakemake`` -> both)."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[:2]
    except OSError:
        return set()
    return {Path(a.decode(errors="replace")).name for a in argv}


class StageRun:
    """What a stage logs: metrics per step and artifacts. Without an MLflow module
    (ranks other than 0 under torchrun) every call does nothing."""

    def __init__(self, mlflow_module: Any | None, run_id: str | None):
        self._mlflow = mlflow_module
        self.run_id = run_id

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        if self._mlflow:
            self._mlflow.log_metrics({k: float(v) for k, v in metrics.items()}, step=step)

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None:
        if self._mlflow:
            self._mlflow.log_artifact(str(path), artifact_path)


@contextlib.contextmanager
def stage_run(stage: str, params: dict[str, Any]) -> Iterator[StageRun]:
    """Open the stage's MLflow run (nested under the invocation's parent) for the block.

    Under torchrun only rank 0 logs; the other ranks get a :class:`StageRun` that does nothing.
    """
    if int(os.environ.get("RANK", "0")) != 0:
        yield StageRun(None, None)
        return
    import mlflow
    from mlflow.tracking import MlflowClient

    uri = os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_TRACKING_URI)
    mlflow.set_tracking_uri(uri)
    experiment = mlflow.set_experiment(os.environ.get("MLFLOW_EXPERIMENT_NAME", "orbis2"))
    client = MlflowClient()
    mark_killed_runs(client, experiment.experiment_id)
    parent_id = _parent_run(client, experiment.experiment_id)
    client.update_run(parent_id, status="RUNNING")
    owner = {OWNER_TAG: key} if (key := process_key(os.getpid())) else {}  # no /proc: not tracked
    if owner:
        client.set_tag(parent_id, OWNER_TAG, key)
    status = "FAILED"
    with mlflow.start_run(run_name=stage, parent_run_id=parent_id, nested=True,
                          tags={"orbis2.stage": stage, **owner}) as run:
        flat = {k: str(v)[:6000] for k, v in flatten(params).items()}
        for start in range(0, len(flat), 100):  # MLflow limits one batch to 100 params
            mlflow.log_params(dict(list(flat.items())[start:start + 100]))
        try:
            yield StageRun(mlflow, run.info.run_id)
            status = "FINISHED"
        finally:
            mlflow.end_run(status=status)
            client.set_terminated(parent_id, status=status)


def process_key(pid: int) -> str | None:
    """``host:pid:start time``: names one process for good (a reused pid has another start time)."""
    stat = _proc_stat(pid)
    return None if stat is None else f"{socket.gethostname()}:{pid}:{stat[19]}"


def mark_killed_runs(client: Any, experiment_id: str) -> list[str]:
    """End as KILLED every RUNNING run whose process, on this host, is gone; returns their ids.

    A stage killed with SIGKILL (or by a power cut) cannot end its own run, which
    would then show as running for ever; the next stage to start ends it.
    """
    killed = []
    host = socket.gethostname()
    for run in client.search_runs([experiment_id], filter_string="attributes.status = 'RUNNING'", max_results=1000):
        owner = run.data.tags.get(OWNER_TAG, "")
        parts = owner.rsplit(":", 2)
        if len(parts) != 3 or parts[0] != host or not parts[1].isdigit():
            continue
        if process_key(int(parts[1])) != owner:
            client.set_terminated(run.info.run_id, status="KILLED")
            killed.append(run.info.run_id)
    return killed


def _parent_run(client: Any, experiment_id: str) -> str:
    key = invocation_key()
    lock = Path(tempfile.gettempdir()) / f"orbis2-{hashlib.sha1(key.encode()).hexdigest()[:16]}.lock"
    with open(lock, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)  # stages running in parallel must share one parent
        found = client.search_runs([experiment_id], filter_string=f"tags.`{INVOCATION_TAG}` = '{key}'",
                                   max_results=1)
        if found:
            return found[0].info.run_id
        run = client.create_run(experiment_id, run_name=f"pipeline {time.strftime('%Y-%m-%d %H:%M:%S')}",
                                tags={INVOCATION_TAG: key, "orbis2.pipeline": "true"})
        return run.info.run_id
