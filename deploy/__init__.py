"""Deployment: the physical-robot runner (hardware interfaces, safety, logging).

Export (safetensors + contract) and numpy inference of models/ policies come next; the runner
takes any object with `reset() -> state` and `step(state, frame[13], frames[k, 13]) ->
(state, action[8])`. Imports numpy only (no JAX) so it starts fast on the robot's computer.
"""
from deploy.contract import Contract, contract_from_dict, contract_from_world, contract_to_dict
from deploy.episode_log import Episode, EpisodeLog, load_episode, save_episode
from deploy.goals import check_goal_region, episode_goals, goals_from_arg, load_goals, parse_goals
from deploy.hardware import BallTracker, Clock, MonotonicClock, Robot
from deploy.interp import Interpolated, SampleBuffer, interpolate
from deploy.modes import Mode, StateMachine, TransitionError
from deploy.runner import (FrameStack, NoBallError, NumpyPolicy, Runner, RunnerConfig,
                           frame_of)
from deploy.safety import (FAULTS, LATCHING, Command, Limits, Violations, count_violations,
                           fault_names, limits_from_contract, safe_target)
