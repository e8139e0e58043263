#!/usr/bin/env bash
# One GPU: a whole episode of paper-sim's rollout (4,000 worlds, 160 control steps) at each pair of
# constraint-solver caps (world.contacts.solver_iterations,line_search_iterations; default: today's
# 10,8 and MuJoCo's 100,50), then, unless ROUNDS=0, practice rounds and pretraining chunks of
# paper-sim at the world's caps (scripts/dev/profile_round.py --no-trace).
#   bash scripts/dev/gpu_solver.sh [IT,LS ...]      (carry .wheels)
#   ROUNDS=0 bash scripts/dev/gpu_solver.sh 10,4 10,2
# -> $OUT/caps_<IT>_<LS>/step_profile.json, $OUT/round/profile_summary.json, $OUT/log.txt
source scripts/dev/device_setup.sh
G="taskset -c $(( $(nproc) - 2 ))-$(( $(nproc) - 1 ))"
for caps in "${@:-10,8 100,50}"; do
  for c in $caps; do
    it=${c%,*}; ls=${c#*,}; d="$OUT/caps_${it}_${ls}"
    s=$(date +%s); mkdir -p "$d"
    $G timeout 200 python3 scripts/dev/step_profile.py paper-sim "$d" --pieces rollout --steps 160 --reps 2 \
      --solver-iterations "$it" --line-search-iterations "$ls" >"$d/stdout" 2>"$d/log"
    log "episode caps $c rc=$? $(( $(date +%s) - s ))s: $(python3 -c "import json,sys; print(json.load(open(sys.argv[1])).get('summary'))" "$d/step_profile.json" 2>&1 | cut -c1-400)"
  done
done
[ "${ROUNDS:-3}" = 0 ] && exit 0
s=$(date +%s); mkdir -p "$OUT/round"
$G timeout "${ROUND_LIMIT:-330}" python3 scripts/dev/profile_round.py paper-sim "$OUT/round" --no-trace --rounds "${ROUNDS:-3}" \
  >"$OUT/round/profile.txt" 2>&1
log "rounds rc=$? $(( $(date +%s) - s ))s: $(tail -1 "$OUT/round/profile.txt" | cut -c1-700)"
