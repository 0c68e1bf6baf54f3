"""Test configuration: float64 for accuracy tests, strict rank promotion everywhere.

jaxrb itself never flips ``jax_enable_x64``; the test suite does, and robustness tests
build float32 params and states explicitly (``dtype=jnp.float32``).
"""

import gc

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


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
