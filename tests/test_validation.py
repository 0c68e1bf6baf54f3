"""Bad input fails early with a ValueError that says what is wrong and how to fix it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrb as rb


def scene_of(*bodies, **kw):
    return rb.Scene(list(bodies), **kw)


BALL = rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: rb.Body("b", shape=rb.Sphere(0.1), mass=-1.0), "mass"),
        (lambda: rb.Body("b", shape=rb.Sphere(0.1), mass=0.0), "mass"),
        (lambda: rb.Body("b", shape=rb.Sphere(0.1), mass=float("nan")), "mass"),
        (lambda: rb.Body("b", mass=1.0, inertia=(1.0, 1.0, 3.0)), "triangle"),
        (lambda: rb.Body("b", mass=1.0, inertia=(1.0, -1.0, 1.0)), "positive definite"),
        (lambda: rb.Body("b", mass=1.0, inertia=[[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]), "symmetric"),
        (lambda: rb.Body("b", mass=1.0, inertia=(1.0, 2.0)), "inertia"),
        (lambda: rb.Body("b", mass=1.0, inertia=(1.0, 2.0, 2.5), density=3.0), "density"),
        (lambda: rb.Body("b", shape=rb.Rod(0.5), mass=1.0), "positive definite|singular"),
        (lambda: rb.Body("b"), "no mass properties"),
        (lambda: rb.Body("b", shape=rb.Sphere(0.1)), "mass|density"),
        (lambda: rb.Body("b", shape=rb.Sphere(0.1), mass=1.0, density=10.0), "mass|density"),
        (lambda: rb.Body("", shape=rb.Sphere(0.1), mass=1.0), "name"),
        (lambda: rb.Body("b", shape="sphere", mass=1.0), "shape"),
        (lambda: rb.Sphere(-0.1), "positive"),
        (lambda: rb.Box((0.1, 0.0, 0.2)), "positive"),
        (lambda: rb.Box((0.1, 0.2)), "3 entries"),
        (lambda: rb.HollowSphere(0.1, thickness=0.2), "thickness"),
        (lambda: rb.Plane(normal=(0, 0, 0)), "normal"),
        (lambda: rb.Plane(normal=1.0), "normal must be a non-zero 3-vector"),
        (lambda: rb.Plane(offset=float("nan")), "offset must be a finite number"),
        (lambda: rb.Plane(offset=float("inf")), "offset must be a finite number"),
    ],
)
def test_invalid_bodies_and_shapes(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_error_messages_name_the_body():
    with pytest.raises(ValueError, match="'wheel'"):
        rb.Body("wheel", mass=1.0, inertia=(1.0, 1.0, 3.0))


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: rb.Scene([]), "at least one body"),
        (lambda: scene_of(BALL, BALL), "unique"),
        (lambda: rb.Scene(["ball"]), "rb.Body"),
        (lambda: scene_of(BALL, gravity=(0.0, -9.81)), "gravity"),
        (lambda: scene_of(BALL, gravity=(0.0, 0.0, float("nan"))), "gravity"),
        (lambda: scene_of(BALL, forces=["drag"]), "force models"),
    ],
)
def test_invalid_scenes(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"mass": -2.0}, "mass"),
        ({"mass": {"ball": 0.0}}, "mass"),
        ({"mass": {"nope": 1.0}}, "Unknown body name 'nope'"),
        ({"inertia": (1.0, 1.0, 3.0)}, "triangle"),
        ({"mass": [1.0, 2.0]}, "shape"),
        ({"linear_damping": -0.1}, "non-negative"),
        ({"gravity": (0.0, 1.0)}, "gravity"),
    ],
)
def test_invalid_params(kwargs, match):
    with pytest.raises(ValueError, match=match):
        scene_of(BALL, forces=[rb.LinearDamping()]).params(**kwargs)


def test_params_for_undeclared_force_models_are_refused():
    # They would be silently ignored by the compiled step.
    with pytest.raises(ValueError, match=r"no rb.LinearDamping\(\)"):
        scene_of(BALL).params(linear_damping=0.5)
    with pytest.raises(ValueError, match=r"no rb.AngularDamping\(\)"):
        scene_of(BALL, forces=[rb.LinearDamping()]).params(angular_damping={"ball": 0.1})
    with pytest.raises(ValueError, match="gravity=None"):
        scene_of(BALL, gravity=None).params(gravity=(0.0, 0.0, -9.81))


def test_params_from_another_scene_are_refused():
    two = scene_of(BALL, rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0))
    with pytest.raises(ValueError, match="this scene has 2"):
        two.state(scene_of(BALL).params(), angular_velocity=(1.0, 0.0, 0.0))


def test_params_of_the_wrong_shape_are_refused_by_the_step():
    """A step checks the params' shapes when it is traced: params from another scene, or a
    field changed by Params.replace, used to broadcast silently (a mass of shape (2,) for
    one ball ran as an ensemble of two)."""
    one = scene_of(BALL)
    two = scene_of(BALL, rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0))
    step = rb.make_step(one, rb.integrators.RK4(), 1e-3)
    params, state = one.params(), step.prepare(one.state())
    with pytest.raises(ValueError, match=r"Params.mass has shape \(2,\); this scene needs \(1,\)"):
        step(params.replace(mass=jnp.ones(2)), state)
    with pytest.raises(ValueError, match=r"Params.mass has shape \(2,\)"):
        rb.rollout(step, two.params(), state, 10)
    with pytest.raises(ValueError, match=r"Params.gravity has shape \(\)"):
        jax.jit(step)(params.replace(gravity=jnp.asarray(9.81)), state)
    # Contact coefficients: one per contact pair.
    ground = scene_of(BALL, ground=rb.Plane(), contacts="all")
    contact_step = rb.make_step(ground, rb.integrators.SymplecticSplitting(), 1e-3)
    contact_params = ground.params()
    with pytest.raises(ValueError, match="one per contact pair"):
        contact_step(contact_params.replace(friction=jnp.asarray([0.5, 0.5])),
                     contact_step.prepare(ground.state(contact_params)))
    step(params, state)  # the right shapes pass


def test_traced_principal_moments_build_the_same_tensor():
    import jax

    scene = scene_of(BALL)
    moments = jnp.array([1.0, 2.0, 2.5])
    eager = scene.params(inertia=moments).inertia
    traced = jax.jit(lambda i: scene.params(inertia=i).inertia)(moments)
    np.testing.assert_array_equal(traced, eager)
    np.testing.assert_array_equal(eager[0], np.diag([1.0, 2.0, 2.5]))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"position": (0.0, float("nan"), 0.0)}, "NaN"),
        ({"velocity": (float("inf"), 0.0, 0.0)}, "NaN or infinite"),
        ({"position": {"nope": (0.0, 0.0, 1.0)}}, "Unknown body name 'nope'"),
        ({"position": np.zeros((2, 3))}, "shape"),
        ({"position": (1.0, 2.0)}, "shape"),
        ({"orientation": (2.0, 0.0, 0.0, 0.0)}, "unit quaternion"),
        ({"orientation": (0.0, 0.0, 0.0, 0.0)}, "unit quaternion"),
        ({"angular_velocity": (1.0, 0, 0), "angular_momentum": (1.0, 0, 0)}, "at most one"),
        ({"time": float("nan")}, "time"),
        ({"position": {"ball": (float("nan"), 0.0, 0.0)}}, "NaN"),
        ({"velocity": {"ball": (float("inf"), 0.0, 0.0)}}, "NaN or infinite"),
        ({"angular_velocity": {"ball": (float("nan"), 0.0, 0.0)}}, "NaN"),
        ({"orientation": {"ball": (float("nan"), 0.0, 0.0, 0.0)}}, "NaN"),
    ],
)
def test_invalid_states(kwargs, match):
    with pytest.raises(ValueError, match=match):
        scene_of(BALL).state(**kwargs)


def test_invalid_steps_and_rollouts():
    scene = scene_of(BALL)
    params, state = scene.params(), scene.state()
    for dt in (0.0, -1e-3, float("nan"), float("inf"), "fast"):
        with pytest.raises(ValueError, match="dt"):
            rb.make_step(scene, rb.integrators.RK4(), dt)
    with pytest.raises(ValueError, match=r"RK4\(\)"):
        rb.make_step(scene, rb.integrators.RK4, 1e-3)
    with pytest.raises(ValueError, match="integrator"):
        rb.make_step(scene, "rk4", 1e-3)
    with pytest.raises(ValueError, match="Scene"):
        rb.make_step("scene", rb.integrators.RK4(), 1e-3)
    step = rb.make_step(scene, rb.integrators.RK4(), 1e-3)
    with pytest.raises(ValueError, match="multiple of save_every"):
        rb.rollout(step, params, state, 10, save_every=3)
    for n in (0, -5, 2.5, True):
        with pytest.raises(ValueError, match="num_steps"):
            rb.rollout(step, params, state, n)


def test_switches_must_be_true_or_false():
    """``checkpoint``, ``include_initial`` and ``debug`` are static switches. A string such as
    ``"no"`` had counted as true (the rollout checkpointed, the step ran the debug checks),
    and a JAX array failed inside the rollout's jit with a tracer error."""
    scene = scene_of(BALL)
    params, state = scene.params(), scene.state()
    step = rb.make_step(scene, rb.integrators.RK4(), 1e-3)
    for name in ("checkpoint", "include_initial"):
        for value in ("no", 1, None, jnp.asarray(True)):
            with pytest.raises(ValueError, match=f"{name} must be True or False"):
                rb.rollout(step, params, state, 2, **{name: value})
        rb.rollout(step, params, state, 2, **{name: np.bool_(True)})  # numpy's bool passes
    for value in ("no", 0, jnp.asarray(False)):
        with pytest.raises(ValueError, match="debug must be True or False"):
            rb.make_step(scene, rb.integrators.RK4(), 1e-3, debug=value)
    assert rb.make_step(scene, rb.integrators.RK4(), 1e-3, debug=np.bool_(True)).debug is True


def test_a_plane_cannot_be_a_body_and_its_offset_is_along_the_unit_normal():
    """A body whose shape was a Plane had been accepted and collided as a plane through the
    world's origin wherever the body was (a ball 5 m from such a 'wall' overlapped it by 0.1 m)."""
    with pytest.raises(ValueError, match="a Plane is static and has no pose"):
        rb.Body("wall", shape=rb.Plane(normal=(1.0, 0.0, 0.0)), mass=1.0, inertia=(1.0, 1.0, 1.0))
    # Plane((0, 0, 2), 1.0) is z = 1: the offset is a distance along the unit normal.
    plane = rb.Plane(normal=(0.0, 0.0, 2.0), offset=1.0)
    assert plane.normal == (0.0, 0.0, 1.0)
    contact = rb.collide(rb.Sphere(0.1), jnp.array([0.0, 0.0, 1.3]), jnp.array([1.0, 0.0, 0.0, 0.0]), plane)
    assert float(contact.gap[0]) == pytest.approx(0.2, abs=1e-12)


def test_mass_properties_of_a_body_are_checked():
    """A NaN centre of mass had become the shape's offset (the ball then fell through the
    ground); a dict had failed with an AttributeError, a batch with a conversion error."""
    mp = rb.mass_properties(rb.Sphere(0.1), mass=1.0)
    bad = [(rb.MassProperties(mp.mass, jnp.array([np.nan, 0.0, 0.0]), mp.inertia), "finite \\(3,\\) com"),
           (rb.MassProperties(mp.mass, jnp.zeros(2), mp.inertia), "finite \\(3,\\) com"),
           (rb.MassProperties(jnp.ones(2), jnp.zeros((2, 3)), jnp.stack([mp.inertia] * 2)), "scalar mass"),
           ({"mass": 1.0, "com": [0, 0, 0], "inertia": np.eye(3)}, "must be an rb.MassProperties")]
    for value, message in bad:
        with pytest.raises(ValueError, match=message):
            rb.Body("ball", shape=rb.Sphere(0.1), mass_properties=value)
    assert rb.Body("ball", shape=rb.Sphere(0.1), mass_properties=mp).mass == pytest.approx(1.0)


def test_helpers_refuse_params_and_state_of_different_scenes():
    """kinetic_energy(two bodies' params, one body's state) had broadcast to two energies;
    angular_momentum_about with a (1, 3) point had returned (1, 1, 3)."""
    one = scene_of(BALL)
    two = scene_of(BALL, rb.Body("b", shape=rb.Sphere(0.1), mass=2.0))
    for helper in (rb.kinetic_energy, rb.potential_energy, rb.linear_momentum, rb.angular_velocity,
                   rb.world_inertia, rb.total_energy):
        with pytest.raises(ValueError, match="params hold 2 bodies and the state 1"):
            helper(two.params(), one.state())
    params, state = one.params(), one.state(velocity=(1.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"point must be one \(3,\) world point"):
        rb.angular_momentum_about(params, state, [[1.0, 2.0, 3.0]])
    assert rb.angular_momentum_about(params, state, [0.0, 1.0, 0.0]).shape == (1, 3)
    # A trajectory, through vmap as documented.
    trajectory = jax.tree.map(lambda x: jnp.stack([x, x]), state)
    assert jax.vmap(rb.kinetic_energy, in_axes=(None, 0))(params, trajectory).shape == (2, 1)


def test_rollout_of_a_wrapped_step_and_of_a_state_of_another_time_type():
    """A step of make_step wrapped in a lambda (or jax.jit) hides its prepare: from an
    unprepared state the loop had failed with JAX's "carry input and carry output must
    have the same pytree structure". An integer time had failed in the scan, a float32
    time with float64 positions had stayed float32."""
    scene = scene_of(rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0))
    params = scene.params(dtype=jnp.float64)
    euler = rb.make_step(scene, rb.integrators.ExplicitEuler(), 0.1)
    with pytest.raises(ValueError, match=r"returns a state whose \['rotation'\] differ.*step.prepare\(state\)"):
        rb.rollout(lambda p, s: euler(p, s), params, scene.state(params), 4)
    _, trajectory = rb.rollout(lambda p, s: euler(p, s), params, euler.prepare(scene.state(params)), 4)
    np.testing.assert_allclose(trajectory.time, [0.1, 0.2, 0.3, 0.4])
    for time in (np.int32(2), jnp.float32(2.0)):
        _, trajectory = rb.rollout(euler, params, scene.state(params).replace(time=time), 3)
        assert trajectory.time.dtype == jnp.float64
        np.testing.assert_allclose(trajectory.time, [2.1, 2.2, 2.3], rtol=1e-15)


def test_user_force_function_with_wrong_shape():
    def wrong(t, params, state):
        return jnp.zeros(3), jnp.zeros(3)  # forgot the body axis

    scene = scene_of(BALL, forces=[rb.ExternalWrench(wrong)])
    step = rb.make_step(scene, rb.integrators.RK4(), 1e-3)
    with pytest.raises(ValueError, match=r"expected \(1, 3\)"):
        step(scene.params(), scene.state())
    # One array returned where a pair is due (the torque forgotten): it had been unpacked
    # along its body axis ("not enough values to unpack", or a shape the function did not return).
    for forces, message in [([rb.ExternalWrench(lambda t, p, s: jnp.ones((2, 3)))], r"pair \(F, tau\), got an array "
                                                                                    r"of shape \(2, 3\)"),
                            ([rb.PointForces(lambda t, p, s: jnp.ones((2, 1, 3)))], r"pair \(points, forces\)")]:
        two = scene_of(BALL, rb.Body("b", shape=rb.Sphere(0.1), mass=1.0), forces=forces)
        with pytest.raises(ValueError, match=message):
            rb.make_step(two, rb.integrators.RK4(), 1e-3)(two.params(), two.state())


def test_valid_inputs_pass_and_normalise():
    # A nearly unit quaternion (within 1e-3) is accepted and normalised exactly.
    scene = scene_of(BALL, rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), density=500.0))
    state = scene.state(orientation={"box": (1.0005, 0.0, 0.0, 0.0)}, position={"ball": (0.0, 0.0, 1.0)})
    np.testing.assert_allclose(np.linalg.norm(state.orientation, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(state.position, [[0, 0, 1], [0, 0, 0]])
    params = scene.params()
    np.testing.assert_allclose(params.mass[1], 500.0 * 0.2 * 0.4 * 0.6, rtol=1e-12)


def test_per_body_dicts_of_mass_and_inertia_are_differentiable_and_checked():
    # The {name: value} form of mass= and inertia= had called float() / np.asarray() on its
    # values, so under jit or grad it failed with a tracer-conversion error, while the
    # array form (and the dict form of restitution and friction) passed traced values.
    scene = rb.Scene(bodies=[rb.Body("ball", rb.Sphere(0.1), mass=1.0),
                             rb.Body("box", rb.Box((0.1, 0.2, 0.3)), mass=2.0)])
    by_dict = jax.grad(lambda m: jnp.sum(scene.params(mass={"ball": m}).mass * jnp.array([3.0, 5.0])))(1.5)
    assert float(by_dict) == 3.0
    moments = jnp.array([0.1, 0.2, 0.3])
    by_dict = jax.grad(lambda k: jnp.sum(scene.params(inertia={"box": k * moments}).inertia))(1.0)
    assert abs(float(by_dict) - 0.6) < 1e-6
    # Concrete dicts give the same params as before, and are still validated.
    p = scene.params(mass={"box": 4.0}, inertia={"ball": [0.5, 0.5, 0.5]})
    np.testing.assert_allclose(np.asarray(p.mass), [1.0, 4.0])
    np.testing.assert_allclose(np.asarray(p.inertia[0]), 0.5 * np.eye(3))
    with pytest.raises(ValueError, match="mass"):
        scene.params(mass={"ball": -1.0})
    with pytest.raises(ValueError, match=r"mass\['ball'\] must be a scalar"):
        scene.params(mass={"ball": [1.0, 2.0]})
    with pytest.raises(ValueError, match=r"inertia\['box'\] must be 3 principal moments or a 3x3 tensor"):
        scene.params(inertia={"box": [1.0, 2.0]})


def test_per_body_dicts_of_every_field_pass_traced_values():
    # The {name: value} form of the damping coefficients and of every state field went
    # through np.asarray, so under jit or grad it failed with a tracer-conversion error.
    scene = rb.Scene([rb.Body("a", rb.Sphere(0.1), mass=1.0), rb.Body("b", rb.Sphere(0.1), mass=2.0)],
                     forces=[rb.LinearDamping()])
    damping = jax.jit(lambda z: scene.params(linear_damping={"b": z}).linear_damping)(0.25)
    np.testing.assert_array_equal(np.asarray(damping), [0.0, 0.25])
    position = jax.jit(lambda z: scene.state(position={"a": jnp.stack([z, 0.0, 1.0])}).position)(2.0)
    np.testing.assert_array_equal(np.asarray(position), [[2.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    # L = I w: the sphere's moment 2/5 m r^2 = 0.004 kg m^2 is the derivative.
    spin = jax.grad(lambda z: scene.state(angular_velocity={"a": jnp.stack([z, 0.0, 0.0])}).angular_momentum.sum())
    np.testing.assert_allclose(float(spin(1.0)), 0.004, rtol=1e-12)
    with pytest.raises(ValueError, match=r"position\['a'\] must have shape \(3,\)"):
        scene.state(position={"a": (1.0, 2.0)})
    with pytest.raises(ValueError, match="NaN"):
        scene.params(linear_damping={"a": float("nan")})


def test_gravity_or_a_repeated_damping_among_the_forces_is_refused():
    # Gravity listed in forces= was applied twice (the scene's gravity is on by default),
    # and two LinearDamping() doubled the damping: both accepted without a word.
    with pytest.raises(ValueError, match="applied twice"):
        scene_of(BALL, forces=[rb.Gravity()])
    with pytest.raises(ValueError, match=r"rb.LinearDamping\(\) more than once"):
        scene_of(BALL, forces=[rb.LinearDamping(), rb.LinearDamping()])
    with pytest.raises(ValueError, match=r"rb.AngularDamping\(\) more than once.*angular_damping"):
        scene_of(BALL, forces=[rb.AngularDamping(), rb.LinearDamping(), rb.AngularDamping()])


def test_an_integer_dtype_is_refused():
    # It truncated every value: an angular velocity of 0.5 rad/s became an L of 0.
    with pytest.raises(ValueError, match="floating-point"):
        scene_of(BALL).params(dtype=jnp.int32)
    with pytest.raises(ValueError, match="floating-point"):
        scene_of(BALL).state(angular_velocity=(0.5, 0.0, 0.0), dtype=jnp.int32)


def test_a_half_precision_dtype_is_refused():
    # bfloat16 was accepted, and a ball 1.1 m up never fell: each 1 ms step's fall rounded
    # away against its 8 mm ulp. float16 fell, but its 1e-3 relative rounding is no physics.
    scene = rb.Scene([rb.Body("ball", rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    for dtype in (jnp.float16, jnp.bfloat16):
        with pytest.raises(ValueError, match="too coarse.*float32 or float64"):
            scene.params(dtype=dtype)
        with pytest.raises(ValueError, match="too coarse"):
            scene.state(position=[(0.0, 0.0, 1.1)], dtype=dtype)
    # Made by hand, past scene.params: the step refuses them too.
    params = scene.params()
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), dt=1e-3)
    state = step.prepare(scene.state(params, position=[(0.0, 0.0, 1.1)]))
    half = jax.tree.map(lambda x: x.astype(jnp.bfloat16) if jnp.issubdtype(x.dtype, jnp.floating) else x, params)
    with pytest.raises(ValueError, match="Params.mass's dtype is bfloat16, too coarse"):
        step(half, state)
    half_state = jax.tree.map(lambda x: x.astype(jnp.bfloat16), state)
    with pytest.raises(ValueError, match="State.position's dtype is bfloat16, too coarse"):
        rb.rollout(step, params, half_state, 3)


def test_per_body_restitution_and_friction_are_checked_and_a_frictionless_ground_has_a_gradient():
    scene = rb.Scene([rb.Body("ball", rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    # Checked before the rule combines them: max(-3, 0) = 0 and sqrt(-0.4 * -0.9) = 0.6 passed.
    with pytest.raises(ValueError, match=r"restitution\['ball'\] must be one number in \[0.0, 1.0\]"):
        scene.params(restitution={"ball": -3.0})
    with pytest.raises(ValueError, match=r"friction\['ground'\] must be one number"):
        scene.params(friction={"ball": 0.4, "ground": -0.9})
    # sqrt(mu_a mu_b) with mu_ground = 0 is 0 for every mu_ball: derivative 0, where sqrt's
    # derivative 1/0 had made it NaN.
    grad = jax.grad(lambda m: scene.params(friction={"ball": m, "ground": 0.0}).friction.sum())(0.5)
    assert float(grad) == 0.0
    grad = jax.grad(lambda m: scene.params(friction={"ball": m, "ground": 0.5}).friction.sum())(0.5)
    np.testing.assert_allclose(float(grad), 0.5 * np.sqrt(0.5 / 0.5), rtol=1e-12)


def test_float32_round_off_in_an_inertia_passes_and_real_asymmetry_does_not():
    # R diag(l) R^T in float32 is asymmetric at ~1e-8 of its largest entry, which the fixed
    # 1e-9 tolerance refused (in Body and in params) though every step reads the
    # symmetric part.
    q = rb.spatial.quat_from_axis_angle(jnp.array([1.0, 2.0, 0.5], jnp.float32), jnp.float32(0.7))
    rotation = rb.spatial.quat_to_matrix(q)
    tensor = np.array(rotation @ jnp.diag(jnp.array([2.0, 3.0, 4.0], jnp.float32)) @ rotation.T)
    # That rounding depends on the compiled product (it came out exactly symmetric with
    # XLA:CPU's older emitters at --xla_backend_optimization_level=0), so 4 ulps of it
    # are set here.
    tensor[0, 1] = tensor[1, 0] + 4 * np.spacing(tensor[1, 0])
    assert tensor.dtype == np.float32 and np.max(np.abs(tensor - tensor.T)) > 1e-9 * 4.0
    body = rb.Body("box", mass=1.0, inertia=tensor)
    stored = np.asarray(body.inertia)
    np.testing.assert_array_equal(stored, stored.T)
    scene = rb.Scene([body])
    params = scene.params(inertia=jnp.asarray(tensor), dtype=jnp.float32)
    assert params.inertia.dtype == jnp.float32
    with pytest.raises(ValueError, match="symmetric"):
        rb.Body("box", mass=1.0, inertia=tensor + np.float32(1e-3) * np.triu(np.ones((3, 3), np.float32), 1))


def test_an_asymmetric_3x3_inertia_for_three_bodies_says_how_it_was_read():
    scene = rb.Scene([rb.Body(n, rb.Sphere(0.1), mass=1.0) for n in "abc"])
    with pytest.raises(ValueError, match=r"read as one tensor.*\(3, 3, 3\)"):
        scene.params(inertia=[[1.0, 2.0, 2.5], [1.0, 1.0, 1.0], [2.0, 2.0, 3.0]])
    moments = {"a": (1.0, 2.0, 2.5), "b": (1.0, 1.0, 1.0), "c": (2.0, 2.0, 3.0)}
    np.testing.assert_array_equal(np.asarray(scene.params(inertia=moments).inertia[0]), np.diag([1.0, 2.0, 2.5]))
    # Three identical balls' moments, row by row: symmetric, so it had been read as one
    # (singular) tensor and refused with advice about rods and point masses.
    with pytest.raises(ValueError, match=r"read as one tensor.*positive definite.*\(3, 3, 3\)"):
        scene.params(inertia=[[0.004, 0.004, 0.004]] * 3)
    tensor = [[2.0, 0.1, 0.0], [0.1, 2.0, 0.0], [0.0, 0.0, 3.0]]  # a physical tensor is still one
    np.testing.assert_array_equal(np.asarray(scene.params(inertia=tensor).inertia[2]), tensor)


def test_a_concrete_inertia_is_checked_beside_a_traced_mass():
    """check_params skipped the inertia whenever the mass was traced (a gradient in the
    mass), so a negative-definite inertia passed."""
    scene = rb.Scene([rb.Body("a", rb.Sphere(0.1), mass=1.0)])
    bad = scene.params().replace(inertia=-jnp.eye(3)[None])

    def check(mass):
        scene.check_params(bad.replace(mass=mass[None]))
        return mass

    with pytest.raises(ValueError, match="positive definite"):
        jax.grad(check)(1.0)
    good = scene.params()
    jax.grad(lambda m: (scene.check_params(good.replace(mass=m[None])), m)[1])(1.0)  # a traced mass alone passes


def test_world_points_take_lists_and_check_their_shape():
    scene = scene_of(BALL)
    state = scene.state(position=(1.0, 2.0, 3.0))
    np.testing.assert_array_equal(np.asarray(rb.kinematics.world_points(state, [[0.0, 0.0, 1.0]])), [[1.0, 2.0, 4.0]])
    with pytest.raises(ValueError, match=r"points_body must be \(N, 3\) or \(N, K, 3\)"):
        rb.kinematics.world_points(state, [[0.0, 1.0]])


def test_a_state_for_another_scene_is_refused_by_the_step():
    # Only params were checked: ExplicitEuler ran a 2-body state on a 1-body scene (the
    # second body silently used the first's parameters), the others failed inside vmap.
    one = scene_of(BALL)
    two = scene_of(BALL, rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0))
    params = one.params()
    for integrator in (rb.integrators.ExplicitEuler(), rb.integrators.RK4()):
        step = rb.make_step(one, integrator, 1e-2)
        with pytest.raises(ValueError, match=r"State.position has shape \(2, 3\); this scene of 1 bodies"):
            rb.rollout(step, params, two.state(), 2)
        with pytest.raises(ValueError, match="State.position"):
            step(params, two.state())


def test_integer_counts_of_any_type_and_a_traced_dt():
    scene = scene_of(BALL)
    step = rb.make_step(scene, rb.integrators.RK4(), 1e-2)
    final, traj = rb.rollout(step, scene.params(), scene.state(), np.int64(4), save_every=np.int32(2))
    assert traj.position.shape == (2, 1, 3)  # np.int64(4) had been refused as "not a positive integer"
    with pytest.raises(ValueError, match="dt is static"):
        jax.jit(lambda dt: rb.make_step(scene, rb.integrators.RK4(), dt))(0.1)


def test_a_traced_field_skips_only_its_own_check():
    scene = scene_of(BALL)
    # A traced gravity failed with a tracer-conversion error: it was left out of the
    # "any field traced" test and then converted with np.asarray.
    g = jax.jit(lambda g: scene.params(gravity=g).gravity)(jnp.array([0.0, 0.0, -9.81]))
    np.testing.assert_array_equal(np.asarray(g), [0.0, 0.0, -9.81])
    assert float(jax.grad(lambda z: scene.params(gravity=jnp.stack([0.0, 0.0, z])).gravity.sum())(-9.81)) == 1.0
    # One traced field had switched every value check off: a NaN gravity passed.
    with pytest.raises(ValueError, match="gravity must be finite"):
        jax.grad(lambda m: scene.params(mass=m, gravity=(0.0, 0.0, float("nan"))).mass.sum())(1.0)


def test_a_state_from_another_scene_gets_this_scenes_impulses():
    """Warm-start impulses of another scene's shape: rollout failed inside its loop (a sphere's
    1 slot against a box's 4: "true_fn and false_fn must return the same shapes"; a scene
    without contacts: a scan carry of None). prepare resets or drops them; a direct step
    call says what is wrong."""
    euler = rb.integrators.SemiImplicitEuler()
    spheres = scene_of(BALL, ground=rb.Plane(), contacts="all")
    boxes = scene_of(rb.Body("ball", shape=rb.Box((0.1, 0.1, 0.1)), mass=1.0), ground=rb.Plane(), contacts="all")
    free = scene_of(BALL)
    start = spheres.state(position=(0, 0, 0.1))
    carried, _ = rb.rollout(rb.make_step(spheres, euler, 1e-2), spheres.params(), start, 4)
    assert carried.contact_impulse.shape == (1, 3)
    final, _ = rb.rollout(rb.make_step(boxes, euler, 1e-2), boxes.params(), carried, 4)
    assert final.contact_impulse.shape == (4, 3)
    assert rb.rollout(rb.make_step(free, euler, 1e-2), free.params(), carried, 4)[0].contact_impulse is None
    with pytest.raises(ValueError, match=r"contact_impulse has shape \(1, 3\).*step.prepare"):
        rb.make_step(boxes, euler, 1e-2)(boxes.params(), carried)


def test_params_and_state_must_fit_the_scene_and_each_other():
    """A float32 state with float64 params was promoted by the step (rollout then failed on its
    carry's type, ode.solve inside diffrax); ode.solve, resolve_impacts and penetration did not
    check that params and state belong to the scene (a vmap size error, a concatenate error,
    and the first body's overlap only, silently)."""
    euler = rb.integrators.SemiImplicitEuler()
    scene = scene_of(BALL)
    wide, narrow = scene.params(dtype=jnp.float64), scene.state(scene.params(dtype=jnp.float32))
    step = rb.make_step(scene, euler, 1e-2)
    for run in (lambda: step(wide, narrow), lambda: rb.rollout(step, wide, narrow, 4),
                lambda: rb.ode.solve(scene, wide, narrow, 0.1)):
        with pytest.raises(ValueError, match="state is float32 and the params float64"):
            run()
    # A contact scene's rollout tries free chunks first, which read params and state before
    # any step checked them: the carry's type error, and for an ensemble's params without a
    # vmap, a narrow-phase error about the (correct) position's shape.
    ground = scene_of(BALL, ground=rb.Plane(), contacts="all")
    contact_step = rb.make_step(ground, euler, 1e-2)
    for steps, every in ((4, 1), (5, 1), (4, 2)):
        with pytest.raises(ValueError, match="state is float32 and the params float64"):
            rb.rollout(contact_step, ground.params(dtype=jnp.float64), ground.state(ground.params(dtype=jnp.float32)),
                       steps, save_every=every)
    members = jax.vmap(lambda m: ground.params(mass={"ball": m}))(jnp.arange(1.0, 5.0))
    with pytest.raises(ValueError, match=r"Params.mass has shape \(4, 1\).*need jax.vmap"):
        rb.rollout(contact_step, members, ground.state(), 4)
    # float32 params with a float64 state run in the state's precision, as before
    assert step(scene.params(dtype=jnp.float32), scene.state(wide)).position.dtype == jnp.float64

    pair = scene_of(BALL, rb.Body("other", shape=rb.Sphere(0.1), mass=2.0))
    with pytest.raises(ValueError, match=r"Params.mass has shape \(2,\)"):
        rb.ode.solve(scene, pair.params(), scene.state(), 0.1)
    ground = scene_of(BALL, ground=rb.Plane(), contacts="all")
    two = scene_of(BALL, rb.Body("other", shape=rb.Sphere(0.1), mass=1.0), ground=rb.Plane(), contacts="all")
    with pytest.raises(ValueError, match=r"State.position has shape \(2, 3\)"):
        rb.contact.resolve_impacts(ground, ground.params(), two.state(velocity=(0, 0, -1.0)))
    with pytest.raises(ValueError, match=r"State.position has shape \(2, 3\)"):
        rb.contact.penetration(ground, two.state(position=(0, 0, 0.05)))


def test_integrator_and_ode_switches_and_limits():
    """Static switches elsewhere take True or False too ("no" had switched Gram-Schmidt, the
    safeguard and dense output on); solve refuses an adjoint that is not diffrax's (a
    string had failed deep inside diffrax); solve_with_impacts checks rtol, atol and max_steps as
    solve does (rtol=-1 was accepted, atol=0 failed at run time in a callback, max_steps=0
    inside diffrax); max_steps of any integer type; Solution.evaluate refuses concrete
    times outside the solve (NaN states had come back)."""
    for make, name in [(rb.integrators.ExplicitEuler, "reorthonormalize"), (rb.integrators.ImplicitGyroscopic,
                       "safeguard"), (rb.integrators.ImplicitMidpoint, "safeguard")]:
        with pytest.raises(ValueError, match=f"{name}=...\\) must be True or False"):
            make(**{name: "no"})
        assert getattr(make(**{name: np.bool_(False)}), name) is False

    box = scene_of(rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0))
    params, state = box.params(), box.state(velocity=(1.0, 0.0, 0.0), time=1.0)
    for name in ("dense", "step_to_ts", "throw"):
        with pytest.raises(ValueError, match=f"{name} must be True or False"):
            rb.ode.solve(box, params, state, 2.0, **{name: "no"})
    with pytest.raises(ValueError, match="adjoint must be a diffrax adjoint instance"):
        rb.ode.solve(box, params, state, 2.0, adjoint="forward")
    solution = rb.ode.solve(box, params, state, 2.0, dense=np.bool_(True), max_steps=np.int64(100))
    np.testing.assert_allclose(solution.evaluate(jnp.array([1.0, 1.5, 2.0])).position[:, 0, 0], [0.0, 0.5, 1.0],
                               atol=1e-12)
    for t in (0.5, jnp.array([1.5, 2.0000001])):
        with pytest.raises(ValueError, match="outside the solve's interval"):
            solution.evaluate(t)

    ball = scene_of(BALL, ground=rb.Plane(), contacts="all")
    p, s = ball.params(restitution=0.8), ball.state(position=(0.0, 0.0, 1.1))
    for kwargs, message in [({"rtol": -1.0}, "rtol must be a positive"), ({"atol": 0.0}, "atol must be a positive"),
                            ({"max_steps": 0}, "max_steps must be a positive integer")]:
        with pytest.raises(ValueError, match=message):
            rb.ode.solve_with_impacts(ball, p, s, 1.0, max_impacts=2, **kwargs)
    # Started 1 cm into the ground, it bounced about that depth, or spent every impact at
    # t ~ 3e-8 s when at rest there.
    with pytest.raises(ValueError, match=r"\('ball', 'ground'\) overlaps by 0.01 m at the start"):
        rb.ode.solve_with_impacts(ball, p, ball.state(position=(0.0, 0.0, 0.09)), 1.0, max_impacts=2)


def test_small_input_mistakes_are_explained():
    """Each of these had passed silently or failed with an error about something else."""
    scene = scene_of(BALL)
    with pytest.raises(ValueError, match=r"gravity must be a 3-vector \(gx, gy, gz\)"):
        scene.params(gravity={"z": -9.81})  # a TypeError from float()
    # A string in extra failed inside the first step, about custom_jvp_call's arguments.
    with pytest.raises(ValueError, match=r"extra\['drag'\]\[1\] is 'quadratic': every leaf of extra must be a number"):
        scene.params(extra={"drag": (0.3, "quadratic")})
    assert scene.params(extra={"drag": (0.3, np.ones(3), True)}).extra["drag"][0] == 0.3  # numbers and arrays pass
    with pytest.raises(ValueError, match="dt must be a positive number"):
        rb.make_step(scene, rb.integrators.RK4(), "0.01")  # float("0.01") had passed
    for kwargs in ({"density": -1000.0}, {"mass": 0.0}, {"density": float("nan")}):
        with pytest.raises(ValueError, match="must be positive and finite"):
            rb.mass_properties(rb.Sphere(0.1), **kwargs)  # a negative mass had come back
    pose = ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="is the class rb.Sphere"):
        rb.collide(rb.Sphere, *pose, rb.Plane())  # an AttributeError on 'radius'
    with pytest.raises(ValueError, match="no position given"):
        rb.collide(rb.Sphere(0.1), None, pose[1], rb.Plane())
    for margin in (jnp.asarray(-5.0), [0.1], "0.1"):
        with pytest.raises(ValueError, match="margin must be one distance >= 0"):
            rb.collide(rb.Sphere(0.1), *pose, rb.Plane(), margin=margin)
    assert rb.collide(rb.Sphere(0.1), *pose, rb.Plane(), margin=jnp.asarray(0.01)).active.shape == (1,)

    params = scene.params()
    # "None is not a valid value for jnp.array", naming no field.
    with pytest.raises(ValueError, match=r"State.replace\(time=None\): State.time is required"):
        scene.state(params).replace(time=None)
    with pytest.raises(ValueError, match=r"Params.replace\(friction=None\): Params.friction is required"):
        params.replace(friction=None)
    assert scene.state(params).replace(contact_impulse=None).contact_impulse is None
    with pytest.raises(ValueError, match="max_steps must be a positive integer"):
        rb.identify.fit(lambda p: jnp.sum(p.mass), scene, params, "mass", max_steps=0, progress=False)
    # Counts beyond int32 had passed the checks and failed later with an OverflowError.
    with pytest.raises(ValueError, match=r"ContactSettings.impact_iterations = 1180591620717411303424 is too large"):
        rb.ContactSettings(impact_iterations=2**70)
    with pytest.raises(ValueError, match=r"max_steps = 4294967296 is too large: counts are at most 2\*\*31 - 1"):
        rb.identify.fit(lambda p: jnp.sum(p.mass), scene, params, "mass", max_steps=2**32, progress=False)
    with pytest.raises(ValueError, match="max_steps must be a positive integer"):
        rb.identify.fit_least_squares(lambda p: p.mass, scene, params, "mass", max_steps=-1, progress=False)
    with pytest.raises(ValueError, match="fit_least_squares"):  # a bare reshape error
        rb.identify.fit(lambda p: jnp.concatenate([p.mass, p.mass]), scene, params, "mass", max_steps=2,
                        progress=False)
    with pytest.raises(ValueError, match="free must name what to fit"):
        rb.identify.FreeParameters(scene, params, None)
    with pytest.raises(ValueError, match=r"Params.mass has shape \(2,\)"):
        rb.identify.FreeParameters(scene, scene_of(BALL, rb.Body("b", shape=rb.Sphere(0.1), mass=1.0)).params(),
                                   "mass")


def test_inputs_of_the_wrong_kind_get_a_value_error_that_names_them():
    """A Body or a force model not in a list, None for params or state, a solver given by
    name and a string for a number had raised TypeError, AttributeError, or NumPy's "could
    not convert string to float" that names no input."""
    body = rb.Body("b", shape=rb.Sphere(0.1), mass=1.0)
    with pytest.raises(ValueError, match=r"got one Body: write bodies=\[body\]"):
        rb.Scene(body)
    with pytest.raises(ValueError, match="forces must be a list of force models"):
        rb.Scene([body], forces=rb.LinearDamping())
    scene = rb.Scene([body])
    params = scene.params()
    state = scene.state(params)
    step = rb.make_step(scene, rb.integrators.RK4(), 1e-2)
    with pytest.raises(ValueError, match=r"params must be an rb.Params \(scene.params"):
        rb.rollout(step, None, state, 10)
    with pytest.raises(ValueError, match=r"state must be an rb.State \(scene.state"):
        step(params, None)
    with pytest.raises(ValueError, match=r"solver must be a diffrax solver instance, e.g. diffrax.Tsit5\(\)"):
        rb.ode.solve(scene, params, state, 1.0, solver="tsit5")
    for build, name in ((lambda: rb.Body("b", shape=rb.Sphere(0.1), mass="x"), "Body 'b': mass"),
                        (lambda: rb.Body("b", mass=1.0, inertia=["a", "b", "c"]), "Body 'b': inertia"),
                        (lambda: scene.params(mass="x"), "mass"),
                        (lambda: scene.state(params, position="abc"), "position"),
                        (lambda: scene.state(params, velocity={"b": "x"}), r"velocity\['b'\]")):
        with pytest.raises(ValueError, match=name + " must be numbers"):
            build()


def test_scene_inputs_found_by_stop_92s_review():
    """Each of these had passed silently or failed with a message that named neither the
    input nor the fix (stop 92's review of the scene API)."""
    ball = rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)
    # A scene without contact pairs takes its own empty per-pair arrays back ("the truth value
    # of an empty array is ambiguous" before).
    free = rb.Scene([ball])
    again = free.params(restitution=free.params().restitution, friction=np.zeros(0))
    assert again.restitution.shape == again.friction.shape == (0,)
    with pytest.raises(ValueError, match=r"restitution must lie in \[0.0, 1.0\]"):
        free.params(restitution=1.5)  # still checked where no pair keeps it
    # One number per body, traced or not (a traced (1,) array failed in jnp.stack).
    scene = rb.Scene([ball], ground=rb.Plane(), contacts="all")
    with pytest.raises(ValueError, match=r"friction\['ball'\] must be one number, got shape \(1,\)"):
        jax.grad(lambda x: scene.params(friction={"ball": x}).friction.sum())(jnp.ones(1))
    # Dict keys that are neither a name nor a pair of names; values that are not numbers.
    with pytest.raises(ValueError, match="a dict's keys are body or plane names"):
        scene.params(restitution={0: 0.5})
    with pytest.raises(ValueError, match=r"mass\['ball'\] must be numbers"):
        scene.params(mass={"ball": "heavy"})
    with pytest.raises(ValueError, match=r"inertia\['ball'\] must be numbers"):
        scene.params(inertia={"ball": "round"})
    # A body's mass and density are one number each (TypeErrors from float() before).
    for kwargs in ({"shape": rb.Sphere(0.1), "mass": [2.0]}, {"mass": [2.0], "inertia": (1.0, 1.0, 1.0)},
                   {"shape": rb.Sphere(0.1), "density": np.array([1000.0, 2000.0])}):
        with pytest.raises(ValueError, match=r"Body 'b': (mass|density) must be one number \((kg|kg/m\^3)\)"):
            rb.Body("b", **kwargs)
    # Strings are not numbers, although float("0.8") and tuple("123") would read them.
    for make in (lambda: rb.Box("123"), lambda: rb.Sphere("0.1"), lambda: rb.Plane("001"),
                 lambda: rb.Plane((0.0, 0.0, 1.0), "1"), lambda: scene.params(restitution="0.8"),
                 lambda: scene.params(friction={"ball": "0.5"})):
        with pytest.raises(ValueError):
            make()
    # A plane's normal is normalised without under- or overflow.
    assert rb.Plane((3e-160, 0.0, 4e-160)).normal == (0.6, 0.0, 0.8)
    assert rb.Plane((0.0, 0.0, 1e-170)).normal == rb.Plane((0.0, 0.0, 1e160)).normal == (0.0, 0.0, 1.0)
