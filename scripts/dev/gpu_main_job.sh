#!/usr/bin/env bash
# The README's main job on the lent GPU machine, as a user runs it, then its export on the robot
# runner: `ttmjx train` (the GPU default preset), `ttmjx export RUN --out EX` (no flag), and
# `ttmjx robot run --policy EX --station sim` in SESSIONS sessions of N uniform goals on the
# machine's CPU cores (seeds 50, 51, ...), side by side.
#   bash scripts/dev/gpu_main_job.sh
# Environment: TRAIN_ARGS (extra `ttmjx train` flags), TRAIN_LIMIT (s, 420), SESSIONS (4), N (50).
# Writes $OUT/main_job.tgz (config, metrics, every JSON) and $OUT/log.txt, refreshed every 20 s.
set -uo pipefail
if ls .wheels/*.whl >/dev/null 2>&1 && ! python3 -c "import mujoco, brax" 2>/dev/null; then
  python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
fi
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false TTMJX_JAX_CACHE=$PWD/.jax_cache
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; R=${R:-/tmp/main_job}; rm -rf "$R"; mkdir -p "$R/res"
SESSIONS=${SESSIONS:-4}; N=${N:-50}; TRAIN_LIMIT=${TRAIN_LIMIT:-420}
log() { echo "=== $* $(date +%T)" | tee -a "$OUT/log.txt"; }
pack() {
  cp "$R/run/config.json" "$R/run/metrics.jsonl" "$R/res/" 2>/dev/null
  cp "$R/ex/contract.json" "$R/res/export_contract.json" 2>/dev/null
  tar czf "$OUT/main_job.tgz.part" -C "$R" res && mv "$OUT/main_job.tgz.part" "$OUT/main_job.tgz"
}
( while sleep 20; do pack; done ) & saver=$!
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null | tee -a "$OUT/log.txt"
log "train ${TRAIN_ARGS:-}"
# shellcheck disable=SC2086
/usr/bin/time -f "train wall %e s" timeout -s TERM "$TRAIN_LIMIT" python3 -m ttmjx train --run-dir "$R/run" \
  ${TRAIN_ARGS:-} --json >"$R/res/train.json" 2>"$R/res/train.err"
log "trained rc=$?"; tail -1 "$R/res/train.err" | tee -a "$OUT/log.txt"
python3 -m ttmjx export "$R/run" --out "$R/ex" >"$R/res/export.txt" 2>&1
log "exported rc=$?"; tail -1 "$R/res/export.txt" | tee -a "$OUT/log.txt"
for k in $(seq 0 $((SESSIONS - 1))); do
  JAX_PLATFORMS=cpu CUDA_VISIBLE_DEVICES= taskset -c $((2 * k)),$((2 * k + 1)) python3 -m ttmjx robot run \
    --policy "$R/ex" --station sim --goals uniform --n "$N" --seed $((50 + k)) --json \
    >"$R/res/robot_run_$k.json" 2>"$R/res/robot_run_$k.err" &
done
wait $(jobs -p | grep -v "^$saver$") 2>/dev/null
log "robot runs done"
kill $saver 2>/dev/null; pack
python3 - "$R/res" <<'EOF' | tee -a "$OUT/log.txt"
import glob, json, sys
rows = [json.loads(open(f).read().strip().splitlines()[-1]) for f in sorted(glob.glob(sys.argv[1] + "/robot_run_*.json"))
        if open(f).read().strip()]
n = sum(r["goals"] for r in rows)
for key in ("within_30cm", "within_20cm"):
    print(key, "robot run:", sum(r["metrics"][key] * r["goals"] for r in rows) / max(n, 1), "over", n, "goals")
ev = [json.loads(l) for l in open(sys.argv[1] + "/metrics.jsonl") if "eval_within_30cm" in l]
if ev:
    print("eval (last):", {k: v for k, v in ev[-1].items() if k.startswith("eval_") or k == "trajectories"})
EOF
