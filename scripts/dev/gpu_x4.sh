#!/usr/bin/env bash
# One call on four H200s (nvidia-h200-x4), each GPU its own process:
#   GPUs 0-2: Table I's QT-Opt row, 120,000 trajectories, seeds 0-1, 2-3 and 4;
#   GPU 3:    the README main job retrained after the tick-0 velocity fix, and its export played
#             by the world and the runner (scripts/dev/gpu_parity2.sh).
#   bash scripts/dev/gpu_x4.sh      (carry .wheels)
# Writes $OUT/qtopt.tgz (each seed's results and timing), $OUT/results.tgz and $OUT/member0.tgz
# (the main job's figures and member 0's export) and $OUT/log.txt.
set -uo pipefail
if ls .wheels/*.whl >/dev/null 2>&1 && ! python3 -c "import mujoco, brax" 2>/dev/null; then
  python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
fi
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 TTMJX_JAX_CACHE=$PWD/.jax_cache XLA_PYTHON_CLIENT_PREALLOCATE=false
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; Q=/tmp/q; mkdir -p "$Q"
t0=$(date +%s)
log() { echo "$(( $(date +%s) - t0 ))s $*" | tee -a "$OUT/log.txt"; }
log "start $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | tr '\n' ' ')"
lane() {  # gpu, first seed, seeds
  ( CUDA_VISIBLE_DEVICES=$1 timeout -s TERM "${Q_LIMIT:-500}" python3 -m ttmjx baseline qtopt --scale full \
      --seed "$2" --seeds "$3" --trajectories 120000 --out "$Q/s$2" >"$Q/s$2.log" 2>&1
    log "qtopt seeds $2..$(( $2 + $3 - 1 )) rc=$?" ) &
}
lane 0 0 2; lane 1 2 2; lane 2 4 1
( CUDA_VISIBLE_DEVICES=3 OUT=/tmp/pout TRAIN_LIMIT=300 bash scripts/dev/gpu_parity2.sh >/tmp/pout.log 2>&1
  log "main job rc=$?" ) &
wait
log done
cp /tmp/pout/results.tgz /tmp/pout/member0.tgz "$OUT/" 2>/dev/null
cat /tmp/pout/log.txt >>"$OUT/log.txt" 2>/dev/null
tar czf "$OUT/qtopt.tgz" -C "$Q" --exclude qtopt_state --exclude '*_state' . 2>/dev/null
