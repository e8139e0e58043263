#!/usr/bin/env bash
# On the lent GPU machine: run cells of one ablation side by side (one process per cell spec;
# MJX rollouts are latency-bound, so runs share one GPU), each under a time limit, then copy the
# small cell results (not the checkpoints) and the rebuilt report to $OUT.
#   bash scripts/dev/gpu_ablate.sh SECONDS NAME TRAJECTORIES CELLS [CELLS ...]
set -uo pipefail
python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false TTMJX_JAX_CACHE=$PWD/.jax_cache
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
secs=$1; name=$2; traj=$3; shift 3
dir=/tmp/ablations/$name-full
for cells in "$@"; do
  ( timeout -s TERM "$secs" python3 -m ttmjx ablate "$name" --scale full --seeds 5 --cells "$cells" \
      --trajectories "$traj" --out "$dir" 2>&1 | tr '\r' '\n' | grep -v "traj/s\|throw/s\|^\s*$" > "$OUT/${name}_${cells//[:,]/_}.log" ) &
done
wait
mkdir -p "$OUT/$name"; cp -r "$dir/results" "$OUT/$name/" 2>/dev/null
for cells in "$@"; do echo "== $cells"; tail -4 "$OUT/${name}_${cells//[:,]/_}.log"; done
