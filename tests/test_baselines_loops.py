"""The RL baselines' loops (training/baselines/ppo.py, sac.py, es.py, resumable.py): each against
brax 0.14.2's own trainer, a stopped run resumed to the uninterrupted result, and the seeds of a
method trained as one program against each seed alone. Apart from tests/test_baselines.py so the
two modules run on different workers."""
import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from eval import baselines
from training.baselines import agents
from training.baselines.env import GoalEnv
from training.runconfig import tiny

WORLD = tiny().world
# Every test here trains (and compiles) brax's and this project's RL loops: ~1,600 s of a worker's
# time with empty caches, the run with `-m slow` (pyproject.toml; docs/BENCHMARKS.md, "Ninth pass").
pytestmark = pytest.mark.slow


# -- PPO, SAC and ES with their state outside brax's call (ppo.py, sac.py, es.py, resumable.py) --
RESUMABLE = agents.BRAX_METHODS   # against brax's own trainers; QT-Opt's resume: tests/test_qtopt.py
BUDGET = {"ppo": 2, "sac": 2, "es": 4}   # trajectories: 2 epochs each (3 curve points)


# Float32 reduction order (brax pmaps SAC's epoch over one device, our loop jits it; seeds
# vmapped against alone) drifts through the many updates of a run, by an amount that depends on
# the processor's vector code: per weight array, ||ours - theirs|| / ||theirs|| was <= 5e-4 on
# the 2-core CPU these tests were written on and 1.2e-3 .. 4.6e-3 on a 2-core AMD EPYC with
# AVX-512 (2026-11-28), where an element-wise 1e-3 failed on near-zero weights. A wrong
# computation (another seed, a wrong target update) moves the arrays by O(1) in this norm.
SAC_REDUCTION_ORDER = 1e-2


def assert_close_in_norm(a, b, rel: float) -> None:
    """||a - b|| <= rel ||b|| over the whole array (float64), with the measured ratio in the
    message: the comparison for arrays that differ by reduction order only."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    assert a.shape == b.shape, (a.shape, b.shape)
    err = np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-30)
    assert err <= rel, f"relative difference {err:.3g} > {rel:g} in an array of shape {a.shape}"


def rl_run(tmp_path, method: str, name: str, stop_after: int | None = None, monkeypatch=None):
    """`method` at the tiny scale on BUDGET[method] trajectories in tmp_path/name; stop_after: a
    Ctrl-C right after the checkpoint of that step is written. Returns ((normalizer, policy),
    [point steps], timing)."""
    from training.baselines import resumable
    cfg = baselines.method_config(method, "tiny", 0, str(tmp_path / name), trajectories=BUDGET[method])
    if stop_after is not None:
        real = resumable.save

        def save_then_stop(directory, step, state, points, cfg_json):
            real(directory, step, state, points, cfg_json)
            if step == stop_after:
                raise KeyboardInterrupt
        monkeypatch.setattr(resumable, "save", save_then_stop)
    points, timing = [], {}
    final = agents.train(cfg, lambda step, p: points.append((step, p)), timing=timing)
    return final, points, timing


def device_put_replicated(x, devices):
    """What jax.device_put_replicated did (JAX 0.10 removed it; brax 0.14.2's ppo.train and
    sac.train call it): a copy per device along a new leading axis, placed as pmap places its
    outputs, strongly typed, so brax's pmapped step compiles once."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec
    place = NamedSharding(Mesh(np.asarray(devices), ("i",)), PartitionSpec("i"))
    return jax.tree.map(lambda a: jax.device_put(jnp.stack([jnp.asarray(a)] * len(devices)).astype(jnp.asarray(a).dtype),
                                                 place), x)


class NoEvaluation:
    """brax's Evaluator (ES and SAC build one) without its episodes: it only reports metrics,
    from a key split off before training, so what brax trains is the same without it, and its
    episode (compiled three times per call: brax hands it three array types) is not compiled."""

    def __init__(self, *args, **kwargs):
        pass

    def run_evaluation(self, policy_params, training_metrics, aggregate_episodes=True):
        return {}


def brax_reference(cfg, monkeypatch):
    """((normalizer, policy), [steps where brax hands its policy out]) from brax 0.14.2's own
    ppo.train / sac.train / es.train with the settings this project's loops stand for."""
    import functools

    from brax.training.agents.es import train as brax_es
    from brax.training.agents.ppo import train as brax_ppo
    from brax.training.agents.sac import train as brax_sac

    from brax.training import acting

    from training.baselines.env import wrap_fresh
    monkeypatch.setattr(jax, "device_put_replicated", device_put_replicated, raising=False)
    monkeypatch.setattr(acting, "Evaluator", NoEvaluation)
    s, steps = agents.schedule(cfg), []
    common = dict(environment=GoalEnv(cfg.run.world, cfg.reward), num_timesteps=s.num_timesteps,
                  episode_length=WORLD.horizon, wrap_env_fn=functools.partial(wrap_fresh, pool=cfg.throw_pool),
                  normalize_observations=True, seed=cfg.run.seed, num_evals=s.num_evals,
                  num_eval_envs=cfg.num_eval_envs, deterministic_eval=True)
    if cfg.method == "es":
        e = cfg.es
        out = brax_es.train(**common, population_size=e.population_size, perturbation_std=e.perturbation_std,
                            learning_rate=e.learning_rate, network_factory=agents.es_networks(cfg),
                            progress_fn=lambda step, _: steps.append(step))
    elif cfg.method == "sac":
        c = cfg.sac
        out = brax_sac.train(**common, num_envs=c.num_envs, batch_size=c.batch_size,
                             grad_updates_per_step=c.grad_updates_per_step, min_replay_size=c.min_replay_size,
                             max_replay_size=c.max_replay_size, learning_rate=c.learning_rate,
                             discounting=c.discounting, network_factory=agents.sac_networks(cfg),
                             progress_fn=lambda step, _: steps.append(step))
    else:
        p = cfg.ppo
        out = brax_ppo.train(**common, num_envs=p.num_envs, unroll_length=p.unroll_length, batch_size=p.batch_size,
                             num_minibatches=p.num_minibatches, num_updates_per_batch=p.num_updates_per_batch,
                             learning_rate=p.learning_rate, entropy_cost=p.entropy_cost, discounting=p.discounting,
                             clipping_epsilon=p.clipping_epsilon, network_factory=agents.ppo_networks(cfg),
                             run_evals=False, policy_params_fn=lambda step, *_: steps.append(step))
    return agents.policy_params(cfg, *out[1][:2]), steps


@pytest.mark.parametrize("method", RESUMABLE)
def test_the_resumable_loop_is_brax_train(method, tmp_path, monkeypatch, caplog):
    """The loop with its state outside the call computes what brax 0.14.2's ppo.train /
    sac.train / es.train computes (same seed, networks, environment and budget): the same
    final policy, and curve points where brax hands its policy out. PPO and ES: bit for bit.
    SAC: within float32 reduction order (SAC_REDUCTION_ORDER: brax pmaps its epoch, this loop jits
    it; measured on a 2-core CPU: the first layer 5e-4 relative, the rest <= 1e-4). The loop's
    epoch is lowered once in the run (a fresh state of weakly typed leaves made it
    compile twice: resumable.strongly_typed)."""
    jax.clear_caches()     # so that this run lowers its epoch itself, whatever ran before in the process
    with caplog.at_level(logging.DEBUG, logger="jax._src.interpreters.pxla"):
        ours, points, _ = rl_run(tmp_path, method, "ours")
    lowered = [r.getMessage()[:200] for r in caplog.records if r.getMessage().startswith("Compiling jit(epoch) ")]
    assert len(lowered) == 1, lowered
    theirs, steps = brax_reference(baselines.method_config(method, "tiny", 0, str(tmp_path / "brax"),
                                                           trajectories=BUDGET[method]), monkeypatch)
    assert [s for s, _ in points] == steps and steps[-1] == BUDGET[method] * WORLD.horizon and len(steps) == 3
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(theirs), strict=True):
        if method == "sac":
            assert_close_in_norm(a, b, SAC_REDUCTION_ORDER)
        else:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("method", RESUMABLE)
def test_a_stopped_run_resumes_to_the_uninterrupted_result(method, tmp_path, monkeypatch, caplog):
    """Stopped right after its first epoch's checkpoint, the same call resumes from it (one epoch
    left to run, the earlier curve points given back) and ends bit-for-bit where the
    uninterrupted run ends, curve included, with the epoch the uninterrupted run compiled (a
    restored state placed as a fresh one: resumable.uncommitted); a checkpoint of other settings
    is refused, naming what differs."""
    from training.baselines import resumable
    whole, whole_points, _ = rl_run(tmp_path, method, "whole")
    with caplog.at_level(logging.DEBUG, logger="jax._src.interpreters.pxla"):
        with pytest.raises(KeyboardInterrupt):
            rl_run(tmp_path, method, "cut", stop_after=whole_points[1][0], monkeypatch=monkeypatch)
        monkeypatch.undo()
        resumed, points, timing = rl_run(tmp_path, method, "cut")
    lowered = [r.getMessage()[:200] for r in caplog.records if r.getMessage().startswith("Compiling jit(epoch) ")]
    assert lowered == [], lowered
    assert [s for s, _ in points] == [s for s, _ in whole_points] and len(timing["epochs"]) == 1
    for a, b in zip(jax.tree.leaves((resumed, points)), jax.tree.leaves((whole, whole_points)), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    cfg = baselines.method_config(method, "tiny", 0, str(tmp_path / "cut"), trajectories=BUDGET[method])
    other = dataclasses.replace(cfg, **{method: dataclasses.replace(getattr(cfg, method), learning_rate=0.5)})
    with pytest.raises(ValueError, match=f"another configuration .*differs in {method}"):
        resumable.resume(resumable.state_dir(str(tmp_path / "cut"), method), {}, ({}, {}), agents.state_json(other))


@pytest.mark.parametrize("method", RESUMABLE)
def test_seeds_trained_together_are_each_seed_alone(method, tmp_path, monkeypatch, caplog):
    """Seeds 0 and 1 as one program (states stacked, the epoch vmapped) end where each ends
    alone, within float32 reduction order: vmapped matrix products sum in another order. ES as
    configured (measured: 2e-4 relative at most after its 2 updates); PPO and SAC at learning
    rate 0, because their 80 and 19 sequential Adam updates amplify that order into percent
    differences. Their environment steps still carry that order through the ball's contacts into
    the observation statistics, which the first layer of the final policy folds in (PPO 1.3%
    relative at most on an AMD EPYC; SAC 1e-4 there, 2e-3 on an Intel Xeon): so their end is
    compared in every layer after the first, exactly (learning rate 0: each seed's initial
    weights, from its own keys), in the curve's steps and in the policy at 0, exactly. A stop between the two
    seeds' saves of the first epoch leaves seed 0 one checkpoint ahead: the same call resumes
    both from the step they share, with the programs the stopped call compiled."""
    from training.baselines import resumable

    def cfg(seed, name):
        c = baselines.method_config(method, "tiny", seed, str(tmp_path / name), trajectories=BUDGET[method])
        return c if method == "es" else dataclasses.replace(
            c, **{method: dataclasses.replace(getattr(c, method), learning_rate=0.0)})
    seen_alone, seen = [[], []], [[], []]
    alone = [agents.train(cfg(s, f"alone{s}"), lambda step, p, s=s: seen_alone[s].append((step, p))) for s in (0, 1)]
    cfgs = [cfg(s, f"batch{s}") for s in (0, 1)]
    real, first = resumable.save, []

    def stop_before_seed1(directory, step, state, points, cfg_json):
        if step > 0 and "batch1" in directory and not first:
            first.append(step)
            raise KeyboardInterrupt
        real(directory, step, state, points, cfg_json)
    monkeypatch.setattr(resumable, "save", stop_before_seed1)
    with pytest.raises(KeyboardInterrupt):
        agents.train_seeds(cfgs)
    assert resumable.good_steps(resumable.state_dir(cfgs[0].run.run_dir, method))[-1] == first[0]
    assert resumable.good_steps(resumable.state_dir(cfgs[1].run.run_dir, method)) == [0]
    timing = {}
    with caplog.at_level(logging.DEBUG, logger="jax._src.interpreters.pxla"):
        together = agents.train_seeds(cfgs, lambda i, step, p: seen[i].append((step, p)), timing=timing)
    assert len(timing["epochs"]) == 2     # both resumed from step 0, the step they share
    again = [r.getMessage()[:120] for r in caplog.records if r.getMessage().startswith(("Compiling jit(epoch) ",
                                                                                           "Compiling jit(prefill) "))]
    assert again == [], again             # the resumed seeds run the programs the stopped call compiled
    assert [[st for st, _ in x] for x in seen] == [[st for st, _ in x] for x in seen_alone]
    for a, b in zip(jax.tree.leaves([x[0] for x in seen]), jax.tree.leaves([x[0] for x in seen_alone]), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    if method == "es":
        for a, b in zip(jax.tree.leaves(together), jax.tree.leaves(alone), strict=True):
            assert_close_in_norm(a, b, 1e-3)
    else:
        later = lambda ps: [({k: v for k, v in p.net["params"].items() if k != "dense0"}, p.norm) for p in ps]  # noqa: E731
        for a, b in zip(jax.tree.leaves(later(together)), jax.tree.leaves(later(alone)), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.allclose(jax.tree.leaves(together[0])[0], jax.tree.leaves(together[1])[0])   # two seeds
