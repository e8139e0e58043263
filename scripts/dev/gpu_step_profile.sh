#!/usr/bin/env bash
# One GPU: a practice round of PRESET (paper-sim) timed piece by piece with kernel counts, instead of
# a jax.profiler trace (issue 45): MJX physics and the policy for B worlds per control step, N
# control steps of the rollout, one update in float32 and bfloat16 (scripts/dev/step_profile.py).
#   PRESET=paper-sim bash scripts/dev/gpu_step_profile.sh [--episode --worlds B --steps N ...]   (carry .wheels)
# -> $OUT/step_profile.json (rewritten after each piece), $OUT/step_profile.log, $OUT/log.txt
source scripts/dev/device_setup.sh
PRESET=${PRESET:-paper-sim}
G="taskset -c $(( $(nproc) - 2 ))-$(( $(nproc) - 1 ))"   # the GPU process's host work: the last 2 cores
s=$(date +%s)
$G timeout "${STEP_PROFILE_LIMIT:-450}" python3 scripts/dev/step_profile.py "$PRESET" "$OUT" "$@" \
  >"$OUT/step_profile.stdout" 2>"$OUT/step_profile.log"
rc=$?
summary=$(python3 -c "import json, sys; r = json.load(open(sys.argv[1])); print(json.dumps(r.get('summary') or
  {k: v.get('per_step_s', v.get('error')) for k, v in r['pieces'].items()}))" "$OUT/step_profile.json" 2>&1)
log "step_profile $PRESET rc=$rc $(( $(date +%s) - s ))s: $(echo "$summary" | cut -c1-900)"
