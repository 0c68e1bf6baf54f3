"""Test configuration: float64 for accuracy tests, strict rank promotion everywhere.

jaxrb itself never flips ``jax_enable_x64``; the test suite does, and robustness tests
build float32 params and states explicitly (``dtype=jnp.float32``).
"""

import gc
import os
import shutil
import tempfile

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# One XLA compilation cache for the whole run, shared through the environment by the
# pytest-xdist workers and by the subprocesses the tests start (examples, notebooks,
# benchmark scripts), so a program compiled twice with the same HLO is built once (the gain
# was not measured separately: small, within the noise of one run). It is new for every run,
# so no run reuses an earlier run's programs, and it is removed when the run ends.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaxrb-test-xla-cache-")
    os.environ["JAXRB_TEST_OWNS_XLA_CACHE"] = str(os.getpid())
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.3")
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs",
                  float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))


def pytest_unconfigure(config):
    if os.environ.get("JAXRB_TEST_OWNS_XLA_CACHE") == str(os.getpid()):
        shutil.rmtree(os.environ["JAX_COMPILATION_CACHE_DIR"], ignore_errors=True)


def _memory_map_count() -> int:
    """Number of this process's memory mappings (Linux), or 0 where /proc is absent."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return 0


# Every XLA:CPU executable keeps a few memory mappings of its own until it is dropped from
# JAX's caches. One pytest-xdist worker compiles thousands of programs over the suite, and
# at Linux's default vm.max_map_count (65530) the next compile's mmap fails and XLA:CPU
# segfaults (seen in CI: a worker crashed inside backend_compile after ~25 minutes, at a
# test that passes alone). Dropping the caches after each module, and after any test that
# leaves the count high, keeps a worker far below the limit; a later module recompiles
# what it uses anyway.
_MAP_COUNT_LIMIT = 20_000


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs_after_module():
    yield
    jax.clear_caches()
    gc.collect()


@pytest.fixture(autouse=True)
def _drop_compiled_programs_if_many():
    yield
    if _memory_map_count() > _MAP_COUNT_LIMIT:
        jax.clear_caches()
        gc.collect()


def pytest_collection_modifyitems(config, items):
    """Run the long tests first: pytest-xdist then fills the end of the run with short ones,
    instead of one worker finishing a long test while the other waits. (The order is the
    same in every worker, as pytest-xdist requires.)"""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
