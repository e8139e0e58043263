#!/usr/bin/env bash
# On the lent GPU machine (device tool), from the repository root: Table I's baseline cells.
#   bash scripts/dev/gpu_baselines.sh PROFILE_S "METHOD:SEEDS:LIMIT_S" ...
# e.g. bash scripts/dev/gpu_baselines.sh 90 ppo:5:300 es:1:140
# Profiles the environment pieces (scripts/dev/baseline_profile.py, at most PROFILE_S seconds; 0
# skips it), then runs `ttmjx baseline METHOD --scale full --seeds SEEDS --out B/table1` for
# each, each under its own limit (SIGTERM: finished cells are kept, a cut one is redone).
# PARALLEL=1 runs the methods side by side (one process each) instead of one after another;
# PPO_FLAGS, SAC_FLAGS, ES_FLAGS add options to that method's command (e.g.
# PPO_FLAGS="--ppo.num-envs 12000 --ppo.num-minibatches 96").
# Writes $OUT/log.txt (everything printed), $OUT/profile.json and $OUT/baselines.tgz (results,
# timing.json per cell, table, curves; no checkpoints), refreshed every 20 s in the background,
# and $OUT/jax_cache.tgz, JAX's persistent compilation cache of this call when it packs under
# 15 MB: unpack it here into .gpu_jax_cache/ (list it in .git/info/exclude) and carry that
# folder in the next call, which then loads the compiled training step instead of compiling it.
set -uo pipefail
python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
mkdir -p .gpu_jax_cache
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false TTMJX_JAX_CACHE=$PWD/.gpu_jax_cache
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; B=/tmp/bl; mkdir -p "$B"
pack() { tar czf "$OUT/baselines.tgz.part" --exclude=checkpoints --exclude=tensorboard -C "$B" . 2>/dev/null \
         && mv "$OUT/baselines.tgz.part" "$OUT/baselines.tgz"
         tar czf /tmp/jax_cache.tgz -C .gpu_jax_cache . 2>/dev/null \
         && [[ $(stat -c %s /tmp/jax_cache.tgz) -lt 15000000 ]] && mv /tmp/jax_cache.tgz "$OUT/jax_cache.tgz"; }
( while sleep 20; do pack; done ) & PACKER=$!
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee -a "$OUT/log.txt"
PROFILE_S=$1; shift
if [[ $PROFILE_S -gt 0 ]]; then
  echo "=== profile $(date +%T)" | tee -a "$OUT/log.txt"
  timeout "$PROFILE_S" python3 scripts/dev/baseline_profile.py 2>>"$OUT/log.txt" | tee "$OUT/profile.json"
fi
one() {
  IFS=: read -r m s lim <<<"$1"
  local flags_var="${m^^}_FLAGS"; local flags=${!flags_var:-}
  echo "=== baseline $m seeds $s limit $lim $flags $(date +%T)" | tee -a "$OUT/log.txt"
  /usr/bin/time -f "wall %e s, peak rss %M kB" timeout -s TERM "$lim" \
    python3 -m ttmjx baseline "$m" --scale full --seeds "$s" --out "$B/table1" $flags 2>&1 \
    | tr '\r' '\n' | grep -v "^\s*$" | tee -a "$OUT/log.txt" "$OUT/log_$m.txt" | grep -E "^\[|wall|error" | tail -20
}
pids=()
for spec in "$@"; do
  if [[ ${PARALLEL:-0} == 1 ]]; then one "$spec" & pids+=($!); else one "$spec"; fi
done
for p in "${pids[@]}"; do wait "$p"; done
kill $PACKER 2>/dev/null; pack
python3 scripts/dev/baseline_timing.py "$B/table1" | tee -a "$OUT/log.txt"
echo "=== done $(date +%T)" | tee -a "$OUT/log.txt"
