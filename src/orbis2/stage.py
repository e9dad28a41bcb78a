"""What every stage script shares: its arguments, the MLflow run around its work, run folders, publishing.

A stage script's ``main()`` reads top to bottom::

    parser = stage_parser(INTERFACES["town"], __doc__)   # --params, --profile and its path options
    args = parser.parse_args(argv)
    with open_stage("town", args, INTERFACES["town"]) as stage:
        cfg, run = stage.cfg, stage.run
        ...                      # load inputs, call the library, save outputs, log to ``run``
        stage.summary = "..."    # the line printed when the stage ends

The stage's declaration (:mod:`orbis2.interfaces`) names its path options and the
params sections it reads; the DAG (the rules in ``rules/*.smk``, and dvc.yaml
generated from them) is made from the same declaration and passes every input and
output path as an option; a stage run by hand without them falls back on
registry.yaml's ``layout``, so the library only ever receives paths.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import functools
import gc
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, Sequence

from orbis2.config.params import PipelineConfig, as_dict
from orbis2.config.training import BOOKKEEPING_FIELDS
from orbis2.errors import REQUEUE_EXIT, WARNING_SIGNALS, OrbisError, TrainingStopped
from orbis2.interfaces import Interface, PathOption
from orbis2.io import atomic_dir, sha256_file, write_json
from orbis2.registry import layout_path, registry
from orbis2.run_profile import SHARD_MANIFEST, resolve_profile
from orbis2.sources import code_version
from orbis2.tracking import StageRun, stage_run


def stage_parser(interface: Interface, description: str | None = None) -> argparse.ArgumentParser:
    """The arguments every stage takes (``--params``, ``--profile``) and the path options of its declaration."""
    parser = argparse.ArgumentParser(prog=interface.script, description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--params", default="params.yaml", help="params file (default: params.yaml)")
    parser.add_argument("--profile", default=None, help="smoke | default | gpu | paper (default: the file's `profile`)")
    add_path_options(parser, interface.paths)
    return parser


def add_path_options(parser: argparse.ArgumentParser, options: Iterable[PathOption]) -> None:
    """One option per declared path: a repeatable ``NAME=PATH`` one for a family, else a path whose default is
    the layout's where it is the same for every entry (else None: the script works it out from its entry)."""
    for option in options:
        if option.named:
            add_named_paths(parser, option.option, option.what, f"every NAME's {option.describe_default()}")
            continue
        default = option.default()
        parser.add_argument(option.option, type=Path, default=default, required=option.required,
                            metavar="DIR" if option.folder else "FILE",
                            help=f"{option.what} (default: {option.describe_default()})" if not option.required
                            else f"{option.what} ({option.describe_default()})")


def add_name_argument(parser: argparse.ArgumentParser, names: Sequence[str], prefix: str = "",
                      default: str | None = None) -> None:
    """``args.name``: which stage of a family one script serves (``python stages/eval_fvd.py hierarchical``).

    The DAG passes the full stage name (``<prefix><name>``, e.g. ``eval_fvd_hierarchical``);
    by hand the short name is enough. With a ``default`` the name may be left out.
    """
    names = list(names)

    def short(value: str) -> str:
        rest = value[len(prefix):]
        return rest if prefix and value.startswith(prefix) and rest in names else value

    parser.add_argument("name", type=short, choices=names, metavar="name", default=default,
                        nargs="?" if default is not None else None,
                        help=f"one of {', '.join(names)}" + (f" (default: {default})" if default else ""))


# The file a tokenizer or predictor stage publishes in its output folder (the folder is what the DAG passes).
TOKENIZER_FILE = "tokenizer.pt"
PREDICTOR_FILE = "predictor.pt"
LEVELS = ("detail", "abstract")


def named_path(value: str) -> tuple[str, Path]:
    """``NAME=PATH`` (an argparse type): which entry of a family a path belongs to."""
    name, sep, path = value.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"{value!r}: expected NAME=PATH")
    return name, Path(path)


def add_named_paths(parser: argparse.ArgumentParser, option: str, what: str, default: str) -> None:
    """A repeatable ``option NAME=PATH`` (collected in a list of pairs)."""
    parser.add_argument(option, type=named_path, action="append", default=[], metavar="NAME=PATH",
                        help=f"{what}, repeatable (default: {default})")


def named_paths(given: Iterable[tuple[str, Path]], names: Iterable[str], default, option: str) -> dict[str, Path]:
    """``{name: path}`` for every name: the one given (``NAME=PATH`` pairs), else ``default(name)``.

    A given name outside ``names`` is an error, so a misspelt name does not silently fall back on the layout.
    """
    names, given = list(names), dict(given)
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise OrbisError(f"{option} {', '.join(unknown)}: not read by this stage; it reads {', '.join(names)}")
    return {name: Path(given[name]) if name in given else Path(default(name)) for name in names}


def predictor_files(args: argparse.Namespace, names: Iterable[str]) -> dict[str, Path]:
    """``{predictor: its predictor.pt}`` for ``names``, from ``--predictor`` or registry.yaml's layout."""
    folders = named_paths(args.predictor, dict.fromkeys(names), lambda n: layout_path("predictor", n), "--predictor")
    return {name: folder / PREDICTOR_FILE for name, folder in folders.items()}


@dataclass(frozen=True)
class LatentPaths:
    """A latent cache and the tokenizer file of each level, as the DAG passes them."""

    root: Path
    tokenizers: dict[str, Path]  # level -> tokenizer.pt


def latent_paths(args: argparse.Namespace, latent_set: str) -> LatentPaths:
    """The paths of ``args`` (``--latents``, ``--<level>-tokenizer``), else those of registry.yaml's ``latent_set``."""
    entry = registry().latent_sets[latent_set]
    given = {level: getattr(args, f"{level}_tokenizer", None) for level in LEVELS}
    tokenizers = {level: (Path(given[level]) / TOKENIZER_FILE if given[level] is not None
                          else entry.tokenizer_file(level)) for level in LEVELS}
    root = getattr(args, "latents", None)
    return LatentPaths(Path(root) if root is not None else entry.root, tokenizers)


@functools.cache
def _freeze_at_exit() -> None:
    atexit.register(gc.freeze)  # registered first, so it runs last, after MLflow's exit handlers


def freeze_imports() -> None:
    """Take every object alive now out of the cyclic garbage collector's sight, now and again at exit (``gc.freeze``).

    A stage's imports (torch, MLflow with SQLAlchemy and pandas) leave millions of long-lived objects, which every
    full collection walks again and the interpreter's shutdown walks once more (at the smoke scale, one thread: a
    probe stage 8.8 -> 6.5 CPU-s, an FVD stage 29.5 -> 28.8, ``orbis2 rollout`` 9.8 -> 8.7). Frozen objects are
    still freed by reference counting; only a reference cycle among them lives on until the process ends. Called
    once a process's imports are done (a stage's start and its open MLflow run, the ``orbis2`` command's start);
    forked workers inherit the frozen heap.
    """
    _freeze_at_exit()
    gc.freeze()


@dataclass
class Stage:
    """A running stage: its resolved config, its MLflow run, and the summary line it prints at the end."""

    name: str
    cfg: PipelineConfig
    run: StageRun
    summary: str = ""


@contextlib.contextmanager
def open_stage(name: str, args: argparse.Namespace, interface: Interface,
               extra: Sequence[str] = ()) -> Iterator[Stage]:
    """Load the config of ``args.params``/``args.profile`` and open the stage's MLflow run for the block.

    The params.yaml sections the stage reads are its declaration's, with ``extra`` (an entry's own section,
    as its rule passes it); they are logged as the run's parameters. On leaving the block the wall time is
    logged as ``wall_seconds`` (the parent's ``tables/stage_times.csv`` collects them) and
    ``[<name>] <summary> (<s> s, profile <p>)`` printed. A user-fixable problem (:class:`OrbisError`) prints
    ``[<name>] error: ...`` and exits with status 2. Training stopped by a signal (:class:`TrainingStopped`,
    its checkpoint written) exits with ``REQUEUE_EXIT`` (75), after asking Slurm to requeue the job on a warning
    (SIGUSR1, SIGURG: :func:`requeue_slurm_job`). Run by hand without ``--profile``, the stage takes the
    profile of the data it works on (:func:`profile_witness`) and says so.
    """
    started = time.perf_counter()
    freeze_imports()  # the script's own imports
    try:
        cfg, which = resolve_profile(args.params, args.profile, [profile_witness(interface, args)])
        if args.profile is None:
            print(f"[{name}] {which}", file=sys.stderr)
        params = {"profile": cfg.profile, **{s: as_dict(cfg.section(s)) for s in interface.sections_with(extra)}}
        with stage_run(name, params, as_dict(cfg)) as run:
            freeze_imports()  # MLflow's, imported by the run
            stage = Stage(name, cfg, run)
            yield stage
            seconds = time.perf_counter() - started
            run.log_metrics({"wall_seconds": seconds})  # the parent's tables/stage_times.csv (report_main)
    except TrainingStopped as err:
        print(f"[{name}] {err} (exit {REQUEUE_EXIT})", file=sys.stderr)
        if err.signal_name in WARNING_SIGNALS:
            requeue_slurm_job(name)
        err.stopped_together()
        sys.exit(REQUEUE_EXIT)
    except OrbisError as err:
        print(f"[{name}] error: {err}", file=sys.stderr)
        sys.exit(2)
    print(f"[{name}] {stage.summary} ({time.perf_counter() - started:.1f} s, profile {cfg.profile})")


def requeue_slurm_job(name: str) -> None:
    """Put this Slurm batch job back in the queue (``scontrol requeue``); rank 0 only, the checkpoint written.

    SIGUSR1 and SIGURG are Slurm's warning ahead of the time limit (``--signal=USR1@<seconds>`` or
    ``URG@<seconds>``, which profiles/slurm asks for on every training rule, with ``--requeue``): the requeued
    job runs the stage again, and it resumes. Like Lightning's and submitit's Slurm handling, the stage asks for
    the requeue itself, as only it knows that its checkpoint is written. Outside a Slurm job nothing happens; a
    refusal (a job without ``--requeue``) is printed, and running the stage again resumes it all the same.
    """
    job = os.environ.get("SLURM_JOB_ID")
    if job is None or int(os.environ.get("RANK", "0")) != 0:
        return
    proc = subprocess.run(["scontrol", "requeue", job], capture_output=True, text=True)
    outcome = ("requeued: it resumes when Slurm starts it again" if proc.returncode == 0 else
               f"not requeued ({proc.stderr.strip() or proc.returncode}): submit it again to resume")
    print(f"[{name}] Slurm job {job} {outcome}", file=sys.stderr)


# Stages that make the data (or need none): a run's profile is what they are told, not what they find.
MAKE_THE_DATA = ("town", "import", "shards", "assets")


def profile_witness(interface: Interface, args: argparse.Namespace) -> Path | None:
    """The artifact that says which profile a stage run by hand without --profile is at: the shard manifest
    of the data it works on (:mod:`orbis2.run_profile`); None for the stages that make the data."""
    if interface.kind in MAKE_THE_DATA:
        return None
    return Path(getattr(args, "shards", None) or layout_path("shards")) / SHARD_MANIFEST


def work_dir(name: str, cfg: PipelineConfig, sections: list[str], inputs: dict[str, Path],
             script: Path | str) -> Path:
    """Where a resumable stage keeps its work (a training stage's checkpoints, the parts of the shards and caches):
    ``data/runs/<stage>-<profile>-<key>``.

    Outside the stage's declared outputs, because Snakemake and DVC delete those
    before re-running a stage. The key covers everything that decides the weights,
    so a killed run resumes while anything else starts afresh: the resolved params
    of ``sections`` (without bookkeeping such as ``checkpoint_every``, which a resume
    may change), the SHA-256 of every file in ``inputs`` (the shards manifest,
    upstream weights, the teacher) and :func:`code_version` of the stage ``script``
    (the stage's ``__file__``): what it and the modules it imports compute, so a
    docstring, comment or message changed resumes. Without the last two, a re-run
    after new data or a bug fix would find the old run finished and publish its
    stale weights.
    """
    key: dict = {s: _without_bookkeeping(as_dict(cfg.section(s))) for s in sections}
    missing = [str(path) for path in inputs.values() if not Path(path).is_file()]
    if missing:
        raise OrbisError(f"{', '.join(missing)}: not found; stage `{name}` reads it, run the stages before it first")
    key["inputs"] = {label: sha256_file(path) for label, path in sorted(inputs.items())}
    key["code"] = code_version(script)
    blob = json.dumps(key, sort_keys=True).encode()
    # Scratch space of the stage itself, not a DAG input or output: where it lives stays the layout's.
    return layout_path("runs") / f"{name}-{cfg.profile}-{hashlib.sha256(blob).hexdigest()[:12]}"


def _without_bookkeeping(section: dict) -> dict:
    """A section with the bookkeeping fields of its ``train`` settings left out."""
    train = section.get("train")
    if not isinstance(train, dict):
        return section
    return {**section, "train": {k: v for k, v in train.items() if k not in BOOKKEEPING_FIELDS}}


# The losses drawn beside each training run's curves, one PNG each (``curves/<metric>.png``) on its own y scale:
# {curve file: column}. They are dvc.yaml's plots, as images so that `dvc plots show`'s page needs no network.
LOSS_PLOTS = {"train": "loss", "eval": "val_loss"}


def draw_loss_curves(curves: Path, title: str) -> list[Path]:
    """Draw each loss of :data:`LOSS_PLOTS` that ``curves`` (a run's ``curves/`` folder, not yet published)
    holds; the PNGs written. Plain matplotlib (Agg), so that every stage does not depend on the report's code."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd
    from matplotlib.ticker import MaxNLocator

    drawn = []
    for curve, metric in LOSS_PLOTS.items():
        table = pd.read_csv(curves / f"{curve}.csv") if (curves / f"{curve}.csv").is_file() else None
        if table is None or metric not in table or table[metric].isna().all():
            continue
        fig, ax = plt.subplots(figsize=(6, 3.5))
        try:
            ax.plot(table["step"], table[metric], marker="o" if len(table) <= 20 else None)
            ax.set(xlabel="step", ylabel=metric, title=f"{title}: {metric}")
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.grid(alpha=0.3)
            fig.savefig(curves / f"{metric}.png", format="png", dpi=100, bbox_inches="tight")
        finally:
            plt.close(fig)
        drawn.append(curves / f"{metric}.png")
    return drawn


def copy_curves(run_dir: Path, dest: Path, title: str) -> None:
    """A training run's ``curves/`` (if it logged any) into ``dest``, a stage output being written, with a PNG
    per loss (:func:`draw_loss_curves`)."""
    if (run_dir / "curves").is_dir():
        shutil.copytree(run_dir / "curves", dest / "curves")
        draw_loss_curves(dest / "curves", title)


# Training results that are sizes, not scores: logged as params (table columns), not as one-point charts.
SIZES = {"steps": "trained_steps", "parameters": "model_parameters"}


def publish_training(run_dir: Path, out: Path, files: list[str], report: Path, metrics: dict[str, float],
                     run: StageRun) -> None:
    """Copy a finished training run's ``files``, ``samples/`` and ``curves/`` (with a PNG per loss,
    :func:`draw_loss_curves`) into the stage output, atomically; write the metrics report; log the final
    scores (at the last step), the sizes (:data:`SIZES`) as params, the samples and the model (weights +
    config)."""
    scores = {k: v for k, v in metrics.items() if k not in SIZES}
    run.log_metrics(scores, step=int(metrics["steps"]))
    run.log_params({name: int(metrics[key]) for key, name in SIZES.items() if key in metrics})
    with atomic_dir(out) as tmp:
        for name in files:
            shutil.copy2(run_dir / name, tmp / name)
        if (run_dir / "samples").is_dir():
            shutil.copytree(run_dir / "samples", tmp / "samples")
        copy_curves(run_dir, tmp, run.stage or out.name)
    for png in sorted((out / "samples").glob("*.png")):
        run.log_artifact(png, "samples")
    write_json(report, metrics)
    run.log_artifact(report)
    run.log_model(out, scores)
