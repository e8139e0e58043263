#!/usr/bin/env bash
# One call on four H200s (nvidia-h200-x4): the practice table as ONE program over the 4 GPUs,
# and, beside it on the host's first cores, CPU development runs of the main job (sweep.sh).
#
#   GPU: ttmjx ablate practice --scale full --seeds 5 [--trajectories $TRAJ] --cells $CELLS --out runs/practice-table
#        (goalseye, goalseye-paper-pool and lfp-equal-updates: 15 lanes over 4 GPUs). Stopped by
#        SIGTERM at $LIMIT s (every lane saves); the same script in the next call resumes it, as
#        long as the machine is still warm (runs/ is kept between calls).
#   CPU: bash scripts/dev/sweep.sh $SWEEP   (cores 0.., 2 per run; nothing when SWEEP is empty)
#
#   LIMIT=500 [TRAJ=120000] SWEEP='base-s100="--seed 100" ...' bash scripts/dev/gpu_practice_table.sh   (carry .wheels)
# Writes $OUT/table.tgz (the table's results, report and every lane's metrics and config, no
# checkpoints), $OUT/sweep.tgz (sweep.sh's) and $OUT/log.txt.
source scripts/dev/device_setup.sh
T=runs/practice-table
CELLS=${CELLS:-goalseye,goalseye-paper-pool,lfp-equal-updates}
pack() { tar czf "$OUT/table.tgz" --exclude checkpoints --exclude tensorboard --exclude demos "$T" "$R" 2>/dev/null; }
trap pack EXIT
mkdir -p "$T"
(
  s=$(date +%s)
  # the table's host work (Orbax saves, evaluation bookkeeping) on the last 16 cores
  taskset -c "$(( $(nproc) - 16 ))-$(( $(nproc) - 1 ))" timeout -s TERM "${LIMIT:-540}" \
    python3 -m ttmjx ablate practice --scale full --seeds 5 ${TRAJ:+--trajectories $TRAJ} --cells "$CELLS" \
    --out "$T" >>"$R/ablate.log" 2>&1
  log "ablate practice ($CELLS) rc=$? wall $(( $(date +%s) - s ))s"
  nvidia-smi --query-gpu=index,memory.used --format=csv,noheader >>"$OUT/log.txt" 2>/dev/null
) &
table=$!
if [[ -n "${SWEEP:-}" ]]; then
  eval "bash scripts/dev/sweep.sh $SWEEP" >/dev/null 2>&1
  log "sweep done"
fi
wait $table
grep -E "it/s|round|cell|lanes|Error|error" "$R/ablate.log" | tail -20 >>"$OUT/log.txt"
log done
