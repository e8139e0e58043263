"""Numpy inference of the exported policies (models/ reimplemented without JAX).

The robot's computer needs numpy only: this module never imports JAX or flax. It computes
exactly what `models.make_policy(cfg).apply` computes, in float32:

  x = (obs - obs_mean) / obs_std                          (models.normalizer.normalize_obs)
  lstm: per layer l (flax OptimizedLSTMCell, carry (c, h)):
        z = x Wx + h Wh + b,   Wx = [ii | if | ig | io],  Wh = [hi | hf | hg | ho],  b = hidden biases
        i, f, o = sigmoid(z_i), sigmoid(z_f), sigmoid(z_o);  g = tanh(z_g)
        c' = f c + i g;  h' = o tanh(c');  x = h'
        y = h'_last Whead + bhead
  framestack: x = flatten(frames [k, O]);  x = relu(x W_l + b_l) per layer;  y = x Whead + bhead
  action = y * act_std + act_mean                          (models.normalizer.denormalize_actions)

Ensembles: every member keeps its own recurrent state and normalizer; the action sent is the
MEAN of the members' actions (absolute joint targets, after denormalization). `step_members`
gives the per-member actions.

State (what `reset` returns and `step` threads through): float32 [members, layers, 2, hidden]
with [..., 0, :] = c and [..., 1, :] = h, zeros at every episode start (models.zero_carry);
None for the stateless frame-stack MLP. `step` never modifies the state it is given.

Weights arrive as a dict of float32 arrays named by their flattened parameter paths with a
leading member axis [N, ...] (deploy/export.py): `net/params/lstm0/hf/kernel`, `norm/obs_mean`.

Latency: `benchmark(...)` times single steps on one CPU core (BLAS threads = 1, pinned), in a
subprocess so the thread settings take effect before numpy loads (`python -m
deploy.numpy_policy --bench --hidden 1024 --layers 2 --json`).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from typing import NamedTuple

import numpy as np

ACTION_SIZE = 8
KINDS = ("lstm", "framestack")
_GATES = ("i", "f", "g", "o")          # flax OptimizedLSTMCell order of the gates
_NORM = ("obs_mean", "obs_std", "act_mean", "act_std")


class PolicySpec(NamedTuple):
    """The architecture (models.PolicyConfig's fields), numpy side."""
    kind: str
    hidden: int
    layers: int
    obs_size: int
    frame_stack: int

    @property
    def input_frames(self) -> int:
        return self.frame_stack if self.kind == "framestack" else 1

    def check(self) -> "PolicySpec":
        if self.kind not in KINDS:
            raise ValueError(f"policy kind {self.kind!r}; expected one of {KINDS}")
        for name in ("hidden", "layers", "obs_size", "frame_stack"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
                raise ValueError(f"policy {name}={v!r}; expected an integer >= 1")
        return self


def tensor_shapes(spec: PolicySpec, members: int) -> dict[str, tuple]:
    """Every tensor of an export of `members` members: name -> shape (leading [members])."""
    spec.check()
    n, h, o = members, spec.hidden, spec.obs_size
    shapes = {f"norm/{k}": (n, o if k.startswith("obs") else ACTION_SIZE) for k in _NORM}
    p = "net/params"
    if spec.kind == "lstm":
        for layer in range(spec.layers):
            fan_in = o if layer == 0 else h
            for g in _GATES:
                shapes[f"{p}/lstm{layer}/i{g}/kernel"] = (n, fan_in, h)
                shapes[f"{p}/lstm{layer}/h{g}/kernel"] = (n, h, h)
                shapes[f"{p}/lstm{layer}/h{g}/bias"] = (n, h)
    else:
        fan_in = spec.frame_stack * o
        for layer in range(spec.layers):
            shapes[f"{p}/dense{layer}/kernel"] = (n, fan_in, h)
            shapes[f"{p}/dense{layer}/bias"] = (n, h)
            fan_in = h
    shapes[f"{p}/head/kernel"] = (n, h, ACTION_SIZE)
    shapes[f"{p}/head/bias"] = (n, ACTION_SIZE)
    return shapes


def check_tensors(spec: PolicySpec, tensors: dict, members: int | None = None) -> int:
    """Raise ValueError naming the first missing, unexpected, mis-shaped or non-float32 tensor;
    returns the number of members."""
    if members is None:
        lead = np.shape(tensors.get("net/params/head/bias", ()))
        members = int(lead[0]) if len(lead) == 2 else 0
        if members < 1:
            raise ValueError("weights lack net/params/head/bias [members, 8]")
    want = tensor_shapes(spec, members)
    missing, extra = sorted(set(want) - set(tensors)), sorted(set(tensors) - set(want))
    if missing or extra:
        raise ValueError(f"weights do not match a {spec.kind} policy (hidden={spec.hidden}, "
                         f"layers={spec.layers}, obs_size={spec.obs_size}, members={members}): "
                         f"missing {missing}, unexpected {extra}")
    for name, shape in want.items():
        t = tensors[name]
        if tuple(t.shape) != shape:
            raise ValueError(f"tensor {name} has shape {tuple(t.shape)}, expected {shape}")
        if t.dtype != np.float32:
            raise ValueError(f"tensor {name} has dtype {t.dtype}, expected float32")
        if not np.all(np.isfinite(t)):
            raise ValueError(f"tensor {name} holds non-finite values")
    if np.any(tensors["norm/obs_std"] <= 0) or np.any(tensors["norm/act_std"] <= 0):
        raise ValueError("normalizer standard deviations must be > 0")
    return members


def _sigmoid(x, out):
    """1 / (1 + exp(-x)) in place into out (float32), as jax.nn.sigmoid."""
    np.negative(x, out=out)
    np.exp(out, out=out)
    out += 1.0
    np.reciprocal(out, out=out)
    return out


class _Member:
    """One member's weights in the layout the step uses."""

    def __init__(self, spec: PolicySpec, tensors: dict, i: int):
        f32 = lambda name: np.ascontiguousarray(tensors[name][i], np.float32)  # noqa: E731
        self.obs_mean, self.obs_std = f32("norm/obs_mean"), f32("norm/obs_std")
        self.act_mean, self.act_std = f32("norm/act_mean"), f32("norm/act_std")
        p, h = "net/params", spec.hidden
        self.layers = []
        if spec.kind == "lstm":
            for layer in range(spec.layers):
                q = f"{p}/lstm{layer}"
                wx = np.concatenate([f32(f"{q}/i{g}/kernel") for g in _GATES], axis=1)
                wh = np.concatenate([f32(f"{q}/h{g}/kernel") for g in _GATES], axis=1)
                b = np.concatenate([f32(f"{q}/h{g}/bias") for g in _GATES])
                # One matrix for [x, h]: a single matrix-vector product per layer and step.
                w = np.ascontiguousarray(np.concatenate([wx, wh], axis=0))
                fan_in = wx.shape[0]
                self.layers.append((w, b, fan_in, np.zeros(fan_in + h, np.float32),
                                    np.zeros(4 * h, np.float32)))
            self.gate = np.zeros(h, np.float32)
        else:
            for layer in range(spec.layers):
                self.layers.append((f32(f"{p}/dense{layer}/kernel"), f32(f"{p}/dense{layer}/bias")))
        self.head_w, self.head_b = f32(f"{p}/head/kernel"), f32(f"{p}/head/bias")

    def lstm_step(self, state_in: np.ndarray, state_out: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """state_in/state_out [layers, 2, H] (c, h); obs [O] raw -> action [8]."""
        x = (obs - self.obs_mean) / self.obs_std
        gate = self.gate
        for layer, (w, b, fan_in, xh, z) in enumerate(self.layers):
            c, h = state_in[layer, 0], state_in[layer, 1]
            hid = h.shape[0]
            xh[:fan_in] = x
            xh[fan_in:] = h
            np.dot(xh, w, out=z)
            z += b
            c_new, h_new = state_out[layer, 0], state_out[layer, 1]
            # c' = f c + i g
            np.tanh(z[2 * hid:3 * hid], out=c_new)                       # g
            c_new *= _sigmoid(z[:hid], gate)                              # i g
            c_new += _sigmoid(z[hid:2 * hid], gate) * c                   # + f c
            # h' = o tanh(c')
            np.tanh(c_new, out=h_new)
            h_new *= _sigmoid(z[3 * hid:], gate)
            x = h_new
        y = x @ self.head_w + self.head_b
        return y * self.act_std + self.act_mean

    def mlp_step(self, frames: np.ndarray) -> np.ndarray:
        """frames [k, O] raw -> action [8]."""
        x = ((frames - self.obs_mean) / self.obs_std).reshape(-1)
        for w, b in self.layers:
            x = np.maximum(x @ w + b, 0.0)
        y = x @ self.head_w + self.head_b
        return y * self.act_std + self.act_mean


class ExportedPolicy:
    """A models/ policy (one member or an ensemble) on numpy; deploy.runner's NumpyPolicy."""

    def __init__(self, spec: PolicySpec, tensors: dict, policy_hash: str = "unknown"):
        self.spec = spec.check()
        self.members = check_tensors(spec, tensors)
        self.policy_hash = policy_hash
        self._m = [_Member(spec, tensors, i) for i in range(self.members)]

    @property
    def state_shape(self) -> tuple:
        """Shape of the recurrent state; () for the stateless MLP."""
        if self.spec.kind != "lstm":
            return ()
        return (self.members, self.spec.layers, 2, self.spec.hidden)

    def reset(self):
        """The state at an episode start: zeros (LSTM) or None (frame stack)."""
        if self.spec.kind != "lstm":
            return None
        return np.zeros(self.state_shape, np.float32)

    def _obs(self, frame, frames):
        o, k = self.spec.obs_size, self.spec.input_frames
        if self.spec.kind == "lstm":
            x = np.asarray(frame, np.float32)
            if x.shape != (o,):
                raise ValueError(f"policy step: frame has shape {x.shape}, expected ({o},)")
            return x
        x = np.asarray(frames, np.float32)
        if x.shape != (k, o):
            raise ValueError(f"policy step: frames has shape {x.shape}, expected ({k}, {o})")
        return x

    def step_members(self, state, frame, frames) -> tuple:
        """(new state, actions [members, 8]): one control step of every member."""
        x = self._obs(frame, frames)
        acts = np.empty((self.members, ACTION_SIZE), np.float32)
        if self.spec.kind == "lstm":
            state = np.asarray(state, np.float32)
            if state.shape != self.state_shape:
                raise ValueError(f"policy step: state has shape {state.shape}, expected {self.state_shape}")
            new = np.empty_like(state)
            for i, m in enumerate(self._m):
                acts[i] = m.lstm_step(state[i], new[i], x)
            return new, acts
        for i, m in enumerate(self._m):
            acts[i] = m.mlp_step(x)
        return None, acts

    def step(self, state, frame, frames) -> tuple:
        """frame [13] (= frames[-1]), frames [k, 13] -> (state, action [8]): the mean over members."""
        state, acts = self.step_members(state, frame, frames)
        return state, (acts[0] if self.members == 1 else acts.mean(axis=0))

    def run(self, frames: np.ndarray, stacks: np.ndarray | None = None, members: bool = False):
        """A whole episode from reset: frames [L, O] (and stacks [L, k, O] for the MLP) ->
        actions [L, 8] (or [members, L, 8] with members=True)."""
        frames = np.asarray(frames, np.float32)
        if stacks is None:
            stacks = frames[:, None, :]
        state = self.reset()
        out = []
        for t in range(frames.shape[0]):
            state, acts = self.step_members(state, frames[t], stacks[t])
            out.append(acts if members else acts.mean(axis=0))
        out = np.stack(out)
        return np.swapaxes(out, 0, 1) if members else out


def random_tensors(spec: PolicySpec, members: int = 1, seed: int = 0, scale: float = 1.0) -> dict:
    """Random float32 weights of the right shapes (tests and the latency benchmark), with
    Glorot-like scales so the activations stay in range; identity normalizer."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, shape in tensor_shapes(spec, members).items():
        if name.endswith("_std"):
            out[name] = np.ones(shape, np.float32)
        elif name.startswith("norm/"):
            out[name] = np.zeros(shape, np.float32)
        elif name.endswith("kernel"):
            out[name] = (rng.standard_normal(shape) * scale / np.sqrt(shape[1])).astype(np.float32)
        else:
            out[name] = (0.1 * scale * rng.standard_normal(shape)).astype(np.float32)
    return out


# --------------------------------------------------------------------------------------------
# Latency benchmark
# --------------------------------------------------------------------------------------------
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
               "BLIS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


def _time_steps(policy: ExportedPolicy, steps: int, warmup: int, seed: int) -> np.ndarray:
    """Wall seconds of `steps` single policy steps (after `warmup`), frames drawn at random."""
    rng = np.random.default_rng(seed)
    o, k = policy.spec.obs_size, max(policy.spec.input_frames, 1)
    frames = rng.standard_normal((warmup + steps, k, o)).astype(np.float32)
    state = policy.reset()
    times = np.empty(steps)
    for t in range(warmup + steps):
        if t % 32 == 0:
            state = policy.reset()          # episodes of 32 ticks, as at 20 Hz
        t0 = time.perf_counter()
        state, _ = policy.step(state, frames[t, -1], frames[t])
        dt = time.perf_counter() - t0
        if t >= warmup:
            times[t - warmup] = dt
    return times


def bench_here(kind: str = "lstm", hidden: int = 1024, layers: int = 2, members: int = 1,
               frame_stack: int = 8, steps: int = 2000, warmup: int = 200, seed: int = 0) -> dict:
    """Time single steps in THIS process (thread settings are whatever numpy started with)."""
    spec = PolicySpec(kind, hidden, layers, 13, frame_stack)
    policy = ExportedPolicy(spec, random_tensors(spec, members, seed))
    ms = 1e3 * _time_steps(policy, steps, warmup, seed)
    return {"kind": kind, "hidden": hidden, "layers": layers, "members": members,
            "steps": steps, "p50_ms": float(np.percentile(ms, 50)),
            "p90_ms": float(np.percentile(ms, 90)), "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max()), "mean_ms": float(ms.mean()),
            "numpy": np.__version__}


def benchmark(kind: str = "lstm", hidden: int = 1024, layers: int = 2, members: int = 1,
              steps: int = 2000, warmup: int = 200, threads: int = 1, cpu: int | None = None,
              timeout_s: float = 600.0) -> dict:
    """Step latency (p50/p90/p99/max, ms) of a numpy policy on `threads` BLAS threads, pinned to
    one CPU core (`cpu`, default: the last one this process may use), in a fresh subprocess so
    OMP/OPENBLAS/MKL_NUM_THREADS apply before numpy loads. Returns the JSON the child prints,
    plus the settings."""
    env = dict(os.environ)
    for v in THREAD_VARS:
        env[v] = str(threads)
    if cpu is None and hasattr(os, "sched_getaffinity"):
        cpu = max(os.sched_getaffinity(0))
    cmd = [sys.executable, "-m", "deploy.numpy_policy", "--bench", "--kind", kind,
           "--hidden", str(hidden), "--layers", str(layers), "--members", str(members),
           "--steps", str(steps), "--warmup", str(warmup), "--json"]
    if cpu is not None:
        cmd += ["--cpu", str(cpu)]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout_s, cwd=root)
    if out.returncode != 0:
        raise RuntimeError(f"benchmark subprocess failed ({out.returncode}): {out.stderr[-2000:]}")
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res.update({"threads": threads, "cpu": cpu})
    return res


def _main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m deploy.numpy_policy",
                                description="numpy policy step latency (see benchmark())")
    p.add_argument("--bench", action="store_true", required=True)
    p.add_argument("--kind", choices=KINDS, default="lstm")
    p.add_argument("--hidden", type=int, default=1024)
    p.add_argument("--layers", type=int, default=2)
    p.add_argument("--members", type=int, default=1)
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--warmup", type=int, default=200)
    p.add_argument("--cpu", type=int, default=None, help="pin to this CPU core")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    if a.cpu is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {a.cpu})
    res = bench_here(a.kind, a.hidden, a.layers, a.members, steps=a.steps, warmup=a.warmup)
    res["threads_env"] = {v: os.environ.get(v) for v in THREAD_VARS[:3]}
    print(json.dumps(res) if a.json else
          f"{a.kind} {a.layers}x{a.hidden} x{a.members}: p50 {res['p50_ms']:.3f} ms, "
          f"p99 {res['p99_ms']:.3f} ms, max {res['max_ms']:.3f} ms over {a.steps} steps")
    return 0


if __name__ == "__main__":
    sys.exit(_main())
