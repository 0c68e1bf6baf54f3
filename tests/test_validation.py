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


def test_user_force_function_with_wrong_shape():
    def wrong(t, params, state):
        return jnp.zeros(3), jnp.zeros(3)  # forgot the body axis

    scene = scene_of(BALL, forces=[rb.ExternalWrench(wrong)])
    step = rb.make_step(scene, rb.integrators.RK4(), 1e-3)
    with pytest.raises(ValueError, match=r"expected \(1, 3\)"):
        step(scene.params(), scene.state())


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
