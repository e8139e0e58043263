#!/usr/bin/env bash
# One GPU: jax.profiler's trace of a practice round and a pretraining chunk of PRESET (paper-sim),
# summarized (scripts/dev/profile_round.py), then `ttmjx bench --train PRESET` for the projection.
#   PRESET=paper-sim bash scripts/dev/gpu_profile.sh      (carry .wheels)
source scripts/dev/device_setup.sh
PRESET=${PRESET:-paper-sim}
G="taskset -c $(( $(nproc) - 2 ))-$(( $(nproc) - 1 ))"   # the GPU process's host work: the last 2 cores
s=$(date +%s)
$G timeout "${PROFILE_LIMIT:-300}" python3 scripts/dev/profile_round.py "$PRESET" "$OUT" >"$OUT/profile.txt" 2>&1
log "profile $PRESET rc=$? $(( $(date +%s) - s ))s: $(tail -1 "$OUT/profile.txt" | cut -c1-600)"
