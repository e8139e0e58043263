"""Policies: LSTM and frame-stack networks, normalization, ensembles with a leading member axis, and the adapter that lets them act in the world (ttmjx.world.env.Policy)."""
from models.config import ACTION_SIZE, PolicyConfig
from models.networks import init_net, net_sequence, net_step, zero_carry
from models.normalizer import (Normalizer, denormalize_actions, identity_normalizer,
                               normalize_actions, normalize_obs, normalizer_from_data)
from models.policy import (Policy, PolicyParams, ensemble_size, init_ensemble, init_params,
                           make_policy, member, predict_sequence,
                           with_action_noise)
