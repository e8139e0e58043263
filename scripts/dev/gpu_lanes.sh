#!/usr/bin/env bash
# On a lent GPU machine (device tool), from the repository root: any ttmjx commands, one lane of
# commands per GPU (a lane's commands one after another), all started in the background
# (setsid), so calls that follow while the machine is warm keep watching them and RL cells
# resume inside the lease; TESTS=1 also runs the README's test command on the host's CPU.
#   LANES="0:es5:baseline+es+--seeds+5+--out+/tmp/lanes/bl 1:sac5:baseline+sac+--seeds+5+--out+/tmp/lanes/bl" \
#     bash scripts/dev/gpu_lanes.sh start WAIT_S      # first call: install, launch, then watch
#   bash scripts/dev/gpu_lanes.sh wait WAIT_S         # later calls: keep watching (the lanes started)
# A lane spec is GPU:NAME:ARGS, ARGS the ttmjx command line with '+' for spaces; specs of one GPU
# run in the order given. After an `ablate` spec with --out, its finished cells are evaluated on
# eval/goals/edges_net.csv into edges/ (scripts/table1_figures.py reads them). Each call leaves
# in $OUT: log.txt and lanes.tgz (every file under 2 MB under /tmp/lanes but checkpoints and RL
# states; each job's log tail), refreshed every 30 s.
# Give WAIT_S at least 40 s under the call's limit.
set -uo pipefail
# JAX's default allocator (preallocating 75% of the GPU as one pool): a lane has its GPU alone.
# With XLA_PYTHON_CLIENT_PREALLOCATE=false the pool grows in regions that are never given back,
# and one large buffer (ES's 5-seed epoch: 67 GiB) may find no region it fits (likely cause of
# that OOM on an H200, not verified).
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; T=/tmp/lanes; mkdir -p "$T"; TESTS=${TESTS:-0}
pack() {
  for f in "$T"/*.log; do [[ -f $f ]] && tail -c 60000 "$f" > "$f.tail"; done
  (cd "$T" && find . -type f -size -2M ! -path '*/checkpoints/*' ! -path '*_state/*' ! -path '*/tensorboard/*' \
    ! -name '*.log' > /tmp/lanes.list && tar czf "$OUT/lanes.tgz.part" -T /tmp/lanes.list 2>/dev/null) \
    && mv "$OUT/lanes.tgz.part" "$OUT/lanes.tgz"
  cp "$T/log.txt" "$OUT/log.txt" 2>/dev/null
}
lane() {   # lane GPU SPEC...: the specs one after another on that GPU
  local gpu=$1; shift
  for spec in "$@"; do
    IFS=: read -r _ name args <<< "$spec"
    echo "=== gpu $gpu $name: ttmjx ${args//+/ } $(date +%T)" >> "$T/log.txt"
    CUDA_VISIBLE_DEVICES=$gpu TTMJX_JAX_CACHE=/tmp/jaxcache$gpu /usr/bin/time -f "$name wall %e s, peak rss %M kB" \
      python3 -m ttmjx ${args//+/ } 2>&1 | stdbuf -oL tr '\r' '\n' | grep --line-buffered -v '^\s*$' > "$T/$name.log"
    echo "=== $name ended $(date +%T): $(grep -E 'wall|rror' "$T/$name.log" | tail -2 | tr '\n' ' ')" >> "$T/log.txt"
    [[ $args == ablate+* ]] && edges "$gpu" "$name" "$args"
  done
}
edges() {   # edges GPU NAME ARGS: each finished cell of an ablation lane on the edges-and-net goals,
  # while its checkpoint is on this machine (it does not come back): $T/edges/ABLATION-CELL.json
  local gpu=$1 name=$2 args=$3 abl out run c
  abl=$(cut -d+ -f2 <<< "$args"); out=$(grep -o -- '--out+[^+]*' <<< "$args" | cut -d+ -f2)
  [[ -n $out && -d $out/runs ]] || return 0
  mkdir -p "$T/edges"
  for run in "$out"/runs/*; do
    c=$(basename "$run")
    [[ -f $out/results/$c.json && ! -s $T/edges/$abl-$c.json ]] || continue
    CUDA_VISIBLE_DEVICES=$gpu TTMJX_JAX_CACHE=/tmp/jaxcache$gpu python3 -m ttmjx eval "$run" \
      --goals eval/goals/edges_net.csv --json 2>>"$T/$name.log" | tail -1 > "$T/edges/$abl-$c.json"
  done
  echo "=== $name: edges-and-net evaluations $(date +%T): $(ls "$T/edges" | grep -c "^$abl-")" >> "$T/log.txt"
}
mode=$1; shift
if [[ $mode == start ]]; then
  python3 -m pip install -q --no-deps --no-index ${WHEELS:-.wheels}/*.whl 2>&1 | grep -v -i warn | tail -2
  { nvidia-smi --query-gpu=index,name,memory.total --format=csv,noheader; nproc | sed 's/^/cpu cores: /'
    lscpu | grep -E "Model name"; } >> "$T/log.txt"
  printf '%s\n' $LANES | cut -d: -f1 | sort -u | wc -l > "$T/lanes.n"; echo "$TESTS" > "$T/tests.n"
  for gpu in $(printf '%s\n' $LANES | cut -d: -f1 | sort -u); do
    specs=$(printf '%s\n' $LANES | grep "^$gpu:" | tr '\n' ' ')
    setsid bash -c "cd $PWD; source scripts/dev/gpu_lanes.sh lib; lane $gpu $specs; touch $T/lane$gpu.done" \
      </dev/null >/dev/null 2>&1 &
  done
  if (( TESTS )); then   # the README's test command, JAX on the CPU, on another x86-64 make
    # the image's own protobuf and requests are kept where it has them (onnx was built against them)
    python3 -m pip install -q --no-deps --no-index ${WHEELS:-.wheels}/test/{pytest_xdist,execnet,abb_robot_client,pymodbus,websocket_client}*.whl 2>&1 | grep -v -i warn | tail -2
    python3 -c "import google.protobuf, requests" 2>/dev/null || python3 -m pip install -q --no-deps --no-index ${WHEELS:-.wheels}/test/*.whl 2>&1 | grep -v -i warn | tail -2
    setsid bash -c "cd $PWD; CUDA_VISIBLE_DEVICES= JAX_PLATFORMS=cpu TTMJX_JAX_CACHE=/tmp/jaxcache_cpu \
      /usr/bin/time -f 'tests wall %e s' python3 -m pytest -n ${TEST_WORKERS:-12} --durations=20 \
      --junitxml=$T/tests.xml -p no:cacheprovider > $T/tests.log 2>&1; touch $T/tests.done" </dev/null >/dev/null 2>&1 &
    echo "started tests $(date +%T)" >> "$T/log.txt"
  fi
  mode=wait
fi
[[ $mode == lib ]] && return 0
wait_s=$1; t_end=$((SECONDS + wait_s))
n_lanes=$(cat "$T/lanes.n"); TESTS=$(cat "$T/tests.n")   # as started
while (( SECONDS < t_end )); do
  pack
  n=$(ls "$T"/lane*.done "$T"/tests.done 2>/dev/null | wc -l)
  (( n >= n_lanes + TESTS )) && break
  sleep 30
done
date +%T >> "$T/log.txt"; pack
cat "$T/log.txt"
for f in "$T"/*.log; do echo "== $(basename "$f")"; tail -4 "$f"; done
nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
