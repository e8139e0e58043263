#!/usr/bin/env bash
# One GPU: a whole episode of paper-sim's rollout (4,000 worlds, 160 control steps) at smaller
# line-search caps than world.contacts' 8 (scripts/dev/step_profile.py --line-search-iterations).
#   bash scripts/dev/gpu_solver_ls.sh 4 2      (carry .wheels)   -> $OUT/ls<N>/step_profile.json
source scripts/dev/device_setup.sh
G="taskset -c $(( $(nproc) - 2 ))-$(( $(nproc) - 1 ))"
for n in "$@"; do
  s=$(date +%s); mkdir -p "$OUT/ls$n"
  $G timeout 150 python3 scripts/dev/step_profile.py paper-sim "$OUT/ls$n" --pieces rollout --steps 160 --reps 2 \
    --line-search-iterations "$n" >"$OUT/ls$n/stdout" 2>"$OUT/ls$n/log"
  log "episode ls=$n rc=$? $(( $(date +%s) - s ))s: $(python3 -c "import json,sys; print(json.load(open(sys.argv[1])).get('summary'))" "$OUT/ls$n/step_profile.json" 2>&1 | cut -c1-400)"
done
