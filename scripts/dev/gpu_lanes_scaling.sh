#!/usr/bin/env bash
# One call on four H200s (nvidia-h200-x4): the same 8 lanes of paper-sim-new (seeds 0-7) as one
# program laid over 4 GPUs (2 lanes each), then over 1 GPU (8 lanes), each for 2 pretraining
# chunks and 3 practice rounds (400 demonstrations each, to keep the setup short); then the same preset as 1 lane alone on 1 GPU: what laying
# lanes over every device gains. Per-iteration seconds are in each lane's metrics.jsonl ("seconds").
#   bash scripts/dev/gpu_lanes_scaling.sh      (carry .wheels)
# Writes $OUT/lanes.tgz (every lane's metrics.jsonl and config.json) and $OUT/log.txt.
source scripts/dev/device_setup.sh
job() {  # name, visible GPUs, seeds, time limit
  local s=$(date +%s)
  CUDA_VISIBLE_DEVICES=$2 timeout -s TERM "$4" python3 -m ttmjx train --preset paper-sim-new --seeds "$3" \
    --pretrain-steps 400 --demos 400 --max-iterations 5 --run-dir "$R/$1" --json >"$R/$1.log" 2>&1
  log "$1 (GPUs $2, $3 lanes) rc=$? wall $(( $(date +%s) - s ))s"
}
job gpu4 0,1,2,3 8 ${LIMIT4:-230}
job gpu1 0 8 ${LIMIT1:-230}
job alone 0 1 ${LIMITA:-95}
log done
tail -3 "$R"/*.log >>"$OUT/log.txt" 2>/dev/null
tar czf "$OUT/lanes.tgz" -C "$R" --exclude checkpoints --exclude tensorboard --exclude demos . 2>/dev/null
