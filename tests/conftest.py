"""Test configuration: float64 for accuracy tests, strict rank promotion everywhere.

jaxrb itself never flips ``jax_enable_x64``; the test suite does, and robustness tests
build float32 params and states explicitly (``dtype=jnp.float32``).
"""

import gc
import os
import shutil
import subprocess
import sys
import tempfile

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

#: XLA:CPU's fusions through its older (LLVM IR) emitters. The suite's time is mostly
#: compilation, which these emitters did faster here: six of the slowest contact and
#: gradient tests took 16-37% less time in each of three pairs of runs side by side
#: (2026-12-02, jaxlib 0.10.2, 2 cores; benchmarks/README.md, "The test suite's XLA flag",
#: where single programs that it compiles more slowly are listed too). The programs are
#: the same HLO, with no fast math in either emitter. jaxrb itself sets no flag; the
#: notebooks' kernels and a few scripts the tests run are given XLA's defaults, as users run. Set
#: JAXRB_TEST_XLA_DEFAULTS=1 to run the suite on XLA's defaults. A jaxlib that does not
#: know the flag aborts every process given it, so it is tried first in a subprocess.
_FAST_COMPILE_FLAG = "--xla_cpu_use_fusion_emitters=false"


def _fast_compile_flag_works(flags: str) -> bool:
    """Whether a process given ``XLA_FLAGS=flags`` starts JAX and runs a program."""
    env = dict(os.environ, XLA_FLAGS=flags)
    probe = "import jax, jax.numpy as jnp; jax.block_until_ready(jax.jit(jnp.sin)(1.0))"
    try:
        return subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                              timeout=120).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


# Decided once, in the process that starts the run: the pytest-xdist workers and the
# subprocesses of the tests inherit the environment (JAXRB_TEST_XLA_FLAG_TRIED marks it).
if (not os.environ.get("JAXRB_TEST_XLA_DEFAULTS") and "JAXRB_TEST_XLA_FLAG_TRIED" not in os.environ
        and _FAST_COMPILE_FLAG not in os.environ.get("XLA_FLAGS", "")):
    os.environ["JAXRB_TEST_XLA_FLAG_TRIED"] = "1"
    _flags = f"{os.environ.get('XLA_FLAGS', '')} {_FAST_COMPILE_FLAG}".strip()
    if _fast_compile_flag_works(_flags):
        os.environ["XLA_FLAGS"] = _flags

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
