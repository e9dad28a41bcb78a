"""What every stage script shares: arguments, config, the MLflow run, errors, the summary line."""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Callable

import orbis2
from orbis2.config import BOOKKEEPING_FIELDS, PipelineConfig, as_dict, load_config
from orbis2.errors import OrbisError
from orbis2.io import atomic_dir, sha256_file, write_json
from orbis2.registry import layout_path
from orbis2.tracking import StageRun, stage_run

StageBody = Callable[[PipelineConfig, argparse.Namespace, StageRun], str]


def stage_main(name: str, sections: list[str], body: StageBody,
               add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
               argv: list[str] | None = None) -> None:
    """Parse ``--params/--profile``, run ``body`` inside the stage's MLflow run, print its summary.

    ``sections`` are the params.yaml sections the stage reads; they are logged as the
    run's parameters. A user-fixable problem (:class:`OrbisError`) exits with status 2.
    """
    parser = argparse.ArgumentParser(prog=f"stages/{name}.py", description=body.__doc__)
    parser.add_argument("--params", default="params.yaml", help="params file (default: params.yaml)")
    parser.add_argument("--profile", default=None, help="smoke | default | gpu | paper (default: the file's `profile`)")
    if add_arguments:
        add_arguments(parser)
    args = parser.parse_args(argv)
    started = time.perf_counter()
    try:
        cfg = load_config(args.params, args.profile)
        params = {"profile": cfg.profile, **{s: as_dict(cfg.section(s)) for s in sections}}
        with stage_run(name, params) as run:
            summary = body(cfg, args, run)
            run.log_metrics({"wall_seconds": time.perf_counter() - started})
    except OrbisError as err:
        print(f"[{name}] error: {err}", file=sys.stderr)
        sys.exit(2)
    print(f"[{name}] {summary} ({time.perf_counter() - started:.1f} s, profile {cfg.profile})")


def named_stage_main(script: str, prefix: str, names: list[str], sections: list[str],
                     body_for: Callable[[str], StageBody], argv: list[str]) -> None:
    """``python stages/<script> <name> [--profile P]``: one script serving a family of stages.

    The DAG passes the full stage name (``<prefix><name>``, e.g. ``eval_fvd_hierarchical``);
    by hand the short name is enough.
    """
    if argv and argv[0].startswith(prefix) and argv[0][len(prefix):] in names:
        argv = [argv[0][len(prefix):], *argv[1:]]
    if not argv or argv[0] not in names:
        given = repr(argv[0]) if argv else "nothing"
        sys.exit(f"usage: python stages/{script} <name> [--profile P]; <name> is one of {', '.join(names)} "
                 f"(got {given})")
    stage_main(f"{prefix}{argv[0]}", sections, body_for(argv[0]), argv=argv[1:])


def training_dir(name: str, cfg: PipelineConfig, sections: list[str], inputs: dict[str, Path]) -> Path:
    """Where a training stage keeps checkpoints: ``data/runs/<stage>-<profile>-<key>``.

    Outside the stage's declared outputs, because Snakemake and DVC delete those
    before re-running a stage. The key covers everything that decides the weights,
    so a killed run resumes while anything else starts afresh: the resolved params
    of ``sections`` (without bookkeeping such as ``checkpoint_every``, which a resume
    may change), the SHA-256 of every file in ``inputs`` (the shards manifest,
    upstream weights, the teacher) and :func:`code_version`. Without the last two, a
    re-run after new data or a bug fix would find the old run finished and publish
    its stale weights.
    """
    key: dict = {s: _without_bookkeeping(as_dict(cfg.section(s))) for s in sections}
    missing = [str(path) for path in inputs.values() if not Path(path).is_file()]
    if missing:
        raise OrbisError(f"{', '.join(missing)}: not found; stage `{name}` reads it, run the stages before it first")
    key["inputs"] = {label: sha256_file(path) for label, path in sorted(inputs.items())}
    key["code"] = code_version()
    blob = json.dumps(key, sort_keys=True).encode()
    return layout_path("runs") / f"{name}-{cfg.profile}-{hashlib.sha256(blob).hexdigest()[:12]}"


def _without_bookkeeping(section: dict) -> dict:
    """A section with the bookkeeping fields of its ``train`` settings left out."""
    train = section.get("train")
    if not isinstance(train, dict):
        return section
    return {**section, "train": {k: v for k, v in train.items() if k not in BOOKKEEPING_FIELDS}}


@functools.cache
def code_version(root: Path = Path(orbis2.__file__).parent) -> str:
    """SHA-256 over the ``*.py`` files of the orbis2 package (relative paths and bytes).

    The whole package rather than the modules a stage imports: a stage reaches most of
    it indirectly, and a spurious fresh start costs less than resuming stale code.
    """
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def publish_training(run_dir: Path, out: Path, files: list[str], report: Path, metrics: dict[str, float],
                     run: StageRun) -> None:
    """Copy a finished training run's ``files``, ``samples/`` and ``curves/`` into the stage output,
    atomically; write the metrics report, log the samples and the model (weights + config)."""
    with atomic_dir(out) as tmp:
        for name in files:
            shutil.copy2(run_dir / name, tmp / name)
        for folder in ("samples", "curves"):
            if (run_dir / folder).is_dir():
                shutil.copytree(run_dir / folder, tmp / folder)
    for png in sorted((out / "samples").glob("*.png")):
        run.log_artifact(png, "samples")
    write_json(report, metrics)
    run.log_artifact(report)
    run.log_model(out)
