"""jit, vmap, grad, jacfwd, no retracing, float32 robustness and the NaN debug mode."""

import contextlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrb as rb
from jaxrb import spatial

INTEGRATORS = [getattr(rb.integrators, name)() for name in rb.integrators.__all__ if name != "Integrator"]
IDS = [type(i).__name__ for i in INTEGRATORS]


def torque(t, params, state):
    return jnp.zeros_like(state.position), 0.3 * jnp.stack([jnp.cos(t), jnp.sin(t), 0.0 * t])[None] * jnp.ones(
        (state.position.shape[0], 1)
    )


def make_scene(num_bodies=2):
    bodies = [rb.Body(f"b{i}", shape=rb.Box((0.1 + 0.05 * i, 0.2, 0.3)), mass=1.0 + i) for i in range(num_bodies)]
    return rb.Scene(bodies, gravity=(0.0, 0.0, -9.81),
                    forces=[rb.LinearDamping(), rb.AngularDamping(), rb.ExternalWrench(torque)])


def initial(scene, dtype=None):
    params = scene.params(linear_damping=0.2, angular_damping=0.01, dtype=dtype)
    n = scene.num_bodies
    state = scene.state(
        params,
        position=np.arange(3 * n, dtype=float).reshape(n, 3),
        orientation=spatial.quat_from_axis_angle(jnp.array([1.0, 2.0, -1.0]), 0.3 * jnp.arange(1, n + 1)),
        velocity=np.tile([1.0, -0.5, 2.0], (n, 1)),
        body_angular_velocity=np.tile([0.4, 3.0, -1.0], (n, 1)),
        dtype=dtype,
    )
    return params, state


def assert_trees_close(a, b, **kw):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(x, y, **kw)


@pytest.mark.parametrize("integrator", INTEGRATORS, ids=IDS)
def test_jit_equals_eager(integrator):
    scene = make_scene()
    params, state = initial(scene)
    step = rb.make_step(scene, integrator, 1e-2)
    state = step.prepare(state)
    jitted = step(params, state)
    with jax.disable_jit():
        eager = integrator.step(scene, params, state, 1e-2)
    assert_trees_close(jitted, eager, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("integrator", INTEGRATORS, ids=IDS)
def test_vmap_equals_python_loop(integrator):
    scene = make_scene()
    params, state = initial(scene)
    step = rb.make_step(scene, integrator, 1e-2)
    masses = jnp.stack([params.mass * s for s in (0.5, 1.0, 2.0)])
    spins = jnp.stack([state.angular_momentum * s for s in (1.0, -0.3, 2.0)])

    def run(mass, angular_momentum):
        p = eqx.tree_at(lambda p: p.mass, params, mass)
        s = eqx.tree_at(lambda s: s.angular_momentum, state, angular_momentum)
        return rb.rollout(step, p, s, 50)[0]

    batched = jax.vmap(run)(masses, spins)
    for i in range(3):
        single = run(masses[i], spins[i])
        assert_trees_close(jax.tree.map(lambda x, i=i: x[i], batched), single, rtol=1e-12, atol=1e-14)


def test_changing_params_or_state_values_does_not_retrace():
    traces = []

    def counting_wrench(t, params, state):
        traces.append(1)  # runs once per trace, never at run time
        return jnp.zeros_like(state.position), jnp.zeros_like(state.position)

    scene = rb.Scene([rb.Body("b", shape=rb.Sphere(0.1), mass=1.0)], forces=[rb.ExternalWrench(counting_wrench)])
    step = rb.make_step(scene, rb.integrators.RK4(), 1e-2)
    for mass, speed in [(1.0, 0.0), (2.0, 1.0), (3.5, -4.0)]:
        params = scene.params(mass=mass, inertia=(0.1 * mass, 0.2, 0.3))
        state = scene.state(params, velocity=(speed, 0.0, 0.0), angular_velocity=(speed, 1.0, 0.0))
        final, _ = rb.rollout(step, params, state, 20)
        np.testing.assert_allclose(final.velocity[0, 0], speed)  # values really flowed through
    # RK4 evaluates the wrench 4 times per step: one trace of the scan body = 4 calls.
    assert len(traces) == 4

    # The same with equinox's own trace counter around a user-level jitted function.
    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def final_height(params, state):
        return rb.rollout(step, params, state, 10)[0].position[0, 2]

    for mass in (1.0, 2.0, 3.0):
        params = scene.params(mass=mass)
        final_height(params, scene.state(params, position=(0.0, 0.0, mass)))


def pose_loss(final):
    # A smooth scalar of the final pose: weighted position and attitude entries.
    r = rb.rotation_matrix(final)
    return jnp.sum(final.position * jnp.array([[0.3, -0.7, 1.1]])) + jnp.sum(r * jnp.arange(9.0).reshape(1, 3, 3))


def trajectory_loss(run):
    """``(params, state) -> scalar`` from ``run(params, state) -> (final, trajectory)``: the
    final pose and the first body's attitude along the way."""
    def value(p, s):
        final, trajectory = run(p, s)
        return pose_loss(final) + jnp.sum(trajectory.orientation[:, 0, 1] ** 2)
    return value


@pytest.mark.parametrize("integrator", INTEGRATORS, ids=IDS)
def test_gradients_of_a_one_second_rollout_match_finite_differences(integrator):
    scene = make_scene(num_bodies=1)
    params, state = initial(scene)
    step = rb.make_step(scene, integrator, 1e-2)

    def loss(mass, inertia_entries, velocity, omega_body):
        inertia = jnp.array([[inertia_entries[0], inertia_entries[3], inertia_entries[4]],
                             [inertia_entries[3], inertia_entries[1], inertia_entries[5]],
                             [inertia_entries[4], inertia_entries[5], inertia_entries[2]]])
        p = eqx.tree_at(lambda p: (p.mass, p.inertia), params, (mass[None], inertia[None]))
        l_world = spatial.quat_rotate(state.orientation[0], spatial.matvec(inertia, omega_body))
        s = eqx.tree_at(lambda s: (s.velocity, s.angular_momentum), state, (velocity[None], l_world[None]))
        return pose_loss(rb.rollout(step, p, s, 100)[0])

    i0 = params.inertia[0]
    args = (jnp.asarray(params.mass[0]), jnp.array([i0[0, 0], i0[1, 1], i0[2, 2], 0.001, -0.002, 0.0015]),
            jnp.array([1.0, -0.5, 2.0]), jnp.array([0.4, 3.0, -1.0]))
    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))(*args)
    fwd = jax.jit(jax.jacfwd(loss, argnums=(0, 1, 2, 3)))(*args)
    # Every perturbed loss in one compiled, vmapped call (one compile instead of 26).
    batched_loss = jax.jit(jax.vmap(loss))
    eps = 1e-6
    for k, (arg, g, gf) in enumerate(zip(args, grads, fwd, strict=True)):
        flat = np.atleast_1d(np.asarray(arg, dtype=float))
        shifts = np.concatenate([np.eye(flat.size), -np.eye(flat.size)]) * eps
        batch = [jnp.broadcast_to(a, (len(shifts), *np.shape(a))) for a in args]
        batch[k] = jnp.asarray((flat[None] + shifts).reshape(len(shifts), *np.shape(arg)))
        values = np.asarray(batched_loss(*batch))
        fd = (values[: flat.size] - values[flat.size :]) / (2 * eps)
        # Acceptance: <= 1e-6 relative, entry by entry. Central differences with eps = 1e-6
        # in float64 are accurate to ~1e-9 here, so 1e-6 tests the gradient, not the
        # reference; the 1e-10 absolute floor only matters for entries that are ~0.
        np.testing.assert_allclose(np.atleast_1d(g), fd, rtol=1e-6, atol=1e-10)
        np.testing.assert_allclose(np.atleast_1d(gf), np.atleast_1d(g), rtol=1e-10, atol=1e-12)
        assert np.max(np.abs(fd)) > 1e-3  # the loss really depends on this argument


def test_gradient_of_checkpointed_rollout_matches_plain():
    scene = make_scene(num_bodies=1)
    params, state = initial(scene)
    step = rb.make_step(scene, rb.integrators.RK4(), 1e-2)

    def loss(params, checkpoint):
        return pose_loss(rb.rollout(step, params, state, 100, save_every=10, checkpoint=checkpoint)[0])

    g_plain = jax.grad(loss)(params, False)
    g_ckpt = jax.grad(loss)(params, True)
    assert_trees_close(g_plain, g_ckpt, rtol=1e-12, atol=1e-14)


def test_gradient_at_rest_is_finite():
    """A body at rest (omega = 0) is where norms of omega would give NaN gradients."""
    scene = rb.Scene([rb.Body("b", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0)], gravity=None)
    params = scene.params()
    state = scene.state(params)
    for integrator in INTEGRATORS:
        step = rb.make_step(scene, integrator, 1e-2)
        # One jitted program per integrator. (This test was where CI's workers segfaulted
        # once they ran out of memory mappings; the cause and the fix are in conftest.py.)
        g = jax.jit(jax.grad(lambda s, step=step: pose_loss(rb.rollout(step, params, s, 10)[0])))(step.prepare(state))
        for leaf in jax.tree.leaves(g):
            assert np.all(np.isfinite(leaf))


@pytest.mark.parametrize("integrator", INTEGRATORS, ids=IDS)
def test_float32_robustness_at_high_spin(integrator):
    """float32, |omega| h = 0.1, 1e4 steps: finite, unit quaternion, L kept, energy bounded."""
    scene = rb.Scene([rb.Body("b", mass=1.0, inertia=(1.0, 2.0, 3.0))], gravity=None)
    params = scene.params(dtype=jnp.float32)
    omega0 = np.array([-0.3, 0.9, -0.5])
    h = 0.1 / np.linalg.norm(omega0)
    state = scene.state(params, body_angular_velocity=omega0, dtype=jnp.float32)
    step = rb.make_step(scene, integrator, h)
    _, traj = rb.rollout(step, params, state, 10_000, save_every=100)
    for leaf in jax.tree.leaves(traj):
        assert leaf.dtype == jnp.float32
        assert np.all(np.isfinite(leaf))
    # |q| = 1 to float32 round-off (the quaternion is renormalised each step).
    np.testing.assert_allclose(np.linalg.norm(traj.orientation[:, 0], axis=-1), 1.0, atol=1e-6)
    energy = np.asarray(jax.vmap(lambda s: rb.kinetic_energy(params, s))(traj))[:, 0]
    e0 = float(rb.kinetic_energy(params, state)[0])
    if isinstance(integrator, rb.integrators.ImplicitGyroscopic):
        # The one method that recomputes L (from the implicit body-frame solve): it is
        # dissipative instead, energy never rising above float32 round-off (2.4e-7 per step).
        assert np.all(np.diff(energy) <= 1e-5 * e0)
        return
    # L is the state: torque-free it is exactly unchanged, in any precision.
    l_start = jnp.broadcast_to(state.angular_momentum, traj.angular_momentum.shape)
    np.testing.assert_array_equal(traj.angular_momentum, l_start)
    if integrator.order == 4:
        # RK4 stays at float32 round-off plus its O(h^4) drift (measured 3.8e-5).
        assert np.max(np.abs(energy / e0 - 1)) < 1e-4
    else:
        # The first-order methods drift a lot (measured: semi-implicit Euler +127%,
        # explicit Euler -22% in this axis order, identical in float64, so it is the method, not round-off).
        # Because L is exact and the attitude stays a rotation, the energy L.I^-1 L / 2
        # can never leave the band [|L|^2 / 2 I_max, |L|^2 / 2 I_min]: no blow-up, no NaN.
        l_sq = float(np.sum(np.asarray(state.angular_momentum[0], dtype=float) ** 2))
        assert np.all(energy >= l_sq / (2 * 3.0) * (1 - 1e-6))
        assert np.all(energy <= l_sq / (2 * 1.0) * (1 + 1e-6))


def test_debug_mode_reports_nan_inside_jit():
    def bad_wrench(t, params, state):
        blow_up = jnp.where(t > 0.05, jnp.nan, 0.0)
        return jnp.zeros_like(state.position) + blow_up, jnp.zeros_like(state.position)

    scene = rb.Scene([rb.Body("b", shape=rb.Sphere(0.1), mass=1.0)], forces=[rb.ExternalWrench(bad_wrench)])
    params = scene.params()
    state = scene.state(params)
    quiet = rb.make_step(scene, rb.integrators.RK4(), 1e-2)
    final, _ = rb.rollout(quiet, params, state, 10)
    assert not np.all(np.isfinite(final.velocity))  # without debug the NaN propagates ...
    loud = rb.make_step(scene, rb.integrators.RK4(), 1e-2, debug=True)
    with pytest.raises(Exception, match="NaN or infinite"):  # ... with debug it is reported
        jax.block_until_ready(rb.rollout(loud, params, state, 10))


def test_rollout_include_initial_and_replace():
    scene = make_scene(num_bodies=1)
    params, state = initial(scene)
    for integrator in INTEGRATORS:  # ExplicitEuler's carried rotation matrix included
        step = rb.make_step(scene, integrator, 1e-2)
        final, traj = rb.rollout(step, params, state, 20, save_every=5, include_initial=True)
        assert traj.position.shape == (5, 1, 3)
        np.testing.assert_array_equal(traj.position[0], state.position)
        np.testing.assert_array_equal(traj.position[-1], final.position)
    heavier = params.replace(mass=params.mass * 2)
    assert float(heavier.mass[0]) == 2 * float(params.mass[0]) and heavier.inertia is params.inertia
    moved = state.replace(position=state.position + 1.0)
    np.testing.assert_array_equal(moved.position, state.position + 1.0)



def _bouncing_ball(dtype=None):
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-2)
    params = scene.params(restitution=0.8, friction=0.5, dtype=dtype)
    # 0.35 m clearance, 0.3 s: the ball lands and bounces inside the rollout.
    state = step.prepare(scene.state(params, position=(0.0, 0.0, 0.45), velocity=(0.3, 0.0, 0.0),
                                     angular_velocity=(0.0, 2.0, 0.0), dtype=dtype))
    return step, params, state


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32], ids=["float64", "float32"])
def test_chunked_recording_equals_the_step_by_step_loop(dtype):
    """rollout(save_every=1) records a small scene's states in chunks of steps (a faster
    loop on XLA:CPU): the same trajectory as the step-by-step loop, bit for bit, alone and
    under vmap."""
    from jaxrb.simulate import _chunk_length, _scan_steps

    step, params, state = _bouncing_ball(dtype)
    assert state.position.dtype == dtype
    steps = 30
    chunk = _chunk_length(state, steps)
    assert chunk > 1 and steps % chunk == 0  # the chunked path is the one under test

    def by_step(p, s):
        return _scan_steps(step, p, s, steps, 1, False, 1)

    with _counting_free_attempts() as attempts:
        final, traj = jax.jit(lambda p, s: rb.rollout(step, p, s, steps))(params, state)
    assert attempts  # the chunks were first tried as free flight (see simulate._speculative)
    final_ref, traj_ref = jax.jit(by_step)(params, state)
    assert traj.position.shape == (steps, 1, 3)
    assert float(traj_ref.position[:, 0, 2].min()) < 0.11  # it reached the ground and bounced
    for x, y in zip(jax.tree.leaves((final, traj)), jax.tree.leaves((final_ref, traj_ref)), strict=True):
        np.testing.assert_array_equal(x, y)

    # Members that disagree: the last one (2 m) never comes near the ground, so its second
    # chunk is free flight while the others' is not.
    heights = jnp.array([0.45, 0.6, 2.0], dtype)
    starts = jax.vmap(lambda z: state.replace(position=state.position.at[0, 2].set(z)))(heights)
    batched = jax.jit(jax.vmap(lambda s: rb.rollout(step, params, s, steps)[1].position))(starts)
    for i in range(len(heights)):
        one = jax.tree.map(lambda x, i=i: x[i], starts)
        np.testing.assert_array_equal(batched[i], jax.jit(by_step)(params, one)[1].position)


@contextlib.contextmanager
def _counting_free_attempts():
    """Records each trace of a free step by the chunked rollout's free-flight attempt."""
    import jaxrb.simulate as simulate

    calls, original = [], simulate.free_step
    jax.clear_caches()  # a rollout traced earlier in this process would not be traced again

    def counted(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    simulate.free_step = counted
    try:
        yield calls
    finally:
        simulate.free_step = original


@pytest.mark.slow
def test_free_chunks_have_the_derivatives_of_the_step_by_step_loop():
    """A bouncing ball's chunks, tried as free flight and kept or run again as contact
    steps: reverse mode with respect to the params and the state, and forward mode under
    vmap (the fitters' pattern), as through the step-by-step loop, across the impact."""
    from jaxrb.simulate import _chunk_length, _scan_steps

    step, params, state = _bouncing_ball()
    # A lighter contact step (no time-of-impact search, fewer sweeps) compiles in a
    # fraction of the time; the chunks do not depend on what the contact step does.
    step = rb.make_step(step.scene, step.integrator, step.dt, contact=rb.ContactSettings(
        time_of_impact=False, iterations=4, impact_iterations=2, position_iterations=2))
    steps = 30
    assert _chunk_length(state, steps) > 1

    def loss(run):
        def value(p, s):
            final, trajectory = run(p, s)
            return jnp.sum(trajectory.position[:, 0, 2] ** 2) + jnp.sum(final.velocity ** 2)
        return value

    chunked = loss(lambda p, s: rb.rollout(step, p, s, steps))
    by_step = loss(lambda p, s: _scan_steps(step, p, s, steps, 1, False, 1))
    with _counting_free_attempts() as attempts:
        g = jax.jit(jax.grad(chunked, argnums=(0, 1)))(params, state)
    assert attempts
    g_ref = jax.jit(jax.grad(by_step, argnums=(0, 1)))(params, state)
    assert_trees_close(g, g_ref, rtol=1e-13, atol=1e-13)
    assert abs(float(g_ref[0].restitution[0])) > 1e-2  # the impact is inside the rollout

    def heights(e, z):
        s = state.replace(position=state.position.at[0, 2].set(z))
        return rb.rollout(step, params.replace(restitution=e), s, steps)[1].position[:, 0, 2]

    def heights_by_step(e, z):
        s = state.replace(position=state.position.at[0, 2].set(z))
        return _scan_steps(step, params.replace(restitution=e), s, steps, 1, False, 1)[1].position[:, 0, 2]

    zs = jnp.array([0.45, 2.0])  # one bounces, one stays in flight
    jac = jax.jit(jax.vmap(jax.jacfwd(heights), in_axes=(None, 0)))(params.restitution, zs)
    ref = jax.jit(jax.vmap(jax.jacfwd(heights_by_step), in_axes=(None, 0)))(params.restitution, zs)
    np.testing.assert_allclose(jac, ref, rtol=1e-12, atol=1e-15)
    assert float(jnp.max(jnp.abs(jac[0]))) > 1e-3 and float(jnp.max(jnp.abs(jac[1]))) == 0.0


@pytest.mark.slow
def test_free_segments_equal_the_step_by_step_loop_with_its_derivatives():
    """rollout(save_every=k) of a scene with contacts tries each segment of k steps as free
    flight first: the recorded states bit for bit and the gradients (checkpointed) as
    through the step-by-step loop, across the impact; and the states of vmapped members
    that disagree (not checkpointed)."""
    from jaxrb.simulate import _scan_steps

    step, params, state = _bouncing_ball()
    step = rb.make_step(step.scene, step.integrator, step.dt, contact=rb.ContactSettings(
        time_of_impact=False, iterations=4, impact_iterations=2, position_iterations=2))
    steps, every = 30, 5

    def loss(run):
        def value(p, s):
            final, trajectory = run(p, s)
            return jnp.sum(trajectory.position[:, 0, 2] ** 2) + jnp.sum(final.velocity ** 2), trajectory
        return jax.jit(jax.value_and_grad(value, argnums=(0, 1), has_aux=True))

    def by_step(p, s):
        final, trajectory = _scan_steps(step, p, s, steps, 1, False, 1)
        return final, jax.tree.map(lambda x: x[every - 1::every], trajectory)

    (value_ref, traj_ref), g_ref = loss(by_step)(params, state)
    z = traj_ref.position[:, 0, 2]
    assert float(z[-1]) > float(z[-2])  # it bounced in the last segment, the others are free flight
    assert abs(float(g_ref[0].restitution[0])) > 1e-2  # the impact is inside the rollout
    # Checkpointed here (the derivative then recomputes each segment's attempt and
    # fallback); without, below, under vmap (one compiled program fewer for CI).
    with _counting_free_attempts() as attempts:
        (value, traj), g = loss(lambda p, s: rb.rollout(step, p, s, steps, save_every=every, checkpoint=True))(
            params, state)
    assert attempts  # the segments were first tried as free flight
    for x, y in zip(jax.tree.leaves(traj), jax.tree.leaves(traj_ref), strict=True):
        np.testing.assert_array_equal(x, y)
    assert float(value) == float(value_ref)
    assert_trees_close(g, g_ref, rtol=1e-13, atol=1e-13)

    # Members that disagree: the last one (2 m) never comes near the ground.
    heights = jnp.array([0.45, 2.0])
    starts = jax.vmap(lambda z: state.replace(position=state.position.at[0, 2].set(z)))(heights)
    batched = jax.jit(jax.vmap(lambda s: rb.rollout(step, params, s, steps, save_every=every)[1].position))(starts)
    for i in range(len(heights)):
        one = jax.tree.map(lambda x, i=i: x[i], starts)
        np.testing.assert_array_equal(batched[i], jax.jit(by_step)(params, one)[1].position)


def test_long_segments_are_tried_as_free_flight_in_parts():
    """A segment longer than a chunk is tried as free flight in parts (the largest divisor
    of save_every from 8 to 16 steps), not whole: a failed attempt is discarded whole, and
    a 2,554-step segment with three bounces ran 2.4x slower tried whole. Where save_every
    has no such divisor, its steps run as contact steps. Either way the states are those
    of the step-by-step loop, bit for bit, across the impact."""
    from jaxrb.simulate import MAX_CHUNK, MIN_ATTEMPT, _attempt_length, _scan_steps

    assert [_attempt_length(n) for n in (5, 16, 17, 40, 64, 1000, 3000, 2554, 37)] == [
        5, 16, None, 10, 16, 10, 15, None, None]
    for n in range(2, 200):
        length = _attempt_length(n)
        assert length is None or (n % length == 0 and (length == n <= MAX_CHUNK or MIN_ATTEMPT <= length <= MAX_CHUNK))

    step, params, state = _bouncing_ball()
    step = rb.make_step(step.scene, step.integrator, step.dt, contact=rb.ContactSettings(
        time_of_impact=False, iterations=4, impact_iterations=2, position_iterations=2))
    for steps, every, tried in [(80, 40, True), (74, 37, False)]:
        with _counting_free_attempts() as attempts:
            final, traj = jax.jit(lambda p, s, n=steps, k=every: rb.rollout(step, p, s, n, save_every=k))(
                params, state)
        assert bool(attempts) == tried
        final_ref, traj_ref = jax.jit(lambda p, s, n=steps: _scan_steps(step, p, s, n, 1, False, 1))(params, state)
        assert float(traj_ref.velocity[:, 0, 2].max()) > 1.0  # it fell from rest and bounced
        np.testing.assert_array_equal(traj.position, traj_ref.position[every - 1::every])
        for x, y in zip(jax.tree.leaves(final), jax.tree.leaves(final_ref), strict=True):
            np.testing.assert_array_equal(x, y)


def test_chunked_recording_has_the_derivatives_of_the_step_by_step_loop():
    """Reverse mode with respect to both arguments and to either alone, forward mode, and
    both under vmap in either order, as through the plain loop. (A free body: the nested
    loops do not depend on the scene, and its programs compile in seconds.)"""
    from jaxrb.simulate import _chunk_length, _scan_steps

    scene = make_scene(num_bodies=1)
    params, state = initial(scene)
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-2)
    steps = 40
    assert _chunk_length(state, steps) > 1

    chunked = trajectory_loss(lambda p, s: rb.rollout(step, p, s, steps))
    by_step = trajectory_loss(lambda p, s: _scan_steps(step, p, s, steps, 1, False, 1))
    g_ref = jax.jit(jax.grad(by_step, argnums=(0, 1)))(params, state)
    g = jax.jit(jax.grad(chunked, argnums=(0, 1)))(params, state)
    assert_trees_close(g, g_ref, rtol=1e-13, atol=1e-13)
    assert_trees_close(jax.jit(jax.grad(chunked))(params, state), g_ref[0], rtol=1e-13, atol=1e-13)
    assert_trees_close(jax.jit(jax.grad(chunked, argnums=1))(params, state), g_ref[1], rtol=1e-13, atol=1e-13)
    d_mass = jax.jit(jax.jacfwd(lambda m: chunked(params.replace(mass=m), state)))(params.mass)
    np.testing.assert_allclose(d_mass, g_ref[0].mass, rtol=1e-12)
    assert float(jnp.max(jnp.abs(g_ref[0].inertia))) > 1e-3  # the loss depends on the attitude

    # Two starting heights, vmapped inside and outside jacfwd (the fitters' pattern; a
    # custom JVP tried here once returned this Jacobian with its axes swapped).
    def heights(m, z):
        s = state.replace(position=state.position.at[0, 2].set(z))
        return rb.rollout(step, params.replace(mass=m), s, steps)[1].position[:, 0, 2]

    zs = jnp.array([1.0, 2.0])
    inside = jax.jit(jax.vmap(jax.jacfwd(heights), in_axes=(None, 0)))(params.mass, zs)
    outside = jax.jit(jax.jacfwd(lambda m: jax.vmap(heights, in_axes=(None, 0))(m, zs)))(params.mass)
    assert inside.shape == outside.shape == (2, steps, 1)
    np.testing.assert_allclose(inside, outside, rtol=1e-13, atol=1e-15)
    for i, z in enumerate(zs):
        s = state.replace(position=state.position.at[0, 2].set(z))
        ref = jax.jacfwd(lambda m, s=s: _scan_steps(step, params.replace(mass=m), s, steps, 1, False, 1)[1]
                         .position[:, 0, 2])(params.mass)
        np.testing.assert_allclose(inside[i], ref, rtol=1e-12, atol=1e-15)
    assert float(jnp.max(jnp.abs(outside))) > 1e-6  # linear damping: the heights depend on the mass


@pytest.mark.parametrize("integrator", [rb.integrators.SymplecticSplitting(), rb.integrators.RK4()],
                         ids=["SymplecticSplitting", "RK4"])
def test_a_users_own_loop_of_steps_has_the_derivatives_of_rollout(integrator):
    """``jax.lax.scan`` over ``step(params, state)`` (each call checkpointed, as rollout's
    steps are) against rollout: the same gradient with respect to params and state, and
    the same forward-mode derivative."""
    scene = make_scene(num_bodies=1)
    params, state = initial(scene)
    step = rb.make_step(scene, integrator, 1e-2)
    state = step.prepare(state)
    steps = 30

    def by_hand(p, s):
        def body(s, _):
            s = step(p, s)
            return s, s
        return jax.lax.scan(body, s, None, length=steps)

    own, ref = trajectory_loss(by_hand), trajectory_loss(lambda p, s: rb.rollout(step, p, s, steps))
    g = jax.jit(jax.grad(own, argnums=(0, 1)))(params, state)
    g_ref = jax.jit(jax.grad(ref, argnums=(0, 1)))(params, state)
    assert_trees_close(g, g_ref, rtol=1e-12, atol=1e-13)
    assert float(jnp.max(jnp.abs(g_ref[0].inertia))) > 1e-3  # the loss depends on the attitude
    d_inertia = jax.jit(jax.jacfwd(lambda i: own(params.replace(inertia=i), state)))(params.inertia)
    np.testing.assert_allclose(d_inertia, g_ref[0].inertia, rtol=1e-11, atol=1e-13)


def test_contact_rollouts_read_the_params_from_one_array():
    """With contacts, rollout's steps read the params (and the integrator's derived
    quantities) from one flat array (simulate._packed): it unpacks to the same leaves, is
    not used where the leaves' dtypes differ, and the rollout equals calling the step
    itself (which reads them as they are), step after step."""
    from jaxrb.simulate import _packed

    step, params, state = _bouncing_ball()
    derived = step.integrator.precompute(params)
    flat, unpack = _packed((params, derived))
    leaves = jax.tree.leaves((params, derived))
    assert flat.shape == (sum(x.size for x in leaves),) and flat.dtype == jnp.float64
    for x, y in zip(jax.tree.leaves(unpack(flat)), leaves, strict=True):
        assert x.shape == y.shape and x.dtype == y.dtype
        np.testing.assert_array_equal(x, y)
    mixed = (params, jnp.zeros(3, jnp.float32))
    assert _packed(mixed) == (mixed, None)
    with_int = (params, jnp.zeros(3, jnp.int32))
    assert _packed(with_int) == (with_int, None)
    assert _packed(None) == (None, None)

    steps = 30
    _, traj = jax.jit(lambda p, s: rb.rollout(step, p, s, steps))(params, state)
    s, expected = step.prepare(state), []
    for _ in range(steps):
        s = step(params, s)
        expected.append(s.position)
    np.testing.assert_allclose(traj.position, jnp.stack(expected), rtol=1e-13, atol=1e-15)
    assert float(traj.position[:, 0, 2].min()) < 0.11  # contact steps ran: it reached the ground


def test_chunk_length_fits_the_sequential_threshold():
    from jaxrb.simulate import MAX_CHUNK, SEQUENTIAL_BUFFER_BYTES, _chunk_length

    _, _, state = _bouncing_ball()
    largest = max(x.size * x.dtype.itemsize for x in jax.tree.leaves(state))  # the (1, 4) float64 quaternion
    assert largest == 32
    assert _chunk_length(state, 1000) == 10  # the largest divisor of 1000 that is <= 16 with 32 bytes each
    assert _chunk_length(state, 997) == 1  # prime: no chunks
    assert _chunk_length(state, 4) == 4
    for steps in [12, 100, 1000, 4096]:
        chunk = _chunk_length(state, steps)
        assert steps % chunk == 0 and chunk <= MAX_CHUNK and chunk * largest <= SEQUENTIAL_BUFFER_BYTES
    boxes = [rb.Body(f"box{i}", shape=rb.Box((0.1, 0.1, 0.1)), mass=1.0) for i in range(5)]
    stack = rb.Scene(boxes, ground=rb.Plane(), contacts="all")
    stack_step = rb.make_step(stack, rb.integrators.SymplecticSplitting(), 1e-3)
    stack_params = stack.params(dtype=jnp.float32)
    stack_state = stack_step.prepare(stack.state(stack_params, position=[[0.0, 0.0, 0.1 + 0.2 * i] for i in range(5)]))
    assert _chunk_length(stack_state, 1000) == 1  # 60 contact impulses: 720 bytes a state
