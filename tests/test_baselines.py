"""RL baselines: the brax environment's reward terms are what RewardConfig says on a
scripted hit; brax's policy converts exactly into a GoalsEye framestack policy; the trajectory
budget brax runs is the one recorded (never above the one asked for); and PPO, SAC and ES each
train a few updates at the tiny scale through `ttmjx baseline`'s cells, with a learning curve of
several points, leaving a checkpoint that `ttmjx eval` scores with the strict metric and
`ttmjx export` exports."""
import dataclasses
import json
import math
import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from eval import baselines
from models.policy import make_policy
from training.baselines import agents
from training.baselines.config import RewardConfig
from training.baselines.env import TERMS, GoalEnv, reach, targets
from training.runconfig import tiny
from ttmjx.tools import striker
from ttmjx.world import env as task

WORLD = tiny().world
N = 4


def test_reward_config_refuses_bad_weights():
    for bad in ({"goal": float("nan")}, {"hit": -1.0}, {"smooth": float("inf")}, {"goal_scale": 0.0}):
        with pytest.raises(ValueError, match=list(bad)[0]):
            RewardConfig(**bad)


def test_actions_map_onto_the_joint_box():
    r = WORLD.robot
    np.testing.assert_allclose(targets(WORLD, jnp.zeros(8)), r.home, atol=1e-6)
    lo, hi = np.asarray(targets(WORLD, -jnp.ones(8))), np.asarray(targets(WORLD, jnp.ones(8)))
    assert (lo <= np.asarray(r.lower) + 1e-6).all() and (hi >= np.asarray(r.upper) - 1e-6).all()


@pytest.fixture(scope="module")
def scripted():
    """N throws played by the scripted striker through GoalEnv (MJX), with per-step records."""
    rcfg = RewardConfig(goal=2.0, goal_scale=0.25, hit=0.7, opponent=0.3, pose=0.01, smooth=0.02)
    env, pol = GoalEnv(WORLD, rcfg), striker.striker_policy(WORLD)
    home, scale = jnp.asarray(WORLD.robot.home), jnp.asarray(reach(WORLD))

    def episode(key):
        k_reset, k_init = jax.random.split(key)
        s0 = env.reset(k_reset)
        carry0 = pol.init(None, k_init)

        def body(c, _):
            s, carry = c
            carry, target = pol.apply(None, carry, task.observe(WORLD, env.lay, s.pipeline_state), None)
            s2 = env.step(s, (target - home) / scale)
            return (s2, carry), (s2.reward, s2.done, {k: s2.metrics[k] for k in TERMS},
                                 s2.pipeline_state.target, s2.pipeline_state.frames[-1][:8])

        (s, _), rec = jax.lax.scan(body, (s0, carry0), None, length=WORLD.horizon)
        return s0.pipeline_state.target, s.pipeline_state, rec

    t0, final, (reward, done, terms, tgt, joints) = jax.jit(jax.vmap(episode))(
        jax.random.split(jax.random.PRNGKey(3), N))
    return rcfg, jax.tree.map(np.asarray, (t0, final, reward, done, terms, tgt, joints))


@pytest.mark.slow
def test_reward_terms_on_a_scripted_hit(scripted):
    rcfg, (t0, final, reward, done, terms, tgt, joints) = scripted
    ev = final.events
    assert ev.hit.any() and ev.on_opponent.any(), "the striker returned no ball: the test shows nothing"
    np.testing.assert_allclose(reward, sum(terms[k] for k in TERMS), rtol=1e-5, atol=1e-7)
    # the event terms: once each, at the step of the event, with the configured weight
    np.testing.assert_allclose(terms["r_hit"].sum(1), rcfg.hit * ev.hit, atol=1e-6)
    for b in np.flatnonzero(ev.hit):
        assert terms["r_hit"][b, ev.hit_step[b]] == pytest.approx(rcfg.hit)
    np.testing.assert_allclose(terms["r_opponent"].sum(1), rcfg.opponent * ev.on_opponent, atol=1e-6)
    d = np.linalg.norm(np.nan_to_num(ev.landing) - final.goal, axis=1)
    np.testing.assert_allclose(terms["r_goal"].sum(1), np.where(ev.landed, rcfg.goal * np.exp(-d / rcfg.goal_scale), 0),
                               rtol=1e-5, atol=1e-6)
    # the style terms, every step
    home, scale = np.asarray(WORLD.robot.home), reach(WORLD)
    np.testing.assert_allclose(terms["r_pose"], -rcfg.pose * (((joints - home) / scale) ** 2).mean(-1), rtol=1e-4, atol=1e-9)
    r = WORLD.robot
    max_step = np.asarray(r.max_speed) * r.speed_margin * WORLD.control_dt
    prev = np.concatenate([t0[:, None], tgt[:, :-1]], 1)
    np.testing.assert_allclose(terms["r_smooth"], -rcfg.smooth * (((tgt - prev) / max_step) ** 2).mean(-1),
                               rtol=1e-4, atol=1e-9)
    assert (terms["r_smooth"] < 0).any() and (terms["r_pose"] < 0).any()
    # done at the horizon (exact trajectory counts), not at the landing
    assert (done[:, -1] == 1).all() and (done[:, :-1] == 0).all()


@pytest.mark.parametrize("method", agents.BRAX_METHODS)
def test_brax_policy_is_a_goalseye_framestack_policy(method):
    """The converted PolicyParams act exactly as brax's deterministic policy through GoalEnv's map."""
    from brax.training.acme import running_statistics
    cfg = baselines.method_config(method, "tiny", 0, "unused", trajectories=4)
    obs_size = WORLD.frame_stack * WORLD.obs_size
    factory = {"ppo": agents.ppo_networks, "sac": agents.sac_networks, "es": agents.es_networks}[method](cfg)
    nets = factory(obs_size, 8, preprocess_observations_fn=running_statistics.normalize)
    params = nets.policy_network.init(jax.random.PRNGKey(0))
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(1), 3)
    stats = running_statistics.init_state(jax.ShapeDtypeStruct((obs_size,), jnp.float32))
    stats = stats.replace(mean=jax.random.normal(k1, (obs_size,)), std=jnp.exp(jax.random.normal(k2, (obs_size,))))
    frames = jax.random.normal(k3, (5, WORLD.frame_stack, WORLD.obs_size))
    out = nets.policy_network.apply(stats, params, frames.reshape(5, -1))
    want = targets(WORLD, (out[0] if isinstance(out, tuple) else out)[:, :8])
    pp = agents.policy_params(cfg, stats, params)
    pol = make_policy(cfg.run.policy)
    obs = task.Obs(frame=frames[:, -1], ball_vel=jnp.zeros((5, 3)), frames=frames, t=jnp.zeros(5, jnp.int32))
    got = jax.vmap(lambda o: pol.apply(pp, (), o, None)[1])(obs)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


def brax_steps(method: str, cfg, num_timesteps: int, num_evals: int) -> int:
    """Environment steps brax 0.14.2 runs, written out from its trainers (action_repeat 1, one
    device), independently of agents.brax_env_steps."""
    h, evals_after_init = cfg.run.world.horizon, max(num_evals - 1, 1)
    if method == "ppo":    # ppo/train.py
        env_step_per_training_step = cfg.ppo.batch_size * cfg.ppo.unroll_length * cfg.ppo.num_minibatches
        num_training_steps_per_epoch = math.ceil(num_timesteps / (evals_after_init * env_step_per_training_step))
        return evals_after_init * num_training_steps_per_epoch * env_step_per_training_step
    if method in ("sac", "qtopt"):    # sac/train.py (QT-Opt's loop is SAC's)
        c = cfg.sac if method == "sac" else cfg.qtopt
        num_envs = c.num_envs
        num_prefill_env_steps = -(-c.min_replay_size // num_envs) * num_envs
        num_training_steps_per_epoch = -(-(num_timesteps - num_prefill_env_steps) // (evals_after_init * num_envs))
        return num_prefill_env_steps + evals_after_init * num_training_steps_per_epoch * num_envs
    per_epoch = 2 * cfg.es.population_size * h   # es/train.py: epochs while steps < num_timesteps
    return math.ceil(num_timesteps / per_epoch) * per_epoch


def exact(cfg, trajectories: int) -> bool:
    """Whether brax runs `trajectories` whole trajectories for some num_timesteps: prefill plus a
    whole number (>= 1) of the method's environment steps per batch, written out from brax's
    trainers independently of agents.schedule."""
    h = cfg.run.world.horizon
    if cfg.method == "ppo":
        prefill, unit = 0, cfg.ppo.batch_size * cfg.ppo.unroll_length * cfg.ppo.num_minibatches
    elif cfg.method in ("sac", "qtopt"):
        c = cfg.sac if cfg.method == "sac" else cfg.qtopt
        prefill, unit = -(-c.min_replay_size // c.num_envs) * c.num_envs, c.num_envs
    else:
        prefill, unit = 0, 2 * cfg.es.population_size * h
    return trajectories * h > prefill and (trajectories * h - prefill) % unit == 0


def test_brax_runs_exactly_the_budget_or_refuses_it():
    """brax rounds num_timesteps up to whole epochs (PPO asked for 120k once ran 143,360
    trajectories; 20,000 once became 16,384 silently): a budget is run exactly, or refused with
    the nearest budgets that are exact, and nothing exact lies between them. Table I's 120,000
    is exact for every method."""
    naive = baselines.method_config("ppo", "full", 0, "r", trajectories=120_000)
    assert brax_steps("ppo", naive, 120_000 * 160 + 1, 8) > 120_000 * 160      # brax alone rounds up
    for method in agents.METHODS:
        for budget in (4_097, 120_000, 123_457, 240_000, 1_000_001, 35_000_000):
            try:
                cfg = baselines.method_config(method, "full", 0, "r", trajectories=budget)
            except ValueError as e:
                if "smallest budget is" in str(e):      # QT-Opt's 12,000 environments: 4,097 is no episode each
                    smallest = int(str(e).split("smallest budget is ")[-1].replace(",", ""))
                    assert budget < smallest and "whole 160-step episode" in str(e), (method, budget, str(e))
                    baselines.method_config(method, "full", 0, "r", trajectories=smallest)   # accepted
                    continue
                nums = [int(x.replace(",", "")) for x in re.findall(r"\d[\d,]*\d|\d", str(e).split("nearest budgets are")[-1])]
                assert len(nums) == 2 and "nearest budgets" in str(e) and f"{budget:,}" in str(e), str(e)
                below, above = nums
                assert below < budget < above, (method, budget, nums)
                base = baselines.method_config(method, "full", 0, "r", trajectories=below)
                assert exact(base, below) and exact(base, above) and not exact(base, budget)
                assert not any(exact(base, t) for t in range(below + 1, above)), (method, budget)
                baselines.method_config(method, "full", 0, "r", trajectories=above)   # accepted
                continue
            s, h = agents.schedule(cfg), cfg.run.world.horizon
            assert exact(cfg, budget), (method, budget)
            ran = brax_steps(method, cfg, s.num_timesteps, s.num_evals)
            assert ran == s.num_timesteps == budget * h == cfg.steps, (method, budget)
            assert cfg.run.total_trajectories == budget
            assert s.num_evals >= 2 and s.units % (s.num_evals - 1) == 0
    for method in agents.METHODS:
        assert baselines.method_config(method, "full", 0, "r").run.total_trajectories == 120_000
    with pytest.raises(ValueError, match="below one batch of ppo .*smallest budget is 4,000"):
        baselines.method_config("ppo", "full", 0, "r", trajectories=3_999)


def test_cli_refuses_an_inexact_budget_with_one_line(tmp_path, capsys):
    """`ttmjx baseline` exits 2 with one line naming the nearest budgets, before writing anything."""
    from ttmjx.cli import main
    out = tmp_path / "table"
    with pytest.raises(SystemExit) as e:
        main(["baseline", "ppo", "--seeds", "2", "--trajectories", "123457", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1, err
    assert err[0].startswith("ttmjx baseline: error: ") and "123,457" in err[0]
    assert "120,000 and 124,000" in err[0], err[0]
    assert not out.exists()
    # brax's settings are flags, checked as well: 12,000 environments make 12,000-trajectory steps
    with pytest.raises(SystemExit) as e:
        main(["baseline", "ppo", "--ppo.num-envs", "12000", "--trajectories", "120000", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "multiple of num_envs (12000)" in err[0], err
    with pytest.raises(SystemExit) as e:
        main(["baseline", "ppo", "--ppo.num-envs", "12000", "--ppo.num-minibatches", "96", "--trajectories", "126000",
              "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and "training steps of 12,000" in err[0] and "120,000 and 132,000" in err[0], err
    assert not out.exists()


def test_throws_are_solved_ahead_and_never_reused(monkeypatch):
    """FreshAutoReset: every episode of every environment starts from a throw of its own, drawn
    from a pool solved `pool` episodes at a time (refilled when used up), and its reset state
    carries exactly the info brax's EpisodeWrapper gives (plus its own keys)."""
    from brax.envs.base import Env, State
    from brax.envs.wrappers.training import EpisodeWrapper, VmapWrapper

    from training.baselines.env import wrap_fresh
    from ttmjx.world import thrower
    solves = []

    def fake_throws(key, cfg, n):            # the pool's logic, not the solver, is under test
        solves.append(n)
        x = jax.random.normal(key, (4, n, 3))
        return thrower.Throw(*x)
    monkeypatch.setattr(thrower, "sample_throws", fake_throws)

    class Stub(Env):
        """Episodes of 3 steps whose observation is the throw's launch velocity."""
        cfg = WORLD

        def reset_with(self, rng, th):
            z = jnp.zeros(())
            return State(pipeline_state={"t": jnp.int32(0)}, obs=th.launch_vel, reward=z, done=z,
                         metrics={"r_goal": z}, info={})

        def reset(self, rng):
            return self.reset_with(rng, thrower.Throw(*jax.random.normal(rng, (4, 3))))

        def step(self, state, action):
            t = state.pipeline_state["t"] + 1
            return state.replace(pipeline_state={"t": t}, done=(t >= 3).astype(jnp.float32))

        observation_size, action_size, backend = 3, 1, "stub"

    n, pool, episodes = 4, 2, 7
    env = wrap_fresh(Stub(), episode_length=3, pool=pool)
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    s0 = env.reset(keys)
    ref = EpisodeWrapper(VmapWrapper(Stub()), 3, 1).reset(keys)
    mine = {k: v for k, v in s0.info.items() if k not in ("reset_key", "throw_pool", "throw_next")}
    assert jax.tree.structure(mine) == jax.tree.structure(ref.info)
    assert jax.tree.map(jnp.shape, mine) == jax.tree.map(jnp.shape, ref.info)

    def run(s, _):
        s = env.step(s, jnp.zeros((n, 1)))
        return s, s.obs
    _, obs = jax.jit(lambda s: jax.lax.scan(run, s, None, length=3 * episodes))(s0)
    starts = np.concatenate([np.asarray(s0.obs)[None], np.asarray(obs)[2::3]])   # each episode's throw
    assert starts.shape == (episodes + 1, n, 3)
    flat = starts.reshape(-1, 3)
    assert len(np.unique(flat.round(6), axis=0)) == len(flat), "a throw was used twice"
    assert solves and set(solves) == {n * pool}          # solved in batches of n x pool, never one by one


def _top_level_conds(fn, *args) -> int:
    return sum(e.primitive.name == "cond" for e in jax.make_jaxpr(fn)(*args).eqns)


def test_seeds_vmapped_restart_each_seed_as_alone_and_branch_only_when_needed(monkeypatch):
    """Seeds stacked under the seeds' vmap (resumable.over_seeds): each seed's episodes start
    from the same throws as alone, also when only one seed's pool runs out, and the restart and
    the pool's refill stay lax.cond branches (vmap turns a cond on a per-seed predicate into a
    select that solves throws and resets every environment at every step)."""
    from brax.envs.base import Env, State

    from training.baselines import env as benv
    from training.baselines import resumable
    from ttmjx.world import thrower

    monkeypatch.setattr(thrower, "sample_throws", lambda key, cfg, n: thrower.Throw(*jax.random.normal(key, (4, n, 3))))

    class Stub(Env):
        """Episodes of 2 steps whose observation is the throw's launch velocity."""
        cfg = WORLD

        def reset_with(self, rng, th):
            z = jnp.zeros(())
            return State(pipeline_state={"t": jnp.int32(0)}, obs=th.launch_vel, reward=z, done=z, metrics={}, info={})

        def step(self, state, action):
            t = state.pipeline_state["t"] + 1
            return state.replace(pipeline_state={"t": t}, done=(t >= 2).astype(jnp.float32))

        reset = None
        observation_size, action_size, backend = 3, 1, "stub"

    n, pool = 3, 3
    env = benv.wrap_fresh(Stub(), episode_length=2, pool=pool)
    starts = [env.reset(jax.random.split(jax.random.PRNGKey(s), n)) for s in (0, 1)]
    starts[1].info["throw_next"] = jnp.full((n,), pool - 1, jnp.int32)   # seed 1 refills one episode earlier

    def run(s):
        return jax.lax.scan(lambda s, _: (env.step(s, jnp.zeros((n, 1))), env.step(s, jnp.zeros((n, 1))).obs),
                            s, None, length=2 * pool + 2)[1]
    alone = [jax.jit(run)(s) for s in starts]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *starts)
    together = resumable.over_seeds(run)(stacked)
    for i in (0, 1):
        np.testing.assert_array_equal(np.asarray(together[i]), np.asarray(alone[i]))
    assert not np.allclose(alone[0], alone[1])
    def step(s):    # a new function each time: jax caches a function's trace
        return env.step(s, jnp.zeros((n, 1)))
    assert _top_level_conds(jax.vmap(step, axis_name=resumable.SEED_AXIS), stacked) == 1   # the restart
    monkeypatch.setattr(benv, "any_seed", lambda pred: pred)   # a per-seed predicate: select, no branch
    assert _top_level_conds(jax.vmap(lambda s: step(s), axis_name=resumable.SEED_AXIS), stacked) == 0


def test_sac_buffer_inserts_each_seed_as_brax_and_rolls_only_when_needed():
    """SAC's replay queue under the seeds' vmap inserts each seed's transitions exactly as brax's
    UniformSamplingQueue does alone, one seed's buffer full and rolling, the other's not, and its
    roll stays a lax.cond branch."""
    from brax.training import replay_buffers

    from training.baselines import resumable, sac
    kw = dict(max_replay_size=10, dummy_data_sample=jnp.zeros((2,)), sample_batch_size=2)
    brax_q, seeds_q = replay_buffers.UniformSamplingQueue(**kw), sac._seeds_queue(replay_buffers)(**kw)
    batch = lambda k: jax.random.normal(jax.random.PRNGKey(k), (3, 2))   # noqa: E731
    states = [brax_q.init(jax.random.PRNGKey(s)) for s in (0, 1)]
    for k in range(3):                                   # seed 1 three inserts ahead: 9 of 10 full
        states[1] = brax_q.insert(states[1], batch(100 + k))
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *states)
    insert = jax.vmap(seeds_q.insert, axis_name=resumable.SEED_AXIS)
    for k in range(3):
        b = batch(k)
        states = [brax_q.insert(s, b) for s in states]
        stacked = jax.jit(insert)(stacked, jnp.stack([b, b]))
        for i in (0, 1):
            for a, r in zip(jax.tree.leaves(jax.tree.map(lambda x: x[i], stacked)), jax.tree.leaves(states[i]), strict=True):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(r))
    assert _top_level_conds(insert, stacked, jnp.stack([batch(0)] * 2)) == 1


@pytest.mark.slow
def test_seeds_that_do_not_fit_the_device_train_in_groups_that_do(monkeypatch):
    """The seeds of a method train as one program where their stacked epoch fits in 90% of the
    device's memory (XLA's memory analysis of the compiled epoch), else in groups that fit, one
    after another, each group a program; on a CPU (no device limit) all together."""
    cfg = baselines.method_config("es", "tiny", 0, "/tmp/fit", trajectories=4)
    need = agents.program_bytes(cfg, 2)
    assert need > 0
    monkeypatch.setattr(agents, "device_bytes_limit", lambda: int(need / 0.9) + 1)
    assert agents.seeds_per_program(cfg, 2) == 2
    lines = []
    monkeypatch.setattr(agents, "device_bytes_limit", lambda: int(need * 0.6 / 0.9))
    assert agents.seeds_per_program(cfg, 2, log=lines.append) == 1
    assert re.search(r"es: 2 seeds as one program need [\d.]+ GiB .* trained 1 at a time", lines[0])
    monkeypatch.setattr(agents, "device_bytes_limit", lambda: None)
    assert agents.seeds_per_program(cfg, 5) == 5
    programs = []
    monkeypatch.setattr(agents, "seeds_per_program", lambda c, n, log=None: 2)
    monkeypatch.setattr(baselines, "_rl_program", lambda cfgs, progress: programs.append(len(cfgs)) or cfgs)
    assert baselines.rl_seeds([cfg] * 5) == [cfg] * 5 and programs == [2, 2, 1]


def test_a_group_the_allocator_refuses_trains_in_halves(monkeypatch, capsys):
    """XLA's memory analysis can say a group fits where the allocator then refuses it (5 ES
    seeds on an H200): the group is split in halves and run again, with one line saying so; any
    other error, or a refusal of a single seed, is raised as it is."""
    cfg = baselines.method_config("es", "tiny", 0, "/tmp/fit", trajectories=4)
    refusal = jax.errors.JaxRuntimeError(
        "RESOURCE_EXHAUSTED: Out of memory while trying to allocate 67.38GiB with allocator GPU_0_bfc")
    programs = []

    def program(cfgs, progress):
        programs.append(len(cfgs))
        if len(cfgs) > 2:
            raise refusal
        return cfgs

    monkeypatch.setattr(agents, "seeds_per_program", lambda c, n, log=None: n)
    monkeypatch.setattr(baselines, "_rl_program", program)
    assert baselines.rl_seeds([cfg] * 5) == [cfg] * 5
    assert programs == [5, 3, 2, 2, 1]
    assert "5 seeds as one program ran out of device memory" in capsys.readouterr().err
    assert agents.out_of_memory(refusal) and not agents.out_of_memory(ValueError("RESOURCE_EXHAUSTED"))
    monkeypatch.setattr(baselines, "_rl_program", lambda cfgs, progress: (_ for _ in ()).throw(refusal))
    with pytest.raises(jax.errors.JaxRuntimeError):
        baselines.rl_seeds([cfg])


def test_sac_q_networks_are_the_policy_size():
    """brax's make_sac_networks has one hidden size for both networks: no q_hidden to ignore."""
    assert "q_hidden" not in {f.name for f in dataclasses.fields(agents.SACConfig)}
    cfg = baselines.method_config("sac", "tiny", 0, "r", trajectories=2)
    nets = agents.sac_networks(cfg)(WORLD.frame_stack * WORLD.obs_size, 8)
    q = nets.q_network.init(jax.random.PRNGKey(0))["params"]
    widths = {k.shape[-1] for k in jax.tree.leaves(q) if k.ndim == 2} - {1}
    assert widths == {cfg.run.policy.hidden}


@pytest.mark.slow
@pytest.mark.parametrize("method", agents.BRAX_METHODS)   # QT-Opt's: tests/test_qtopt.py
def test_trains_evaluates_and_exports(method, tmp_path, monkeypatch):
    from brax.training import acting

    from deploy.robot.exported import load_export
    from deploy.sim.export import export_checkpoint
    from eval.evaluate import evaluate_checkpoint
    from training.checkpoint import load_checkpoint
    evaluators, init = [], acting.Evaluator.__init__

    def recording_init(self, *args, **kwargs):
        evaluators.append(self)
        init(self, *args, **kwargs)
    monkeypatch.setattr(acting.Evaluator, "__init__", recording_init)
    out = str(tmp_path / "table")
    n = 4 if method == "es" else 2    # ES: 2 episodes per epoch, 2 epochs
    summary = baselines.run([method], "tiny", 1, out, trajectories=n, progress=False)
    # no brax evaluator is built (its episode-reward rollout would compile an MJX episode): the
    # strict-metric curve replaces it
    assert evaluators == []
    result = json.load(open(os.path.join(out, "results", f"{method}-seed0.json")))
    assert result["final"]["goals"] == tiny().eval_goals and 0 <= result["final"]["hit_rate"] <= 1
    assert result["config"]["method"] == method and result["config"]["run"]["total_trajectories"] == n
    # a point at 0, one between, one at the end: brax's own step counts, ending at the budget
    xs = [p["trajectories"] for p in result["curve"]]
    assert len(xs) == 3 and xs[0] == 0 < xs[1] < xs[2] == n, xs
    assert result["curve"][-1]["env_steps"] == n * WORLD.horizon
    assert os.path.exists(summary["outputs"]["table"]) and method in open(summary["outputs"]["table"]).read()
    run_dir = os.path.join(out, "runs", f"{method}-seed0")
    loaded = load_checkpoint(run_dir)
    assert loaded.cfg.preset == f"baseline-{method}" and int(loaded.ck.counters.trajectories) == n
    assert loaded.cfg.total_trajectories == n
    # the curve's points, scored together at the end, are what evaluate_uniform gives each policy:
    # the last one is the saved policy
    from eval.evaluate import evaluate_uniform
    from ttmjx.world.backends import Backend, resolve_backend
    cfg = loaded.cfg
    last = evaluate_uniform(cfg.world, cfg.policy, jax.tree.map(lambda x: x[0], loaded.params),
                            Backend(cfg.world, resolve_backend(cfg.backend)), jax.random.PRNGKey(cfg.seed + 1),
                            cfg.eval_goals)
    got = {k: math.nan if result["curve"][-1][k] is None else result["curve"][-1][k] for k in last}
    assert got == pytest.approx(last, nan_ok=True)
    timing = json.load(open(os.path.join(run_dir, "timing.json")))
    assert [p[0] for p in timing["points"]] == [p["env_steps"] for p in result["curve"]]
    assert timing["env_steps"] == n * WORLD.horizon and timing["train_s"] > 0
    metrics = evaluate_checkpoint(run_dir, goals="4")
    assert metrics["goals"] == 4 and set(metrics) >= {"within_30cm", "within_20cm", "hit_rate"}
    policy, contract = load_export(export_checkpoint(run_dir, str(tmp_path / "export")))
    assert policy.spec.kind == "framestack" and policy.members == 1
    # the same cell again: skipped, same result
    again = baselines.run([method], "tiny", 1, out, trajectories=n, progress=False)
    assert again["cells_run"] == [f"{method}-seed0"]
    assert json.load(open(os.path.join(out, "results", f"{method}-seed0.json"))) == result


def test_gcsl_and_lfp_are_the_presets():
    g = baselines.method_config("gcsl", "tiny", 0, "r")
    lfp = baselines.method_config("lfp", "tiny", 0, "r")
    assert g.demos == 0 and g.practice and not lfp.practice and lfp.demos == lfp.total_trajectories
    assert dataclasses.replace(g, demos=tiny().demos, pretrain_steps=tiny().pretrain_steps, preset="tiny") == \
        dataclasses.replace(tiny(), run_dir="r")


def test_first_seed_plans_the_later_seeds_of_one_table(tmp_path):
    cells = baselines.plan(["gcsl"], "tiny", 2, str(tmp_path), first_seed=3)
    assert [(c.name, c.seed, c.config.seed) for c in cells] == [("gcsl-seed3", 3, 3), ("gcsl-seed4", 4, 4)]
