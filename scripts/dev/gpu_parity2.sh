#!/usr/bin/env bash
# The world against the runner on one GPU, second call: the README main job (the GPU default preset) trained on MJX
# again, then on the same 400 goals and throws (seed 2026): the ensemble as the runner plays it
# (actions averaged) in the MJX world; `ttmjx eval` of member 0 alone on MJX and on MuJoCo C; the
# parity harness on the averaged ensemble (MJX world against the runner); member 0's export
# comes back (member0.tgz) for the CPU side's runner-against-world comparison.
#   bash scripts/dev/gpu_parity2.sh   (carry .wheels)
set -uo pipefail
if ls .wheels/*.whl >/dev/null 2>&1 && ! python3 -c "import mujoco, brax" 2>/dev/null; then
  python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
fi
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 TTMJX_JAX_CACHE=$PWD/.jax_cache
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; R=/tmp/gpujob; W=/tmp/res; mkdir -p "$W"
t0=$(date +%s)
log() { echo "$(( $(date +%s) - t0 ))s $*" | tee -a "$OUT/log.txt"; }
log "start $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null)"
timeout -s TERM "${TRAIN_LIMIT:-300}" python3 -m ttmjx train --run-dir "$R" --json >"$W/train.json" 2>"$W/train.err"
log "trained rc=$?"
cp "$R/config.json" "$R/metrics.jsonl" "$W/" 2>/dev/null
python3 -m ttmjx export "$R" --out /tmp/ex_ens --ensemble --onnx off >"$W/export_ens.txt" 2>&1
python3 -m ttmjx export "$R" --out /tmp/member0 --member 0 --onnx off >"$W/export_m0.txt" 2>&1
tar czf "$OUT/member0.tgz" -C /tmp member0
log "exported"
export XLA_PYTHON_CLIENT_PREALLOCATE=false
( timeout 200 python3 scripts/dev/ensemble_world.py /tmp/ex_ens 400 2026 mjx >"$W/ensemble_world_mjx.json" 2>"$W/ensemble_world_mjx.err"; log "ensemble world rc=$?" ) &
for b in mjx c; do
  ( timeout 200 python3 -m ttmjx eval "$R" --member 0 --goals 400 --seed 2026 --backend "$b" --json \
      >"$W/eval_member0_$b.json" 2>"$W/eval_member0_$b.err"; log "eval member0 $b rc=$?" ) &
done
( timeout 230 python3 -m ttmjx robot parity --policy /tmp/ex_ens --n 24 --seed 2026 --backend mjx \
    --out "$W/parity_mjx" >"$W/parity_mjx.txt" 2>"$W/parity_mjx.err"; log "parity mjx rc=$?" ) &
wait
log done
tar czf "$OUT/results.tgz" -C "$W" .
