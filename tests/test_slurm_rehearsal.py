"""Rehearsal through a real Slurm cluster: the generated launcher (tools/slurm_torchrun.sh) in one job of two
tasks on one node, two torchrun agents meeting through a c10d rendezvous (gloo, CPU), training a tiny predictor of
the smoke profile; then the same job stopped mid-run by ``scancel --signal=USR1``, which checkpoints, requeues
itself and ends with the uninterrupted job's weights, bit for bit. And a job of one task shaped as the Slurm
plugin runs a one-task rule (a parent process and a shell above the training one in one job step), stopped by
the SIGURG its generated request asks for: only the training process acts on it, and the job requeues and ends
bit-identical too.

Needs a Slurm cluster whose node takes a job of two tasks (``tools/slurm_local.sh start`` makes one on this
machine); skipped without one. The request is the generated profile's for a training rule, but for its shape:
8 nodes of one task each cannot fit one machine, so the job asks for one node of two tasks (``AGENTS=2``: one
torchrun agent per task, as there would be one per node).

    pytest -n 0 -s tests/test_slurm_rehearsal.py     # prints the jobs' times
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml
from test_predictors import SPAN, write_cache

from orbis2.train import load_checkpoint, load_weights

from conftest import ROOT, slurm_answers

LAUNCHER = ROOT / "tools" / "slurm_torchrun.sh"
SCRIPT = Path(__file__).with_name("multinode_train.py")
ENDED = ("COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY", "PREEMPTED", "BOOT_FAIL",
         "DEADLINE")


def slurm_up() -> bool:
    if not slurm_answers():
        return False
    proc = subprocess.run(["sinfo", "--noheader", "--format", "%t"], capture_output=True, text=True)
    return proc.returncode == 0 and any(state.startswith(("idle", "mix", "alloc")) for state in proc.stdout.split())


pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not slurm_up(), reason="no Slurm cluster here (tools/slurm_local.sh start)")]


def profile_extra(rule: str) -> list[str]:
    """The ``slurm_extra`` words of a rule in the generated profile."""
    return yaml.safe_load((ROOT / "profiles/slurm/config.yaml").read_text())["set-resources"][rule]["slurm_extra"
                                                                                          ].split()


def request() -> list[str]:
    """The generated profile's request of a training rule (`detail`), its shape overridden to fit one node:
    one node of two tasks, one CPU each, instead of TRAIN's nodes of one task."""
    kept = [word for word in profile_extra("detail") if not word.startswith("--ntasks-per-node")]
    assert kept == ["--signal=USR1@600", "--requeue"], kept
    return ["--nodes=1", "--ntasks=2", "--ntasks-per-node=2", "--cpus-per-task=1", "--mem=4000", *kept]


def state(job: str) -> str:
    proc = subprocess.run(["squeue", "--noheader", "--states=all", "--jobs", job, "--format", "%T"],
                          capture_output=True, text=True)
    return proc.stdout.strip()


def wait_until(test, what: str, timeout_s: float = 600) -> float:
    """Seconds until ``test()`` holds, polled; fails after ``timeout_s``."""
    started = time.monotonic()
    while not test():
        if time.monotonic() - started > timeout_s:
            raise TimeoutError(f"{what}: not within {timeout_s} s")
        time.sleep(0.5)
    return time.monotonic() - started


def submit(log: Path, out: Path, env: dict, shape: list[str], command: str) -> str:
    cmd = ["sbatch", "--parsable", f"--job-name={out.name}", f"--output={log}", "--open-mode=append", "-D",
           str(ROOT), "--export=ALL", *shape, "--wrap", command]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return proc.stdout.strip().split(";")[0]


def environment() -> dict:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "tests")]),
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",  # this interpreter's torchrun
           "OMP_NUM_THREADS": "1", "AGENTS": "2", "NPROC_PER_NODE": "1"}
    env.pop("WAIT_AT_STEP", None)
    return env


def stop_and_requeue(job: str, out: Path, signal_name: str, ranks: int) -> tuple[float, float, float]:
    """Once every rank waits in step 4, ``scancel --signal``; then wait for the requeue and the end. Returns the
    seconds from submission to step 4, from the signal to the requeue, and from the requeue to the end."""
    waiting = [Path(f"{out}.waiting.{rank}") for rank in range(ranks)]
    until_step = wait_until(lambda: all(path.exists() for path in waiting), "every rank in step 4")
    subprocess.run(["scancel", f"--signal={signal_name}", job], check=True)
    signalled = time.monotonic()
    wait_until(lambda: restarts(job) >= 1, "the requeue", timeout_s=120)
    requeued = time.monotonic() - signalled
    # Slurm holds a requeued batch job about two minutes before it may start again; the rehearsal lets it start
    # as soon as the first run's processes are gone from the node, this machine (the job, its requeue and what it
    # runs unchanged).
    wait_until(lambda: state(job) == "PENDING", "the requeued job pending", timeout_s=120)
    wait_until(lambda: subprocess.run(["scontrol", "listpids", job], capture_output=True).returncode != 0,
               "the first run's processes gone", timeout_s=120)
    subprocess.run(["scontrol", "update", f"JobId={job}", "StartTime=now"], check=True)
    return until_step, requeued, wait_until(lambda: state(job) in ENDED, "the requeued job")


def restarts(job: str) -> int:
    text = subprocess.run(["scontrol", "show", "job", job], capture_output=True, text=True).stdout
    return int(text.split("Restarts=")[1].split()[0])


def test_a_slurm_job_of_two_tasks_stopped_by_scancel_requeues_and_ends_bit_identical(tmp_path):
    cache = write_cache(tmp_path / "cache", {"train": [SPAN + 7], "val": [SPAN + 5]}).root
    env = environment()
    command = f"{LAUNCHER} {SCRIPT} {cache} {{out}}"

    straight = submit(tmp_path / "straight.log", tmp_path / "straight", env, request(),
                      command.format(out=tmp_path / "straight"))
    seconds = wait_until(lambda: state(straight) in ENDED, "the uninterrupted job")
    log = (tmp_path / "straight.log").read_text()
    assert state(straight) == "COMPLETED", log[-4000:]
    print(f"\nuninterrupted job {straight}: {seconds:.0f} s from submission to COMPLETED")

    stopped_out = tmp_path / "stopped"
    stopped = submit(tmp_path / "stopped.log", stopped_out, {**env, "WAIT_AT_STEP": "4"}, request(),
                     command.format(out=stopped_out))
    until_step, requeued, rest = stop_and_requeue(stopped, stopped_out, "USR1", ranks=2)
    log = (tmp_path / "stopped.log").read_text()
    assert state(stopped) == "COMPLETED", log[-4000:]
    assert restarts(stopped) == 1
    assert log.count("stopped by SIGUSR1 at step 5 of 12") == 2, log[-4000:]  # both ranks, the same step
    assert f"[multinode_train] Slurm job {stopped} requeued" in log, log[-4000:]
    assert load_checkpoint(stopped_out / "checkpoints" / "last.pt")["step"] == 12
    print(f"stopped job {stopped}: in step 4 {until_step:.0f} s after submission; requeued {requeued:.1f} s "
          f"after `scancel --signal=USR1`; COMPLETED {rest:.0f} s after that")
    one, two = (load_weights(path / "model.pt") for path in (tmp_path / "straight", stopped_out))
    assert one.keys() == two.keys() and all(torch.equal(one[k], two[k]) for k in one)
    print(f"final weights bit-identical: {len(one)} tensors")


# A one-task rule as the Slurm plugin runs it: a job step whose task is a Snakemake process, which runs the rule's
# command through a shell; here a Python parent and `bash -c` stand for the two.
ONE_TASK_STEP = ("srun -n1 python -c \"import subprocess, sys; "
                 "sys.exit(subprocess.call(['bash', '-c', 'set -euo pipefail; python {script} {cache} {out}']))\"")


def test_a_one_task_job_stopped_by_the_sigurg_of_its_request_requeues_and_ends_bit_identical(tmp_path):
    cache = write_cache(tmp_path / "cache", {"train": [SPAN + 7], "val": [SPAN + 5]}).root
    env = environment()
    subprocess.run([sys.executable, SCRIPT, cache, tmp_path / "straight"], env=env, check=True, capture_output=True)
    extra = profile_extra("inverse_dynamics")
    assert extra == ["--signal=URG@600", "--requeue"]
    out = tmp_path / "stopped"
    job = submit(tmp_path / "stopped.log", out, {**env, "WAIT_AT_STEP": "4"},
                 ["--ntasks=1", "--cpus-per-task=1", "--mem=4000", *extra],
                 ONE_TASK_STEP.format(script=SCRIPT, cache=cache, out=out))
    until_step, requeued, rest = stop_and_requeue(job, out, "URG", ranks=1)
    log = (tmp_path / "stopped.log").read_text()
    assert state(job) == "COMPLETED", log[-4000:]
    assert "rank 0: stopped by SIGURG at step 5 of 12" in log, log[-4000:]
    assert f"[multinode_train] Slurm job {job} requeued" in log, log[-4000:]
    print(f"\none-task job {job}: in step 4 {until_step:.0f} s after submission; requeued {requeued:.1f} s after "
          f"`scancel --signal=URG`; COMPLETED {rest:.0f} s after that")
    one, two = (load_weights(path / "model.pt") for path in (tmp_path / "straight", out))
    assert one.keys() == two.keys() and all(torch.equal(one[k], two[k]) for k in one)
    print(f"final weights bit-identical to an uninterrupted process: {len(one)} tensors")
