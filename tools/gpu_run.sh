#!/usr/bin/env bash
# The GPU measurement: one script of at most 8 minutes, results as JSON in $OUT, written as it goes.
#
#   OUT=/path/to/results bash tools/gpu_run.sh         # from the repository root, on the GPU machine
#   DRY=1 OUT=/tmp/gpu-dry bash tools/gpu_run.sh       # the same parts on the CPU at the smoke preset
#
# Parts, each under its own time limit (seconds, overridable: T_PEAK, T_FORWARDS, T_TOGGLES,
# T_GRAPHS, T_ROLLOUTS, T_TRAIN, T_DAG) and all within BUDGET (default 470 s): a failed or timed-out
# part does not stop the others, and a part never gets more than what is left of the budget.
#   peak      device, memory, bf16 matmul peak (table and measured)          -> peak.json
#   forwards  detail / abstract / cached / flat forward: CUDA-event time,
#             kernel count and top kernels (torch.profiler)                  -> forwards.json
#   toggles   compile, KV cache, bf16, TF32 against their references         -> toggles.json
#   graphs    CUDA-graph capture and replay of the detail forward vs eager   -> graphs.json
#   rollouts  hierarchy, distilled hierarchy, flat detail, v1-style:
#             3 repeats x 4 steps, median and minimum, peak memory            -> rollouts.json
#   train     detail and abstract training steps at the paper preset, the paper
#             profile's per-GPU batch and checkpointing: MFU against the table's
#             bf16 peak and the measured matmul                              -> train.json
#   dag       the gpu profile's DAG with its steps scaled down, on CUDA       -> dag.json
#
# The machine needs Python 3.12 with torch (CUDA), numpy and opencv; whatever
# else the project imports comes from ./wheelhouse (built by
# tools/build_wheelhouse.sh), installed without network into $DEPS (default
# /tmp/pydeps), skipping distributions the machine already has.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:?set OUT to the folder that receives the results}
DEPS=${DEPS:-/tmp/pydeps}
PY=${PYTHON:-python3}
mkdir -p "$OUT" "$DEPS"
log() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$OUT/gpu_run.log"; }

if [ -d wheelhouse ] && compgen -G "wheelhouse/*.whl" > /dev/null; then
  # Only the distributions this Python lacks: never shadow the machine's torch, numpy or their dependencies.
  mapfile -t missing < <("$PY" - <<'EOF'
import importlib.metadata as md, pathlib, re
for wheel in sorted(pathlib.Path("wheelhouse").glob("*.whl")):
    name = re.sub(r"[-_.]+", "-", wheel.name.split("-")[0]).lower()
    try:
        md.version(name)
    except md.PackageNotFoundError:
        print(wheel)
EOF
  )
  if [ "${#missing[@]}" -gt 0 ]; then
    log "installing ${#missing[@]} wheels into $DEPS"
    # Wheels repacked from installed copies carry console scripts outside the package (../bin), which
    # `pip install --target` refuses: unpack those as plain archives (their scripts are not needed).
    plain=() unpacked=()
    for wheel in "${missing[@]}"; do
      if unzip -l "$wheel" | grep -q '\.\./'; then unpacked+=("$wheel"); else plain+=("$wheel"); fi
    done
    for wheel in "${unpacked[@]}"; do unzip -q -o "$wheel" -x '../*' -d "$DEPS"; done
    "$PY" -m pip install --quiet --no-index --no-deps --no-compile --target "$DEPS" "${plain[@]}" \
      >> "$OUT/gpu_run.log" 2>&1
  fi
fi
export PYTHONPATH="$PWD/src:$DEPS${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONDONTWRITEBYTECODE=1

"$PY" - <<'EOF' | tee "$OUT/environment.txt"
import torch
print("torch", torch.__version__, "cuda", torch.version.cuda)
print("device", torch.cuda.get_device_name() if torch.cuda.is_available() else "none")
EOF

DRY=${DRY:-}
SLACK=${DRY:+10}  # a dry run's limits: the CPU may be shared (a test suite), and no device time is at stake
SLACK=${SLACK:-1}
BUDGET=${BUDGET:-$((470 * SLACK))}
step() {  # step NAME SECONDS COMMAND...: run with a time limit within the budget, record the exit status, go on
  local name=$1 limit=$(($2 * SLACK)); shift 2
  local left=$((BUDGET - SECONDS - 5))
  if [ "$left" -lt 10 ]; then
    log "skip $name: budget spent"
    echo "{\"step\": \"$name\", \"exit\": null, \"seconds\": 0, \"skipped\": \"budget\"}" >> "$OUT/steps.jsonl"
    return 0
  fi
  [ "$limit" -gt "$left" ] && limit=$left
  log "start $name (limit ${limit} s)"
  local start=$SECONDS status=0
  timeout --kill-after=10 "$limit" "$@" > "$OUT/$name.txt" 2>&1 || status=$?
  log "end $name: exit $status after $((SECONDS - start)) s"
  echo "{\"step\": \"$name\", \"exit\": $status, \"seconds\": $((SECONDS - start))}" >> "$OUT/steps.jsonl"
  tail -n 15 "$OUT/$name.txt"
}

if [ -n "$DRY" ]; then  # CPU, smoke preset: every part's code path in a few minutes
  suite=(--dry --no-compile) preset=smoke device=cpu
  rollout=(--seconds 0.5 --repeats 1 --systems distilled --distill-nfe 1)
  train=(--presets smoke --mfu-preset smoke --batch-size 2 --checkpointing 2 --steps 1 --warmup 0)
else
  suite=() preset=paper device=cuda
  rollout=(--seconds 2 --repeats 3)
  train=(--presets paper --mfu-preset paper --batch-size 8 --checkpointing 24 --steps 3 --warmup 2)
fi
step peak "${T_PEAK:-15}" "$PY" benchmarks/gpu_suite.py peak --out "$OUT" "${suite[@]}"
step forwards "${T_FORWARDS:-40}" "$PY" benchmarks/gpu_suite.py forwards --out "$OUT" "${suite[@]}"
step toggles "${T_TOGGLES:-70}" "$PY" benchmarks/gpu_suite.py toggles --out "$OUT" "${suite[@]}"
step graphs "${T_GRAPHS:-20}" "$PY" benchmarks/gpu_suite.py graphs --out "$OUT" "${suite[@]}"
step rollouts "${T_ROLLOUTS:-90}" "$PY" benchmarks/bench_rollout.py --preset "$preset" --device "$device" \
  "${rollout[@]}" --timeout $((45 * SLACK)) --json "$OUT/rollouts.json"
step train "${T_TRAIN:-60}" "$PY" benchmarks/bench_train.py "${train[@]}" --policy selective --max-batch 0 \
  --device "$device" --json "$OUT/train.json"
step dag "${T_DAG:-170}" "$PY" benchmarks/gpu_suite.py dag --out "$OUT" "${suite[@]}"
log "done in $SECONDS s; results in $OUT"
