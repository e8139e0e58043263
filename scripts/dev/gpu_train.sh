#!/usr/bin/env bash
# On the lent GPU machine: train several runs side by side (one process each; MJX rollouts are
# latency-bound, so runs share one GPU well), each stopped by SIGTERM after SECONDS (it saves a
# checkpoint; the same command resumes it on a warm machine).
#   bash scripts/dev/gpu_train.sh SECONDS NAME=PRESET[:extra args] ...   -> runs/NAME, $OUT/NAME_*
set -uo pipefail
python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false TTMJX_JAX_CACHE=$PWD/.jax_cache
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
secs=$1; shift
for spec in "$@"; do
  name=${spec%%=*}; rest=${spec#*=}; preset=${rest%%:*}; extra=""; [[ $rest == *:* ]] && extra=${rest#*:}
  ( timeout -s TERM "$secs" python3 -m ttmjx train --preset "$preset" --run-dir "runs/$name" --json $extra 2>&1 \
      | tr '\r' '\n' | grep -v "traj/s\|^\s*$" > "$OUT/$name.log"
    for f in metrics.jsonl learning_curve.png config.json; do cp "runs/$name/$f" "$OUT/${name}_$f"; done ) &
done
wait
for spec in "$@"; do n=${spec%%=*}; echo "== $n"; tail -2 "$OUT/$n.log"; done
