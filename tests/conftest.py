"""Test configuration: float64 for accuracy tests, strict rank promotion everywhere.

jaxrb itself never flips ``jax_enable_x64``; the test suite does, and robustness tests
build float32 params and states explicitly (``dtype=jnp.float32``).
"""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
