"""How policies learn: relabeling, the one device cache, windows, the loss, ensemble updates, the practice round, checkpoints and the run that composes them.

Layer: above ttmjx.world, ttmjx.tools and models; below eval, deploy and the CLI (training never
imports them: the run is given its evaluation as a function)."""
from training.cache import Cache, add_episodes, append, empty_cache
from training.config import TrainConfig
from training.data import data_normalizer, keep_for_training, relabel
from training.loss import masked_mse, policy_loss
from training.sampler import Batch, sample_subsequences, window_starts
from training.update import (TrainState, init_train_state, make_train_loop, make_train_step,
                             member_update, optimizer)
