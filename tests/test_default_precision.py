"""The default configuration users get: x64 disabled. Everything must stay float32.

The rest of the suite enables x64 for accuracy checks, so this runs in a subprocess.
"""

import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    import jaxrb as rb
    assert not jax.config.jax_enable_x64
    def wrench(t, params, state):
        return jnp.zeros_like(state.position), 0.1 * jnp.ones_like(state.position) * jnp.cos(t)
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0),
                      rb.Body("ball", shape=rb.Sphere(0.1), density=500.0)],
                     forces=[rb.LinearDamping(), rb.ExternalWrench(wrench)])
    params = scene.params(linear_damping=0.1)
    state = scene.state(params, velocity=(1.0, 0.0, 2.0), body_angular_velocity=(0.3, 2.0, -1.0),
                        orientation=rb.spatial.euler_to_quat(0.1, 0.2, 0.3))
    for leaf in jax.tree.leaves((params, state)):
        assert leaf.dtype == jnp.float32, leaf.dtype
    for integrator in [rb.integrators.ExplicitEuler(), rb.integrators.SemiImplicitEuler(), rb.integrators.RK4()]:
        step = rb.make_step(scene, integrator, 1e-3)
        final, traj = rb.rollout(step, params, state, 200, save_every=50)
        for leaf in jax.tree.leaves((final, traj)):
            assert leaf.dtype == jnp.float32 and np.all(np.isfinite(leaf)), (integrator, leaf.dtype)
        loss = lambda p: jnp.sum(rb.rollout(step, p, state, 50)[0].position)
        jaxpr = str(jax.make_jaxpr(jax.grad(loss))(params))
        assert "f64" not in jaxpr, integrator
        grads = jax.grad(loss)(params)
        assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))
        assert abs(float(grads.linear_damping[0])) > 0
    print("ok")
    """
)


def test_everything_stays_float32_with_x64_disabled():
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300,
                            env={**__import__("os").environ, "JAX_ENABLE_X64": "0"})
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stderr[-3000:]
