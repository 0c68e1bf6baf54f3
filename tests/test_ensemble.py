"""Ensembles sharded over several devices give the same numbers as on one device.

Asking for two CPU devices must happen before JAX starts, so the check runs in a
subprocess. The errors of ``shard_ensemble`` run here, on whatever devices exist.
"""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import pytest

import jaxrb as rb

SCRIPT = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_num_cpu_devices", 2)
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp, numpy as np
    import jaxrb as rb

    assert len(jax.devices()) == 2, jax.devices()
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0)], forces=[rb.LinearDamping()])
    envs = 8
    params = jax.vmap(lambda m: scene.params(mass=m, linear_damping=0.1))(jnp.linspace(0.5, 2.0, envs))
    state = jax.vmap(lambda w: scene.state(params=None, velocity=(1.0, 0.0, 2.0),
                                           body_angular_velocity=jnp.stack([w, 2.0, -1.0])))(
        jnp.linspace(-1.0, 1.0, envs))
    step = rb.make_step(scene, rb.integrators.RK4(), 1e-3)
    run = jax.jit(jax.vmap(lambda p, s: rb.rollout(step, p, s, 200, save_every=200)[0]))
    single = run(params, state)
    sharded_params, sharded_state = rb.shard_ensemble((params, state))
    assert len(sharded_state.position.sharding.device_set) == 2
    sharded = run(sharded_params, sharded_state)
    # The result stays split over both devices: each ran its half of the ensemble.
    assert len(sharded.position.sharding.device_set) == 2
    assert sharded.position.addressable_shards[0].data.shape == (envs // 2, 1, 3)
    for a, b in zip(jax.tree.leaves(single), jax.tree.leaves(sharded)):
        # Same arithmetic on each environment, only placed differently: bitwise equal
        # up to the order XLA picks for fused operations (1e-15 in float64).
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-13)
    # Gradients through a sharded ensemble work as well.
    loss = lambda p: jnp.sum(run(p, sharded_state).position[..., 2])
    g_single = jax.grad(lambda p: jnp.sum(run(p, state).position[..., 2]))(params)
    g_sharded = jax.grad(loss)(sharded_params)
    np.testing.assert_allclose(np.asarray(g_sharded.mass), np.asarray(g_single.mass), rtol=1e-12, atol=1e-14)
    print("ok")
    """
)


def test_sharded_ensemble_equals_single_device():
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stderr[-3000:]


def test_shard_ensemble_refuses_unbatched_or_uneven_input():
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    state = scene.state()
    with pytest.raises(ValueError, match="leading ensemble axis"):
        rb.shard_ensemble(state)  # State.time is a scalar: not batched
    batched = jax.tree.map(lambda x: jnp.broadcast_to(x, (4, *x.shape)), state)
    with pytest.raises(ValueError, match="one ensemble size"):
        rb.shard_ensemble((batched, jnp.zeros((3, 2))))
    fake_devices = jax.devices() * 3  # three "devices" cannot split 4 environments
    with pytest.raises(ValueError, match="does not split evenly over 3 devices"):
        rb.shard_ensemble(batched, devices=fake_devices)
    placed = rb.shard_ensemble(batched)
    assert jnp.array_equal(placed.position, batched.position)
