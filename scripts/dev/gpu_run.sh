#!/usr/bin/env bash
# Runs on the lent GPU machine (device tool) from the repository root. Installs the carried
# wheels (../shared/gpu/wheelhouse.sh builds them into .wheels), then runs the named steps,
# writing JSON results and small artefacts under $OUT.
#   bash scripts/dev/gpu_run.sh bench demos ...      (training runs: scripts/dev/gpu_train.sh)
set -uo pipefail
python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
export TTMJX_JAX_CACHE=$PWD/.jax_cache
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee "$OUT/gpu.txt"
tt() { python3 -m ttmjx "$@"; }
for step in "$@"; do
  echo "=== $step $(date +%T)"
  case "$step" in
    bench)
      for b in 4096 16384 32768; do tt bench --backend mjx --batch $b --json | tail -1 | tee -a "$OUT/bench_mjx.jsonl"; done ;;
    demos)
      rm -rf runs/gpu_demos_any
      tt demos --source scripted --distribution any --n 16384 --backend mjx --out runs/gpu_demos_any --json | tail -1 | tee "$OUT/demos_mjx.json"
      tt plot-landings runs/gpu_demos_any --out "$OUT/landings_any_gpu.png" ;;
    *) python3 - <<<"$step" ;;
  esac
done
