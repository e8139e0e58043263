#!/usr/bin/env bash
# scripts/dev/confirm.sh's fresh-seed runs on a lent GPU machine's CPUs, side by side: for each
# SEEDS x {default, lfp} one process pinned to CORES cores (MuJoCo C physics, as the README's main
# job), trained with `timeout -s TERM $LIMIT` (a stopped run saves; the next call resumes it in
# the same W folder, which lives in /tmp while the machine stays warm), then the evaluations of
# confirm.sh once the run has finished. Outputs are named as confirm.sh's, so
# `python3 scripts/dev/confirm_table.py DIR` reads them; $OUT/confirm.tgz holds them.
#   SEEDS="3 4" LIMIT=470 bash scripts/dev/gpu_confirm.sh
# EXTRA: flags added to both presets' training (e.g. EXTRA="--policy.head mixture"); CORES cores a run.
set -uo pipefail
if ls .wheels/*.whl >/dev/null 2>&1 && ! python3 -c "import mujoco, brax" 2>/dev/null; then
  python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
fi
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 JAX_PLATFORMS=cpu CUDA_VISIBLE_DEVICES= TTMJX_JAX_CACHE=$PWD/.jax_cache_cpu
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; W=${W:-/tmp/confirm}; mkdir -p "$W"
SEEDS=${SEEDS:-3 4}; LIMIT=${LIMIT:-470}; CORES=${CORES:-4}; EXTRA=${EXTRA:-}
one() {  # variant seed cores
  local v=$1 s=$2 cores=$3 d=$W/$1-s$2
  [ -f "$d.done" ] && return
  if ! python3 -c "import json,sys; sys.exit(0 if json.loads(open('$d.train.json').read().strip().splitlines()[-1]).get('finished') else 1)" 2>/dev/null; then
    echo "=== $v-s$s train $(date +%T)" >>"$OUT/log.txt"
    taskset -c "$cores" timeout -s TERM "$LIMIT" python3 -m ttmjx train --preset "$v" --seed "$s" --run-dir "$d" \
      --keep-checkpoints 100 $EXTRA --json >"$d.train.json" 2>"$d.train.err"
    echo "=== $v-s$s trained rc=$? $(date +%T) $(tail -c 200 "$d.train.json")" >>"$OUT/log.txt"
    python3 -c "import json,sys; sys.exit(0 if json.loads(open('$d.train.json').read().strip().splitlines()[-1]).get('finished') else 1)" 2>/dev/null || return
  fi
  for g in 400 eval/goals/edges_net.csv; do
    tag=$([ "$g" = 400 ] && echo uniform400 || echo edges_net)
    [ "$v" = default ] && [ ! -s "$d.eval_lfp_$tag.json" ] && taskset -c "$cores" python3 -m ttmjx eval "$d" --goals "$g" \
      --seed 2026 --step 10 --json >"$d.eval_lfp_$tag.json" 2>>"$d.eval.err"
    [ -s "$d.eval_final_$tag.json" ] || taskset -c "$cores" python3 -m ttmjx eval "$d" --goals "$g" --seed 2026 --json \
      >"$d.eval_final_$tag.json" 2>>"$d.eval.err"
  done
  touch "$d.done"
  echo "=== $v-s$s evaluated $(date +%T)" >>"$OUT/log.txt"
}
i=0
for s in $SEEDS; do
  for v in default lfp; do
    a=$(( (CORES * i) % $(nproc) )); one $v "$s" "$a-$((a + CORES - 1))" &
    i=$((i + 1))
  done
done
wait
tar czf "$OUT/confirm.tgz" -C "$W" --exclude checkpoints --exclude tensorboard --exclude demos --exclude '*.npz' . 2>/dev/null
cat "$OUT/log.txt"
