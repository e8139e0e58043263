"""One step of an exported policy as an ONNX graph, and that graph served by onnxruntime.

The graph computes exactly what deploy/robot/numpy_policy.py computes (normalization, network,
denormalization, the mean over ensemble members), for every member at once: the weights keep
their leading member axis [N, ...] and each product is a batched MatMul.

  framestack: inputs  frames [k, O]                    (oldest first, raw units)
              outputs action [8], member_actions [N, 8]
  lstm:       inputs  frame [O], state [N, L, 2, H]     (state[..., 0, :] = c, [..., 1, :] = h;
                                                         zeros at an episode start)
              outputs action [8], member_actions [N, 8], state_out [N, L, 2, H]

The state layout is the contract's `policy.state` and numpy_policy's, so a state can be handed
from one engine to the other. Per LSTM layer the four gates (i, f, g, o, flax's order) come from
ONE MatMul of [x, h] with the stacked [Wx; Wh] [N, in + H, 4H].

`onnx` (to build) and `onnxruntime` (to run) are the optional extra `ttmjx[onnx]`: they are
imported inside the functions that need them, and a missing one is an ExportError saying how to
install it. Opset 17, IR version 8: what onnxruntime >= 1.14 runs.
"""
from __future__ import annotations

import numpy as np

from deploy.robot.numpy_policy import _GATES, ACTION_SIZE, PolicySpec, StepPolicy, check_tensors

OPSET = 17
IR_VERSION = 8
INPUTS = {"lstm": ("frame", "state"), "framestack": ("frames",)}
OUTPUTS = {"lstm": ("action", "member_actions", "state_out"), "framestack": ("action", "member_actions")}
INSTALL = "pip install 'ttmjx[onnx]' (or: pip install onnx onnxruntime)"


class MissingExtra(ValueError):
    """An optional package (onnx, onnxruntime) is not installed; the message says how to get it."""


def import_onnx():
    """The `onnx` package, or MissingExtra naming the install command."""
    try:
        import onnx
    except ImportError:
        raise MissingExtra(f"ONNX export needs the optional package 'onnx', not installed here: "
                           f"{INSTALL}") from None
    return onnx


def import_onnxruntime():
    """The `onnxruntime` package, or MissingExtra naming the install command."""
    try:
        import onnxruntime
    except ImportError:
        raise MissingExtra(f"running an ONNX policy needs the optional package 'onnxruntime', not "
                           f"installed here: {INSTALL}") from None
    return onnxruntime


# --------------------------------------------------------------------------------------------
# Graph
# --------------------------------------------------------------------------------------------
class _Graph:
    """Nodes and initializers of one graph under construction; names are made unique here."""

    def __init__(self, onnx):
        self.onnx, self.nodes, self.inits, self._n = onnx, [], [], 0

    def const(self, name: str, value) -> str:
        """An initializer (float32 unless `value` is an int64 array) -> its name."""
        arr = np.asarray(value)
        arr = arr if arr.dtype == np.int64 else np.ascontiguousarray(arr, np.float32)
        self.inits.append(self.onnx.numpy_helper.from_array(arr, name))
        return name

    def op(self, op_type: str, *inputs: str, outputs: int = 1, name: str | None = None, **attrs):
        """Append a node; returns its output name (or names when outputs > 1)."""
        self._n += 1
        outs = [name] if name else [f"{op_type.lower()}{self._n}_{i}" for i in range(outputs)]
        self.nodes.append(self.onnx.helper.make_node(op_type, list(inputs), outs, **attrs))
        return outs[0] if outputs == 1 else outs


def _normalize(g: _Graph, obs: str, tensors: dict, n: int, o: int) -> str:
    """obs [..., O] -> (obs - obs_mean) / obs_std per member, [N, ..., O] (models.normalizer)."""
    mean = g.const("obs_mean", tensors["norm/obs_mean"].reshape(n, 1, o))
    std = g.const("obs_std", tensors["norm/obs_std"].reshape(n, 1, o))
    return g.op("Div", g.op("Sub", obs, mean), std)


def _head(g: _Graph, x: str, tensors: dict, n: int) -> list[str]:
    """x [N, 1, H] -> (action [8] = mean over members, member_actions [N, 8])."""
    p = "net/params/head"
    y = g.op("Add", g.op("MatMul", x, g.const("head_w", tensors[f"{p}/kernel"])),
             g.const("head_b", tensors[f"{p}/bias"][:, None, :]))
    std = g.const("act_std", tensors["norm/act_std"][:, None, :])
    mean = g.const("act_mean", tensors["norm/act_mean"][:, None, :])
    acts = g.op("Reshape", g.op("Add", g.op("Mul", y, std), mean),
                g.const("members_by_action", np.array([n, ACTION_SIZE], np.int64)), name="member_actions")
    g.op("ReduceMean", acts, axes=[0], keepdims=0, name="action")
    return ["action", "member_actions"]


def _framestack_body(g: _Graph, spec: PolicySpec, tensors: dict, n: int) -> list[str]:
    """frames [k, O] -> relu MLP per member -> head."""
    k, o = spec.frame_stack, spec.obs_size
    x = _normalize(g, "frames", tensors, n, o)                                     # [N, k, O]
    x = g.op("Reshape", x, g.const("flat_shape", np.array([n, 1, k * o], np.int64)))  # [N, 1, kO]
    for layer in range(spec.layers):
        q = f"net/params/dense{layer}"
        w = g.const(f"dense{layer}_w", tensors[f"{q}/kernel"])
        b = g.const(f"dense{layer}_b", tensors[f"{q}/bias"][:, None, :])
        x = g.op("Relu", g.op("Add", g.op("MatMul", x, w), b))
    return _head(g, x, tensors, n)


def _lstm_weights(tensors: dict, layer: int) -> tuple[np.ndarray, np.ndarray]:
    """([Wx; Wh] [N, in + H, 4H], b [N, 1, 4H]) of one layer, gates side by side (i, f, g, o)."""
    q = f"net/params/lstm{layer}"
    wx = np.concatenate([tensors[f"{q}/i{g}/kernel"] for g in _GATES], axis=2)
    wh = np.concatenate([tensors[f"{q}/h{g}/kernel"] for g in _GATES], axis=2)
    b = np.concatenate([tensors[f"{q}/h{g}/bias"] for g in _GATES], axis=1)
    return np.concatenate([wx, wh], axis=1), b[:, None, :]


def _lstm_body(g: _Graph, spec: PolicySpec, tensors: dict, n: int) -> list[str]:
    """(frame [O], state [N, L, 2, H]) -> LSTM cells per member -> head, state_out."""
    h_size = spec.hidden
    x = _normalize(g, "frame", tensors, n, spec.obs_size)                        # [N, 1, O]
    one_hidden = g.const("one_hidden", np.array([n, 1, h_size], np.int64))
    four = g.const("gate_sizes", np.array([h_size] * 4, np.int64))
    layers_out = []
    for layer in range(spec.layers):
        # c, h of this layer: state[:, layer, 0] and state[:, layer, 1] as [N, 1, H]
        c, h = (g.op("Reshape", g.op("Slice", "state", g.const(f"s{layer}{j}", np.array([layer, j], np.int64)),
                                     g.const(f"e{layer}{j}", np.array([layer + 1, j + 1], np.int64)),
                                     g.const(f"a{layer}{j}", np.array([1, 2], np.int64))), one_hidden)
                for j in (0, 1))
        w, b = _lstm_weights(tensors, layer)
        z = g.op("Add", g.op("MatMul", g.op("Concat", x, h, axis=2), g.const(f"lstm{layer}_w", w)),
                 g.const(f"lstm{layer}_b", b))                                     # [N, 1, 4H]
        zi, zf, zg, zo = g.op("Split", z, four, axis=2, outputs=4)
        # c' = f c + i g;  h' = o tanh(c')   (flax OptimizedLSTMCell)
        c_new = g.op("Add", g.op("Mul", g.op("Sigmoid", zf), c),
                     g.op("Mul", g.op("Sigmoid", zi), g.op("Tanh", zg)))
        h_new = g.op("Mul", g.op("Sigmoid", zo), g.op("Tanh", c_new))
        layers_out.append(g.op("Concat", g.op("Unsqueeze", c_new, g.const(f"u{layer}c", np.array([1], np.int64))),
                               g.op("Unsqueeze", h_new, g.const(f"u{layer}h", np.array([1], np.int64))),
                               axis=2))                                            # [N, 1, 2, H]
        x = h_new
    if len(layers_out) == 1:
        g.op("Identity", layers_out[0], name="state_out")
    else:
        g.op("Concat", *layers_out, axis=1, name="state_out")                    # [N, L, 2, H]
    return [*_head(g, x, tensors, n), "state_out"]


def build_model(spec: PolicySpec, tensors: dict, doc: str = ""):
    """onnx.ModelProto of one step of the policy (module docstring) from an export's tensors
    (names and shapes of deploy.robot.numpy_policy.tensor_shapes, leading [N] member axis);
    checked with onnx.checker. Deterministic: the same tensors give the same bytes."""
    onnx = import_onnx()
    from onnx import TensorProto, helper
    spec = spec.check()
    n = check_tensors(spec, tensors)
    g = _Graph(onnx)
    f32 = lambda name, shape: helper.make_tensor_value_info(name, TensorProto.FLOAT, shape)  # noqa: E731
    state = [n, spec.layers, 2, spec.hidden]
    if spec.kind == "lstm":
        outputs = _lstm_body(g, spec, tensors, n)
        inputs = [f32("frame", [spec.obs_size]), f32("state", state)]
    else:
        outputs = _framestack_body(g, spec, tensors, n)
        inputs = [f32("frames", [spec.frame_stack, spec.obs_size])]
    shapes = {"action": [ACTION_SIZE], "member_actions": [n, ACTION_SIZE], "state_out": state}
    graph = helper.make_graph(g.nodes, f"ttmjx_{spec.kind}_step", inputs,
                              [f32(name, shapes[name]) for name in outputs], initializer=g.inits)
    model = helper.make_model(graph, producer_name="ttmjx", doc_string=doc,
                              opset_imports=[helper.make_opsetid("", OPSET)], ir_version=IR_VERSION)
    onnx.checker.check_model(model, full_check=True)
    return model


def model_bytes(spec: PolicySpec, tensors: dict, doc: str = "") -> bytes:
    """The serialized graph of build_model."""
    return build_model(spec, tensors, doc).SerializeToString()


# --------------------------------------------------------------------------------------------
# Running the graph
# --------------------------------------------------------------------------------------------
def session(model: bytes, threads: int = 1):
    """An onnxruntime CPU session of a serialized graph on `threads` intra-op threads (one
    thread: the robot's budget is one core; no inter-op parallelism, no spinning threads)."""
    ort = import_onnxruntime()
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(model, sess_options=opts, providers=["CPUExecutionProvider"])


def reference_session(model: bytes):
    """onnx's own numpy evaluator of the graph (onnx.reference), for when onnxruntime is
    absent: slow, but it checks the graph with the `onnx` package alone."""
    from onnx.reference import ReferenceEvaluator
    return ReferenceEvaluator(import_onnx().load_from_string(model))


class OnnxPolicy(StepPolicy):
    """An exported policy on onnxruntime with numpy_policy.ExportedPolicy's interface
    (`reset`, `step`, `step_members`, `run`), so the runner or a benchmark can take either."""

    def __init__(self, spec: PolicySpec, members: int, model: bytes, threads: int = 1,
                 policy_hash: str = "unknown", evaluator=None):
        self.spec, self.members, self.policy_hash = spec.check(), int(members), policy_hash
        self._sess = session(model, threads) if evaluator is None else evaluator
        self._want = list(OUTPUTS[spec.kind])
        self.self_test_error: float | None = None
        self.contract_doc: dict | None = None

    def prepare(self, state) -> None:
        """No-op (the runner may call it between ticks; the graph does the whole step)."""

    def _step_all(self, state, frame, frames) -> tuple:
        """The graph's outputs for one step; `action` is the mean over members, in the graph."""
        x = self._obs(frame, frames)
        if self.spec.kind == "lstm":
            action, acts, new = self._sess.run(self._want, {"frame": x, "state": self._state(state)})
            return new, acts, action
        action, acts = self._sess.run(self._want, {"frames": x})
        return None, acts, action
