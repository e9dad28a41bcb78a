"""Kill a training stage with SIGKILL (or stop it with SIGUSR1 / SIGTERM) at random moments and check that
resuming loses nothing.

For one training stage of a profile (default: ``tokenizer_detail`` on ``smoke``,
which needs only ``data/shards`` and ``data/assets``; build them first, e.g.
``snakemake --cores 2 --config profile=smoke data/shards data/assets``):

1. run the stage once uninterrupted: the reference weights;
2. N times, in a fresh workspace: start the stage with ``checkpoint_every: 1``
   (bookkeeping: it must not change the resume key or the weights), kill its
   process group with SIGKILL at a random moment of a random training step, run
   it again to the end; with ``--signal USR1`` or ``TERM`` the signal instead
   (a scheduler's warning or preemption): the stage must stop at the next step
   with a checkpoint and exit with status 75 (``orbis2.errors.REQUEUE_EXIT``);
3. check the published weights are bit-identical to the reference, and that the
   killed MLflow run ended KILLED or FAILED (the next start ends it), not RUNNING
   (a stopped one KILLED, as the stage ends it).

Each workspace sees the project's ``data/`` through symlinks, except ``data/runs``
and the stage's own output, so nothing of the project is written. Exit status 1
if any trial fails. From the repository root:

    python tools/kill_resume_check.py --trials 5
    python tools/kill_resume_check.py --trials 3 --signal USR1
    python tools/kill_resume_check.py --stage abstract_df --trials 5   # needs data/latents
"""

from __future__ import annotations

import argparse
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from orbis2.config.params import load_config, load_yaml  # noqa: E402
from orbis2.errors import REQUEUE_EXIT  # noqa: E402
from orbis2.tasks.predictors import STAGES as PREDICTOR_STAGES  # noqa: E402


def stage_command(stage: str, profile: str) -> tuple[list[str], Path]:
    """The stage's command line and its published weights file (relative to a workspace)."""
    if stage == "tokenizer_detail":
        return [sys.executable, str(ROOT / "stages/tokenizer_detail.py"), "--profile", profile], \
            Path("data/tokenizers/detail/tokenizer.pt")
    if stage in PREDICTOR_STAGES:
        return [sys.executable, str(ROOT / "stages/predictor.py"), stage, "--profile", profile], \
            Path(f"data/predictors/{stage}/predictor.pt")
    raise SystemExit(f"--stage {stage}: use tokenizer_detail or one of {sorted(PREDICTOR_STAGES)}")


def mirror(src: Path, dest: Path, keep_out: Path) -> None:
    """Symlink every entry of ``src`` into ``dest`` except ``runs`` and ``keep_out`` (real folders on its way)."""
    dest.mkdir(parents=True, exist_ok=True)
    for entry in sorted(src.iterdir()):
        if entry.name == "runs" and src.name == "data":
            continue
        target = dest / entry.name
        if entry == keep_out:
            continue
        if entry in keep_out.parents:
            mirror(entry, target, keep_out)
        else:
            target.symlink_to(entry)


def workspace(base: Path, name: str, out: Path, stage: str, checkpoint_every: int | None) -> Path:
    ws = base / name
    mirror(ROOT / "data", ws / "data", ROOT / out.parent)
    params = load_yaml((ROOT / "params.yaml").read_text())
    if checkpoint_every is not None:
        for profile in ("smoke", "default", "paper"):
            section = params[stage].setdefault(profile, {}) or {}
            params[stage][profile] = section
            section.setdefault("train", {})["checkpoint_every"] = checkpoint_every
    (ws / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    return ws


def start(cmd: list[str], ws: Path, db: Path, pipeline: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "MLFLOW_TRACKING_URI": f"sqlite:///{db}",
           "ORBIS2_PIPELINE_ID": pipeline}
    log = open(ws / f"{pipeline}.log", "w")
    return subprocess.Popen(cmd, cwd=ws, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def finish(proc: subprocess.Popen, ws: Path, pipeline: str, expected: int = 0) -> str:
    code = proc.wait()
    text = (ws / f"{pipeline}.log").read_text()
    if code != expected:
        raise SystemExit(f"{pipeline} exited with {code}, not {expected}:\n{text[-3000:]}")
    return text


def weights(path: Path) -> dict[str, torch.Tensor]:
    return torch.load(path, map_location="cpu", weights_only=True)["state_dict"]


def identical(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def kill_during_step(proc: subprocess.Popen, ws: Path, step: int, rng: random.Random,
                     sig: signal.Signals = signal.SIGKILL) -> bool:
    """Send ``sig`` to the stage's process group at a random moment after its ``step``-th checkpoint write.

    With ``checkpoint_every: 1`` the checkpoint is rewritten after every step, so the
    kill lands anywhere in the next step: mid-update, mid-save or mid-rename.
    """
    seen, last, gaps = 0, None, []
    stamp = time.monotonic()
    while proc.poll() is None:
        found = sorted(ws.glob("data/runs/*/checkpoints/last.pt"))
        mtime = found[0].stat().st_mtime_ns if found else None
        if mtime is not None and mtime != last:
            last, seen = mtime, seen + 1
            now = time.monotonic()
            gaps.append(now - stamp)
            stamp = now
            if seen == step:
                time.sleep(rng.uniform(0.0, 1.0) * (min(gaps[1:]) if len(gaps) > 1 else 1.0))
                os.killpg(proc.pid, sig)
                return True
        time.sleep(0.05)
    return False


def run_statuses(db: Path, pipeline: str, stage: str) -> list[str]:
    """Statuses of the stage's runs under the pipeline run ``pipeline``, oldest first."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{db}")
    experiment = client.get_experiment_by_name(os.environ.get("MLFLOW_EXPERIMENT_NAME", "orbis2"))
    parents = client.search_runs([experiment.experiment_id], f"tags.`orbis2.invocation` = '{pipeline}'")
    if not parents:
        return []  # killed before the stage opened its run
    runs = client.search_runs([experiment.experiment_id],
                              f"tags.`mlflow.parentRunId` = '{parents[0].info.run_id}' and "
                              f"tags.`orbis2.stage` = '{stage}'", order_by=["attributes.start_time ASC"])
    return [run.info.status for run in runs]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stage", default="tokenizer_detail")
    parser.add_argument("--profile", default="smoke")
    parser.add_argument("--trials", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0, help="seeds the kill steps and moments")
    parser.add_argument("--signal", choices=("KILL", "USR1", "URG", "TERM"), default="KILL",
                        help="SIGKILL (default), or the signal of a time limit's warning (USR1, or URG to a "
                             "one-task job) or a preemption (TERM)")
    parser.add_argument("--keep", action="store_true", help="keep the workspaces (printed) for inspection")
    args = parser.parse_args()
    cmd, out = stage_command(args.stage, args.profile)
    sig = signal.Signals[f"SIG{args.signal}"]
    cfg = load_config(ROOT / "params.yaml", args.profile)
    steps = cfg.section(args.stage).train.steps
    rng = random.Random(args.seed)
    base = Path(tempfile.mkdtemp(prefix="kill_resume_"))
    db = base / "mlflow.db"

    ref_ws = workspace(base, "reference", out, args.stage, None)
    began = time.monotonic()
    finish(start(cmd, ref_ws, db, "reference"), ref_ws, "reference")
    ref_seconds = time.monotonic() - began
    reference = weights(ref_ws / out)
    print(f"reference: {ref_seconds:.1f} s uninterrupted -> {ref_ws / out}", flush=True)

    failures = 0
    for trial in range(args.trials):
        name = f"trial{trial}"
        ws = workspace(base, name, out, args.stage, checkpoint_every=1)
        # A stop signal must land in a step before the last (then the run ends instead); SIGKILL anywhere.
        kill_step = rng.randint(1, steps - 1 if sig == signal.SIGKILL else max(1, steps - 3))
        proc = start(cmd, ws, db, name)
        killed = kill_during_step(proc, ws, kill_step, rng, sig)
        if killed and sig != signal.SIGKILL:  # stopped at the next step boundary, its checkpoint written
            stopped = re.search(rf"stopped by {sig.name} at step (\d+)", finish(proc, ws, name, REQUEUE_EXIT))
            killed = stopped is not None
        proc.wait()
        text = finish(start(cmd, ws, db, name + "-resume"), ws, name + "-resume")
        resumed = re.search(r"resumed at (\d+)", text)
        same = identical(reference, weights(ws / out))
        statuses = run_statuses(db, name, args.stage) + run_statuses(db, name + "-resume", args.stage)
        # A stopped stage ends its run KILLED itself; a SIGKILLed one is ended by the next start (KILLED or FAILED).
        ended = ("KILLED", "FAILED") if sig == signal.SIGKILL else ("KILLED",)
        status_ok = statuses[-1:] == ["FINISHED"] and all(s in ended for s in statuses[:-1])
        ok = same and status_ok and killed
        failures += not ok
        print(f"{name}: {sig.name} during step {kill_step + 1}: {killed}; resumed at step "
              f"{resumed.group(1) if resumed else 0}; weights bit-identical: {same}; MLflow runs "
              f"{' -> '.join(statuses)}: {'ok' if ok else 'FAIL'}", flush=True)
    print(f"{args.trials - failures}/{args.trials} trials passed ({args.stage}, profile {args.profile}, "
          f"{sig.name})")
    if args.keep:
        print(f"workspaces in {base}")
    else:
        import shutil

        shutil.rmtree(base, ignore_errors=True)
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
