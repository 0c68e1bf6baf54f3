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
    # float64 asked for without 64-bit JAX had quietly given float32 (a warning per array).
    for build in (lambda: scene.params(dtype=jnp.float64), lambda: scene.state(params, dtype=jnp.float64)):
        try:
            build()
        except ValueError as error:
            assert "jax_enable_x64" in str(error), error
        else:
            raise AssertionError("dtype=float64 accepted with x64 disabled")
    print("ok")
    """
)


def test_everything_stays_float32_with_x64_disabled():
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300,
                            env={**__import__("os").environ, "JAX_ENABLE_X64": "0"})
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stderr[-3000:]


# ------------------------------------------------ float32 inputs under x64 (the rest of the suite)


def _strong_float64(closed_jaxpr) -> list[str]:
    """Primitives of a jaxpr (and its sub-jaxprs) with a float64 value that is not weakly typed.

    Weakly typed float64 (a Python scalar such as ``0.5``) takes the other operand's dtype, so
    it leaves a float32 computation float32; a strong float64 value would promote it.
    """
    import jax
    import jax.numpy as jnp
    from jax.extend import core

    found = []

    def strong(v):
        aval = getattr(v, "aval", None)
        return getattr(aval, "dtype", None) == jnp.float64 and not getattr(aval, "weak_type", False)

    def walk(jaxpr):
        found.extend(f"constvar {v.aval}" for v in jaxpr.constvars if strong(v))
        for eqn in jaxpr.eqns:
            if any(strong(v) for v in (*eqn.invars, *eqn.outvars)):
                found.append(f"{eqn.primitive.name} {eqn.source_info.traceback}")
            for value in eqn.params.values():
                for sub in value if isinstance(value, (list, tuple)) else (value,):
                    if isinstance(sub, core.ClosedJaxpr):
                        walk(sub.jaxpr)
                    elif isinstance(sub, core.Jaxpr):
                        walk(sub)

    assert jax.config.jax_enable_x64
    walk(closed_jaxpr.jaxpr)
    return found


def test_float32_contact_steps_have_no_float64_under_x64():
    """The suite's in-process float32 tests run with x64 on. They are float32 computations only
    if nothing in a step promotes: no strong float64 constant, literal or conversion in the
    traced step (every shape pair, both contact solvers, time of impact, two integrators).
    (Their results may still differ from an x64-off process in the last bits, which a stack
    amplifies: XLA may fuse and order the float32 arithmetic differently. The gradient's
    jaxpr is checked in the x64-off process above, for free bodies: tracing a contact
    gradient takes ~40 s.)"""
    import jax
    import jax.numpy as jnp

    import jaxrb as rb

    box, ball, capsule = rb.Box((0.1, 0.1, 0.1)), rb.Sphere(0.1), rb.Capsule(0.05, 0.1)
    bodies = [rb.Body("box", shape=box, mass=1.0), rb.Body("ball", shape=ball, mass=1.0),  # every pair type
              rb.Body("capsule", shape=capsule, mass=1.0), rb.Body("box2", shape=box, mass=2.0),
              rb.Body("can", shape=rb.Cylinder(0.05, 0.1), mass=1.0),
              rb.Body("can2", shape=rb.Cylinder(0.05, 0.1), mass=1.0)]
    scene = rb.Scene(bodies, ground=rb.Plane(), contacts="all")
    params = scene.params(friction=0.5, restitution=0.5, dtype=jnp.float32)
    state = scene.state(params, position=[[0.0, 0.0, 0.1], [0.0, 0.0, 0.3], [0.3, 0.0, 0.05], [0.3, 0.0, 0.2],
                                          [0.6, 0.0, 0.1], [0.6, 0.0, 0.35]], velocity=[[0.0, 0.0, -1.0]] * 6)
    cases = [(rb.integrators.SymplecticSplitting(), "pgs"), (rb.integrators.SymplecticSplitting(), "exact"),
             (rb.integrators.RK4(), "pgs")]
    for integrator, solver in cases:
        step = rb.make_step(scene, integrator, 1e-3, contact=rb.ContactSettings(solver=solver))
        start = step.prepare(state)
        assert start.position.dtype == jnp.float32
        assert _strong_float64(jax.make_jaxpr(step)(params, start)) == [], (integrator, solver)
