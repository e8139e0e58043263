"""The training world's strict metrics of an export as the runner plays it (an ensemble's actions
averaged at every step), on the draw of `ttmjx eval --goals N --seed S`, under the export's
trained timing: one JSON line. For the comparison with `ttmjx eval` (an ensemble plays its
members in blocks there, one member per goal).
    python scripts/dev/ensemble_world.py EXPORT N SEED BACKEND
"""
import json
import sys

from deploy.sim import parity
from deploy.sim.station import load_for_station
from ttmjx.world.goals import goal_metrics

if __name__ == "__main__":
    policy, n, seed, backend = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
    loaded = load_for_station(policy)
    w = parity.world_play(loaded, loaded.cfg.timing, backend, n, seed)
    print(json.dumps({"export": policy, "goals": n, "seed": seed, "backend": backend,
                      **goal_metrics(w.tr.landing, w.goals, w.tr.hit, w.tr.on_opponent)}))
