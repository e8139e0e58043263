"""How policies learn: relabeling, the device cache, the window sampler, the loss, ensemble
updates and checkpoints. (Practice rollouts and the trainer loop build on these.)"""
from training.cache import Cache, add_episodes, append, empty_cache
from training.config import TrainConfig
from training.data import data_normalizer, keep_for_training, relabel
from training.loss import masked_mse, policy_loss
from training.sampler import Batch, sample_subsequences, window_starts
from training.update import (TrainState, init_train_state, make_train_loop, make_train_step,
                             member_update, optimizer)
