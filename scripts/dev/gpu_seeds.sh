#!/usr/bin/env bash
# On the lent GPU machine (device tool), from the repository root: `ttmjx bench --train` for
# PRESET:SEEDS pairs, then any further ttmjx command lines, each under its own time limit.
#   bash scripts/dev/gpu_seeds.sh paper-sim:1 paper-sim:5 -- "train --preset paper-sim --seeds 5 ..."
# Writes $OUT/gpu.txt, $OUT/bench_<preset>_<seeds>.json and $OUT/log.txt (everything printed).
set -uo pipefail
python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false TTMJX_JAX_CACHE=$PWD/.jax_cache
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
LIMIT=${LIMIT:-280}
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee "$OUT/gpu.txt"
while [[ $# -gt 0 && $1 != "--" ]]; do
  p=${1%%:*}; s=${1#*:}; shift
  echo "=== bench $p seeds $s $(date +%T)" | tee -a "$OUT/log.txt"
  timeout "$LIMIT" python3 -m ttmjx bench --train "$p" --seeds "$s" --reps 1 --json 2>>"$OUT/log.txt" \
    | tail -1 | tee "$OUT/bench_${p}_$s.json"
done
[[ ${1:-} == "--" ]] && shift
for cmd in "$@"; do
  echo "=== ttmjx $cmd $(date +%T)" | tee -a "$OUT/log.txt"
  /usr/bin/time -f "wall %e s, peak rss %M kB" timeout -s TERM "$LIMIT" python3 -m ttmjx $cmd 2>&1 \
    | tr '\r' '\n' | grep -v "traj/s\|throw/s\|^\s*$" | tee -a "$OUT/log.txt" | tail -3
done
echo "=== done $(date +%T)" | tee -a "$OUT/log.txt"
