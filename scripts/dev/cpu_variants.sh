#!/usr/bin/env bash
# Train several CPU-preset variants side by side, each on its own pair of cores (the lent GPU
# machine's 16 CPU cores, or any many-core machine), then export each and play it on the
# simulated station: the default session (timing drawn per throw within the trained ranges,
# start pose perturbed) and the fixed-timing sweep points.
#   bash scripts/dev/cpu_variants.sh NAME="--flag v ..." NAME2="..."
# Sweeps: ball latency +0/25/50 ms, command delay +0/10/20 ms, on the trained timing's centre.
# Environment: PRESET (cpu), SEED (0), N (goals per station session, 100), SWEEP (1: sweeps too), TRAIN_LIMIT (s).
# Writes $OUT/variants.tgz (every run's config, metrics, export and station JSON) and $OUT/log.txt.
set -uo pipefail
if ls .wheels/*.whl >/dev/null 2>&1 && ! python3 -c "import mujoco, brax" 2>/dev/null; then
  python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
fi
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 JAX_PLATFORMS=cpu CUDA_VISIBLE_DEVICES= TTMJX_JAX_CACHE=$PWD/.jax_cache_cpu
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; W=${W:-/tmp/variants}; mkdir -p "$W"
PRESET=${PRESET:-cpu}; SEED=${SEED:-0}; N=${N:-100}; SWEEP=${SWEEP:-1}; TRAIN_LIMIT=${TRAIN_LIMIT:-420}
ncpu=$(nproc); i=0
one() {  # name, cores, flags...
  local name=$1 cores=$2; shift 2
  local d=$W/$name
  echo "=== $name: train $* $(date +%T)" >>"$OUT/log.txt"
  taskset -c "$cores" timeout -s TERM "$TRAIN_LIMIT" python3 -m ttmjx train --preset "$PRESET" --seed "$SEED" \
    --run-dir "$d/run" "$@" --json >"$d/train.json" 2>"$d/train.err"
  echo "=== $name: trained rc=$? $(date +%T)" >>"$OUT/log.txt"
  taskset -c "$cores" python3 -m ttmjx export "$d/run" --out "$d/ex" >"$d/export.txt" 2>&1 || return
  taskset -c "$cores" python3 -m ttmjx robot run --policy "$d/ex" --station sim --goals uniform --n "$N" \
    --seed 5 --json >"$d/robot_run.json" 2>"$d/robot_run.err" &
  if [[ $SWEEP == 1 ]]; then
    local c0=${cores%%,*} c1=${cores##*,}
    taskset -c "$c0" python3 -m ttmjx robot sweep --policy "$d/ex" --out "$d/sweep_ball" --n "$N" --max-ms 50 \
      --points 3 --series ball --json >"$d/sweep_ball.json" 2>"$d/sweep_ball.err" &
    taskset -c "$c1" python3 -m ttmjx robot sweep --policy "$d/ex" --out "$d/sweep_action" --n "$N" --max-ms 20 \
      --points 3 --series action --json >"$d/sweep_action.json" 2>"$d/sweep_action.err" &
  fi
  wait
  echo "=== $name: station done $(date +%T)" >>"$OUT/log.txt"
}
for arg in "$@"; do
  name=${arg%%=*}; flags=${arg#*=}; mkdir -p "$W/$name"
  a=$(( (2 * i) % ncpu )); b=$(( (2 * i + 1) % ncpu ))
  # shellcheck disable=SC2086
  one "$name" "$a,$b" $flags &
  i=$((i + 1))
done
# Copy what exists every 30 s, so a call cut short still returns its partial results.
( while sleep 30; do tar czf "$OUT/variants.tgz.part" -C "$W" --exclude checkpoints --exclude tensorboard \
    --exclude demos . 2>/dev/null && mv "$OUT/variants.tgz.part" "$OUT/variants.tgz"; done ) &
saver=$!
wait $(jobs -p | grep -v "^$saver$") 2>/dev/null
kill $saver 2>/dev/null
tar czf "$OUT/variants.tgz" -C "$W" --exclude checkpoints --exclude tensorboard --exclude demos .
echo "=== done $(date +%T)" >>"$OUT/log.txt"
cat "$OUT/log.txt"
