#!/usr/bin/env bash
# The training launcher inside a Slurm job of one or more nodes (profiles/slurm's training rules):
# one torchrun per node of the job's allocation (srun, one task a node), one process per GPU,
# a c10d rendezvous on the allocation's first node with the job id as its id.
#
#   snakemake --workflow-profile profiles/slurm ... --config profile=paper train_launcher=tools/slurm_torchrun.sh
#   tools/slurm_torchrun.sh stages/predictor.py detail --profile paper     # inside `salloc -N 2 ...`, by hand
#
# The arguments are the training script's. Node list, node count and CPUs come from Slurm (`squeue`):
# Snakemake's job step hands the rule's command only SLURM_JOB_ID, and a step gets one CPU a task
# unless it asks for the node's. Every node must reach the first one on RDZV_PORT (default
# 20000 + job id mod 10000, so that two jobs sharing a node do not meet); NPROC_PER_NODE
# (default `gpu`: one process per visible GPU) sets the processes per agent. AGENTS (default:
# the job's node count, one agent a node) sets how many torchrun agents start, spread evenly
# over the nodes: a rehearsal on one machine starts two, as two nodes would
# (tests/test_slurm_rehearsal.py).
#
# torchrun itself ignores SIGUSR1 (it would otherwise die of it and take the workers with it): Slurm's
# `--signal=USR1@<seconds>` reaches every process of the step, and only the training processes act on it
# (they stop at the next step boundary, write a checkpoint and exit 75; orbis2.train).
set -euo pipefail

job=${SLURM_JOB_ID:?"not inside a Slurm job; on one machine use: torchrun --standalone --nproc_per_node N"}
read -r nodelist nodes cpus < <(squeue --noheader --jobs "$job" --format "%N %D %C")
head=$(scontrol show hostnames "$nodelist" | sed -n 1p)
port=${RDZV_PORT:-$((20000 + job % 10000))}

agents=${AGENTS:-$nodes}
(( agents % nodes == 0 )) || { echo "slurm_torchrun.sh: AGENTS=$agents does not spread evenly over $nodes nodes" >&2; exit 2; }

exec srun --nodes "$nodes" --ntasks "$agents" --ntasks-per-node $((agents / nodes)) \
    --cpus-per-task $((cpus / agents)) --kill-on-bad-exit=1 \
    bash -c 'trap "" USR1; exec "$@"' launcher \
    torchrun --nnodes "$agents" --nproc_per_node "${NPROC_PER_NODE:-gpu}" \
    --rdzv_backend c10d --rdzv_endpoint "$head:$port" --rdzv_id "$job" "$@"
