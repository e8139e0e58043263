"""The robot side: what runs on the robot's computer, with numpy (and onnxruntime for the ONNX
graph) only, never JAX, MuJoCo or the trainer (tests/test_layers.py checks every import).

An export (deploy/robot/exported.py reads it, checked against its manifest and contract) becomes a
numpy policy (numpy_policy.py) or an ONNX one (onnx_policy.py); the runner (runner.py) paces it
at the contract's rate behind the safety filters (safety.py), through the hardware interfaces
(hardware.py) that the cell's drivers (drivers/) and the fakes (fakes.py) implement, and logs
every episode (episode_log.py) for a later `ttmjx train --data`. `ttmjx robot run` and
`ttmjx robot bench` are this side's commands (cli.py).
"""
from deploy.robot.contract import ROBOT_MODEL_ID, Contract, contract_from_dict, contract_from_world, contract_to_dict
from deploy.robot.episode_log import Episode, EpisodeLog, load_episode, save_episode
from deploy.robot.exported import ExportError, load_export, load_onnx_export, read_contract
from deploy.robot.goals import check_goal_region, episode_goals, goals_from_arg, parse_goals
from deploy.robot.hardware import BallTracker, Clock, MonotonicClock, Robot
from deploy.robot.interp import Interpolated, SampleBuffer, interpolate
from deploy.robot.modes import Mode, StateMachine, TransitionError
from deploy.robot.numpy_policy import ExportedPolicy, PolicySpec
from deploy.robot.runner import FrameStack, NoBallError, NumpyPolicy, Runner, RunnerConfig, frame_of
from deploy.robot.safety import (
                             FAULTS,
                             LATCHING,
                             Command,
                             Limits,
                             Violations,
                             count_violations,
                             fault_names,
                             limits_from_contract,
                             safe_target,
)
