#!/usr/bin/env bash
# CUDA checks and speed benchmarks on one GPU machine, results as JSON in $OUT.
#
#   OUT=/path/to/results bash tools/gpu_run.sh        # from the repository root
#
# The machine needs Python 3.12 with torch (CUDA), numpy and opencv; whatever
# else the project imports comes from ./wheelhouse (built by
# tools/build_wheelhouse.sh), installed without network into $DEPS (default
# /tmp/pydeps), skipping distributions the machine already has. Each step has
# its own time limit (seconds, overridable: T_TESTS, T_ROLLOUT, T_FP32,
# T_COMPILE, T_TRAIN, T_DEPS) and a failed or timed-out step does not stop the others;
# the whole run stays under 9 minutes. Compilation time is reported apart
# (warmup_s in the rollout JSON).
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

step() {  # step NAME SECONDS COMMAND...: run with a time limit, record the exit status, never abort the script
  local name=$1 limit=$2; shift 2
  log "start $name (limit ${limit} s)"
  local start=$SECONDS status=0
  timeout --kill-after=10 "$limit" "$@" > "$OUT/$name.txt" 2>&1 || status=$?
  log "end $name: exit $status after $((SECONDS - start)) s"
  echo "{\"step\": \"$name\", \"exit\": $status, \"seconds\": $((SECONDS - start))}" >> "$OUT/steps.jsonl"
  tail -n 25 "$OUT/$name.txt"
}

step deps "${T_DEPS:-60}" bash -c "\"$PY\" -m snakemake --version && \"$PY\" -m dvc --version && \"$PY\" -c '
import mlflow, webdataset, tempfile, os
uri = \"sqlite:///\" + os.path.join(tempfile.mkdtemp(), \"check.db\")
mlflow.set_tracking_uri(uri)
with mlflow.start_run():
    mlflow.log_metric(\"x\", 1.0)
print(\"mlflow\", mlflow.__version__, \"sqlite tracking ok; webdataset ok\")'"
step tests "${T_TESTS:-110}" "$PY" -m pytest -q -p no:cacheprovider tests/test_gpu.py tests/test_acceleration.py \
  --junitxml="$OUT/tests.xml"
step rollout_bf16 "${T_ROLLOUT:-130}" "$PY" benchmarks/bench_rollout.py --preset paper --seconds 1 --repeats 1 \
  --timeout 65 --json "$OUT/rollout_bf16.json"
step rollout_fp32 "${T_FP32:-40}" "$PY" benchmarks/bench_rollout.py --preset paper --seconds 0.5 --repeats 1 \
  --precision fp32 --systems hierarchical --timeout 40 --json "$OUT/rollout_fp32.json"
step rollout_compile "${T_COMPILE:-110}" "$PY" benchmarks/bench_rollout.py --preset paper --seconds 1 --repeats 2 \
  --compile --systems distilled --timeout 105 --json "$OUT/rollout_compile.json"
step train "${T_TRAIN:-90}" "$PY" benchmarks/bench_train.py --presets default,paper --mfu-preset paper \
  --batch-size 2 --checkpointing 0 --steps 3 --warmup 1 --max-batch 32 --json "$OUT/train.json"
log "done; results in $OUT"
