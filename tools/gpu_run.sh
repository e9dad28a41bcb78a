#!/usr/bin/env bash
# The GPU measurement: one script of at most 6 minutes; everything it measures ends up in two files,
# $OUT/summary.json (each figure, its repeats and each part's status) and $OUT/results.tar.gz (every part's
# JSON and log), so a machine that returns few files returns all of it. Nothing else is written under $OUT:
# the lent machine returns at most 8 of its files, chosen by it, so the parts write to a working folder
# outside it (a new temporary folder, removed at the end; its files are the archive's work/).
#
#   OUT=/path/to/results bash tools/gpu_run.sh          # from the repository root, on the GPU machine
#   REHEARSE=1 OUT=/tmp/rehearsal bash tools/gpu_run.sh  # every part on the CPU, smoke preset
#   (the rollouts' predictors compiled through dynamo alone, rollouts_v1 eager and the toggles without their compile check there;
#   the DAG part a Snakemake dry run)
#
# Parts, in the order of what they are worth if time runs out, each under its own limit (seconds; T_<PART>
# overrides) within BUDGET (default 350 s): a part that fails or times out does not stop the others.
#   peak            device, driver, memory, bf16 matmul peak (table and measured)
#   forwards        detail / abstract / cached / flat forward, weights cast once: time, kernels, top kernels
#   rollouts        hierarchy and distilled rollouts at the paper preset, compiled with CUDA graphs
#                   (compile time apart), frames/s with decoding, peak memory
#   train           detail and abstract training steps at the paper preset, compiled, the paper profile's
#                   checkpointing: MFU against the table's bf16 peak and the measured matmul
#   graphs          CUDA-graph capture and replay of the detail forward against eager
#   rollouts_eager  the same two rollouts eager, for the compiled/eager ratio
#   toggles         compile, KV cache, bf16 (weights cast once), TF32, each against its reference
#   rollouts_v1     flat detail and the Orbis v1-style baseline (the slowest systems), compiled
#   dag             the gpu profile's DAG scaled down; needs the I3D/Inception assets (ASSETS=dir holding
#                   data/assets) and the DAG's packages (./wheelhouse, tools/build_wheelhouse.sh): skipped
#                   without them, since the machine has no network
#
# The machine needs Python with torch (CUDA), numpy, pyyaml, opencv and pillow, which every part but the DAG
# imports alone. The files to carry there: the repository (and ./wheelhouse for the DAG part); the script
# reports their size (carried_mib) and refuses to start the DAG part's install over CARRY_LIMIT_MIB.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:?set OUT to the folder that receives summary.json and results.tar.gz}
PY=${PYTHON:-python3}
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
WORK=$(mktemp -d)/work
mkdir -p "$WORK"
log() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$WORK/gpu_run.log"; }

pack() {  # whatever happened: the summary and one archive of every file written
  "$PY" benchmarks/gpu_suite.py summary --out "$WORK" --summary "$OUT/summary.json" >> "$WORK/gpu_run.log" 2>&1 \
    || echo "{\"error\": \"summary failed; see results.tar.gz work/gpu_run.log\"}" > "$OUT/summary.json"
  tar -czf "$OUT/results.tar.gz" -C "$(dirname "$WORK")" work
  rm -rf "$(dirname "$WORK")"
}
trap pack EXIT

REHEARSE=${REHEARSE:-}
SLACK=${REHEARSE:+4}  # a rehearsal's limits: the CPU may be shared (a test suite), and no device time is at stake
SLACK=${SLACK:-1}
BUDGET=${BUDGET:-$((350 * SLACK))}
CARRY_LIMIT_MIB=${CARRY_LIMIT_MIB:-60}
"$PY" benchmarks/gpu_suite.py carried --root . --out "$WORK" --limit-mib "$CARRY_LIMIT_MIB" | tee -a "$WORK/gpu_run.log"

step() {  # step NAME SECONDS COMMAND...: run with a time limit within the budget, record the exit status, go on
  local name=$1 limit=$(($2 * SLACK)); shift 2
  local left=$((BUDGET - SECONDS - 10))
  if [ "$left" -lt 10 ]; then
    log "skip $name: budget spent"
    echo "{\"step\": \"$name\", \"exit\": null, \"seconds\": 0, \"skipped\": \"budget\"}" >> "$WORK/steps.jsonl"
    return 0
  fi
  [ "$limit" -gt "$left" ] && limit=$left
  log "start $name (limit ${limit} s)"
  local start=$SECONDS status=0
  timeout --kill-after=10 "$limit" "$@" > "$WORK/$name.txt" 2>&1 || status=$?
  log "end $name: exit $status after $((SECONDS - start)) s"
  echo "{\"step\": \"$name\", \"exit\": $status, \"seconds\": $((SECONDS - start)), \"limit\": $limit}" \
    >> "$WORK/steps.jsonl"
  tail -n 5 "$WORK/$name.txt"
}

export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1
suite=(--out "$WORK")
if [ -n "$REHEARSE" ]; then  # CPU, smoke preset: every part's real code path in minutes
  suite+=(--rehearse)
  toggles=(--no-compile)  # the rollouts and train parts rehearse the compiled paths; the suite has no time to spare
  preset=smoke device=cpu
  # The compiled paths without inductor's CPU code generation, which is not what runs on a GPU: the rollouts trace
  # the predictors and the decoder through dynamo only (the eager backend), the training step through dynamo and
  # AOTAutograd (aot_eager: forward and backward graphs, the checkpointing policy in them). tests/test_compiled_path.py
  # runs the predictors' inductor code; the suite has no time to spare.
  rollout=(--seconds 0.5 --repeats 1 --distill-nfe 2 --backend eager)
  v1=()  # eager: the rollouts part rehearses the compiled rollout already, and the test suite has no time to spare
  train=(--presets smoke --mfu-preset smoke --batch-size 2 --checkpointing 2 --steps 1 --warmup 1 --backend aot_eager)
else
  preset=paper device=cuda
  rollout=(--seconds 2 --repeats 3)
  v1=(--compile) toggles=()
  train=(--presets paper --mfu-preset paper --batch-size 8 --checkpointing 24 --steps 3 --warmup 2)
fi
rollout_cmd=("$PY" benchmarks/bench_rollout.py --preset "$preset" --device "$device" "${rollout[@]}"
             --timeout $((100 * SLACK)))
step peak "${T_PEAK:-20}" "$PY" benchmarks/gpu_suite.py peak "${suite[@]}"
step forwards "${T_FORWARDS:-35}" "$PY" benchmarks/gpu_suite.py forwards "${suite[@]}"
step rollouts "${T_ROLLOUTS:-140}" "${rollout_cmd[@]}" --systems hierarchical,distilled --compile \
  --json "$WORK/rollouts.json"
step train "${T_TRAIN:-80}" "$PY" benchmarks/bench_train.py "${train[@]}" --policy selective --max-batch 0 \
  --compile --device "$device" --json "$WORK/train.json"
step graphs "${T_GRAPHS:-20}" "$PY" benchmarks/gpu_suite.py graphs "${suite[@]}"
step rollouts_eager "${T_ROLLOUTS_EAGER:-35}" "${rollout_cmd[@]}" --systems hierarchical,distilled \
  --json "$WORK/rollouts_eager.json"
step toggles "${T_TOGGLES:-30}" "$PY" benchmarks/gpu_suite.py toggles "${suite[@]}" "${toggles[@]}"
step rollouts_v1 "${T_ROLLOUTS_V1:-60}" "${rollout_cmd[@]}" --systems flat_detail,v1_style "${v1[@]}" \
  --json "$WORK/rollouts_v1.json"
step dag "${T_DAG:-120}" "$PY" benchmarks/gpu_suite.py dag "${suite[@]}" --assets "${ASSETS:-}"
log "done in $SECONDS s"
