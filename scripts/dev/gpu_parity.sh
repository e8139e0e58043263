#!/usr/bin/env bash
# The world against the runner on one GPU: the README main job (the default preset on a GPU) trained on MJX,
# exported (all members, actions averaged), then on the same 400 goals and throws (seed 2026)
# evaluated by MJX at JAX's default matmul precision, by MJX at "highest" and by MuJoCo C, and
# played by the parity harness (world on MJX against the runner on the MuJoCo C station).
#   bash scripts/dev/gpu_parity.sh          (on the lent GPU machine; carry .wheels)
# Environment: TRAIN_LIMIT (s, 330). Writes $OUT/export/ (for the CPU side), the run's config and
# metrics, eval_*.json, parity_mjx/ and log.txt.
set -uo pipefail
if ls .wheels/*.whl >/dev/null 2>&1 && ! python3 -c "import mujoco, brax" 2>/dev/null; then
  python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
fi
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 TTMJX_JAX_CACHE=$PWD/.jax_cache
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; R=/tmp/gpujob
t0=$(date +%s)
log() { echo "$(( $(date +%s) - t0 ))s $*" | tee -a "$OUT/log.txt"; }
log "start $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null)"
timeout -s TERM "${TRAIN_LIMIT:-330}" python3 -m ttmjx train --run-dir "$R" --json >"$OUT/train.json" 2>"$OUT/train.err"
log "trained rc=$?"
cp "$R/config.json" "$R/metrics.jsonl" "$OUT/" 2>/dev/null
python3 -m ttmjx export "$R" --out "$OUT/export" --ensemble --onnx off >"$OUT/export.txt" 2>&1
log "exported rc=$?"
export XLA_PYTHON_CLIENT_PREALLOCATE=false
for v in "mjx default" "mjx highest" "c default"; do
  set -- $v
  ( JAX_DEFAULT_MATMUL_PRECISION=$2 timeout 150 python3 -m ttmjx eval "$R" --goals 400 --seed 2026 --backend "$1" \
      --json >"$OUT/eval_$1_$2.json" 2>"$OUT/eval_$1_$2.err"; log "eval $1 $2 rc=$?" ) &
done
( timeout 170 python3 -m ttmjx robot parity --policy "$OUT/export" --n 40 --seed 2026 --backend mjx \
    --out "$OUT/parity_mjx" >"$OUT/parity_mjx.txt" 2>"$OUT/parity_mjx.err"; log "parity mjx rc=$?" ) &
wait
log done
