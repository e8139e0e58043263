#!/usr/bin/env bash
# One GPU: a whole episode of paper-sim's rollout (4,000 worlds, 160 control steps) under each set
# of XLA flags given (one argument per set, "" for XLA's defaults), each compiled afresh, with the
# rollout's output checksum so that a flag that changes results shows; then, unless ROUNDS=0,
# practice rounds and pretraining chunks of paper-sim (scripts/dev/profile_round.py --no-trace)
# under the fastest set. Issue 45: an MJX step is ~2,900 kernel launches and ~110 while-loop
# iterations per control step, each of which reads its predicate back to the host unless the loop
# runs inside a CUDA graph (XLA's command buffers).
#   bash scripts/dev/gpu_xla_flags.sh "" "--xla_gpu_enable_command_buffer=+WHILE"     (carry .wheels)
# -> $OUT/flags_<i>/step_profile.json, $OUT/round/profile_summary.json, $OUT/log.txt
source scripts/dev/device_setup.sh
G="taskset -c $(( $(nproc) - 2 ))-$(( $(nproc) - 1 ))"
i=0
for flags in "$@"; do
  d="$OUT/flags_$i"; mkdir -p "$d"; echo "$flags" >"$d/xla_flags"; s=$(date +%s)
  XLA_FLAGS="$flags" $G timeout "${EPISODE_LIMIT:-240}" python3 scripts/dev/step_profile.py paper-sim "$d" \
    --pieces rollout --steps 160 --reps 2 >"$d/stdout" 2>"$d/log"
  log "flags [$flags] rc=$? $(( $(date +%s) - s ))s: $(python3 -c "
import json,sys; d=json.load(open(sys.argv[1])); r=d['pieces']['rollout']
print(d['summary']['rollout'], 'checksum', r['checksum'])" "$d/step_profile.json" 2>&1 | cut -c1-400)"
  i=$((i + 1))
done
[ "${ROUNDS:-3}" = 0 ] && exit 0
best=$(python3 - "$OUT" <<'EOF'
import glob, json, sys
rows = []
for p in glob.glob(sys.argv[1] + "/flags_*/step_profile.json"):
    try:
        d = json.load(open(p))
        rows.append((d["summary"]["rollout"]["per_step_ms"], d["xla_flags"]))
    except (KeyError, ValueError):
        pass
print(min(rows)[1] if rows else "")
EOF
)
s=$(date +%s); mkdir -p "$OUT/round"; echo "$best" >"$OUT/round/xla_flags"
XLA_FLAGS="$best" $G timeout "${ROUND_LIMIT:-300}" python3 scripts/dev/profile_round.py paper-sim "$OUT/round" \
  --no-trace --rounds "${ROUNDS:-3}" >"$OUT/round/profile.txt" 2>&1
log "rounds under [$best] rc=$? $(( $(date +%s) - s ))s: $(tail -1 "$OUT/round/profile.txt" | cut -c1-700)"
