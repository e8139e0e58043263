#!/usr/bin/env bash
# On a lent machine with 4 GPUs: Table I's GoalsEye, LFP and GCSL rows and a demonstrations
# cell at TRAJ trajectories (default 120,000), 5 seeds each, one GPU per program; meanwhile the
# paper's bootstrap procedure for any-ball throws is built from scratch on the host's CPU cores.
# Every job outlives one device call (setsid), so calls that follow while the machine is warm
# keep watching it (a GoalsEye arm at 120k takes longer than one call).
#   bash scripts/dev/gpu_table1_x4.sh start WAIT_S    # first call: install, launch, then watch
#   bash scripts/dev/gpu_table1_x4.sh wait WAIT_S     # later calls: keep watching
# Environment: TRAJ, SEEDS, SCALE, BOOT (1: build the bootstrap), TESTS (1: the tests on the CPU), JOBS and FLAGS, the run
# configuration's flags as `ttmjx train` takes them for every job (e.g. FLAGS="--demo-source paper").
# Each call leaves in $OUT: log.txt and table1.tgz (every file under 2 MB but checkpoints: the
# ablations' results/, each run's metrics.jsonl and config.json, the reports, the bootstrap
# build's record, ES weights, policy and maps; each job's log tail as *.log.tail), refreshed
# every 30 s. Give WAIT_S at least 40 s under the call's limit (the lease's budget_left_s may
# cut the last call short, and a call cut by its limit returns only what $OUT held then). A finished arm's seeds are then evaluated on
# eval/goals/edges_net.csv (goals along the net, the end line and the sidelines) on its GPU.
set -uo pipefail
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false TTMJX_JAX_CACHE=/tmp/jaxcache
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; T=${T1_DIR:-/tmp/t1x4}; mkdir -p "$T/edges"
TRAJ=${TRAJ:-120000}; SEEDS=${SEEDS:-5}; SCALE=${SCALE:-full}; BOOT=${BOOT:-1}; TESTS=${TESTS:-0}
FLAGS=${FLAGS:-}   # e.g. FLAGS="--demo-source paper": train's flags, which `ttmjx ablate` passes to every job's cells
# GPU:job:ablation:cells
JOBS=${JOBS:-"0:goalseye:practice:goalseye 1:lfp:practice:lfp-equal-updates,lfp-equal-data 2:gcsl:demos:d0 3:d100:demos:d100"}
pack() {   # $OUT gets two files (a call returns at most 8): table1.tgz and log.txt
  for f in "$T"/*.log; do [[ -f $f ]] && tail -c 100000 "$f" > "$f.tail"; done
  (cd "$T" && find . -type f -size -2M ! -path '*/checkpoints/*' ! -path '*/tensorboard/*' ! -name '*.log' \
    > /tmp/t1x4.list && tar czf "$OUT/table1.tgz.part" -T /tmp/t1x4.list 2>/dev/null) \
    && mv "$OUT/table1.tgz.part" "$OUT/table1.tgz"
  cp "$T/log.txt" "$OUT/log.txt" 2>/dev/null
}
edges() {   # edges GPU JOB ABLATION CELLS: every finished seed of the job's cells on the edge goals
  local gpu=$1 job=$2 abl=$3 cells=$4
  for cell in ${cells//,/ }; do
    for run in "$T/$abl/runs/$cell-seed"*; do
      local c; c=$(basename "$run")
      [[ -f $T/edges/$abl-$c.json ]] || CUDA_VISIBLE_DEVICES=$gpu python3 -m ttmjx eval "$run" \
        --goals eval/goals/edges_net.csv --json 2>>"$T/$job.log" | tail -1 > "$T/edges/$abl-$c.json"
    done
  done
}
cores() {   # cores FIRST LAST: a taskset prefix pinning to those cores, if the machine has them
  (( $2 < $(nproc) && $1 <= $2 )) && echo "taskset -c $1-$2"
}
mode=$1; shift
if [[ $mode == start ]]; then
  [[ -z ${NOINSTALL:-} ]] && python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
  nvidia-smi --query-gpu=index,name,memory.total --format=csv,noheader | tee -a "$T/log.txt"
  nproc | sed 's/^/cpu cores: /' | tee -a "$T/log.txt"
  for spec in $JOBS; do
    IFS=: read -r gpu job abl cells <<< "$spec"
    setsid bash -c "cd $PWD; source scripts/dev/gpu_table1_x4.sh lib; export CUDA_VISIBLE_DEVICES=$gpu
      /usr/bin/time -f 'wall %e s, peak rss %M kB' $(cores $((gpu * 4)) $((gpu * 4 + 3))) python3 -m ttmjx ablate $abl \
        --scale $SCALE --seeds $SEEDS --cells $cells --trajectories $TRAJ $FLAGS --out $T/$abl 2>&1 | stdbuf -oL tr '\r' '\n' \
        | grep --line-buffered -v 'traj/s\|throw/s\|absl\|^\s*$' > $T/$job.log
      touch $T/$job.done; edges $gpu $job $abl $cells; touch $T/$job.edges" </dev/null >/dev/null 2>&1 &
    echo "started $job on GPU $gpu $(date +%T)" | tee -a "$T/log.txt"
  done
  # The paper's procedure on any-ball throws, from scratch, on the remaining cores (JAX on the CPU).
  (( BOOT )) && setsid bash -c "cd $PWD; CUDA_VISIBLE_DEVICES= JAX_PLATFORMS=cpu /usr/bin/time -f 'wall %e s' $(cores 16 $(( $(nproc) - 1 ))) \
    python3 -m ttmjx demos --source paper --rebuild all --distribution any --n 3600 --seed 0 \
    --out $T/boot_any --json 2>&1 | stdbuf -oL tr '\r' '\n' | grep --line-buffered -v 'absl\|^\s*$' > $T/boot_any.log; touch $T/boot_any.done" \
    </dev/null >/dev/null 2>&1 &
  (( BOOT )) && echo "started boot_any $(date +%T)" | tee -a "$T/log.txt"
  # TESTS=1: the README's test command on the host's CPU (another x86-64 make than the
  # developers'), JAX on the CPU, 16 workers on the cores the GPU jobs leave free.
  if (( TESTS )); then
    python3 -m pip install -q --no-deps --no-index .wheels/test/{pytest_xdist,execnet,abb_robot_client,pymodbus,websocket_client}*.whl 2>&1 | grep -v -i warn | tail -2
    python3 -c "import google.protobuf, requests" 2>/dev/null || python3 -m pip install -q --no-deps --no-index .wheels/test/*.whl
    lscpu | grep -E "Model name|Vendor" | tee -a "$T/log.txt"
    setsid bash -c "cd $PWD; CUDA_VISIBLE_DEVICES= JAX_PLATFORMS=cpu TTMJX_JAX_CACHE=/tmp/jaxcache_cpu \
      /usr/bin/time -f 'wall %e s' $(cores 16 $(( $(nproc) - 1 ))) python3 -m pytest -n 12 --durations=20 \
      --junitxml=$T/tests.xml -p no:cacheprovider > $T/tests.log 2>&1; touch $T/tests.done" </dev/null >/dev/null 2>&1 &
    echo "started tests $(date +%T)" | tee -a "$T/log.txt"
  fi
  mode=wait
fi
[[ $mode == lib ]] && return 0
wait_s=$1; t_end=$((SECONDS + wait_s))
while (( SECONDS < t_end )); do
  pack
  n=$(ls "$T"/*.edges "$T"/boot_any.done "$T"/tests.done 2>/dev/null | wc -l)
  (( n >= $(echo $JOBS | wc -w) + BOOT + TESTS )) && break
  sleep 30
done
date +%T >> "$T/log.txt"; cp "$T/log.txt" "$OUT/"; pack
for f in "$T"/*.log; do echo "== $(basename "$f")"; grep -E "^\[|wall|rror|cell|seed" "$f" | tail -6; done
nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
