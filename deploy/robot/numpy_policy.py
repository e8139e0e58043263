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
  head mean:    a = y [8]
  head mixture: y = [logits K | means K x 8 | log stds K x 8];  a = means[argmax(logits)]
                                                          (models.heads.head_action)
  action = a * act_std + act_mean                          (models.normalizer.denormalize_actions)

Ensembles: every member keeps its own recurrent state and normalizer; the action sent is the
MEAN of the members' actions (absolute joint targets, after denormalization). `step_members`
gives the per-member actions.

State (what `reset` returns and `step` threads through): float32 [members, layers, 2, hidden]
with [..., 0, :] = c and [..., 1, :] = h, zeros at every episode start (models.zero_carry);
None for the stateless frame-stack MLP. `step` never modifies the state it is given.

Weights arrive as a dict of float32 arrays named by their flattened parameter paths with a
leading member axis [N, ...] (deploy/sim/export.py): `net/params/lstm0/hf/kernel`, `norm/obs_mean`.

Latency: an LSTM step reads every weight once (2x1024: 50 MB of float32), so it is bound by
memory bandwidth. `prepare(state)`, called between control ticks, computes the recurrent
products h Wh + b of the next step in advance; `step` then reads only the input matrices (a
third of the bytes), with bit-identical results. deploy/robot/policy_bench.py times single steps
(`ttmjx robot bench`).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

ACTION_SIZE = 8
KINDS = ("lstm", "framestack")
HEADS = ("mean", "mixture")
_GATES = ("i", "f", "g", "o")          # flax OptimizedLSTMCell order of the gates
NORM_FIELDS = ("obs_mean", "obs_std", "act_mean", "act_std")


class PolicySpec(NamedTuple):
    """The architecture (models.PolicyConfig's fields), numpy side."""
    kind: str
    hidden: int
    layers: int
    obs_size: int
    frame_stack: int
    head: str = "mean"
    components: int = 1

    @property
    def input_frames(self) -> int:
        return self.frame_stack if self.kind == "framestack" else 1

    @property
    def head_size(self) -> int:
        """Outputs of the last layer (models.PolicyConfig.head_size)."""
        return ACTION_SIZE if self.head == "mean" else self.components * (1 + 2 * ACTION_SIZE)

    def check(self) -> "PolicySpec":
        if self.kind not in KINDS:
            raise ValueError(f"policy kind {self.kind!r}; expected one of {KINDS}")
        if self.head not in HEADS:
            raise ValueError(f"policy head {self.head!r}; expected one of {HEADS}")
        for name in ("hidden", "layers", "obs_size", "frame_stack", "components"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
                raise ValueError(f"policy {name}={v!r}; expected an integer >= 1")
        return self


def tensor_shapes(spec: PolicySpec, members: int) -> dict[str, tuple]:
    """Every tensor of an export of `members` members: name -> shape (leading [members])."""
    spec.check()
    n, h, o = members, spec.hidden, spec.obs_size
    shapes = {f"norm/{k}": (n, o if k.startswith("obs") else ACTION_SIZE) for k in NORM_FIELDS}
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
    shapes[f"{p}/head/kernel"] = (n, h, spec.head_size)
    shapes[f"{p}/head/bias"] = (n, spec.head_size)
    return shapes


def check_tensors(spec: PolicySpec, tensors: dict, members: int | None = None) -> int:
    """Raise ValueError naming the first missing, unexpected, mis-shaped or non-float32 tensor;
    returns the number of members."""
    if members is None:
        lead = np.shape(tensors.get("net/params/head/bias", ()))
        members = int(lead[0]) if len(lead) == 2 else 0
        if members < 1:
            raise ValueError(f"weights lack net/params/head/bias [members, {spec.head_size}]")
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
                # The four gates side by side, as OptimizedLSTMCell concatenates them.
                wx = np.ascontiguousarray(np.concatenate([f32(f"{q}/i{g}/kernel") for g in _GATES], axis=1))
                wh = np.ascontiguousarray(np.concatenate([f32(f"{q}/h{g}/kernel") for g in _GATES], axis=1))
                b = np.concatenate([f32(f"{q}/h{g}/bias") for g in _GATES])
                self.layers.append((wx, wh, b, np.zeros(4 * h, np.float32)))
            self.gate = np.zeros(h, np.float32)
        else:
            for layer in range(spec.layers):
                self.layers.append((f32(f"{p}/dense{layer}/kernel"), f32(f"{p}/dense{layer}/bias")))
        self.head_w, self.head_b = f32(f"{p}/head/kernel"), f32(f"{p}/head/bias")
        self.components = spec.components if spec.head == "mixture" else 0

    def action(self, y: np.ndarray) -> np.ndarray:
        """The head's outputs [D] -> the joint targets [8] (models.heads.head_action, then
        denormalized)."""
        if self.components:
            k = self.components
            best = int(np.argmax(y[:k]))
            y = y[k + best * ACTION_SIZE:k + (best + 1) * ACTION_SIZE]
        return y * self.act_std + self.act_mean

    def recurrent(self, state: np.ndarray) -> list:
        """Per layer h Wh + b of the state [layers, 2, H]: the part of the next step that does
        not depend on the next observation (ExportedPolicy.prepare)."""
        return [state[layer, 1] @ wh + b for layer, (_, wh, b, _) in enumerate(self.layers)]

    def lstm_step(self, state_in: np.ndarray, state_out: np.ndarray, obs: np.ndarray,
                  rec: list | None = None) -> np.ndarray:
        """state_in/state_out [layers, 2, H] (c, h); obs [O] raw -> action [8]. rec: the
        recurrent() of state_in if already computed."""
        x = (obs - self.obs_mean) / self.obs_std
        gate = self.gate
        for layer, (wx, wh, b, z) in enumerate(self.layers):
            c, h = state_in[layer, 0], state_in[layer, 1]
            hid = h.shape[0]
            # z = h Wh + b + x Wx (flax: the hidden dense with its bias, plus the input dense)
            if rec is None:
                np.dot(h, wh, out=z)
                z += b
            else:
                z[:] = rec[layer]
            z += x @ wx
            c_new, h_new = state_out[layer, 0], state_out[layer, 1]
            # c' = f c + i g
            np.tanh(z[2 * hid:3 * hid], out=c_new)                       # g
            c_new *= _sigmoid(z[:hid], gate)                              # i g
            c_new += _sigmoid(z[hid:2 * hid], gate) * c                   # + f c
            # h' = o tanh(c')
            np.tanh(c_new, out=h_new)
            h_new *= _sigmoid(z[3 * hid:], gate)
            x = h_new
        return self.action(x @ self.head_w + self.head_b)

    def mlp_step(self, frames: np.ndarray) -> np.ndarray:
        """frames [k, O] raw -> action [8]."""
        x = ((frames - self.obs_mean) / self.obs_std).reshape(-1)
        for w, b in self.layers:
            x = np.maximum(x @ w + b, 0.0)
        return self.action(x @ self.head_w + self.head_b)


class StepPolicy:
    """What the numpy and the ONNX engines share (deploy.robot.runner's NumpyPolicy): the recurrent
    state's shape, the input checks, and a whole episode from its per-step `_step_all`."""
    spec: PolicySpec
    members: int

    @property
    def state_shape(self) -> tuple:
        """Shape of the recurrent state [N, L, 2, H]; () for the stateless MLP."""
        if self.spec.kind != "lstm":
            return ()
        return (self.members, self.spec.layers, 2, self.spec.hidden)

    def reset(self):
        """The state at an episode start: zeros (LSTM) or None (frame stack)."""
        if self.spec.kind != "lstm":
            return None
        return np.zeros(self.state_shape, np.float32)

    def _obs(self, frame, frames) -> np.ndarray:
        """The step's input, checked: frame [O] (LSTM) or frames [k, O] (MLP), float32."""
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

    def _state(self, state) -> np.ndarray:
        """The LSTM state as float32, checked against state_shape."""
        s = np.asarray(state, np.float32)
        if s.shape != self.state_shape:
            raise ValueError(f"policy step: state has shape {s.shape}, expected {self.state_shape}")
        return s

    def _step_all(self, state, frame, frames) -> tuple:
        """(new state, actions [members, 8], action [8]) of one control step."""
        raise NotImplementedError

    def step_members(self, state, frame, frames) -> tuple:
        """(new state, actions [members, 8]): one control step of every member."""
        state, acts, _ = self._step_all(state, frame, frames)
        return state, acts

    def step(self, state, frame, frames) -> tuple:
        """frame [O] (= frames[-1]), frames [k, O] -> (state, action [8]): the ensemble's action."""
        state, _, action = self._step_all(state, frame, frames)
        return state, action

    def run(self, frames: np.ndarray, stacks: np.ndarray | None = None, members: bool = False):
        """A whole episode from reset: frames [L, O] (and stacks [L, k, O] for the MLP) ->
        actions [L, 8] (or [members, L, 8] with members=True)."""
        frames = np.asarray(frames, np.float32)
        stacks = frames[:, None, :] if stacks is None else stacks
        state, out = self.reset(), []
        for t in range(frames.shape[0]):
            state, acts, action = self._step_all(state, frames[t], stacks[t])
            out.append(acts if members else action)
        out = np.stack(out)
        return np.swapaxes(out, 0, 1) if members else out


class ExportedPolicy(StepPolicy):
    """A models/ policy (one member or an ensemble) on numpy; deploy.robot.runner's NumpyPolicy."""

    def __init__(self, spec: PolicySpec, tensors: dict, policy_hash: str = "unknown"):
        self.spec = spec.check()
        self.members = check_tensors(spec, tensors)
        self.policy_hash = policy_hash
        self._m = [_Member(spec, tensors, i) for i in range(self.members)]
        self._prepared = None
        self.self_test_error: float | None = None   # set by deploy.robot.exported.load_export
        self.contract_doc: dict | None = None       # the export's contract.json (load_export)

    def prepare(self, state) -> None:
        """Optional, between control ticks: compute the part of the NEXT step that depends on
        the state only (per LSTM layer h Wh + b, two thirds of a 2x1024 step's arithmetic), so
        that `step(state, ...)` then does only the observation-dependent third. Call it after
        the command of the previous step has been sent; `step` uses the result only for this
        very state object (states are never modified in place). No-op for the MLP."""
        if self.spec.kind != "lstm" or state is None:
            return
        state_arr = np.asarray(state)
        if state_arr.shape != self.state_shape:
            raise ValueError(f"policy prepare: state has shape {state_arr.shape}, expected {self.state_shape}")
        self._prepared = (state, [m.recurrent(state_arr[i]) for i, m in enumerate(self._m)])

    def _step_all(self, state, frame, frames) -> tuple:
        x = self._obs(frame, frames)
        acts = np.empty((self.members, ACTION_SIZE), np.float32)
        if self.spec.kind == "lstm":
            prepared, self._prepared = self._prepared, None
            rec = prepared[1] if prepared is not None and prepared[0] is state else None
            state = self._state(state)
            new = np.empty_like(state)
            for i, m in enumerate(self._m):
                acts[i] = m.lstm_step(state[i], new[i], x, None if rec is None else rec[i])
        else:
            new = None
            for i, m in enumerate(self._m):
                acts[i] = m.mlp_step(x)
        return new, acts, (acts[0] if self.members == 1 else acts.mean(axis=0))


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
