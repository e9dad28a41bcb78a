"""Training over several nodes: the generated Slurm request and what the Slurm executor submits of it, the
launcher (tools/slurm_torchrun.sh), and a rehearsal on this machine: two simulated nodes (two torchrun agents
meeting through a c10d rendezvous, gloo) against one node of two processes, and SIGUSR1 sent mid-run."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml
from test_predictors import SPAN, write_cache

from orbis2.interfaces import TRAIN
from orbis2.train import load_checkpoint, load_weights

from conftest import controller_listens

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = Path(__file__).with_name("multinode_train.py")
LAUNCHER = ROOT / "tools" / "slurm_torchrun.sh"

# Slurm's commands as the launcher uses them, for a job of two nodes that are both this machine.
FAKE_SLURM = {
    "squeue": 'echo "localhost 2 4"\n',  # squeue --noheader --jobs JOB --format "%N %D %C"
    "scontrol": "echo localhost\n",  # scontrol show hostnames NODELIST
    # srun: the command once per node, side by side; its arguments are recorded.
    "srun": """echo "$*" >> "$SRUN_LOG"
nodes=1
while [[ $# -gt 0 && $1 == --* ]]; do
    case $1 in
        --nodes) nodes=$2; shift 2 ;;
        --*=*) shift ;;
        *) shift 2 ;;
    esac
done
pids=()
for _ in $(seq "$nodes"); do "$@" & pids+=($!); done
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=$?; done
exit $status
""",
    "torchrun": f'exec {sys.executable} -m torch.distributed.run "$@"\n',  # this interpreter's
}


def test_the_slurm_profile_spans_nodes_for_training_and_asks_for_the_warning():
    """Training rules (and only they) get TRAIN's nodes, one task a node with the node's GPUs, SIGUSR1 ahead of
    the time limit and --requeue; the sbatch call the executor plugin makes of that says so, and nothing that
    contradicts it (a job-wide --gpus, tasks per GPU)."""
    slurm = yaml.safe_load((ROOT / "profiles/slurm/config.yaml").read_text())["set-resources"]
    spanning = sorted(name for name, request in slurm.items() if "nodes" in request)
    assert {"tokenizer_detail", "tokenizer_abstract", "abstract_df", "detail", "action", "detail_distill"} <= set(
        spanning)
    assert not {"latents", "inverse_dynamics", "eval_fvd_hierarchical", "town"} & set(spanning)
    assert TRAIN.nodes == 8
    assert slurm["detail"] == {
        "slurm_partition": "gpu", "cpus_per_task": TRAIN.threads, "mem_mb": TRAIN.mem_mb, "runtime": TRAIN.runtime,
        "gres": f"gpu:{TRAIN.gpu}", "nodes": TRAIN.nodes, "mpi": "srun", "tasks": TRAIN.nodes, "tasks_per_gpu": 0,
        "gpu": 0, "slurm_extra": "--ntasks-per-node=1 --signal=USR1@600 --requeue"}

    submit = pytest.importorskip("snakemake_executor_plugin_slurm.submit_string")
    from snakemake_executor_plugin_slurm.utils import set_gres_string
    from snakemake_executor_plugin_slurm.validation import validate_slurm_extra

    class Resources(dict):
        __getattr__ = dict.__getitem__

    job = SimpleNamespace(resources=Resources({"gpu": TRAIN.gpu, **slurm["detail"]}), threads=TRAIN.threads)
    validate_slurm_extra(job)
    params = {"run_uuid": "job", "slurm_logfile": "log", "comment_str": "detail", "account": "",
              "partition": "-p gpu", "workdir": "."}
    call = submit.get_submit_command(job, params) + set_gres_string(job)
    words = call.split()
    for expected in ("--nodes=8", "--ntasks=8", "--ntasks-per-node=1", "--cpus-per-task=16", "--gres=gpu:8",
                     "--signal=USR1@600", "--requeue", "480000"):
        assert expected in words, (expected, call)
    assert not [w for w in words if w.startswith(("--gpus", "--ntasks-per-gpu"))], call


def sbatch_call(request: dict) -> list[str]:
    """The words of the sbatch call that snakemake-executor-plugin-slurm makes of a rule's profile entry."""
    submit = pytest.importorskip("snakemake_executor_plugin_slurm.submit_string")
    from snakemake_executor_plugin_slurm.utils import set_gres_string
    from snakemake_executor_plugin_slurm.validation import validate_slurm_extra

    class Resources(dict):
        __getattr__ = dict.__getitem__

    job = SimpleNamespace(resources=Resources({"gpu": 0, **request}), threads=request["cpus_per_task"])
    validate_slurm_extra(job)
    params = {"run_uuid": "job", "slurm_logfile": "log", "comment_str": "rule", "account": "", "partition": "-p gpu",
              "workdir": "."}
    return (submit.get_submit_command(job, params) + set_gres_string(job)).split()


def test_every_training_rule_is_warned_and_requeued_and_a_one_task_job_with_sigurg():
    """A training rule of one task (inverse_dynamics; every training rule when TRAIN is one node) asks for
    SIGURG ahead of its limit: the plugin runs it under Snakemake in a one-task job step, which Slurm's signal
    reaches and SIGUSR1 would kill. No other rule asks for a signal."""
    from orbis2 import dag
    from orbis2.interfaces import GPU, INTERFACES, Resources

    slurm = yaml.safe_load((ROOT / "profiles/slurm/config.yaml").read_text())["set-resources"]
    training = {name for name, request in slurm.items() if "--requeue" in request.get("slurm_extra", "")}
    assert {"tokenizer_detail", "detail", "abstract_df", "inverse_dynamics"} <= training
    assert not {name for name, request in slurm.items() if "slurm_extra" in request} - training
    assert "mpi" not in slurm["inverse_dynamics"]
    assert slurm["inverse_dynamics"]["slurm_extra"] == "--signal=URG@600 --requeue"
    words = sbatch_call(slurm["inverse_dynamics"])
    assert {"--signal=URG@600", "--requeue", "--gres=gpu:1"} <= set(words), words

    class Value(int):
        value = property(int)

    rule = SimpleNamespace(shellcmd="{config[train_launcher]} stages/predictor.py detail --profile paper",
                           resources={"gpu": Value(8), "_cores": Value(16), "mem_mb": Value(480000),
                                      "runtime": Value(2880)})
    one_node = Resources(threads=16, gpu=8, mem_mb=480000, runtime=2880, nodes=1)
    assert dag.slurm_resources(rule)["nodes"] == TRAIN.nodes
    original = dag.TRAIN
    try:
        dag.TRAIN = one_node
        request = dag.slurm_resources(rule)
    finally:
        dag.TRAIN = original
    assert request == {"slurm_partition": "gpu", "cpus_per_task": 16, "mem_mb": 480000, "runtime": 2880,
                       "gres": "gpu:8", "slurm_extra": "--signal=URG@600 --requeue"}
    assert {"--signal=URG@600", "--requeue", "--gres=gpu:8"} <= set(sbatch_call(request))
    evaluation = SimpleNamespace(shellcmd=f"python {INTERFACES['eval_steering'].script} --profile paper",
                                 resources=rule.resources)
    assert "slurm_extra" not in dag.slurm_resources(evaluation) and GPU.nodes == 1


def test_the_launcher_refuses_to_run_outside_slurm():
    env = {k: v for k, v in os.environ.items() if k != "SLURM_JOB_ID"}
    proc = subprocess.run([str(LAUNCHER), "stages/predictor.py"], env=env, capture_output=True, text=True)
    assert proc.returncode != 0
    assert "not inside a Slurm job; on one machine use: torchrun --standalone" in proc.stderr


def test_the_suite_asks_sinfo_only_where_a_controller_listens(tmp_path, monkeypatch):
    """conftest.controller_listens, run before the session's one `sinfo` (9 s where nothing answers): the
    controller slurm.conf names found listening, the same address refused at once, no slurm.conf left to
    `sinfo`."""
    conf = tmp_path / "slurm.conf"
    monkeypatch.setenv("SLURM_CONF", str(conf))
    assert controller_listens() is None
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        conf.write_text(f"ClusterName=x\nSlurmctldHost=node(127.0.0.1)  # the controller\nSlurmctldPort={port}\n")
        assert controller_listens() is True
    assert controller_listens() is False


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def launch(cmd: list, env: dict, expect_ok: bool = True) -> str:
    proc = subprocess.run([str(c) for c in cmd], env=env, capture_output=True, text=True, timeout=300)
    text = proc.stdout + proc.stderr
    assert (proc.returncode == 0) == expect_ok, text[-4000:]
    return text


@pytest.mark.slow
def test_two_simulated_nodes_stopped_by_sigusr1_and_requeued_end_as_one_node_of_two_processes(tmp_path):
    """The generated launcher over two simulated nodes, with SIGUSR1 sent to rank 1 and its torchrun mid-run:
    both ranks stop at the next step with a checkpoint; the requeued job ends with the weights of one
    uninterrupted `torchrun --standalone --nproc_per_node 2`, bit for bit. (One stopped and one requeued
    launch rather than an uninterrupted one as well: each launch costs 15 s of imports here.)"""
    cache = write_cache(tmp_path / "cache", {"train": [SPAN + 7], "val": [SPAN + 5]})  # 2 global batches of 4
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "tests")]),
           "OMP_NUM_THREADS": "1"}
    env.pop("SLURM_JOB_ID", None)
    launch([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", SCRIPT,
            cache.root, tmp_path / "one"], env)

    fake = tmp_path / "bin"
    fake.mkdir()
    for name, body in FAKE_SLURM.items():
        (fake / name).write_text("#!/usr/bin/env bash\n" + body)
        (fake / name).chmod(0o755)
    port = free_port()
    nodes = {**env, "PATH": f"{fake}{os.pathsep}{env['PATH']}", "SLURM_JOB_ID": "4242", "RDZV_PORT": str(port),
             "NPROC_PER_NODE": "1", "SRUN_LOG": str(tmp_path / "srun.log")}
    text = launch([LAUNCHER, SCRIPT, cache.root, tmp_path / "two", 4], nodes, expect_ok=False)
    srun = (tmp_path / "srun.log").read_text().splitlines()[0]
    assert srun.startswith("--nodes 2 --ntasks 2 --ntasks-per-node 1 --cpus-per-task 2 --kill-on-bad-exit=1 bash")
    assert (f"torchrun --nnodes 2 --nproc_per_node 1 --rdzv_backend c10d --rdzv_endpoint localhost:{port} "
            f"--rdzv_id 4242 {SCRIPT}") in srun
    assert text.count("stopped by SIGUSR1 at step 5 of 12") == 2, text[-4000:]  # both ranks, the same step
    assert load_checkpoint(tmp_path / "two" / "checkpoints" / "last.pt")["step"] == 5
    assert not (tmp_path / "two" / "model.pt").exists()
    launch([LAUNCHER, SCRIPT, cache.root, tmp_path / "two"], nodes)  # the requeued job
    one, two = (load_weights(tmp_path / name / "model.pt") for name in ("one", "two"))
    assert one.keys() == two.keys() and all(torch.equal(one[k], two[k]) for k in one)


@pytest.mark.parametrize("signal_name, requeued", [("SIGUSR1", True), ("SIGURG", True), ("SIGTERM", False)])
def test_a_stopped_stage_exits_75_and_requeues_its_slurm_job_on_sigusr1(tmp_path, monkeypatch, capfd, signal_name,
                                                                        requeued):
    """SIGUSR1 and SIGURG are the warning ahead of the time limit: the stage asks Slurm to requeue its job;
    SIGTERM (a cancel, a preemption) does not. Either way the stage exits with REQUEUE_EXIT."""
    import argparse
    import contextlib

    from orbis2 import stage
    from orbis2.errors import REQUEUE_EXIT, TrainingStopped
    from orbis2.interfaces import INTERFACES

    (tmp_path / "scontrol").write_text('#!/usr/bin/env bash\necho "$*" >> "$SCONTROL_LOG"\n')
    (tmp_path / "scontrol").chmod(0o755)
    monkeypatch.setenv("PATH", f"{tmp_path}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("SCONTROL_LOG", str(tmp_path / "scontrol.log"))
    monkeypatch.setenv("SLURM_JOB_ID", "77")
    monkeypatch.setattr(stage, "stage_run", lambda *args: contextlib.nullcontext(None))  # no MLflow run
    args = argparse.Namespace(params=str(ROOT / "params.yaml"), profile="smoke")
    with pytest.raises(SystemExit) as end:
        with stage.open_stage("train_something", args, INTERFACES["town"]):
            raise TrainingStopped(f"stopped by {signal_name} at step 5 of 12, checkpoint c written; run the stage "
                                  "again to resume", signal_name, 5)
    assert end.value.code == REQUEUE_EXIT == 75
    err = capfd.readouterr().err
    assert f"[train_something] stopped by {signal_name} at step 5 of 12" in err
    if requeued:
        assert (tmp_path / "scontrol.log").read_text() == "requeue 77\n"
        assert "[train_something] Slurm job 77 requeued: it resumes when Slurm starts it again" in err
    else:
        assert not (tmp_path / "scontrol.log").exists()
