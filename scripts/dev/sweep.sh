#!/usr/bin/env bash
# Development sweep of the CPU main job: several variants trained side by side, each on its own
# pair of cores of a many-core machine (the lent GPU machine's CPUs), then each evaluated on one
# larger goal set. Development protocol only: seeds 100 and up, the in-run goals and EVAL_SEED's.
# With STATION=1 each run is also exported and played on the simulated station: the default
# session (timing drawn per throw within the trained ranges, start pose perturbed) and the
# fixed-timing sweep points (ball latency +0/25/50 ms, command delay +0/10/20 ms).
#   bash scripts/dev/sweep.sh NAME="--seed 100 --train.balance 1" NAME2="--preset lfp --seed 100" ...
# Environment: TRAIN_LIMIT (s, 440), EVAL_GOALS (400), EVAL_SEED (4242), W (work folder),
# STATION (0; 1: export and play on the station), N (goals per station session, 100).
# Writes $OUT/sweep.tgz (each run's config, metrics, eval summary; export and station JSON) and $OUT/log.txt.
set -uo pipefail
if ls .wheels/*.whl >/dev/null 2>&1 && ! python3 -c "import mujoco, brax" 2>/dev/null; then
  python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
fi
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 JAX_PLATFORMS=cpu CUDA_VISIBLE_DEVICES= TTMJX_JAX_CACHE=$PWD/.jax_cache_cpu
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; W=${W:-/tmp/sweep}; mkdir -p "$W"
TRAIN_LIMIT=${TRAIN_LIMIT:-440}; EVAL_GOALS=${EVAL_GOALS:-400}; EVAL_SEED=${EVAL_SEED:-4242}
STATION=${STATION:-0}; N=${N:-100}
ncpu=$(nproc); i=0
station() {  # dir, cores: export the run, then the station session and the two sweeps side by side
  local d=$1 cores=$2 c0=${2%%,*} c1=${2##*,}
  taskset -c "$cores" python3 -m ttmjx export "$d/run" --out "$d/ex" >"$d/export.txt" 2>&1 || return
  taskset -c "$cores" python3 -m ttmjx robot run --policy "$d/ex" --station sim --goals uniform --n "$N" \
    --seed 5 --json >"$d/robot_run.json" 2>"$d/robot_run.err" &
  taskset -c "$c0" python3 -m ttmjx robot sweep --policy "$d/ex" --out "$d/sweep_ball" --n "$N" --max-ms 50 \
    --points 3 --series ball --json >"$d/sweep_ball.json" 2>"$d/sweep_ball.err" &
  taskset -c "$c1" python3 -m ttmjx robot sweep --policy "$d/ex" --out "$d/sweep_action" --n "$N" --max-ms 20 \
    --points 3 --series action --json >"$d/sweep_action.json" 2>"$d/sweep_action.err" &
  wait
}
one() {  # name, cores, flags...
  local name=$1 cores=$2; shift 2
  local d=$W/$name
  echo "=== $name: train $* $(date +%T)" >>"$OUT/log.txt"
  taskset -c "$cores" timeout -s TERM "$TRAIN_LIMIT" python3 -m ttmjx train --run-dir "$d/run" --keep-checkpoints 100 \
    "$@" --json >"$d/train.json" 2>"$d/train.err"
  echo "=== $name: trained rc=$? $(date +%T)" >>"$OUT/log.txt"
  # The LFP point (the checkpoint after pretraining) and the newest, on the same goals and throws.
  local lfp
  lfp=$(python3 -c "import json, math; c = json.load(open('$d/run/config.json')); print(math.ceil(c['pretrain_steps'] / c['steps_between_ssp']))")
  taskset -c "$cores" python3 -m ttmjx eval "$d/run" --goals "$EVAL_GOALS" --seed "$EVAL_SEED" --step "$lfp" --json \
    >"$d/eval_lfp.json" 2>"$d/eval_lfp.err"
  taskset -c "$cores" python3 -m ttmjx eval "$d/run" --goals "$EVAL_GOALS" --seed "$EVAL_SEED" --json \
    >"$d/eval.json" 2>"$d/eval.err"
  echo "=== $name: evaluated $(date +%T) lfp point $(tail -c 250 "$d/eval_lfp.json") newest $(tail -c 250 "$d/eval.json")" >>"$OUT/log.txt"
  if [[ $STATION == 1 ]]; then
    station "$d" "$cores"
    echo "=== $name: station done $(date +%T)" >>"$OUT/log.txt"
  fi
}
for arg in "$@"; do
  name=${arg%%=*}; flags=${arg#*=}; mkdir -p "$W/$name"
  a=$(( (2 * i) % ncpu )); b=$(( (2 * i + 1) % ncpu ))
  # shellcheck disable=SC2086
  one "$name" "$a,$b" $flags &
  i=$((i + 1))
done
pack() { tar czf "$OUT/sweep.tgz.part" -C "$W" --exclude checkpoints --exclude tensorboard --exclude demos . 2>/dev/null \
  && mv "$OUT/sweep.tgz.part" "$OUT/sweep.tgz"; }
# Pack what exists every 30 s, so a call cut short still returns its partial results.
( while sleep 30; do pack; done ) &
saver=$!
wait $(jobs -p | grep -v "^$saver$") 2>/dev/null
kill $saver 2>/dev/null
pack
echo "=== done $(date +%T)" >>"$OUT/log.txt"
cat "$OUT/log.txt"
