#!/usr/bin/env bash
# One GPU, the updates' LSTM by cuDNN (TrainConfig.lstm_kernel, models/cudnn_lstm.py). Each phase
# fits one device call; give them in order on a warm machine (each has its own cold compilation
# cache, so the real command's wall time includes its compiles).
#   PHASE=profile bash scripts/dev/gpu_cudnn.sh   # updates by scan / bfloat16 / cuDNN, their agreement; rounds
#   PHASE=real    bash scripts/dev/gpu_cudnn.sh   # ttmjx train --preset paper-sim (120k, 1 seed), wall time
#   PHASE=bench   bash scripts/dev/gpu_cudnn.sh   # ttmjx bench --train paper-sim --seeds 1: the projection
# (carry .wheels) -> $OUT/log.txt and the phase's JSON
source scripts/dev/device_setup.sh
export TTMJX_JAX_CACHE=/tmp/jax_cache_$PHASE
[ -z "${KEEP_CACHE:-}" ] && rm -rf "$TTMJX_JAX_CACHE"     # KEEP_CACHE=1: the phase's cache as the last call left it
s=$(date +%s)
case "$PHASE" in
  profile)
    timeout 240 python3 scripts/dev/step_profile.py paper-sim "$OUT/updates" --pieces train --updates 50 --reps 3 \
      >"$OUT/updates.stdout" 2>"$OUT/updates.log"
    log "updates rc=$? $(( $(date +%s) - s ))s: $(python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print(d.get('summary'), d.get('cudnn_vs_scan'))" "$OUT/updates/step_profile.json" 2>&1 | cut -c1-900)"
    grep -i "error\|Traceback" "$OUT/updates.log" | head -5 | tee -a "$OUT/log.txt"
    s=$(date +%s); mkdir -p "$OUT/round"
    timeout "${ROUND_LIMIT:-300}" python3 scripts/dev/profile_round.py paper-sim "$OUT/round" --no-trace --rounds 3 \
      >"$OUT/round/profile.txt" 2>&1
    log "rounds rc=$? $(( $(date +%s) - s ))s: $(tail -1 "$OUT/round/profile.txt" | cut -c1-700)" ;;
  real)
    rm -rf runs/cudnn-real
    /usr/bin/time -f "wall %e s, peak rss %M kB" timeout -s TERM "${LIMIT:-570}" python3 -m ttmjx train --preset paper-sim \
      --run-dir runs/cudnn-real --json 2>&1 | tr '\r' '\n' | grep -v "traj/s\|throw/s\|^\s*$" > "$OUT/train.log"
    log "train rc=$? $(( $(date +%s) - s ))s: $(tail -2 "$OUT/train.log" | cut -c1-600)"
    cp runs/cudnn-real/metrics.jsonl "$OUT/train_metrics.jsonl"; cp runs/cudnn-real/config.json "$OUT/train_config.json" ;;
  bench)
    timeout "${LIMIT:-500}" python3 -m ttmjx bench --train paper-sim --seeds 1 --reps 1 --json 2>"$OUT/bench.log" \
      | tail -1 > "$OUT/bench_paper-sim_1.json"
    log "bench rc=$? $(( $(date +%s) - s ))s: $(cut -c1-600 "$OUT/bench_paper-sim_1.json")" ;;
esac
