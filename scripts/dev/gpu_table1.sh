#!/usr/bin/env bash
# On the lent GPU machine: Table I's GoalsEye and LFP (equal updates) arms, 5 seeds each, as
# two programs side by side that outlive one device call (setsid), so a table longer than one
# call is finished by the calls that follow while the machine stays warm.
#   bash scripts/dev/gpu_table1.sh start TRAJECTORIES WAIT_S   # first call: launch, then watch
#   bash scripts/dev/gpu_table1.sh wait WAIT_S                 # later calls: keep watching
# Each call leaves in $OUT: log.txt, the two arms' logs and table1.tgz (results/*.json, every
# seed's metrics.jsonl and config.json, the report; no checkpoints), refreshed every 30 s.
# When both arms are done, every seed's final policy is also evaluated on
# eval/goals/edges_net.csv (goals along the net, the end line and the sidelines), into
# edges/<cell>.json in the same archive.
set -uo pipefail
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 PATH=$PATH XLA_PYTHON_CLIENT_PREALLOCATE=false TTMJX_JAX_CACHE=/tmp/jaxcache
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; T=/tmp/t1; mkdir -p "$T/edges"
ARMS="goalseye lfp-equal-updates"; SCALE=${SCALE:-full}; T=${T1_DIR:-$T}; mkdir -p "$T/edges"
pack() {
  tar czf "$OUT/table1.tgz.part" --exclude=checkpoints --exclude=tensorboard --exclude=demos -C "$T" . 2>/dev/null \
    && mv "$OUT/table1.tgz.part" "$OUT/table1.tgz"
  for a in $ARMS; do [[ -f $T/$a.log ]] && tail -c 200000 "$T/$a.log" > "$OUT/$a.log"; done
}
mode=$1; shift
if [[ $mode == start ]]; then
  [[ -z ${NOINSTALL:-} ]] && python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
  command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee -a "$T/log.txt"
  traj=$1; shift
  for a in $ARMS; do
    setsid bash -c "cd $PWD; /usr/bin/time -f 'wall %e s, peak rss %M kB' python3 -m ttmjx ablate practice \
      --scale $SCALE --seeds ${SEEDS:-5} --cells $a --trajectories $traj --out $T/table 2>&1 | tr '\r' '\n' \
      | grep -v 'traj/s\|throw/s\|^\s*$' > $T/$a.log; touch $T/$a.done" </dev/null >/dev/null 2>&1 &
    echo "started $a $(date +%T)" | tee -a "$T/log.txt"
  done
fi
wait_s=$1; t_end=$((SECONDS + wait_s))
while (( SECONDS < t_end )); do
  pack
  [[ -f $T/goalseye.done && -f $T/lfp-equal-updates.done ]] && break
  sleep 30
done
if [[ -f $T/goalseye.done && -f $T/lfp-equal-updates.done && ! -f $T/edges.done ]]; then
  echo "=== edges evaluation $(date +%T)" | tee -a "$T/log.txt"
  for run in "$T"/table/runs/*-seed*; do
    c=$(basename "$run")
    [[ -f $T/edges/$c.json ]] || python3 -m ttmjx eval "$run" --goals eval/goals/edges_net.csv --json \
      2>>"$T/log.txt" | tail -1 > "$T/edges/$c.json"
    (( SECONDS < t_end + 120 )) || break
  done
  ls "$T"/edges/*.json | wc -l | grep -q "^$(( ${SEEDS:-5} * 2 ))$" && touch "$T/edges.done"
fi
date +%T >> "$T/log.txt"; cp "$T/log.txt" "$OUT/"; pack
for a in $ARMS; do echo "== $a"; grep -E "^\[|wall|rror" "$T/$a.log" | tail -8; done
