"""Where each baseline cell's time went, and its final result, one line each (the GPU scripts'
summary): python3 scripts/dev/baseline_timing.py TABLE_DIR [TABLE_DIR ...]"""
import glob
import json
import os
import sys

for table in sys.argv[1:]:
    for f in sorted(glob.glob(os.path.join(table, "runs", "*", "timing.json"))):
        t = json.load(open(f))
        print(os.path.basename(os.path.dirname(f)), "train", t.get("train_s"), "curve", t.get("curve_eval_s"),
              "final", t.get("final_eval_s"), "sps", [round(x["sps"]) for x in t.get("epochs", [])][:12])
    for f in sorted(glob.glob(os.path.join(table, "results", "*.json"))):
        r = json.load(open(f))
        fin = r.get("final", {})
        print(os.path.basename(f), {k: fin.get(k) for k in ("within_30cm", "within_20cm", "hit_rate", "mean_dist")},
              "wall", r.get("wall_s"))
