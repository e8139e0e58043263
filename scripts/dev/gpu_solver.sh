#!/usr/bin/env bash
# One GPU: the constraint solver's caps against MuJoCo's defaults (world.contacts.solver_iterations
# and line_search_iterations: 10 and 8 against 100 and 50): a whole episode of paper-sim's rollout
# (4,000 worlds, 160 control steps) with each, then practice rounds and pretraining chunks of
# paper-sim at the new caps (scripts/dev/profile_round.py --no-trace).
#   bash scripts/dev/gpu_solver.sh      (carry .wheels)
# -> $OUT/new/step_profile.json, $OUT/old/step_profile.json, $OUT/round/profile_summary.json, $OUT/log.txt
source scripts/dev/device_setup.sh
G="taskset -c $(( $(nproc) - 2 ))-$(( $(nproc) - 1 ))"
for arm in "new" "old --solver-iterations 100 --line-search-iterations 50"; do
  set -- $arm; name=$1; shift
  s=$(date +%s); mkdir -p "$OUT/$name"
  $G timeout 200 python3 scripts/dev/step_profile.py paper-sim "$OUT/$name" --pieces rollout --steps 160 --reps 2 "$@" \
    >"$OUT/$name/stdout" 2>"$OUT/$name/log"
  log "episode $name rc=$? $(( $(date +%s) - s ))s: $(python3 -c "import json,sys; print(json.load(open(sys.argv[1])).get('summary'))" "$OUT/$name/step_profile.json" 2>&1 | cut -c1-400)"
done
s=$(date +%s); mkdir -p "$OUT/round"
$G timeout "${ROUND_LIMIT:-330}" python3 scripts/dev/profile_round.py paper-sim "$OUT/round" --no-trace --rounds 3 \
  >"$OUT/round/profile.txt" 2>&1
log "rounds rc=$? $(( $(date +%s) - s ))s: $(tail -1 "$OUT/round/profile.txt" | cut -c1-700)"
