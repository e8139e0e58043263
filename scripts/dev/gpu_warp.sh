#!/usr/bin/env bash
# MuJoCo Warp against MJX in JAX on one GPU, with the development sweep beside it on the host's CPUs.
#
# warp-lang's library (~390 MB unpacked, 95 MB as .tar.xz) is larger than one call may carry, so it
# travels in parts over several calls to a machine kept warm (idle release 30 s: start the next
# call at once); each call stages its part in .wstage/ (ignored: kept between calls):
#   parts of a tar.xz of the wheel's contents (examples and tests left out): the first 11 MB
#   (it travels with .wheels), then 30 MB each; put one at a time in .wx/ as part.NN
#   PHASE=stage bash scripts/dev/gpu_warp.sh           (carry .wx; the first call also .wheels)
#   PHASE=bench [SWEEP='name="flags" ...'] bash scripts/dev/gpu_warp.sh   (carry .wx: the last part)
# bench: unpacks warp, then `ttmjx bench --backend mjx --batch B --mjx-impl jax|warp` (physics
# alone) and `ttmjx bench --train paper-sim --mjx-impl jax|warp` (a practice round), into $OUT.
source scripts/dev/device_setup.sh
W8=/tmp/wstage; mkdir -p $W8
cp .wx/* $W8/ 2>/dev/null
log "staged: $(ls $W8 | tr "\n" " ") $(du -sh $W8 | cut -f1)"
[[ "${PHASE:-stage}" == stage ]] && exit 0
SP=$(python3 -c 'import site; print(site.getsitepackages()[0])')
if ! python3 -c "import warp" 2>/dev/null; then
  cat $W8/part.* | tar xJf - -C "$SP" || { log "unpack failed: $(ls -la $W8)"; exit 1; }
fi
python3 -c "import warp; warp.init(); print('warp', warp.__version__, 'cuda devices', warp.get_cuda_device_count())" 2>&1 | tail -1 | tee -a "$OUT/log.txt"
if [[ -n "${SWEEP:-}" ]]; then
  (eval "bash scripts/dev/sweep.sh $SWEEP" >/dev/null 2>&1; log "sweep done") &
fi
G="taskset -c $(( $(nproc) - 2 ))-$(( $(nproc) - 1 ))"   # the GPU process's host work: the last 2 cores
for B in ${BATCHES:-4096 16384}; do
  for impl in warp jax; do
    s=$(date +%s)
    $G timeout 200 python3 -m ttmjx bench --backend mjx --batch "$B" --mjx-impl $impl --json \
      >"$OUT/phys_${impl}_$B.txt" 2>&1
    log "physics $impl batch $B rc=$? $(( $(date +%s) - s ))s: $(tail -1 "$OUT/phys_${impl}_$B.txt" | cut -c1-400)"
  done
done
for impl in ${TRAIN_IMPLS:-warp jax}; do
  s=$(date +%s)
  $G timeout "${TRAIN_LIMIT_S:-240}" python3 -m ttmjx bench --train paper-sim --reps 2 --mjx-impl $impl --json \
    >"$OUT/train_$impl.txt" 2>&1
  log "bench --train paper-sim $impl rc=$? $(( $(date +%s) - s ))s: $(tail -1 "$OUT/train_$impl.txt" | cut -c1-600)"
done
wait
log done
