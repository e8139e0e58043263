"""A practice round's pieces timed one by one, with their kernel counts (issue 45: a jax.profiler
trace of a whole round overflowed CUPTI). For a preset (default paper-sim), on the default JAX
backend, always on MJX physics (never MuJoCo C, whatever the device):

  physics   one control step of the world's physics for B worlds: Backend._physics (the timing
            model's targets, then world.substeps MJX steps with the air forces), the robot held
  policy    the acting policy for B worlds, one control step: Backend._act_fn (observe, the preset's
            practice policy -- models.make_policy plus the held action noise --, command)
  rollout   N control steps of Backend.rollout_fn as practice plays them (reset, policy, physics,
            events, record): the per-step cost a round's rollout pays
  train     training.update.make_train_loop over a synthetic full cache of random episodes (the
            preset's capacity, horizon, window, batch, members), for update_dtype float32 and bfloat16
            by the scan, and on a GPU float32 by cuDNN's LSTM (train_cudnn), with the two kernels'
            loss and gradients on one batch compared (cudnn_vs_scan)
  episode   (--episode) a whole episode (world.horizon control steps) of Backend.rollout_fn

B = the preset's practice episodes per round (--worlds). Each piece is one jitted lax.scan of
--steps control steps (--updates updates), lowered and compiled once (lower_s, compile_s), called
once (first_call_s), then timed over --reps calls: median seconds per call and per step.

Kernels: the optimized HLO (`jit(f).lower(...).compile().as_text()`) is parsed into its
computations. Walking from ENTRY into while bodies and conditions, conditional branches and
called computations (GPU command buffers) -- not into fusions' or reductions' computations --
every instruction is counted by kind: `fusion`, `custom-call` (cuBLAS/cuDNN, ...), `while`,
`conditional`, and `other` (any op but parameter, constant, tuple, get-tuple-element, bitcast
and the control ops). `static` counts each instruction once in the program; `per_step` counts
the launches of one iteration of the scan's while loop (the one whose known trip count is the
scan length), nested loops multiplied by their known trip count (1 where XLA gives none: a
lower bound then, `per_step.loops_without_trip_count` says how many such loops ran), so
`per_step.kernels` = fusion + custom-call + other launched per control step (per update) and
`per_step.loop_iterations` the while iterations in it (on a GPU each one reads its predicate
back to the host unless the loop runs in a command buffer).

    JAX_PLATFORMS=cpu python scripts/dev/step_profile.py tiny /tmp/sp --worlds 8 --steps 3 --updates 3
    python scripts/dev/step_profile.py paper-sim OUT [--worlds B] [--steps N] [--updates N] [--episode]

Prints one JSON object and writes OUT/step_profile.json (rewritten after each piece, so a run
cut short keeps what it measured).
"""
import argparse
import collections
import dataclasses
import json
import os
import re
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from models import cudnn_lstm  # noqa: E402
from models.normalizer import identity_normalizer  # noqa: E402
from models.policy import init_ensemble  # noqa: E402
from training.cache import Cache  # noqa: E402
from training.loss import policy_loss  # noqa: E402
from training.practice import practice_policy  # noqa: E402
from training.sampler import sample_subsequences  # noqa: E402
from training.runconfig import preset  # noqa: E402
from training.update import init_train_state, make_train_loop  # noqa: E402
from ttmjx.world import thrower  # noqa: E402
from ttmjx.world.backends import Backend, batched_policy  # noqa: E402
from ttmjx.world.env import uniform_goals  # noqa: E402

FREE = {"parameter", "constant", "tuple", "get-tuple-element", "bitcast", "after-all", "add-dependency",
        "opt-barrier", "partition-id", "replica-id", "domain", "while", "conditional", "call", "async-start",
        "async-update", "async-done", "copy-done", "send-done", "recv-done"}
_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%?[\w.\-]+\s*=\s*(.*)$")


def _opcode(rest: str) -> str:
    """The opcode of an instruction's text after '=': skip the shape (a tuple in parentheses)."""
    if rest.startswith("("):
        depth = 0
        for i, ch in enumerate(rest):
            depth += {"(": 1, ")": -1}.get(ch, 0)
            if depth == 0:
                break
        rest = rest[i + 1:]
    else:
        rest = rest.split(" ", 1)[-1]
    return rest.lstrip().split("(", 1)[0].strip()


def parse_hlo(text: str):
    """{computation: [(opcode, line)]} and the ENTRY computation's name."""
    comps, entry, cur = {}, None, None
    for line in text.splitlines():
        if cur is None:
            m = re.match(r"^(ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$", line)
            if m and not line.startswith(("HloModule", " ")):
                cur = m.group(2)
                comps[cur] = []
                entry = cur if m.group(1) else entry
        elif line.strip() == "}":
            cur = None
        else:
            m = _INSTR.match(line)
            if m:
                comps[cur].append((_opcode(m.group(1)), line))
    return comps, entry


def _callees(op: str, line: str) -> list[str]:
    if op == "while":
        return re.findall(r"(?:condition|body)=%?([\w.\-]+)", line)
    if op == "conditional":
        m = re.search(r"branch_computations=\{([^}]*)\}", line)
        return [s.strip().lstrip("%") for s in m.group(1).split(",")] if m else \
            re.findall(r"(?:true|false)_computation=%?([\w.\-]+)", line)
    if op in ("call", "async-start"):
        return re.findall(r"(?:to_apply|calls)=%?([\w.\-]+)", line)
    return []


def _trips(line: str) -> int | None:
    m = re.search(r'"known_trip_count":\{"n":"(\d+)"', line)
    return int(m.group(1)) if m else None


def kernel_counts(text: str, scan_len: int) -> dict:
    comps, entry = parse_hlo(text)
    static = collections.Counter()
    others = collections.Counter()
    seen = {}                           # insertion-ordered

    def walk(c):                        # every executed computation once
        if c in seen or c not in comps:
            return
        seen[c] = True
        for op, line in comps[c]:
            kind = op if op in ("fusion", "custom-call", "while", "conditional") else (
                None if op in FREE else "other")
            if kind:
                static[kind] += 1
            if kind == "other":
                others[op] += 1
            if op == "call" and "command_buffer" in line:
                static["command_buffers"] += 1
            for callee in _callees(op, line):
                walk(callee)

    def dyn(c) -> collections.Counter:  # launches of one execution of computation c
        n = collections.Counter()
        for op, line in comps.get(c, []):
            if op in ("fusion", "custom-call"):
                n[op] += 1
            elif op == "while":
                t = _trips(line)
                n["loop_iterations"] += t or 1
                n["loops_without_trip_count"] += t is None
                t = t or 1
                for callee in _callees(op, line):
                    for k, v in dyn(callee).items():
                        n[k] += t * v
            elif op == "conditional":
                branches = [dyn(b) for b in _callees(op, line)]
                if branches:
                    n.update(max(branches, key=lambda x: sum(x.values())))
            elif op in ("call", "async-start"):
                for callee in _callees(op, line):
                    n.update(dyn(callee))
            elif op not in FREE:
                n["other"] += 1
        return n

    walk(entry)
    loops = [(op, line) for c in seen for op, line in comps[c] if op == "while" and _trips(line) == scan_len]
    if loops:       # the scan's loop (the busiest of trip count N): one iteration = one control step (update)
        def iteration(line):
            n = collections.Counter()
            for callee in _callees("while", line):
                n.update(dyn(callee))
            return n
        per = max((iteration(line) for _, line in loops), key=lambda x: x["fusion"] + x["custom-call"] + x["other"])
        how = f"one iteration of the while loop of trip count {scan_len}"
    else:           # unrolled or not found: the whole program over the scan's length
        per = collections.Counter({k: v / scan_len for k, v in dyn(entry).items()})
        how = f"the whole program / {scan_len} (no while loop of trip count {scan_len})"
    per["kernels"] = per["fusion"] + per["custom-call"] + per["other"]
    static["kernels"] = static["fusion"] + static["custom-call"] + static["other"]
    return {"static": dict(static), "static_other_ops": dict(others.most_common(8)),
            "per_step": {k: round(v, 2) for k, v in per.items()}, "per_step_is": how,
            "hlo_lines": text.count("\n")}


def measure(fn, args, steps: int, reps: int) -> dict:
    """Lower, compile, call once, then time `reps` calls of fn(*args), a scan of `steps` steps."""
    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    first = jax.block_until_ready(compiled(*args))
    t3 = time.perf_counter()
    times = []
    for _ in range(reps):
        s = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - s)
    med = statistics.median(times)
    return {"steps_per_call": steps, "lower_s": round(t1 - t0, 3), "compile_s": round(t2 - t1, 3),
            "first_call_s": round(t3 - t2, 4), "call_s": [round(t, 5) for t in times],
            "median_call_s": round(med, 5), "per_step_s": med / steps,
            "kernels": kernel_counts(compiled.as_text(), steps), "checksum": checksum(first)}


def checksum(out) -> float:
    """The sum of every float leaf of out, in float64 on the host: equal programs (an XLA flag
    that changes only how kernels are launched) give equal sums."""
    leaves = [np.asarray(x, np.float64) for x in jax.tree.leaves(out)
              if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating)]
    return float(sum(np.nansum(x) for x in leaves))


def synthetic_cache(key, capacity: int, horizon: int, window: int, demos: int) -> Cache:
    """A full cache of random episodes: valid prefixes of window..horizon steps, the hit inside,
    the first `demos` rows demonstrations."""
    k = jax.random.split(key, 6)
    length = jax.random.randint(k[0], (capacity,), min(window, horizon), horizon + 1)
    valid = jnp.arange(horizon)[None] < length[:, None]
    hit = (jax.random.uniform(k[1], (capacity,)) * length).astype(jnp.int32)
    n = lambda kk, *s: jax.random.normal(kk, (capacity, *s), jnp.float32)  # noqa: E731
    return Cache(n(k[2], horizon, 13), n(k[3], horizon, 3), n(k[4], horizon, 8), valid, hit,
                 jax.random.uniform(k[5], (capacity, 2), minval=-0.7, maxval=0.7) + jnp.array([2.0, 0.0]),
                 jnp.arange(capacity) < demos, jnp.int32(capacity), jnp.int32(capacity))


def kernel_agreement(pcfg, tcfg, params, cache, key) -> dict:
    """The members' loss and gradients on one batch by the scan and by cuDNN (vmapped over the
    members, as the updates are): the largest differences, absolute and relative to the largest
    gradient value."""
    batch = sample_subsequences(key, cache, tcfg.window, tcfg.batch_size, pcfg.input_frames, pcfg.obs_size)

    def grads(kernel):
        one = lambda p: jax.value_and_grad(lambda net: policy_loss(pcfg, p._replace(net=net), batch, "float32", kernel))(p.net)  # noqa: E731
        return jax.jit(jax.vmap(one))(params)

    (l_s, g_s), (l_c, g_c) = grads("scan"), grads("cudnn")
    gmax = max(float(jnp.abs(g).max()) for g in jax.tree.leaves(g_s))
    gdiff = max(float(jnp.abs(a - b).max()) for a, b in zip(jax.tree.leaves(g_s), jax.tree.leaves(g_c)))
    return {"loss_scan": np.asarray(l_s).tolist(), "loss_cudnn": np.asarray(l_c).tolist(),
            "loss_max_rel_diff": float(jnp.max(jnp.abs(l_s - l_c) / jnp.abs(l_s))),
            "grad_max_abs_diff": gdiff, "grad_max_abs": gmax, "grad_max_diff_over_max": gdiff / gmax}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("preset", nargs="?", default="paper-sim")
    ap.add_argument("out")
    ap.add_argument("--worlds", type=int, help="B worlds (default: the preset's episodes per round)")
    ap.add_argument("--steps", type=int, default=20, help="control steps per timed scan")
    ap.add_argument("--updates", type=int, default=50, help="updates per timed train loop")
    ap.add_argument("--reps", type=int, default=5, help="timed calls of each program")
    ap.add_argument("--capacity", type=int, help="synthetic cache rows (default: the preset's)")
    ap.add_argument("--pieces", default="physics,policy,train,rollout", help="a subset of physics,policy,train,rollout")
    ap.add_argument("--episode", action="store_true", help="also a whole episode of rollout_fn")
    ap.add_argument("--members", type=int, help="train.members (default: the preset's)")
    ap.add_argument("--solver-iterations", type=int, help="world.contacts.solver_iterations (default: the preset's)")
    ap.add_argument("--line-search-iterations", type=int,
                    help="world.contacts.line_search_iterations (default: the preset's)")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    t_start = time.perf_counter()
    cfg = preset(a.preset)
    cfg = dataclasses.replace(cfg, world=cfg.world.with_solver_caps(a.solver_iterations, a.line_search_iterations))
    if a.members:
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, members=a.members))
    world, pcfg, tcfg = cfg.world, cfg.policy, cfg.train
    b = a.worlds or cfg.episodes_per_ssp
    members = tcfg.members
    b = max(members, b - b % members)               # every member plays an equal block
    pieces = [p for p in a.pieces.split(",") if p] + (["episode"] if a.episode else [])
    res = {"preset": a.preset, "jax": jax.__version__, "backend": jax.default_backend(), "xla_flags": os.environ.get("XLA_FLAGS", ""),
           "device": str(jax.devices()[0].device_kind), "devices": jax.device_count(), "physics": "mjx",
           "mjx_impl": world.mjx_impl, "solver_iterations": world.contacts.solver_iterations,
           "line_search_iterations": world.contacts.line_search_iterations,
           "shapes": {"worlds": b, "members": members, "policy": dataclasses.asdict(pcfg),
                      "substeps_per_control_step": world.substeps, "control_hz": world.control_hz,
                      "horizon": world.horizon, "timing_ideal": world.timing.ideal,
                      "window": tcfg.window, "batch_size": tcfg.batch_size, "capacity": a.capacity or tcfg.capacity,
                      "steps_per_scan": a.steps, "updates_per_scan": a.updates},
           "pieces": {}}
    path = os.path.join(a.out, "step_profile.json")

    def save():
        res["wall_s"] = round(time.perf_counter() - t_start, 1)
        with open(path, "w") as f:
            json.dump(res, f, indent=1)

    key = jax.random.key(0)
    s = time.perf_counter()
    backend = Backend(world, "mjx")
    throws = jax.jit(thrower.sample_throws, static_argnums=(1, 2))(jax.random.fold_in(key, 1), world, b)
    goals = uniform_goals(jax.random.fold_in(key, 2), b, world.table, tcfg.practice_goal_margin)
    states = backend.reset(jax.random.fold_in(key, 3), throws, goals)
    norm = identity_normalizer(pcfg.obs_size)
    norm = norm._replace(act_mean=jnp.array(world.robot.home, jnp.float32), act_std=jnp.full(8, 0.1))
    params = init_ensemble(jax.random.fold_in(key, 4), pcfg, norm, members)
    policy = practice_policy(pcfg, tcfg)
    jax.block_until_ready((throws, states, params))
    res["setup_s"] = round(time.perf_counter() - s, 2)
    save()
    n = a.steps

    def run(name, fn, args, steps, reps=a.reps, **extra):
        print(f"[step_profile] {name} ...", file=sys.stderr, flush=True)
        try:
            res["pieces"][name] = {**measure(fn, args, steps, reps), **extra}
        except Exception as e:  # noqa: BLE001 -- a piece that fails is reported, the others still run
            res["pieces"][name] = {"error": f"{type(e).__name__}: {str(e)[:500]}"}
        print(f"[step_profile] {name}: {json.dumps(res['pieces'][name])[:400]}", file=sys.stderr, flush=True)
        save()

    if "physics" in pieces:
        def physics(states):
            target = states.target                   # the robot holds its last command

            def body(st, _):
                qpos, qvel, *_, cmds = backend._physics(st, target)
                return st._replace(qpos=qpos.astype(jnp.float32), qvel=qvel.astype(jnp.float32), cmds=cmds,
                                   t=st.t + 1), None
            return jax.lax.scan(body, states, None, length=n)[0]
        run("physics", physics, (states,), n, what="Backend._physics: timing-model targets + substeps MJX steps")
        if "per_step_s" in res["pieces"]["physics"]:
            res["pieces"]["physics"]["per_substep_s"] = res["pieces"]["physics"]["per_step_s"] / world.substeps

    if "policy" in pieces:
        act, init_b = backend._act_fn(policy, members), batched_policy(policy, members)[0]

        def forward(params, states, key):
            carry = init_b(params, jax.random.split(key, b))

            def body(c, t):
                carry, st = c
                carry, _, target = act(params, carry, st, jax.random.fold_in(key, t))
                # new frames every step (rolled), or XLA hoists a frame-stack net out of the loop
                return (carry, st._replace(target=target, frames=jnp.roll(st.frames, 1, axis=1))), None
            return jax.lax.scan(body, (carry, states), jnp.arange(n))[0]
        run("policy", forward, (params, states, key), n, what="observe + practice policy + command")

    if "train" in pieces:
        cap = a.capacity or tcfg.capacity
        cache = jax.jit(synthetic_cache, static_argnums=(1, 2, 3, 4))(
            jax.random.fold_in(key, 5), cap, world.horizon, tcfg.window, min(cfg.demos, cap))
        state = init_train_state(jax.random.fold_in(key, 6), pcfg, tcfg, norm)
        variants = [("float32", "scan"), ("bfloat16", "scan")]
        if pcfg.kind == "lstm" and cudnn_lstm.available() and members == 1:    # cuDNN: one member (training.loss)
            variants.append(("float32", "cudnn"))
        for dt, kernel in variants:
            t = dataclasses.replace(tcfg, update_dtype=dt, lstm_kernel=kernel)
            name = f"train_{dt}" if kernel == "scan" else f"train_{kernel}"
            run(name, make_train_loop(pcfg, t, a.updates), (state, cache, key), a.updates,
                what=f"make_train_loop: {a.updates} updates of {members} member(s), {dt}, the LSTM by {kernel}")
        if len(variants) == 3:
            res["cudnn_vs_scan"] = kernel_agreement(pcfg, tcfg, state.params, cache, key)
            print(f"[step_profile] cudnn_vs_scan: {res['cudnn_vs_scan']}", file=sys.stderr, flush=True)
            save()
        del cache

    roll = lambda t_max: backend.rollout_fn(policy, t_max, members)  # noqa: E731
    if "rollout" in pieces:
        run("rollout", roll(n), (params, key, throws, goals), n, what=f"Backend.rollout_fn, {n} control steps")

    if "episode" in pieces:
        h = world.horizon
        run("episode", roll(h), (params, key, throws, goals), h, reps=min(a.reps, 2),
            what=f"Backend.rollout_fn, a whole episode ({h} steps)")

    summary = {k: {"per_step_ms": round(1e3 * v["per_step_s"], 4), "compile_s": v["compile_s"],
                   "kernels_per_step": v["kernels"]["per_step"]["kernels"]}
               for k, v in res["pieces"].items() if "per_step_s" in v}
    res["summary"] = summary
    save()
    print(json.dumps(res))


if __name__ == "__main__":
    main()
