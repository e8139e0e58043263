"""Shared test set-up: JAX's persistent compilation cache (this process and every subprocess a
test starts), CPU-friendly defaults, the session's shared fixtures (tiny's oracle demonstrations
and the recorded tiny run, each made once for every module and every xdist worker that uses
them) and the order modules start in (the longest first, so that two workers finish together).

The suite runs on 2 workers (pyproject.toml: `-n 2 --dist loadfile`): a module's tests stay in
one worker (module fixtures are made once), modules are handed out in the order below."""
import fcntl
import gc
import json
import os
import shutil

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import pytest  # noqa: E402

_cache = os.environ.get("TTMJX_JAX_CACHE", os.path.join(os.path.dirname(__file__), "..", ".jax_cache"))
_cache = os.path.abspath(_cache)
jax.config.update("jax_compilation_cache_dir", _cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
# Subprocesses (`ttmjx ...`, scripts) read and fill the same cache: `ttmjx` through
# TTMJX_JAX_CACHE (ttmjx/cli.py enable_compile_cache), plain Python through JAX's variables.
os.environ["TTMJX_JAX_CACHE"] = _cache
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _cache)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")



if os.environ.get("TTMJX_COMPILE_LOG"):          # opt-in profile: tests/compile_log.py
    import compile_log
    compile_log.install(os.path.abspath(os.environ["TTMJX_COMPILE_LOG"]))

    def pytest_runtest_logstart(nodeid, location):
        compile_log.set_test(nodeid)


def machine_stalled(summary: dict, stats: dict) -> bool:
    """Whether a session over loopback (a runner summary, `ttmjx robot serve`'s stats) was held
    up by the computer, not the wire: the runner missed tick deadlines or saw its joints go stale
    (nothing is lost over loopback), or serve's real-time loop paused over 100 ms."""
    return (summary["faults"].get("skipped", 0) > 0 or summary["faults"].get("joint_stale", 0) > 0
            or stats["counts"].get("loop_gaps_over_100ms", 0) > 0)


def private_compilation_cache(directory) -> dict:
    """Environment variables that give a subprocess its own copy of the session's compilation
    cache, for a child whose writes are cut short (a file-size limit): JAX writes an entry in
    place and keeps it when the write fails, and every later process that needs that program
    would read the truncated entry and compile it again."""
    shutil.copytree(_cache, directory, dirs_exist_ok=True)
    return {"TTMJX_JAX_CACHE": str(directory), "JAX_COMPILATION_CACHE_DIR": str(directory)}


# Modules in the order they start, longest first (seconds of a worker's time, measured on 2 cores
# with --durations=0: docs/BENCHMARKS.md "The test loop"); the rest follow in their collection
# order. With two workers the two longest run side by side and the short ones fill in at the end.
# pyproject.toml passes --no-loadscope-reorder, or xdist would order modules by their test count.
# test_physics.py moved from 4th to the end: its MJX runs compile without XLA:CPU's fusion
# emitters since 98224ff (ttmjx/tools/calibration.py), ~30 s with a cold cache instead of ~190 s.
FIRST = ("test_baselines_loops.py", "test_trainer.py", "test_bad_input.py", "test_baselines.py",
         "test_qtopt.py", "test_paper_bootstrap.py", "test_seeds.py", "test_cli.py", "test_striker.py",
         "test_training_core.py", "test_timing.py", "test_ablate.py", "test_models.py",
         "test_sharding.py", "test_bootstrap.py", "test_drivers.py", "test_world.py",
         "test_export.py", "test_es.py", "test_cell_cli.py", "test_deploy_runner.py", "test_physics.py")


# The slow set (`-m slow`, pyproject.toml; docs/BENCHMARKS.md "Ninth pass"): marked with
# @pytest.mark.slow in their modules, and here by node id the parametrized cases that are slow
# where their siblings are not. The README's command runs the rest; CI (.ci/run) runs
# both sets. Marked with @pytest.mark.slow in their own modules: test_baselines_loops (all),
# test_baselines, test_trainer, test_qtopt, test_paper_bootstrap, test_timing, test_cli, test_bootstrap.
SLOW_ELSEWHERE = (   # parametrized cases slow where the module's other cases are not
    "test_bad_input.py::test_a_damaged_config_json_is_repaired_from_the_checkpoint_on_resume[empty]",
    "test_bad_input.py::test_a_damaged_config_json_is_repaired_from_the_checkpoint_on_resume[deleted]",
)


@pytest.hookimpl(tryfirst=True)            # before `-m` selects on the marks
def pytest_collection_modifyitems(config, items):
    for item in items:
        name = item.nodeid.split("/")[-1]
        if name in SLOW_ELSEWHERE or name.split("[")[0] in SLOW_ELSEWHERE:
            item.add_marker(pytest.mark.slow)
    rank = {name: i for i, name in enumerate(FIRST)}
    module = lambda item: os.path.basename(item.nodeid.split("::")[0])  # noqa: E731
    items.sort(key=lambda item: rank.get(module(item), len(FIRST)))   # stable: a module stays in order


@pytest.fixture(autouse=True, scope="module")
def _compiled_code_released_after_each_module():
    """Every XLA:CPU executable JAX keeps holds its own memory mappings; the whole suite in one
    process kept ~65,000 of them by tests/test_trainer.py, the kernel's default vm.max_map_count
    (65,530), and the next compile failed with LLVM's "Cannot allocate memory" (CI, 2026-11-24).
    Each module's compiled functions are dropped when it ends (its module fixtures are torn down
    before this one); the persistent cache above still serves a later module that needs the
    same program."""
    yield
    jax.clear_caches()
    gc.collect()


def made_once(tmp_path_factory, name, make):
    """make(directory) -> a JSON-able result, run once per test session: under xdist the first
    worker that asks makes it in a directory all workers see (the session's base temporary
    directory) while the others wait for it, then read its result."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        return make(tmp_path_factory.mktemp(name))
    root = tmp_path_factory.getbasetemp().parent          # shared by this session's workers
    done = root / f"{name}.json"
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not done.exists():
                directory = root / name
                directory.mkdir()
                result = make(directory)
                done.write_text(json.dumps(result))
            return json.loads(done.read_text())
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def oracle_demos(tmp_path_factory):
    """tiny's 200 oracle (goal-directed striker) narrow demonstrations, seed 5: those of
    tests/data/before_renovation.json, collected once for every module (read-only)."""
    def make(d):
        from training import runconfig
        from ttmjx.tools import demos
        from ttmjx.world import record
        traj = demos.collect(runconfig.tiny().world, "oracle", 200, seed=5)
        record.save(str(d), traj, {"source": "oracle", "distribution": "narrow", "seed": 5})
        return str(d)
    return made_once(tmp_path_factory, "oracle_demos", make)


@pytest.fixture(scope="session")
def recorded_tiny_run(oracle_demos, tmp_path_factory):
    """One uninterrupted tiny run as the recordings were made (tests/recorded.py tiny_recorded),
    every checkpoint kept: tests/test_trainer.py's reference for resumes and
    tests/test_sharding.py's 1-device run, trained once (read-only: copy it to resume it)."""
    from pathlib import Path

    def make(d):
        from eval.evaluate import training_evaluation
        from recorded import tiny_recorded
        from training.trainer import Run
        cfg = tiny_recorded(oracle_demos, d)
        return [str(d), Run(cfg, evaluation=training_evaluation, progress=False).run()]
    d, out = made_once(tmp_path_factory, "recorded_tiny_run", make)
    return Path(d), out
