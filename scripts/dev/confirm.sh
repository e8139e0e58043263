#!/usr/bin/env bash
# Fresh-seed check of the CPU main job (docs/RESULTS.md, "Practice that lifts"): for each seed,
# the README's training command and GCBC on the demonstrations alone at equal updates
# (--preset lfp), every checkpoint kept; then the LFP point (checkpoint 10, after pretraining)
# and the final checkpoint on 400 uniform goals and on the edges-and-net goal set, the same
# goals and throws for every run. Resumable: a finished seed leaves RUN.done.
#   bash scripts/dev/confirm.sh            # SEEDS="0 1 2 3 4", OUT_DIR=runs/confirm
#   python3 scripts/dev/confirm_table.py   # the table of docs/RESULTS.md
set -uo pipefail
SEEDS=${SEEDS:-0 1 2 3 4}; OUT_DIR=${OUT_DIR:-runs/confirm}; mkdir -p "$OUT_DIR"
for s in $SEEDS; do
  for v in default lfp; do
    d=$OUT_DIR/$v-s$s
    [ -f "$d.done" ] && continue
    python3 -m ttmjx train --preset $v --seed "$s" --run-dir "$d" --keep-checkpoints 100 --json >"$d.train.json" 2>"$d.train.err"
    for g in 400 eval/goals/edges_net.csv; do
      tag=$([ "$g" = 400 ] && echo uniform400 || echo edges_net)
      [ $v = default ] && python3 -m ttmjx eval "$d" --goals "$g" --seed 2026 --step 10 --json >"$d.eval_lfp_$tag.json"
      python3 -m ttmjx eval "$d" --goals "$g" --seed 2026 --json >"$d.eval_final_$tag.json"
    done
    touch "$d.done"
  done
done
