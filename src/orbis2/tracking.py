"""MLflow tracking: one run per stage, nested under one parent run per pipeline invocation.

The store is ``sqlite:///mlflow.db`` unless ``MLFLOW_TRACKING_URI`` says otherwise;
the experiment is ``orbis2`` unless ``MLFLOW_EXPERIMENT_NAME`` says otherwise.
SQLite is for one machine: on a cluster, point ``MLFLOW_TRACKING_URI`` at a
tracking server (``mlflow server``), since SQLite locking on NFS/Lustre is unsafe.

A *pipeline invocation* is one ``snakemake`` or ``dvc repro`` call. Its stages are
separate processes, possibly on other nodes, so the invocation is named by the
orchestrator (:func:`invocation_key`) and every stage finds the parent run by
that name. The parent's status follows its children: FAILED as soon as one
stage failed, FINISHED only when every stage finished.

The parent is what a reviewer opens first, so it carries the run's headline: the
profile, commit and params digest (tags and params, set when it is created) and
whatever stages :meth:`StageRun.publish` there (the report's headline numbers,
claims, tables, intervals, stage times and summary, the figures, a rollout gallery).
The experiment is tagged as a model-development one; MLflow 3.17's UI does not read
that tag, so ``mlflow server --app-name orbis2`` (:mod:`orbis2.mlflow_app`) opens it
in model-training mode.

A SQLite store records absolute artifact locations (MLflow resolves a relative
one against the working directory when it creates an experiment), so a project
folder that moved would lose its artifacts: :func:`relocate_store` re-points them
at the folder the store now lives in. Every stage does so when it opens the store;
before ``mlflow server`` on a moved store, run ``python -m orbis2.tracking relocate``.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import shutil
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
import uuid
import warnings
from pathlib import Path
from typing import Any, Iterator
from urllib.parse import unquote, urlparse

from filelock import FileLock

from orbis2.config.params import flatten
from orbis2.errors import OrbisError, TrainingStopped

DEFAULT_TRACKING_URI = "sqlite:///mlflow.db"
PIPELINE_ENV = "ORBIS2_PIPELINE_ID"
INVOCATION_TAG = "orbis2.invocation"
SHARD_MANIFEST = Path("data/shards/manifest.json")
# Stages upstream of the shards (or beside them): they do not read the dataset.
NOT_SHARD_READERS = ("town", "import", "shards", "assets", "report_main", "report_all")
_RUN_KEY = uuid.uuid4().hex  # a stage started by hand is its own invocation
OWNER_TAG = "orbis2.process"  # the process that set the run RUNNING (see process_key)
KIND_TAG, EXPERIMENT_KIND = "mlflow.experimentKind", "custom_model_development"  # MLflow 3's "not GenAI"
# What a stage does with the shard set, as MLflow's dataset context (the others train on it).
DATASET_CONTEXTS = {"eval_": "evaluation", "latents": "inference"}


def dataset_context(stage: str) -> str:
    """``training``, ``evaluation`` (eval_* stages) or ``inference`` (the latent cache)."""
    return next((context for prefix, context in DATASET_CONTEXTS.items() if stage.startswith(prefix)), "training")


def invocation_key() -> str:
    """The name of the pipeline invocation this stage belongs to.

    1. ``ORBIS2_PIPELINE_ID``: the Snakefile sets it once per ``snakemake`` call and
       every job inherits it (on Slurm through ``sbatch --export=ALL``); set it
       yourself for ``dvc repro`` (``ORBIS2_PIPELINE_ID=$(uuidgen) dvc repro``).
    2. Under ``dvc repro`` without it: DVC writes its pid into ``.dvc/tmp/lock``
       while it runs; that pid and the process's start time name the call.
    3. Otherwise this process alone (a stage run by hand).
    """
    explicit = os.environ.get(PIPELINE_ENV)
    if explicit:
        return explicit
    if os.environ.get("DVC_ROOT"):
        lock = Path(os.environ["DVC_ROOT"]) / ".dvc" / "tmp" / "lock"
        with contextlib.suppress(OSError, ValueError):
            pid = int(lock.read_text().split()[0])
            return f"dvc:{socket.gethostname()}:{pid}:{_started(pid)}"
    return f"process:{socket.gethostname()}:{_RUN_KEY}"


def _started(pid: int) -> str:
    """A process's start time (psutil), so that a reused pid names another call; '' without psutil."""
    try:
        import psutil

        return f"{psutil.Process(pid).create_time():.3f}"
    except Exception:  # psutil missing, or the process already gone
        return ""


def store_lock(uri: str) -> FileLock:
    """A lock around store creation: next to a SQLite file, else in the temp folder (per node)."""
    path = sqlite_path(uri)
    if path is not None:
        return FileLock(str(path.absolute()) + ".lock")
    digest = hashlib.sha1(uri.encode()).hexdigest()[:16]
    return FileLock(str(Path(tempfile.gettempdir()) / f"orbis2-mlflow-{digest}.lock"))


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` store URI (relative to the working directory, as MLflow reads it);
    None for any other store, and for an in-memory one."""
    parsed = urlparse(uri)
    if parsed.scheme != "sqlite" or parsed.path in ("", "/:memory:"):
        return None
    return Path(uri[len("sqlite:///"):] if uri.startswith("sqlite:///") else parsed.path)


# Where a SQLite store keeps artifact locations: (table, column, the rows that hold one), for the tables that exist.
ARTIFACT_COLUMNS = (("experiments", "artifact_location", ""), ("runs", "artifact_uri", ""),
                    ("logged_models", "artifact_location", ""),
                    ("trace_tags", "value", "key = 'mlflow.artifactLocation'"),
                    ("model_versions", "source", ""), ("model_versions", "storage_location", ""))


def _local_path(uri: str) -> Path | None:
    parsed = urlparse(uri)
    return Path(unquote(parsed.path)) if parsed.scheme == "file" else Path(uri) if parsed.scheme == "" else None


def relocate_store(db: Path) -> tuple[str, str] | None:
    """Re-point a moved SQLite store's local artifact locations at the folder it now lives in.

    MLflow has no relative artifact locations for a SQLite store: an experiment keeps the absolute
    path (or ``file://`` URI) it was created with (``<project>/mlruns/<id>``), and every run and logged model a
    path below it. An experiment located outside ``db``'s folder whose location's tail
    (``mlruns/<id>``, or longer) exists below it says the store moved, or was copied (the original
    may still exist: the copy must not write into it); the old root is what precedes the longest such
    tail, and every location under it is rewritten under the new one, in one transaction. Returns
    (old root, new root), or None when there is nothing to re-point.
    """
    root = db.resolve().parent
    with contextlib.closing(sqlite3.connect(db)) as con:
        tables = {name for (name,) in con.execute("select name from sqlite_master where type = 'table'")}
        if "experiments" not in tables:
            raise OrbisError(f"{db}: not an MLflow store (no experiments table); pass the store's database")
        old = None
        for (location,) in con.execute("select artifact_location from experiments"):
            path = _local_path(location or "")
            if path is None or not path.is_absolute() or path.is_relative_to(root):
                continue
            # At least <artifact root>/<experiment id>, so that a lone id never matches by chance.
            tail = next((len(path.parts) - k for k in range(1, len(path.parts) - 1)
                         if root.joinpath(*path.parts[k:]).exists()), None)
            if tail is not None:
                old = Path(*path.parts[:len(path.parts) - tail])
                break
        if old is None or old == root:
            return None
        prefixes = ((old.as_uri(), root.as_uri()), (str(old), str(root)))  # file:// URIs, and plain paths

        def moved(value: str | None) -> str | None:
            for before, after in prefixes:
                if value and (value == before or value.startswith(before + "/")):
                    return after + value[len(before):]
            return None

        with con:  # one transaction: all re-pointed, or none
            for table, column, where in ARTIFACT_COLUMNS:
                if table in tables:
                    rows = con.execute(f"select rowid, {column} from {table}" + (f" where {where}" if where else ""))
                    updates = [(new, rowid) for rowid, value in rows.fetchall() if (new := moved(value))]
                    con.executemany(f"update {table} set {column} = ? where rowid = ?", updates)
    return str(old), str(root)


def provenance(params: dict[str, Any]) -> dict[str, str]:
    """Tags that say what produced a run: profile, params hash, shard manifest digest, git commit,
    host and Slurm job."""
    blob = json.dumps(params, sort_keys=True, default=str).encode()
    tags = {"orbis2.profile": str(params.get("profile", "")),
            "orbis2.params_sha256": hashlib.sha256(blob).hexdigest()}
    if SHARD_MANIFEST.is_file():
        tags["orbis2.shards_sha256"] = hashlib.sha256(SHARD_MANIFEST.read_bytes()).hexdigest()
    commit = _git_commit()
    if commit:
        tags["mlflow.source.git.commit"] = commit
    tags["orbis2.host"] = socket.gethostname()
    if os.environ.get("SLURM_JOB_ID"):
        tags["orbis2.slurm_job_id"] = os.environ["SLURM_JOB_ID"]
    return tags


def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _system_metrics() -> bool:
    """MLflow samples CPU/GPU/memory when psutil is installed, unless ORBIS2_SYSTEM_METRICS=0."""
    if os.environ.get("ORBIS2_SYSTEM_METRICS", "1") == "0":
        return False
    try:
        import psutil  # noqa: F401
    except ImportError:
        return False
    return True


class StageRun:
    """What a stage logs: metrics per step, artifacts, models. Without an MLflow module
    (ranks other than 0 under torchrun) every call does nothing."""

    def __init__(self, mlflow_module: Any | None, run_id: str | None, stage: str = "",
                 params: dict[str, Any] | None = None, parent_id: str | None = None):
        self._mlflow = mlflow_module
        self.run_id, self.stage, self.params, self.parent_id = run_id, stage, params or {}, parent_id
        self.dataset: Any = None  # the shard set logged as this run's input (log_shards)

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        if self._mlflow:
            self._mlflow.log_metrics({k: float(v) for k, v in metrics.items()}, step=step)

    def log_params(self, params: dict[str, Any]) -> None:
        if self._mlflow:
            self._mlflow.log_params({k: str(v) for k, v in params.items()})

    def log_artifact(self, path: Path, artifact_path: str | None = None) -> None:
        if self._mlflow:
            self._mlflow.log_artifact(str(path), artifact_path)

    def publish(self, path: Path, artifact_path: str | None = None, name: str | None = None) -> None:
        """Log an artifact on the pipeline's parent run too (as ``name`` when given), where a
        reviewer looks first."""
        if not (self._mlflow and self.parent_id):
            return
        client = self._mlflow.MlflowClient()
        if name is None:
            client.log_artifact(self.parent_id, str(path), artifact_path)
            return
        with tempfile.TemporaryDirectory() as tmp:
            shutil.copy2(path, Path(tmp) / name)
            client.log_artifact(self.parent_id, str(Path(tmp) / name), artifact_path)

    def publish_metrics(self, metrics: dict[str, float]) -> None:
        """Log headline metrics on the parent run (one value each, no step)."""
        if self._mlflow and self.parent_id and metrics:
            from mlflow.entities import Metric

            now = int(time.time() * 1000)
            items = [Metric(k, float(v), now, 0) for k, v in metrics.items()]
            client = self._mlflow.MlflowClient()
            for start in range(0, len(items), 1000):  # MLflow's batch limit
                client.log_batch(self.parent_id, metrics=items[start:start + 1000])

    def publish_tags(self, tags: dict[str, str]) -> None:
        """Set tags on the parent run (verdicts: text, shown on its page)."""
        if self._mlflow and self.parent_id:
            client = self._mlflow.MlflowClient()
            for key, value in tags.items():
                client.set_tag(self.parent_id, key, str(value)[:5000])

    def stage_times(self) -> dict[str, float]:
        """Every finished stage run of this invocation so far: its ``wall_seconds`` by stage name."""
        if not (self._mlflow and self.parent_id):
            return {}
        client = self._mlflow.MlflowClient()
        parent = client.get_run(self.parent_id)
        children = client.search_runs([parent.info.experiment_id],
                                      filter_string=f"tags.`mlflow.parentRunId` = '{self.parent_id}'", max_results=5000)
        return {run.info.run_name: run.data.metrics["wall_seconds"] for run in children
                if "wall_seconds" in run.data.metrics}

    def log_model(self, folder: Path, metrics: dict[str, float] | None = None) -> None:
        """Record a trained model: an MLflow logged model named after the stage, holding the
        folder's files (final weights) and ``config.json`` (the stage's resolved params),
        listed among the run's outputs, with ``metrics`` linked to it and to the shard set
        it trained on."""
        if not self._mlflow:
            return
        from mlflow.entities import LoggedModelOutput

        mlflow, config = self._mlflow, self.params
        flat = {k: str(v)[:6000] for k, v in flatten(config).items()}
        model = mlflow.initialize_logged_model(name=self.stage, source_run_id=self.run_id, params=flat,
                                               model_type="orbis2")
        client = mlflow.MlflowClient()
        client.log_model_artifacts(model.model_id, str(folder))
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / "config.json").write_text(json.dumps(config, indent=2, sort_keys=True, default=str))
            client.log_model_artifacts(model.model_id, tmp)
        mlflow.finalize_logged_model(model.model_id, "READY")
        client.log_outputs(self.run_id, [LoggedModelOutput(model.model_id, 0)])
        if metrics:
            mlflow.log_metrics({k: float(v) for k, v in metrics.items()}, model_id=model.model_id,
                               dataset=self.dataset)

    def log_shards(self, manifest: Path, context: str = "training") -> None:
        """Log the shard set as the run's input dataset, identified by the manifest's SHA-256;
        ``context`` says what the stage does with it (:func:`dataset_context`)."""
        if not self._mlflow:
            return
        from mlflow.data.dataset_source_registry import resolve_dataset_source
        from mlflow.data.meta_dataset import MetaDataset

        digest = hashlib.sha256(manifest.read_bytes()).hexdigest()
        with warnings.catch_warnings():  # MLflow registers its local-file source twice and says so
            warnings.simplefilter("ignore")
            source = resolve_dataset_source(str(manifest.absolute()))
        self.dataset = MetaDataset(source, name=f"shards-{digest[:12]}", digest=digest[:36])
        self._mlflow.log_input(self.dataset, context=context)


@contextlib.contextmanager
def _not_a_notebook() -> Iterator[None]:
    """Start a run without MLflow importing IPython (0.4 s a stage, where it is installed) to ask whether it runs
    in a notebook: a process that has not imported IPython is not in one, and MLflow reads a refused import so."""
    if "IPython" in sys.modules:
        yield
        return
    sys.modules["IPython"] = None  # `import IPython` raises ImportError
    try:
        yield
    finally:
        if "IPython" in sys.modules and sys.modules["IPython"] is None:
            del sys.modules["IPython"]


@contextlib.contextmanager
def stage_run(stage: str, params: dict[str, Any], pipeline: dict[str, Any] | None = None) -> Iterator[StageRun]:
    """Open the stage's MLflow run (nested under the invocation's parent) for the block.

    ``pipeline`` is the whole resolved config (default ``params``): the parent's
    profile and params digest when this stage is the one that creates it.
    Under torchrun only rank 0 logs; the other ranks get a :class:`StageRun` that does nothing. The run ends
    FINISHED, FAILED on an exception, or KILLED when training stopped on a signal (:class:`TrainingStopped`).
    """
    if int(os.environ.get("RANK", "0")) != 0:
        yield StageRun(None, None)
        return
    import mlflow
    from mlflow.tracking import MlflowClient

    uri = os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_TRACKING_URI)
    mlflow.set_tracking_uri(uri)
    with store_lock(uri):  # the first stages of a fresh store would race on its schema migration
        if (db := sqlite_path(uri)) is not None and db.is_file():
            with contextlib.suppress(OrbisError):  # not a store yet: MLflow creates or rejects it below
                relocate_store(db)  # a project folder that moved: its runs' artifacts are where it is now
        experiment = mlflow.set_experiment(os.environ.get("MLFLOW_EXPERIMENT_NAME", "orbis2"))
        client = MlflowClient()
        if experiment.tags.get(KIND_TAG) != EXPERIMENT_KIND:
            client.set_experiment_tag(experiment.experiment_id, KIND_TAG, EXPERIMENT_KIND)
        mark_killed_runs(client, experiment.experiment_id)
        parent_id = parent_run(client, experiment.experiment_id, invocation_key(), pipeline or params)
    owner = {OWNER_TAG: key} if (key := process_key(os.getpid())) else {}  # no /proc: not tracked
    tags = {"orbis2.stage": stage, **provenance(params), **owner}
    status = "FAILED"
    with _not_a_notebook():
        active = mlflow.start_run(run_name=stage, parent_run_id=parent_id, nested=True, tags=tags,
                                  log_system_metrics=_system_metrics())
    with active as run:
        _settle_parent(client, experiment.experiment_id, parent_id)
        flat = {k: str(v)[:6000] for k, v in flatten(params).items()}
        for start in range(0, len(flat), 100):  # MLflow limits one batch to 100 params
            mlflow.log_params(dict(list(flat.items())[start:start + 100]))
        logger = StageRun(mlflow, run.info.run_id, stage, params, parent_id)
        if stage not in NOT_SHARD_READERS and SHARD_MANIFEST.is_file():
            logger.log_shards(SHARD_MANIFEST, dataset_context(stage))
        try:
            yield logger
            status = "FINISHED"
        except TrainingStopped:
            status = "KILLED"  # stopped by a scheduler's signal with its checkpoint written: a re-run resumes it
            raise
        finally:
            mlflow.end_run(status=status)
            _settle_parent(client, experiment.experiment_id, parent_id)


def parent_run(client: Any, experiment_id: str, key: str, pipeline: dict[str, Any] | None = None) -> str:
    """The invocation's parent run, created by whichever stage comes first.

    A new parent gets the provenance of ``pipeline`` (the whole resolved config): its profile,
    commit and params digest as params (the runs table's columns; not repeated as tags, whose
    keys the run page cuts short), the rest as tags, and the config itself as ``params.json``.
    Stages on other nodes (where the store lock does not reach) may create one at the
    same moment; every stage then keeps the oldest (by start time, then id) and deletes the others.
    """
    found = _parents(client, experiment_id, key)
    if not found:
        from mlflow.entities import Param

        pipeline = pipeline or {}
        tags = provenance(pipeline)
        profile, digest = tags.pop("orbis2.profile"), tags.pop("orbis2.params_sha256")
        run = client.create_run(experiment_id,
                                run_name=f"pipeline {profile} {time.strftime('%Y-%m-%d %H:%M:%S')}",
                                tags={INVOCATION_TAG: key, "orbis2.pipeline": "true", **tags})
        shown = {"profile": profile, "git_commit": tags.get("mlflow.source.git.commit", "unknown"),
                 "params_sha256": digest[:12]}
        client.log_batch(run.info.run_id, params=[Param(k, v) for k, v in shown.items()])
        client.log_text(run.info.run_id, json.dumps(pipeline, indent=2, sort_keys=True, default=str), "params.json")
        found = _parents(client, experiment_id, key)
    keep, *duplicates = found
    for run in duplicates:
        if run.info.lifecycle_stage == "active":
            with contextlib.suppress(Exception):  # another stage may have deleted it already
                client.delete_run(run.info.run_id)
    return keep.info.run_id


def _parents(client: Any, experiment_id: str, key: str) -> list[Any]:
    from mlflow.entities import ViewType

    runs = client.search_runs([experiment_id], filter_string=f"tags.`{INVOCATION_TAG}` = '{key}'",
                              run_view_type=ViewType.ALL, max_results=50)
    return sorted(runs, key=lambda r: (r.info.start_time, r.info.run_id))


def _settle_parent(client: Any, experiment_id: str, parent_id: str) -> None:
    """Derive the parent's status from all its children, so a later success never hides a failure."""
    children = client.search_runs([experiment_id], filter_string=f"tags.`mlflow.parentRunId` = '{parent_id}'",
                                  max_results=5000)
    states = {run.info.status for run in children}
    if "FAILED" in states or "KILLED" in states:
        status = "FAILED"
    elif "RUNNING" in states or "SCHEDULED" in states:
        status = "RUNNING"
    else:
        status = "FINISHED"
    if status == "RUNNING":
        client.update_run(parent_id, status="RUNNING")
    else:
        client.set_terminated(parent_id, status=status)


def _proc_stat(pid: int) -> list[str] | None:
    """Fields of /proc/<pid>/stat after the command name (state, ppid, ..., starttime at 19)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def process_key(pid: int) -> str | None:
    """``host:pid:start time``: names one process for good (a reused pid has another start time)."""
    stat = _proc_stat(pid)
    return None if stat is None else f"{socket.gethostname()}:{pid}:{stat[19]}"


def mark_killed_runs(client: Any, experiment_id: str) -> list[str]:
    """End as KILLED every RUNNING stage run whose process, on this host, is gone; returns their ids.

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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m orbis2.tracking",
                                     description="Re-point a moved SQLite MLflow store at its new folder.")
    sub = parser.add_subparsers(dest="command", required=True)
    relocate = sub.add_parser("relocate", help="point the store's artifact locations at the folder it now lives in")
    relocate.add_argument("--store", default=os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_TRACKING_URI),
                          help="the store's URI (default: $MLFLOW_TRACKING_URI, else sqlite:///mlflow.db)")
    args = parser.parse_args(argv)
    db = sqlite_path(args.store)
    try:
        if db is None:
            raise OrbisError(f"--store {args.store}: not a SQLite store; a tracking server's artifacts "
                             "(mlflow-artifacts:/) do not need re-pointing")
        if not db.is_file():
            raise OrbisError(f"{db}: no such store; run from the project folder or pass --store sqlite:///<path>")
        with store_lock(args.store):
            moved = relocate_store(db)
    except OrbisError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    print(f"{db}: artifacts re-pointed from {moved[0]} to {moved[1]}" if moved else
          f"{db}: artifact locations already point here")


if __name__ == "__main__":
    main()
