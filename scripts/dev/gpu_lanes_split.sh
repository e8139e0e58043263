#!/usr/bin/env bash
# One call on four H200s (nvidia-h200-x4), after the first lanes call crashed (segmentation
# fault in the first practice round of 8 paper-sim-new lanes over 4 GPUs): 4 lanes (seeds 0-3)
# over 4 GPUs with the lanes split by shard_map, then by jit's partitioner
# (TTMJX_LANE_SPLIT=jit), then the 4 lanes on 1 GPU; each 1 pretraining chunk and 3 practice
# rounds, Python's fault handler on.
#   bash scripts/dev/gpu_lanes_split.sh      (carry .wheels)
# TTMJX_LANE_SPLIT chose the split when this ran (8f2a45f's parent); the code now always uses
# jit's partitioner (training.practice.over_lanes), so both 4-GPU jobs run it today.
# Writes $OUT/lanes.tgz (every lane's metrics.jsonl, each job's log) and $OUT/log.txt.
source scripts/dev/device_setup.sh
job() {  # name, visible GPUs, lane split, time limit
  local s=$(date +%s)
  CUDA_VISIBLE_DEVICES=$2 TTMJX_LANE_SPLIT=$3 timeout -s TERM "$4" python3 -X faulthandler -m ttmjx train \
    --preset paper-sim-new --seeds 4 --pretrain-steps 200 --demos 400 --max-iterations 4 --run-dir "$R/$1" \
    >"$R/$1.log" 2>&1
  log "$1 (GPUs $2, split $3) rc=$? wall $(( $(date +%s) - s ))s"
}
job shardmap4 0,1,2,3 shard_map 165
job jit4 0,1,2,3 jit 170
job one 0 jit 200
log done
tar czf "$OUT/lanes.tgz" -C "$R" --exclude checkpoints --exclude tensorboard --exclude demos . 2>/dev/null
