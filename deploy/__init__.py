"""Deployment: export, numpy inference and the physical-robot runner (hardware interfaces,
safety, logging), plus a simulated station.

deploy/export.py writes a policy as safetensors + contract + golden self-test (+ an ONNX graph,
with the optional `onnx` extra) under a manifest of SHA-256 hashes, and loads it back
(`load_export`) as a numpy policy (deploy/numpy_policy.py), or (`load_onnx_export`) on
onnxruntime (deploy/onnx_policy.py); the runner takes any object with
`reset() -> state` and `step(state, frame[13], frames[k, 13]) -> (state, action[8])`. This
package imports numpy only (no JAX) so it starts fast on the robot's computer; export() itself
and the simulated station (deploy/station.py: MuJoCo C + the thrower) import JAX/MuJoCo and are
not imported here.
"""
from deploy.contract import (ROBOT_MODEL_ID, Contract, contract_from_dict, contract_from_world,
                             contract_to_dict)
from deploy.export import ExportError, load_export, load_onnx_export, read_contract
from deploy.episode_log import Episode, EpisodeLog, load_episode, save_episode
from deploy.goals import check_goal_region, episode_goals, goals_from_arg, load_goals, parse_goals
from deploy.hardware import BallTracker, Clock, MonotonicClock, Robot
from deploy.interp import Interpolated, SampleBuffer, interpolate
from deploy.modes import Mode, StateMachine, TransitionError
from deploy.numpy_policy import ExportedPolicy, PolicySpec
from deploy.runner import (FrameStack, NoBallError, NumpyPolicy, Runner, RunnerConfig,
                           frame_of)
from deploy.safety import (FAULTS, LATCHING, Command, Limits, Violations, count_violations,
                           fault_names, limits_from_contract, safe_target)
