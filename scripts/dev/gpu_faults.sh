#!/usr/bin/env bash
# Issue 49's drivers rows (docs/RESULTS.md, "Over the drivers' sockets") on a lent GPU machine's
# CPUs, side by side, each row on its own pinned pair of cores (runner on the first, `serve` on
# the second; in process: the first only): in-process, over sockets, over sockets with
# `egm.loss=0.05,modbus.delay_ms=10` (the gantry's latency lead on, the default) and the same
# faults with the lead off (`--no-lead`, the comparison only); the two faults rows REPEAT times
# (run-to-run spread: the same goals and throws, the real clock's timing). GOALS goals of seed 0.
# $OUT gets (the device returns at most 8 files): rows.json ({row: scripts/cell_figures.py's JSON}),
# table.md (also on stdout), log.txt, rows.tgz (each row's JSON and stderr), episodes.tgz (the
# episode logs, with the gantry's targets as sent); the rows themselves are written under $W.
#   bash scripts/dev/gpu_faults.sh [EXPORT]       (EXPORT: an export directory in the repository,
#                                                  default docs/results/parity/export_member0)
# Without an export there, and with the run directory RUN (default runs/confirm/default-s0),
# member 0 of its newest checkpoint is exported to /tmp/gpu_faults_export first.
set -uo pipefail
PY=${PY:-python3}        # the project's python (locally: PY=.venv/bin/python)
if ls .wheels/*.whl >/dev/null 2>&1 && ! "$PY" -c "import mujoco, brax" 2>/dev/null; then
  "$PY" -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
fi
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 JAX_PLATFORMS=cpu CUDA_VISIBLE_DEVICES= TTMJX_JAX_CACHE=$PWD/.jax_cache_cpu
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; W=${W:-/tmp/gpu_faults}; rm -rf "$W"; mkdir -p "$W"
EX=${1:-docs/results/parity/export_member0}; RUN=${RUN:-runs/confirm/default-s0}
GOALS=${GOALS:-40}; SEED=${SEED:-0}; REPEAT=${REPEAT:-2}; LIMIT=${LIMIT:-420}
FAULTS='egm.loss=0.05,modbus.delay_ms=10'
if [ ! -f "$EX/manifest.json" ]; then
  if [ -d "$RUN/checkpoints" ]; then
    EX=/tmp/gpu_faults_export
    [ -f "$EX/manifest.json" ] || "$PY" -m ttmjx export "$RUN" --member 0 --out "$EX" >"$OUT/log.txt" 2>&1 \
      || { echo "export of $RUN failed: $(tail -2 "$OUT/log.txt")"; exit 2; }
  else
    echo "no export at $EX (no manifest.json) and no run at $RUN: carry the export directory"; exit 2
  fi
fi
echo "export $EX ($(du -sh "$EX" | cut -f1)), $GOALS goals of seed $SEED, $(nproc) cores, $(date +%T)" | tee -a "$OUT/log.txt"
N=$(nproc)
row() {  # name core args... (cores wrap around a smaller machine's: a short check only)
  local name=$1 c=$(( $2 % N )); shift 2
  timeout -s TERM "$LIMIT" "$PY" scripts/cell_figures.py "$EX" --goals "$GOALS" --seed "$SEED" \
    --runner-cpu "$c" "$@" --out "$W/$name.episodes" >"$W/$name.json" 2>"$W/$name.err"
  echo "=== $name rc=$? $(date +%T)" | tee -a "$OUT/log.txt"
}
row inproc 0 --inprocess &
row sockets 2 --server-cpu $(( 3 % N )) &
for r in $(seq 1 "$REPEAT"); do
  c=$(( 4 * r ))
  row "faults_r$r" "$c" --server-cpu $(( (c + 1) % N )) --faults "$FAULTS" &
  row "faults_nolead_r$r" $((c + 2)) --server-cpu $(( (c + 3) % N )) --faults "$FAULTS" --no-lead &
done
wait
tar czf "$OUT/rows.tgz" -C "$W" $(cd "$W" && ls *.json *.err)
tar czf "$OUT/episodes.tgz" -C "$W" $(cd "$W" && ls -d *.episodes) 2>/dev/null
if [ "$(stat -c %s "$OUT/episodes.tgz")" -gt 15000000 ]; then     # the device returns 16 MiB a file
  tar czf "$OUT/episodes.tgz" -C "$W" faults_r1.episodes faults_nolead_r1.episodes
fi
"$PY" - "$W" "$OUT" <<'EOF' | tee "$OUT/table.md"
import glob, json, os, sys
rows = {}
print("| row | <= 30 cm | <= 20 cm | hit | opponent's half | episodes | gantry transport p50/p99 ms (not arrived) | gantry excess ms | lead p50 ms | shift p50 mm |")
print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
for path in sorted(glob.glob(os.path.join(sys.argv[1], "*.json"))):
    try:
        d = json.loads(open(path).read().strip().splitlines()[-1])
        rows[os.path.basename(path)[:-5]] = d
    except (ValueError, IndexError):
        print(f"| {os.path.basename(path)[:-5]} | (no result: see its .err) |")
        continue
    m, tr, g = d.get("metrics") or {}, (d.get("transport") or {}).get("gantry") or {}, d.get("gantry") or {}
    link, lead = g.get("link") or {}, g.get("lead") or {}
    f = lambda v, k=100, p=1: "" if v is None else f"{k * v:.{p}f}"
    print(f"| {os.path.basename(path)[:-5]} | {f(m.get('within_30cm'))}% | {f(m.get('within_20cm'))}% | {f(m.get('hit_rate'))}% "
          f"| {f(m.get('on_opponent'))}% | {d.get('episodes')} | {f(tr.get('p50_ms'), 1)}/{f(tr.get('p99_ms'), 1)} ({tr.get('not_arrived', '')}) "
          f"| {f(link.get('excess_ms'), 1)} | {f(lead.get('lead_p50_ms'), 1)} | {f(lead.get('shift_p50_mm'), 1, 2)} |")
json.dump(rows, open(os.path.join(sys.argv[2], "rows.json"), "w"), indent=1, default=float)
EOF
