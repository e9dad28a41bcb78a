"""What every stage script shares: arguments, config, the MLflow run, errors, the summary line."""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Callable

from orbis2.config import PipelineConfig, as_dict, load_config
from orbis2.errors import OrbisError
from orbis2.io import atomic_dir, write_json
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
    parser.add_argument("--profile", default=None, help="smoke | default | paper (default: the file's `profile`)")
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


def training_dir(name: str, cfg: PipelineConfig, sections: list[str], inputs: dict | None = None) -> Path:
    """Where a training stage keeps checkpoints: ``data/runs/<stage>-<profile>-<params hash>``.

    Outside the stage's declared outputs, because Snakemake and DVC delete those
    before re-running a stage; keyed by the resolved params (and ``inputs``, e.g.
    checksums of upstream weights), so a killed run resumes while a changed config
    or input starts afresh.
    """
    key = {s: as_dict(cfg.section(s)) for s in sections}
    if inputs:
        key["inputs"] = inputs
    blob = json.dumps(key, sort_keys=True).encode()
    return layout_path("runs") / f"{name}-{cfg.profile}-{hashlib.sha256(blob).hexdigest()[:12]}"


def publish_training(run_dir: Path, out: Path, files: list[str], report: Path, metrics: dict[str, float],
                     run: StageRun) -> None:
    """Copy a finished training run's ``files`` and ``samples/`` into the stage output, atomically;
    write the metrics report and log the samples."""
    with atomic_dir(out) as tmp:
        for name in files:
            shutil.copy2(run_dir / name, tmp / name)
        if (run_dir / "samples").is_dir():
            shutil.copytree(run_dir / "samples", tmp / "samples")
    for png in sorted((out / "samples").glob("*.png")):
        run.log_artifact(png, "samples")
    write_json(report, metrics)
    run.log_artifact(report)
