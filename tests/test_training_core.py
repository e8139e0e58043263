"""The learning core: relabeling, filtering into the device cache, the window sampler, the loss,
vmapped ensemble updates, checkpoints, and a small policy that learns a synthetic task."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from models import (Normalizer, PolicyConfig, ensemble_size, identity_normalizer, init_params, member,
                    predict_sequence)
from ttmjx.world.config import Table, World
from ttmjx.world import observation
from ttmjx.world.record import Trajectories
from training import (Batch, TrainConfig, add_episodes, append, data_normalizer, empty_cache,
                      init_train_state, keep_for_training, make_train_loop, make_train_step,
                      masked_mse, member_update, policy_loss, relabel, sample_subsequences)
from training.sampler import sample_episodes
from training.update import acting_params, updated_ema
from training import checkpoint

TABLE = Table()


def synthetic(seed: int, b: int, t: int, min_len: int = 4, hit_rate: float = 0.7) -> Trajectories:
    """Random episodes of varied length; hit ones have a hit step and a landing point that is
    sometimes off the table. Actions are a fixed smooth function of the frame (goal included)."""
    rng = np.random.default_rng(seed)
    length = rng.integers(min_len, t + 1, b)
    valid = np.arange(t)[None] < length[:, None]
    hit = rng.random(b) < hit_rate
    hit_step = np.where(hit, rng.integers(0, length), -1).astype(np.int32)
    landing = np.stack([rng.uniform(-0.6, 2.0, b), rng.uniform(-1.3, 1.3, b)], -1)
    landing = np.where(hit[:, None], landing, np.nan).astype(np.float32)
    goal = np.stack([rng.uniform(0, 1.37, b), rng.uniform(-0.76, 0.76, b)], -1).astype(np.float32)
    obs = rng.normal(size=(b, t, 13)).astype(np.float32)
    obs[..., 11:] = goal[:, None]
    return Trajectories(
        obs=obs, ball_vel=rng.normal(size=(b, t, 3)).astype(np.float32),
        actions=target_actions(obs), valid=valid, goal=goal, hit=hit, hit_step=hit_step,
        landing=landing, on_opponent=np.zeros(b, bool), bounce_own=np.zeros(b, bool),
        net=np.zeros(b, bool), launch_pos=np.zeros((b, 3), np.float32),
        launch_vel=np.zeros((b, 3), np.float32), launch_spin=np.zeros((b, 3), np.float32),
        aim=np.zeros((b, 2), np.float32))


_W = np.random.default_rng(123).normal(size=(13, 8)).astype(np.float32) / math.sqrt(13)


def target_actions(obs):
    """[..., 13] -> [..., 8]: a nonlinear function of the current frame and the goal."""
    return np.tanh(obs @ _W + 0.8 * obs[..., 11:12] - 0.5 * obs[..., 12:13]).astype(np.float32)


@pytest.fixture(scope="module")
def traj():
    return synthetic(0, 64, 40)


@pytest.fixture(scope="module")
def cache(traj):
    # Every episode hit and landed: the sampler tests need all rows used.
    hit_step = np.where(traj.hit_step < 0, traj.valid.sum(1) - 1, traj.hit_step).astype(np.int32)
    t = traj._replace(hit=np.ones(traj.size, bool), hit_step=hit_step,
                      landing=np.nan_to_num(traj.landing, nan=0.5))
    return append(empty_cache(64, 40), relabel(t), np.ones(t.size, bool))


# --- relabeling and filtering ---------------------------------------------------------------

def test_relabel_sets_goal_to_landing_in_goal_and_every_frame(traj):
    out = relabel(traj)
    assert isinstance(out.obs, np.ndarray)
    hit = traj.hit
    np.testing.assert_array_equal(out.goal[hit], traj.landing[hit])
    np.testing.assert_array_equal(out.goal[~hit], traj.goal[~hit])   # no landing: unchanged
    np.testing.assert_array_equal(out.obs[..., 11:], np.broadcast_to(out.goal[:, None], out.obs[..., 11:].shape))
    np.testing.assert_array_equal(out.obs[..., :11], traj.obs[..., :11])
    np.testing.assert_array_equal(out.actions, traj.actions)
    jitted = jax.jit(relabel)(jax.tree.map(jnp.asarray, traj))
    np.testing.assert_array_equal(np.asarray(jitted.obs), out.obs)


def test_keep_for_training_drops_misses_and_landings_beyond_the_margin(traj):
    keep = keep_for_training(traj, TABLE, 0.3)
    x, y = traj.landing[:, 0], traj.landing[:, 1]
    on_table = (x >= 0) & (x <= 1.37) & (np.abs(y) <= 0.7625)
    near = (x >= -0.3) & (x <= 1.67) & (np.abs(y) <= 1.0625)
    assert not keep[~traj.hit].any()
    assert keep[on_table].all()
    np.testing.assert_array_equal(keep, traj.hit & near)
    assert (keep & ~on_table).any(), "the fixture should hold kept off-table landings"
    np.testing.assert_array_equal(keep_for_training(traj, TABLE, 0.0), traj.hit & on_table)


def test_practice_keeps_every_hit_by_default_and_the_near_half_filter_on_request(traj):
    """Paper: a practice episode is dropped only if the ball was not hit; "near_half" is the
    filter this project used before (hits landing within goal_margin of the half). Checked on
    the append a practice round compiles (training.practice.Practice)."""
    from training.practice import Practice
    from ttmjx.world.backends import Backend
    from ttmjx.world.config import World
    world = World()
    assert traj.hit.any() and np.isfinite(traj.landing[traj.hit]).all()
    near = keep_for_training(traj, TABLE, 0.3)
    assert (traj.hit & ~near).any(), "the fixture should hold hits landing far off the table"
    for keep, expected in [("hits", traj.hit), ("near_half", near)]:
        tcfg = TrainConfig(practice_keep=keep, window=8)
        parts = Practice(world, PolicyConfig(), tcfg, Backend(world, "c"), episodes=8, train_steps=0)._pure_parts(None)
        cache = parts.append(empty_cache(64, traj.valid.shape[1]), traj, traj.size)
        assert int(cache.count) == int(expected.sum()), keep
        # A run's last round counts its first n episodes only: the rest join neither the pool
        # nor the round's statistics.
        n = traj.size // 3
        cache = parts.append(empty_cache(64, traj.valid.shape[1]), traj, jnp.int32(n))
        assert int(cache.count) == int(expected[:n].sum()), keep
    assert TrainConfig().practice_keep == "hits" and TrainConfig().practice_goal_margin == 0.2


def test_practice_statistics_cover_the_counted_episodes_only(traj):
    from training.practice import practice_stats
    from ttmjx.world.goals import goal_stats
    t = jax.tree.map(jnp.asarray, traj._replace(on_opponent=np.isfinite(traj.landing[:, 0])))
    n = traj.size // 2
    table = World().table
    part = practice_stats(t, jnp.int32(0), jnp.int32(5), jnp.int32(n), table, members=2)
    landing, goal, hit, on_opp = (np.asarray(x)[:n] for x in (t.landing, t.goal, t.hit, t.on_opponent))
    first = goal_stats(landing, goal, hit, on_opp)
    for k in ("hit_rate", "on_table_rate", "within_30cm", "within_20cm"):
        np.testing.assert_allclose(float(getattr(part, k)), first[k], rtol=1e-6, err_msg=k)
    # By goal region, against a plain loop over the counted attempts.
    third, ok = table.half_length / 3, []
    for (x, y), l, h, o in zip(goal, landing, hit, on_opp):
        good = bool(h and o and np.hypot(*(l - (x, y))) <= 0.3)
        edge = abs(y) > table.half_width - 0.2 or x > table.half_length - 0.2
        ok.append((x < third, third <= x < 2 * third, x >= 2 * third, edge, good))
    ok = np.array(ok)
    for r, name in enumerate(("near", "middle", "far", "edges")):
        want = ok[ok[:, r], 4].mean() if ok[:, r].any() else np.nan
        np.testing.assert_allclose(float(getattr(part, f"{name}_30cm")), want, rtol=1e-6, err_msg=name)
    # By member: member i played the i-th contiguous half of the round; only counted ones score.
    half = traj.size // 2 + traj.size % 2
    for i in range(2):
        mine = ok[i * half:min((i + 1) * half, n), 4]
        want = mine.mean() if len(mine) else np.nan
        np.testing.assert_allclose(float(part.members_30cm[i]), want, rtol=1e-6, err_msg=f"member {i}")
    assert 0 < first["hit_rate"] < 1 and first["within_30cm"] > 0, "the fixture should hold hits and successes"


def test_practice_goals_use_the_configured_margin():
    from training.practice import Practice
    from ttmjx.world.backends import Backend
    from ttmjx.world.config import World
    world = World()
    for margin in (0.0, 0.2, 0.5):
        tcfg = TrainConfig(practice_goal_margin=margin)
        parts = Practice(world, PolicyConfig(), tcfg, Backend(world, "c"), episodes=512, train_steps=0)._pure_parts(None)
        g = np.asarray(parts.goals(jax.random.PRNGKey(1)))
        assert g[:, 0].min() >= 0 and g[:, 0].max() <= TABLE.half_length + margin + 1e-6
        assert np.abs(g[:, 1]).max() <= TABLE.half_width + margin + 1e-6
        beyond = np.maximum(g[:, 0] - TABLE.half_length, np.abs(g[:, 1]) - TABLE.half_width).max()
        assert beyond > 0.5 * margin if margin else beyond <= 0, (margin, beyond)


@pytest.mark.parametrize("field,value,match", [
    ("practice_goal_margin", -0.1, r"practice_goal_margin=-0.1, expected metres in \[0, 1.0\]"),
    ("practice_goal_margin", float("nan"), "practice_goal_margin=nan"),
    ("practice_goal_margin", 1.5, "practice_goal_margin=1.5"),
    ("practice_keep", "all", r"practice_keep='all', expected one of \('hits', 'near_half'\)")])
def test_practice_options_are_bounded(field, value, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig(**{field: value})


# --- the cache ------------------------------------------------------------------------------

def test_cache_append_keeps_only_hit_episodes():
    tr = synthetic(1, 12, 20)
    c = jax.jit(lambda c, t: add_episodes(c, t, TABLE, math.inf))(empty_cache(32, 20), tr)
    kept = np.flatnonzero(tr.hit)
    assert int(c.size) == int(c.count) == len(kept)
    np.testing.assert_array_equal(c.hit_step[:len(kept)], tr.hit_step[kept])
    np.testing.assert_array_equal(c.actions[:len(kept)], tr.actions[kept])
    np.testing.assert_array_equal(c.goal[:len(kept)], tr.landing[kept])   # relabeled
    assert not np.asarray(c.valid[len(kept):]).any()                        # rest untouched


def test_cache_respects_capacity_fifo():
    tr = synthetic(2, 10, 8, hit_rate=1.0)
    keep = np.array([1, 0, 1, 1, 0, 1, 1, 1, 0, 1], bool)                   # 7 kept
    app = jax.jit(append)
    c = app(empty_cache(5, 8), tr, keep)
    kept = np.flatnonzero(keep)
    assert (int(c.size), int(c.count)) == (5, 7)
    # one call keeping more than the capacity: the last 5 kept, at rows (count + rank) % 5
    rows = [(i % 5) for i in range(2, 7)]
    np.testing.assert_array_equal(np.asarray(c.actions)[rows], tr.actions[kept[2:]])
    c = app(c, tr, np.eye(10, dtype=bool)[3])                                # one more -> row 7 % 5
    assert (int(c.size), int(c.count)) == (5, 8)
    np.testing.assert_array_equal(c.actions[2], tr.actions[3])
    np.testing.assert_array_equal(c.actions[3], tr.actions[kept[3]])        # neighbours intact
    with pytest.raises(ValueError, match="expected \\[B, 8, 13\\]"):
        append(c, synthetic(3, 2, 9), np.ones(2, bool))


# --- the sampler ----------------------------------------------------------------------------

def test_windows_always_contain_the_hit_and_cover_valid_steps(cache):
    k, n = 16, 4096
    sample = jax.jit(sample_subsequences, static_argnums=(2, 3, 4))
    b = jax.tree.map(np.asarray, sample(jax.random.PRNGKey(0), cache, k, n, 1))
    hit = np.asarray(cache.hit_step)[b.episode]
    length = np.asarray(cache.valid).sum(1)[b.episode]
    assert ((b.start <= hit) & (hit < b.start + k)).all()
    assert b.mask[np.arange(n), hit - b.start].all()
    steps = b.start[:, None] + np.arange(k)
    np.testing.assert_array_equal(b.mask, steps < length[:, None])
    long = length >= k
    assert b.mask[long].all(), "a window that fits must lie inside the episode"
    assert (b.start[~long] == 0).all() and (~long).any() and long.any()
    assert len(np.unique(b.episode)) == cache.size                       # every row gets drawn
    # the full range of starts is drawn for one long episode
    e = int(np.flatnonzero((np.asarray(cache.valid).sum(1) >= 30))[0])
    h, ln = int(cache.hit_step[e]), int(np.asarray(cache.valid[e]).sum())
    want = set(range(max(h - k + 1, 0), min(h, ln - k) + 1))
    assert set(b.start[b.episode == e]) == want


def test_window_frames_match_record_frame_stack(cache):
    k, s = 12, 4
    b = sample_subsequences(jax.random.PRNGKey(1), cache, k, 32, s)
    stacks = observation.frame_stack(np.asarray(cache.obs), s)                     # [C, T, s, 13]
    t = np.minimum(np.asarray(b.start)[:, None] + np.arange(k), cache.horizon - 1)
    want = stacks[np.asarray(b.episode)[:, None], t]
    m = np.asarray(b.mask)
    np.testing.assert_array_equal(np.asarray(b.frames)[m], want[m])
    np.testing.assert_array_equal(np.asarray(b.actions)[m],
                                  np.asarray(cache.actions)[np.asarray(b.episode)[:, None], t][m])
    b16 = sample_subsequences(jax.random.PRNGKey(1), cache, k, 32, 1, 16)
    vel = np.asarray(cache.ball_vel)[np.asarray(b16.episode)[:, None], t]
    assert b16.frames.shape == (32, k, 1, 16)
    np.testing.assert_array_equal(np.asarray(b16.frames)[:, :, 0, 11:14][m], vel[m])


# --- the loss -------------------------------------------------------------------------------

def test_masked_mse_hand_computed():
    pred = jnp.zeros((1, 3, 8))
    target = jnp.stack([jnp.full(8, 1.0), jnp.full(8, 2.0), jnp.full(8, 100.0)])[None]
    mask = jnp.array([[True, True, False]])
    # (8 * 1^2 + 8 * 2^2) / (2 steps * 8 dims) = 2.5; the masked step (100) does not count
    assert float(masked_mse(pred, target, mask)) == pytest.approx(2.5)
    target = target.at[0, 1, 3].set(4.0)                                  # one dim: 2 -> 4
    assert float(masked_mse(pred, target, mask)) == pytest.approx((8 + 7 * 4 + 16) / 16)
    assert float(masked_mse(pred, target, jnp.zeros((1, 3), bool))) == 0.0
    with pytest.raises(ValueError, match="masked_mse"):
        masked_mse(pred, target, jnp.ones((3,), bool))


def test_policy_loss_uses_normalized_actions():
    cfg = PolicyConfig("framestack", hidden=8, layers=1, frame_stack=1)
    norm = Normalizer(jnp.zeros(13), jnp.ones(13), jnp.full(8, 1.0), jnp.full(8, 2.0))
    p = init_params(jax.random.PRNGKey(0), cfg, norm)
    frames = jax.random.normal(jax.random.PRNGKey(1), (2, 5, 1, 13))
    pred = jax.vmap(lambda f: predict_sequence(cfg, p, f))(frames)         # normalized
    actions = pred * 2.0 + 1.0 + 0.2                                       # +0.1 normalized
    zeros = jnp.zeros(2, jnp.int32)
    batch = Batch(frames, actions, jnp.ones((2, 5), bool), zeros, zeros)
    assert float(policy_loss(cfg, p, batch)) == pytest.approx(0.01, rel=1e-4)


@pytest.mark.parametrize("kind", ["lstm", "framestack"])
def test_bfloat16_updates_compute_the_float32_loss_and_gradient_to_bfloat16_precision(kind):
    """TrainConfig.update_dtype='bfloat16': the same loss and gradient as float32 within what
    bfloat16's 8-bit mantissa allows (relative 2^-8 per product, a few per cent after a sum over
    a window), with the gradient float32 for the float32 weights."""
    cfg = PolicyConfig(kind, hidden=32, layers=2, frame_stack=2)
    norm = Normalizer(jnp.zeros(13), jnp.ones(13), jnp.zeros(8), jnp.ones(8))
    p = init_params(jax.random.PRNGKey(0), cfg, norm)
    frames = jax.random.normal(jax.random.PRNGKey(1), (4, 12, cfg.input_frames, 13))
    actions = jax.random.normal(jax.random.PRNGKey(2), (4, 12, 8))
    zeros = jnp.zeros(4, jnp.int32)
    batch = Batch(frames, actions, jnp.ones((4, 12), bool), zeros, zeros)
    out = {dt: jax.value_and_grad(lambda net, dt=dt: policy_loss(cfg, p._replace(net=net), batch, dt))(p.net)
           for dt in ("float32", "bfloat16")}
    (l32, g32), (l16, g16) = out["float32"], out["bfloat16"]
    assert l16.dtype == jnp.float32 and all(g.dtype == jnp.float32 for g in jax.tree.leaves(g16))
    assert float(l16) == pytest.approx(float(l32), rel=2e-2)
    flat = lambda g: jnp.concatenate([x.ravel() for x in jax.tree.leaves(g)])  # noqa: E731
    a, b = flat(g32), flat(g16)
    assert float(jnp.linalg.norm(a - b) / jnp.linalg.norm(a)) < 5e-2
    assert float(jnp.dot(a, b) / (jnp.linalg.norm(a) * jnp.linalg.norm(b))) > 0.99


# --- ensemble updates -----------------------------------------------------------------------

def test_ensemble_members_differ_and_train_in_one_vmapped_step(cache):
    pcfg = PolicyConfig("lstm", hidden=8, layers=2)
    tcfg = TrainConfig(window=8, batch_size=4, members=3, learning_rate=1e-2)
    state = init_train_state(jax.random.PRNGKey(0), pcfg, tcfg, identity_normalizer(13))
    assert ensemble_size(state.params) == 3
    k0 = state.params.net["params"]["head"]["kernel"]
    assert k0.shape == (3, 8, 8) and not np.allclose(k0[0], k0[1])
    new, loss = make_train_step(pcfg, tcfg)(state, cache, jax.random.PRNGKey(1))
    assert loss.shape == (3,) and int(new.step) == 1 and len(set(np.asarray(loss).tolist())) == 3
    # the vmapped step equals each member's own update with its own key
    keys = jax.random.split(jax.random.PRNGKey(1), 3)
    one = jax.jit(lambda p, o, k: member_update(pcfg, tcfg, p, o, cache, k))
    for i in (0, 2):
        p, _, l_i = one(member(state.params, i), jax.tree.map(lambda x: x[i], state.opt_state), keys[i])
        assert float(l_i) == pytest.approx(float(loss[i]), rel=1e-5)
        np.testing.assert_allclose(p.net["params"]["head"]["kernel"],
                                   new.params.net["params"]["head"]["kernel"][i], rtol=1e-5, atol=1e-6)


def test_ema_is_the_running_average_of_the_updates(cache):
    """The acting policy after two steps is d^2 p0 + d(1-d) p1 + (1-d) p2 of the iterates; with
    decay 0 it is the trained weights themselves."""
    pcfg = PolicyConfig("framestack", hidden=8, layers=1, frame_stack=2)
    d = 0.9
    tcfg = TrainConfig(window=8, batch_size=4, members=2, learning_rate=1e-2, ema_decay=d)
    step = make_train_step(pcfg, tcfg)
    s0 = init_train_state(jax.random.PRNGKey(0), pcfg, tcfg, identity_normalizer(13))
    s1, _ = step(s0, cache, jax.random.PRNGKey(1))
    s2, _ = step(s1, cache, jax.random.PRNGKey(2))
    k = lambda p: np.asarray(p.net["params"]["head"]["kernel"], np.float64)  # noqa: E731
    want = d * d * k(s0.params) + d * (1 - d) * k(s1.params) + (1 - d) * k(s2.params)
    np.testing.assert_allclose(k(acting_params(s2)), want, rtol=1e-5, atol=1e-7)
    assert not np.allclose(k(acting_params(s2)), k(s2.params))
    assert updated_ema(0.0, s1.ema, s2.params) is s2.params
    with pytest.raises(ValueError, match="ema_decay=1.0"):
        TrainConfig(ema_decay=1.0)


def test_demo_fraction_keeps_demonstrations_in_every_batch():
    """With demo_fraction f, rows come from demonstrations with probability max(f, their share),
    uniformly within each group; 0 is uniform over the pool; one empty group falls back to uniform."""
    c = empty_cache(100, 4)
    c = c._replace(demo=jnp.zeros(100, bool).at[:10].set(True), size=jnp.int32(60), count=jnp.int32(60))
    draw = jax.jit(sample_episodes, static_argnums=(2, 3))
    n = 40_000
    for f, p_demo in ((0.5, 0.5), (0.1, 10 / 60), (0.0, 10 / 60)):
        rows = np.asarray(draw(jax.random.PRNGKey(0), c, n, f))
        assert rows.min() >= 0 and rows.max() < 60                           # only filled rows
        share = np.mean(rows < 10)
        assert abs(share - p_demo) < 4 * math.sqrt(p_demo * (1 - p_demo) / n)
        counts = np.bincount(rows, minlength=60)
        for grp in (counts[:10], counts[10:60]):                                # uniform within groups
            assert grp.min() > 0.8 * grp.mean() and grp.max() < 1.2 * grp.mean()
    only_practice = c._replace(demo=jnp.zeros(100, bool))
    rows = np.asarray(draw(jax.random.PRNGKey(1), only_practice, n, 0.5))
    assert rows.max() < 60 and abs(np.mean(rows < 10) - 1 / 6) < 0.02
    with pytest.raises(ValueError, match="demo_fraction=1.5"):
        TrainConfig(demo_fraction=1.5)


def test_balanced_sampling_draws_each_landing_cell_equally_often():
    """balance = 1: a row's chance is 1 / (occupied cells x episodes in its cell), so a cell
    holding 40 episodes is drawn as often as one holding 2 (a plain count over the rows is the
    reference); balance = 0.5 in between; with demo_fraction the demonstrations keep their share."""
    c = empty_cache(100, 4)
    # 40 landings in one cell, 2 in another far away, 8 in a third; 50 rows filled.
    goals = np.zeros((100, 2), np.float32)
    goals[:40] = (0.70, 0.00)
    goals[40:42] = (0.20, 0.60)
    goals[42:50] = (1.20, -0.60)
    c = c._replace(goal=jnp.asarray(goals), size=jnp.int32(50), count=jnp.int32(50),
                   demo=jnp.zeros(100, bool).at[40:50].set(True))
    draw = jax.jit(sample_episodes, static_argnums=(2, 3, 4))
    n = 60_000
    group = np.repeat([0, 1, 2], [40, 2, 8])
    for balance, counts in ((1.0, (40, 2, 8)), (0.5, (40, 2, 8))):
        rows = np.asarray(draw(jax.random.PRNGKey(0), c, n, 0.0, balance))
        assert rows.min() >= 0 and rows.max() < 50
        w = np.array(counts, float) ** (1 - balance)          # total weight of each cell
        want = w / w.sum()
        got = np.bincount(group[rows], minlength=3) / n
        np.testing.assert_allclose(got, want, atol=4 * np.sqrt(want * (1 - want) / n).max())
    rows = np.asarray(draw(jax.random.PRNGKey(2), c, n, 0.8, 1.0))
    assert abs(np.mean(rows >= 40) - 0.8) < 0.01                # the demonstrations' share
    with pytest.raises(ValueError, match="balance=3"):
        TrainConfig(balance=3)


def test_a_lanes_demo_fraction_as_data_draws_what_the_constant_draws():
    """In a batch of lanes the demonstrations' share is a traced [] array (training.update.Knobs):
    at 0 it must draw the paper's uniform rows, and at f > 0 the rows of the constant f, so that a
    lane is the same experiment as that run alone; the same for landing-balanced sampling."""
    c = empty_cache(100, 4)
    c = c._replace(demo=jnp.zeros(100, bool).at[:10].set(True), size=jnp.int32(60), count=jnp.int32(60),
                   goal=jax.random.uniform(jax.random.PRNGKey(3), (100, 2)))
    traced = jax.jit(sample_episodes, static_argnums=(2, 4))
    for balance in (0.0, 1.0):
        for f in (0.0, 0.5):
            want = sample_episodes(jax.random.PRNGKey(5), c, 64, f, balance)
            got = traced(jax.random.PRNGKey(5), c, 64, jnp.float32(f), balance)
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


# --- checkpoints ----------------------------------------------------------------------------

def test_checkpoint_round_trip_is_bit_exact_and_keeps_the_latest(tmp_path, cache):
    pcfg = PolicyConfig("framestack", hidden=8, layers=1, frame_stack=2)
    tcfg = TrainConfig(window=8, batch_size=4, members=2)
    state = init_train_state(jax.random.PRNGKey(0), pcfg, tcfg, identity_normalizer(13))
    state, _ = make_train_step(pcfg, tcfg)(state, cache, jax.random.PRNGKey(1))  # nonzero Adam moments
    tree = {"state": state, "cache": cache, "key": jax.random.PRNGKey(7),
            "typed_key": jax.random.key(8), "counters": {"episodes": jnp.int32(1234), "updates": jnp.int32(5)}}
    config = {"policy": {"kind": "framestack", "hidden": 8}, "train": {"window": 8}}
    d = str(tmp_path / "ckpt")
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        checkpoint.restore(d, tree)
    for s in (10, 20, 30):
        checkpoint.save(d, s, tree, {**config, "step": s}, keep=2)
    assert checkpoint.steps(d) == [20, 30]
    template = jax.tree.map(jnp.zeros_like, tree)
    out, cfg = checkpoint.restore(d, template)
    assert cfg == {**config, "step": 30} and checkpoint.restore_config(d, 20)["step"] == 20
    assert jax.tree.structure(out) == jax.tree.structure(tree)
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(tree)):
        if jax.dtypes.issubdtype(b.dtype, jax.dtypes.prng_key):
            a, b = jax.random.key_data(a), jax.random.key_data(b)
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(FileNotFoundError, match="saved steps: \\[20, 30\\]"):
        checkpoint.restore(d, template, step=10)


# --- learning -------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["lstm", "framestack"])
def test_small_policy_learns_a_synthetic_goal_conditioned_task(kind):
    """Actions are a fixed nonlinear function of the current frame and goal (target_actions).

    The normalizer gives every action dim unit variance over the data, so predicting the mean
    scores ~1.0 (checked below as the initial loss). A 0.1 threshold means the policy explains
    over 90% of the action variance on held-out episodes, which it can only do by reading the
    observation and the goal; a 2x32 network fits this smooth 13 -> 8 map well below that.
    """
    pcfg = PolicyConfig(kind, hidden=32, layers=2, frame_stack=2)
    tcfg = TrainConfig(window=8, batch_size=32, members=2, learning_rate=3e-3)
    train = synthetic(10, 128, 16, min_len=8, hit_rate=1.0)
    test = synthetic(11, 64, 16, min_len=8, hit_rate=1.0)
    train, test = (t._replace(landing=t.goal) for t in (train, test))         # relabel = identity
    norm = data_normalizer(relabel(train), 13)
    c_train = append(empty_cache(128, 16), relabel(train), np.ones(128, bool))
    c_test = append(empty_cache(64, 16), relabel(test), np.ones(64, bool))
    state = init_train_state(jax.random.PRNGKey(0), pcfg, tcfg, norm)

    def test_loss(params):
        b = sample_subsequences(jax.random.PRNGKey(99), c_test, 8, 256, pcfg.input_frames)
        return jax.vmap(lambda p: policy_loss(pcfg, p, b))(params)            # [N]

    before = np.asarray(test_loss(state.params))
    state, losses = make_train_loop(pcfg, tcfg, 400)(state, c_train, jax.random.PRNGKey(1))
    after = np.asarray(test_loss(state.params))
    assert losses.shape == (400, 2)
    assert (before > 0.7).all(), before
    assert (after < 0.1).all(), (before, after)


def test_a_checkpoint_keeps_the_pools_filled_rows_and_restores_the_whole_pool(tmp_path):
    """The pool's empty rows are not written (a block past its filled ones is); the restored
    pool is the saved one, bit for bit, at its full capacity."""
    import dataclasses
    from training import runconfig
    cfg = runconfig.tiny()
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, capacity=3 * checkpoint.CACHE_ROW_BLOCK))
    ck = jax.eval_shape(lambda: checkpoint.template(cfg))
    ck = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), ck)
    rng = np.random.default_rng(0)
    n = checkpoint.CACHE_ROW_BLOCK + 5                      # two blocks kept, the third not
    obs = np.zeros(ck.cache.obs.shape, np.float32)
    obs[:n] = rng.normal(size=(n,) + obs.shape[1:])
    cache = ck.cache._replace(obs=jnp.asarray(obs), demo=ck.cache.demo.at[:n].set(True),
                              size=jnp.int32(n), count=jnp.int32(n))
    ck = ck._replace(cache=cache)
    d = str(tmp_path / "checkpoints")
    checkpoint.save(d, 3, ck, runconfig.to_json(cfg))
    assert checkpoint.restore_config(d)["cache_rows"] == 2 * checkpoint.CACHE_ROW_BLOCK
    back = checkpoint.load_checkpoint(d).ck
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(ck)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_overlapping_saves_put_stderr_back_whatever_order_they_end_in(tmp_path):
    """Lanes save from several threads at once: two saves whose output holds overlap and end in
    the order they started (not nested) leave sys.stderr as it was, and what they held is shown."""
    import io
    import sys
    before, shown = sys.stderr, io.StringIO()
    sys.stderr = shown
    try:
        a, b = checkpoint._disk_errors(str(tmp_path), 1), checkpoint._disk_errors(str(tmp_path), 2)
        a.__enter__()
        print("from the first save", file=sys.stderr)
        b.__enter__()
        a.__exit__(None, None, None)
        assert sys.stderr is not shown          # the second save still holds its output
        b.__exit__(None, None, None)
        assert sys.stderr is shown
    finally:
        sys.stderr = before
    assert "from the first save" in shown.getvalue()


def test_reading_a_checkpoint_logs_no_read_only_notices(tmp_path, caplog):
    """Every evaluation and export opens the checkpoints read-only; Orbax's two notices about it
    are dropped, other warnings are not."""
    import logging
    from training import checkpoint as ck
    ck.save(str(tmp_path), 1, {"w": np.zeros(3, np.float32)}, {"preset": "x"})
    with caplog.at_level(logging.WARNING, logger="absl"):
        ck._manager(str(tmp_path), read_only=True).close()
        logging.getLogger("absl").warning("another warning")
    said = [r.getMessage() for r in caplog.records]
    assert not any(m.startswith(("CheckpointManagerOptions.read_only=True", "Given directory is read only")) for m in said), said
    assert "another warning" in said
