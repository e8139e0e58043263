#!/usr/bin/env bash
# On a lent machine of 4 GPUs (device tool, kind nvidia-h100-x4), from the repository root: the
# RL rows of Table I, one process per GPU, each a slice of the seeds (ttmjx baseline --seed S
# --seeds N), each under its own limit, all inside one device call.
#   bash scripts/dev/gpu_baselines_x4.sh LIMIT_S "GPU:METHOD:FIRST_SEED:SEEDS[:FLAGS]" ...
# e.g. bash scripts/dev/gpu_baselines_x4.sh 540 "0:ppo:0:2" "1:ppo:2:2" "2:ppo:4:1" "3:es:0:2"
# Specs of one lane (GPU, with an optional letter: 1, 1b) run one after another; lanes run side by
# side, so 1 and 1b share GPU 1. FLAGS is a method's options with '+' for spaces
# (0:ppo:0:2:--ppo.num-envs+12000).
# Writes $OUT/log.txt and $OUT/baselines.tgz: every process's table directory and log
# (results/*.json, runs/*/timing.json, table, curves; no checkpoints), refreshed every 30 s, so a
# call that runs out of time still brings back the finished cells. Here, merge the results/
# folders into one table directory and rebuild it: ttmjx baseline ppo,es --report --out DIR.
set -uo pipefail
python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; B=/tmp/bl; mkdir -p "$B"
LIMIT=$1; shift
pack() { tar czf "$OUT/baselines.tgz.part" --exclude=checkpoints --exclude=tensorboard -C "$B" . 2>/dev/null \
         && mv "$OUT/baselines.tgz.part" "$OUT/baselines.tgz"; }
( while sleep 30; do pack; done ) & PACKER=$!
nvidia-smi --query-gpu=index,name,memory.total --format=csv,noheader | tee -a "$OUT/log.txt"
t_end=$((SECONDS + LIMIT))
lane() {   # the specs of one lane, one after another, each stopped at the call's end
  local gpu=${1%%[a-z]*}; shift
  for spec in "$@"; do
    IFS=: read -r _ m first n flags <<<"$spec"
    local name="$m-s$first-n$n" left=$((t_end - SECONDS))
    (( left > 30 )) || { echo "=== $name: no time left" | tee -a "$OUT/log.txt"; continue; }
    echo "=== gpu $gpu $name ${flags//+/ } limit ${left}s $(date +%T)" | tee -a "$OUT/log.txt"
    CUDA_VISIBLE_DEVICES=$gpu TTMJX_JAX_CACHE=/tmp/jaxcache$gpu /usr/bin/time -f "$name wall %e s, peak rss %M kB" \
      timeout -s TERM "$left" python3 -m ttmjx baseline "$m" --scale full --seed "$first" --seeds "$n" \
      --out "$B/$name" ${flags//+/ } 2>&1 | tr '\r' '\n' | grep -v "^\s*$" > "$B/$name.log"
    grep -E "wall|rror" "$B/$name.log" | tail -3 | tee -a "$OUT/log.txt"
  done
}
pids=()
for key in $(printf '%s\n' "$@" | cut -d: -f1 | sort -u); do
  lane "$key" $(printf '%s\n' "$@" | grep "^$key:") & pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
kill $PACKER 2>/dev/null; pack
python3 scripts/dev/baseline_timing.py "$B"/*/ | tee -a "$OUT/log.txt"
echo "=== done $(date +%T)" | tee -a "$OUT/log.txt"
