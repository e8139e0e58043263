"""Shared test set-up: JAX's persistent compilation cache and CPU-friendly defaults."""
import gc
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import pytest  # noqa: E402

_cache = os.environ.get("TTMJX_JAX_CACHE", os.path.join(os.path.dirname(__file__), "..", ".jax_cache"))
jax.config.update("jax_compilation_cache_dir", os.path.abspath(_cache))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


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
