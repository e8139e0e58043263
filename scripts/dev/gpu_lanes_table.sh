#!/usr/bin/env bash
# One call on four H200s (nvidia-h200-x4), lanes split by jit's partitioner:
#  1. 16 lanes of paper-sim-new (seeds 0-15) over 4 GPUs, 4 lanes a GPU, 1 pretraining chunk and
#     3 practice rounds: against the 4 lanes on 1 GPU of scripts/dev/gpu_lanes_split.sh (the same
#     load per GPU), the 4-GPU speed-up of a table;
#  2. `ttmjx ablate practice --scale full --seeds 5 --cells goalseye,lfp-equal-updates`, the 10
#     lanes of GoalsEye and LFP at equal updates as one program over 4 GPUs, at 3,000 trajectories.
#   bash scripts/dev/gpu_lanes_table.sh      (carry .wheels)
# Its first run (2026-11-28) lost its outputs: the 16 lanes ran 291 s, the ablation past the
# call's limit, and the archive came last; now it is written on exit, and LIMITA is 200.
# Writes $OUT/lanes.tgz (metrics.jsonl of every lane, the ablation's results and table, logs) and $OUT/log.txt.
source scripts/dev/device_setup.sh
# Whatever happens (a step past the call's limit), what was written comes back.
trap 'tar czf "$OUT/lanes.tgz" -C "$R" --exclude checkpoints --exclude tensorboard --exclude demos . 2>/dev/null' EXIT
s=$(date +%s)
timeout -s TERM "${LIMIT16:-230}" python3 -m ttmjx train --preset paper-sim-new --seeds 16 --pretrain-steps 200 \
  --demos 400 --max-iterations 4 --run-dir "$R/lanes16" >"$R/lanes16.log" 2>&1
log "16 lanes over 4 GPUs rc=$? wall $(( $(date +%s) - s ))s"
s=$(date +%s)
timeout -s TERM "${LIMITA:-200}" python3 -m ttmjx ablate practice --scale full --seeds 5 \
  --cells goalseye,lfp-equal-updates --trajectories 3000 --out "$R/ablate" >"$R/ablate.log" 2>&1
log "ablate practice (10 lanes, 3,000 trajectories) rc=$? wall $(( $(date +%s) - s ))s"
log done
