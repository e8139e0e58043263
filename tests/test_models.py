"""Policies: configuration, normalization, ensembles, the rollout adapter and its noise."""
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from models import (Normalizer, PolicyConfig, ensemble_size, identity_normalizer, init_ensemble,
                    make_policy, member, normalizer_from_data,
                    predict_sequence, with_action_noise)
from models.normalizer import denormalize_actions
from ttmjx.world import observation


class Obs(NamedTuple):     # the fields of ttmjx.world.env.Obs the policies read
    frame: jnp.ndarray     # [13] or [16] (World.ball_velocity_obs)
    ball_vel: jnp.ndarray  # [3]
    frames: jnp.ndarray    # [k, 13] or [k, 16]
    t: jnp.ndarray


def random_norm(key, obs_size):
    k = jax.random.split(key, 4)
    return Normalizer(jax.random.normal(k[0], (obs_size,)), 1 + jax.random.uniform(k[1], (obs_size,)),
                      jax.random.normal(k[2], (8,)), 0.5 + jax.random.uniform(k[3], (8,)))


def test_policy_config_rejects_bad_values():
    with pytest.raises(ValueError, match="kind='gru'"):
        PolicyConfig("gru")
    with pytest.raises(ValueError, match="obs_size=14"):
        PolicyConfig(obs_size=14)
    assert PolicyConfig("lstm").input_frames == 1 and PolicyConfig("framestack").input_frames == 8
    with pytest.raises(ValueError, match="head='median'"):
        PolicyConfig(head="median")
    with pytest.raises(ValueError, match="components=0"):
        PolicyConfig(head="mixture", components=0)
    assert PolicyConfig().head_size == 8 and PolicyConfig(head="mixture", components=3).head_size == 51


def test_mixture_head_reads_as_a_plain_mixture_of_gaussians():
    """models.heads against a plain loop: the action is the mean of the largest-weight component,
    the loss the mixture's negative log-likelihood per action value."""
    from models.heads import head_action, step_losses
    k = 3
    cfg = PolicyConfig(head="mixture", components=k)
    y = np.asarray(jax.random.normal(jax.random.PRNGKey(0), (5, cfg.head_size)), np.float64)
    target = np.asarray(jax.random.normal(jax.random.PRNGKey(1), (5, 8)), np.float64)
    for row, a in zip(range(5), target):
        logits, means = y[row, :k], y[row, k:k + 8 * k].reshape(k, 8)
        log_std = np.clip(y[row, k + 8 * k:].reshape(k, 8), -5, 1)
        w = np.exp(logits - logits.max()) / np.exp(logits - logits.max()).sum()
        dens = [np.prod(np.exp(-0.5 * ((a - means[j]) / np.exp(log_std[j])) ** 2)
                        / (np.exp(log_std[j]) * np.sqrt(2 * np.pi))) for j in range(k)]
        np.testing.assert_allclose(step_losses(cfg, jnp.asarray(y[row], jnp.float32), jnp.asarray(a, jnp.float32)),
                                   -np.log(np.dot(w, dens)) / 8, rtol=1e-4)
        np.testing.assert_allclose(head_action(cfg, jnp.asarray(y[row], jnp.float32)), means[np.argmax(logits)],
                                   rtol=1e-6)
    mean_cfg = PolicyConfig()
    np.testing.assert_allclose(step_losses(mean_cfg, jnp.ones(8), jnp.zeros(8)), 1.0)


def test_the_mixture_head_imitates_one_of_two_strokes_the_mean_head_averages():
    """Data holding two strokes for one input (every action +1 or every action -1, half each, as
    two timings that land alike): the MSE head learns their mean, 0, a stroke the data never
    made; the mixture head acts with one of the two."""
    import optax
    from models.networks import init_net, net_sequence, net_sequence_outputs
    from models.heads import step_losses
    x = jnp.broadcast_to(jax.random.normal(jax.random.PRNGKey(2), (1, 1, 13)), (256, 1, 13))  # one input
    sign = jnp.where(jax.random.bernoulli(jax.random.PRNGKey(0), 0.5, (256, 1)), 1.0, -1.0)
    target = jnp.broadcast_to(sign, (256, 8))
    actions = {}
    for head in ("mean", "mixture"):
        cfg = PolicyConfig("framestack", hidden=16, layers=1, frame_stack=1, head=head, components=2)
        net, opt = init_net(jax.random.PRNGKey(1), cfg), optax.adam(1e-2)
        loss = lambda p: jnp.mean(step_losses(cfg, net_sequence_outputs(cfg, p, x), target))  # noqa: E731

        def step(carry, _, loss=loss, opt=opt):
            p, s = carry
            g = jax.grad(loss)(p)
            u, s = opt.update(g, s, p)
            return (optax.apply_updates(p, u), s), None
        (net, _), _ = jax.lax.scan(step, (net, opt.init(net)), None, length=400)
        actions[head] = np.asarray(net_sequence(cfg, net, x[:1]))[0]
    assert np.abs(actions["mean"]).max() < 0.2, actions["mean"]
    assert np.abs(np.abs(actions["mixture"]) - 1).max() < 0.2, actions["mixture"]
    assert len(set(np.sign(actions["mixture"]))) == 1            # one stroke, not a mix of the two


def test_normalizer_from_data_uses_valid_steps_and_floors_std():
    obs = jnp.array([[[1.0, 5.0], [3.0, 5.0], [100.0, -9.0]]])       # [1, 3, 2]
    actions = jnp.tile(jnp.array([[[0.0], [2.0], [50.0]]]), (1, 1, 8))
    mask = jnp.array([[True, True, False]])
    n = normalizer_from_data(obs, actions, mask, min_std=1e-3)
    np.testing.assert_allclose(n.obs_mean, [2.0, 5.0])
    np.testing.assert_allclose(n.obs_std, [1.0, 1e-3])                # constant column -> floor
    np.testing.assert_allclose(n.act_mean, np.full(8, 1.0))
    np.testing.assert_allclose(n.act_std, np.full(8, 1.0))
    with pytest.raises(ValueError, match="normalizer_from_data"):
        normalizer_from_data(obs, actions[..., :3], mask)


@pytest.mark.parametrize("kind,obs_size", [("lstm", 13), ("lstm", 16), ("framestack", 13)])
def test_ensemble_shapes_and_members_differ(kind, obs_size):
    cfg = PolicyConfig(kind, hidden=16, layers=2, obs_size=obs_size, frame_stack=4)
    params = init_ensemble(jax.random.PRNGKey(0), cfg, identity_normalizer(obs_size), 3)
    assert ensemble_size(params) == 3
    assert all(x.shape[0] == 3 for x in jax.tree.leaves(params))
    assert params.norm.obs_mean.shape == (3, obs_size)
    head = params.net["params"]["head"]["kernel"]                      # [3, H, 8]
    assert head.shape == (3, 16, 8) and not np.allclose(head[0], head[1])
    x = jax.random.normal(jax.random.PRNGKey(1), (5, cfg.input_frames, obs_size))
    out = jax.vmap(lambda p: predict_sequence(cfg, p, x))(params)       # [N, L, 8]
    assert out.shape == (3, 5, 8) and not np.allclose(out[0], out[1])
    with pytest.raises(ValueError, match=f"obs_mean \\(3,\\).*expected \\({obs_size},\\)"):
        init_ensemble(jax.random.PRNGKey(0), cfg, identity_normalizer(3), 2)


@pytest.mark.parametrize("kind,obs_size,env_width", [("lstm", 16, 13), ("lstm", 16, 16), ("lstm", 13, 16),
                                                     ("framestack", 13, 13), ("framestack", 16, 16),
                                                     ("framestack", 13, 16)])
def test_rollout_adapter_matches_training_sequence(kind, obs_size, env_width):
    """Stepping the Policy through an episode gives the actions the loss trains on, whether the
    env's frames are 13 or 16 wide (World.ball_velocity_obs)."""
    cfg = PolicyConfig(kind, hidden=16, layers=2, obs_size=obs_size, frame_stack=3)
    norm = random_norm(jax.random.PRNGKey(2), obs_size)
    params = member(init_ensemble(jax.random.PRNGKey(0), cfg, norm, 2), 1)
    t = 10
    obs = jax.random.normal(jax.random.PRNGKey(1), (t, 13))               # as the record stores it
    vel = jax.random.normal(jax.random.PRNGKey(3), (t, 3))
    env_frames = observation.to_width(obs, env_width, vel, xp=jnp)                     # as the env builds it
    stacks = observation.frame_stack(env_frames[None], 3)[0]                             # [T, 3, env_width]
    policy = make_policy(cfg)

    def step(carry, i):
        return policy.apply(params, carry, Obs(env_frames[i], vel[i], stacks[i], i), jax.random.PRNGKey(0))

    _, actions = jax.lax.scan(step, policy.init(params, jax.random.PRNGKey(0)), jnp.arange(t))
    # the training side: record columns (13) + ball_vel, stacked as the sampler does
    seq = observation.to_width(observation.frame_stack(obs[None], cfg.input_frames)[0], obs_size,
                               observation.frame_stack(vel[None], cfg.input_frames)[0], xp=jnp)
    want = denormalize_actions(params.norm, predict_sequence(cfg, params, seq))
    np.testing.assert_allclose(actions, want, rtol=1e-5, atol=1e-5)
    if kind == "framestack":
        with pytest.raises(ValueError, match="obs.frames has shape \\(8, 13\\), expected \\(3, 13 or 16\\)"):
            policy.apply(params, (), Obs(obs[0], vel[0], jnp.zeros((8, 13)), 0), jax.random.PRNGKey(0))


def test_action_noise_is_one_hidden_offset_per_episode():
    """z ~ U(-b a_std, b a_std), one per episode, different across episodes; the inner policy sees
    the joints (of the frame and of the stack) moved by -z and its action is sent moved by +z."""
    cfg = PolicyConfig("framestack", hidden=8, layers=1, frame_stack=3)
    params = member(init_ensemble(jax.random.PRNGKey(0), cfg, random_norm(jax.random.PRNGKey(1), 13), 1), 0)
    base, noisy = make_policy(cfg), with_action_noise(make_policy(cfg), 0.5)
    frames = jax.random.normal(jax.random.PRNGKey(2), (6, 3, 13))
    obs = lambda i, shift: Obs(frames[i, -1] + shift, jnp.zeros(3), frames[i] + shift, i)  # noqa: E731

    def episode(key):
        def step(carry, i):
            carry, a = noisy.apply(params, carry, obs(i, 0.0), jax.random.fold_in(key, i))
            return carry, (a, carry[1])
        return jax.lax.scan(step, noisy.init(params, key), jnp.arange(6))[1]   # ([6, 8], [6, 8])

    actions, zs = jax.vmap(episode)(jax.random.split(jax.random.PRNGKey(3), 4))
    np.testing.assert_array_equal(zs, np.broadcast_to(zs[:, :1], zs.shape))    # held all episode
    z = np.asarray(zs[:, 0])
    assert len({tuple(np.round(r, 5)) for r in z}) == 4                        # differs across episodes
    assert (np.abs(z) <= 0.5 * np.asarray(params.norm.act_std) + 1e-6).all() and np.abs(z).max() > 0
    for e in range(4):
        shift = jnp.zeros(13).at[:8].set(-z[e])                                # joints only
        want = jnp.stack([base.apply(params, (), obs(i, shift), None)[1] for i in range(6)]) + z[e]
        np.testing.assert_allclose(actions[e], want, rtol=1e-5, atol=1e-5)


def test_ensemble_policies_vmap_over_members():
    cfg = PolicyConfig("framestack", hidden=8, layers=1, frame_stack=2)
    params = init_ensemble(jax.random.PRNGKey(0), cfg, identity_normalizer(13), 3)
    policy = with_action_noise(make_policy(cfg), 0.1)
    keys = jax.random.split(jax.random.PRNGKey(1), 3)
    carry = jax.vmap(policy.init)(params, keys)
    o = Obs(jnp.zeros(13), jnp.zeros(3), jnp.ones((2, 13)), 0)
    _, a = jax.vmap(policy.apply, in_axes=(0, 0, None, 0))(params, carry, o, keys)
    assert a.shape == (3, 8) and not np.allclose(a[0], a[1])


@pytest.mark.parametrize("layers", [1, 3])
def test_the_layerwise_lstm_sequence_is_the_step_by_step_lstm(layers):
    """Training's LSTM (input projections outside the recurrence, models.networks.lstm_sequence)
    against flax's cell stepped one control step at a time: same actions and same gradients."""
    from models.networks import init_net, lstm_sequence, net_step, zero_carry
    cfg = PolicyConfig("lstm", hidden=32, layers=layers, obs_size=16)
    net = init_net(jax.random.PRNGKey(4), cfg)
    xs = jax.random.normal(jax.random.PRNGKey(5), (24, 1, 16))

    def stepped(p):
        return jax.lax.scan(lambda c, x: net_step(cfg, p, c, x), zero_carry(cfg), xs)[1]

    np.testing.assert_allclose(lstm_sequence(net, xs[:, 0]), stepped(net), rtol=1e-5, atol=1e-6)
    g_fast = jax.grad(lambda p: jnp.sum(lstm_sequence(p, xs[:, 0]) ** 2))(net)
    g_ref = jax.grad(lambda p: jnp.sum(stepped(p) ** 2))(net)
    for a, b in zip(jax.tree.leaves(g_fast), jax.tree.leaves(g_ref)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


def test_the_cudnn_weight_packing_gives_jaxs_reference_lstm_the_same_outputs():
    """The GPU updates' cuDNN LSTM (models.cudnn_lstm) reads flax's cells through cudnn_weights.
    Unpacked by JAX's own reader and run through JAX's reference of cuDNN's arithmetic
    (rnn.lstm_ref, which runs on this CPU), the packed weights give lstm_sequence's outputs."""
    from jax.experimental import rnn
    from models.cudnn_lstm import cudnn_weights, lstm_layers
    from models.networks import init_net, lstm_sequence
    cfg = PolicyConfig("lstm", hidden=32, layers=2, obs_size=16)
    net = init_net(jax.random.PRNGKey(6), cfg)
    p = net["params"]
    x = jax.random.normal(jax.random.PRNGKey(7), (3, 24, 16))                  # [B, L, I]
    w = cudnn_weights(p)
    assert lstm_layers(p) == 2 and w.shape == (rnn.get_num_params_in_lstm(16, 32, 2, False),)
    w_ih, w_hh, b_ih, b_hh = rnn.unpack_lstm_weights(w, 16, 32, 2, False)
    zero = jnp.zeros((2, 3, 32))
    y = rnn.lstm_ref(x, zero, zero, w_ih, w_hh, b_ih, b_hh, jnp.full((3,), 24, jnp.int32), 16, 32, 2, 0.0, False)[0]
    head = p["head"]
    want = jax.vmap(lambda s: lstm_sequence(net, s))(x)
    np.testing.assert_allclose(y @ head["kernel"] + head["bias"], want, rtol=1e-5, atol=1e-6)


def test_cudnns_batching_rule_refuses_more_than_one_set_of_weights():
    """cuDNN's LSTM serves one member of one lane (its looped gradients were wrong: BENCHMARKS):
    its batching rule refuses a mapped axis of 2 before any call, naming the count."""
    from jax.experimental import rnn
    from models.cudnn_lstm import _unit_rule
    x, w = jnp.zeros((2, 3, 4, 5)), jnp.zeros((2, 7))
    with pytest.raises(NotImplementedError, match="mapped over 2 sets of operands"):
        _unit_rule(rnn.rnn_fwd_p)([x, w], [0, 0])
