"""Free-body dynamics against closed forms, conservation laws, convergence orders and scipy.

Float64 throughout (conftest enables x64). Each tolerance is stated with its reason.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrb as rb
from jaxrb import spatial
from tests import reference
from tests.problems import forced_setup

INTEGRATORS = {
    "ExplicitEuler": rb.integrators.ExplicitEuler(),
    "SemiImplicitEuler": rb.integrators.SemiImplicitEuler(),
    "RK4": rb.integrators.RK4(),
}


def free_body(inertia, gravity=None, forces=(), mass=1.0):
    return rb.Scene([rb.Body("body", mass=mass, inertia=inertia)], gravity=gravity, forces=forces)


def run(scene, integrator, params, state, dt, num_steps, save_every=None):
    step = rb.make_step(scene, integrator, dt)
    return rb.rollout(step, params, state, num_steps, save_every=save_every or num_steps)


# ----------------------------------------------------------------------------- translation


def test_projectile_rk4_exact_and_semi_implicit_error_is_g_h_t_over_2():
    scene = free_body((1.0, 2.0, 3.0), gravity=(0.0, 0.0, -9.81))
    params = scene.params()
    x0, v0 = np.array([1.0, -2.0, 3.0]), np.array([2.0, 1.0, 10.0])
    state = scene.state(params, position=x0, velocity=v0)
    h, n = 0.01, 200
    t = h * n
    g = np.array([0.0, 0.0, -9.81])
    exact = x0 + v0 * t + 0.5 * g * t**2
    final, _ = run(scene, rb.integrators.RK4(), params, state, h, n)
    # RK4 integrates a quadratic exactly; 1e-10 leaves room for 200 steps of round-off.
    np.testing.assert_allclose(final.position[0], exact, atol=1e-10)
    np.testing.assert_allclose(final.velocity[0], v0 + g * t, atol=1e-10)
    final, _ = run(scene, rb.integrators.SemiImplicitEuler(), params, state, h, n)
    # x_n = x0 + v0 t + g h^2 n(n+1)/2 = exact + g h t / 2 (seed 001's update order).
    np.testing.assert_allclose(final.position[0] - exact, g * h * t / 2, atol=1e-10)


# ------------------------------------------------------------------------------- rotation


def test_symmetric_top_rk4_matches_closed_form():
    i_perp, i_axis = 2.0, 1.0
    omega0 = np.array([0.3, -0.2, 2.0])
    scene = free_body((i_perp, i_perp, i_axis))
    params = scene.params()
    state = scene.state(params, body_angular_velocity=omega0)
    h, n = 1e-3, 10_000
    _, traj = run(scene, rb.integrators.RK4(), params, state, h, n, save_every=1000)
    times = h * 1000 * np.arange(1, 11)
    errors = [
        reference.rotation_angle(reference.symmetric_top_attitude(i_perp, i_axis, omega0, t),
                                 np.asarray(spatial.quat_to_matrix(q[0])))
        for t, q in zip(times, traj.orientation, strict=True)
    ]
    # Acceptance: <= 1e-9 rad over 10 s at h = 1e-3.
    assert max(errors) <= 1e-9, max(errors)


def test_symmetric_top_closed_form_agrees_with_scipy():
    # Guards the reference itself: the closed form and an ODE solve must agree.
    omega0 = np.array([0.3, -0.2, 2.0])
    times = np.linspace(0, 10, 11)
    _, q = reference.torque_free_body_frame((2.0, 2.0, 1.0), omega0, [1, 0, 0, 0], times)
    for t, qi in zip(times, q, strict=True):
        err = reference.rotation_angle(reference.symmetric_top_attitude(2.0, 1.0, omega0, t),
                                       reference.quat_to_matrix(qi))
        assert err < 1e-10


ASYM_INERTIA = (1.0, 2.0, 3.0)
ASYM_OMEGA0 = np.array([-0.3, 0.9, -0.5])


def asymmetric_top_errors(integrator, ks, t_final=10.0):
    scene = free_body(ASYM_INERTIA)
    params = scene.params()
    state = scene.state(params, body_angular_velocity=ASYM_OMEGA0)
    omega_ref, q_ref = reference.torque_free_body_frame(ASYM_INERTIA, ASYM_OMEGA0, [1, 0, 0, 0], [0.0, t_final])
    r_ref = reference.quat_to_matrix(q_ref[-1])
    hs, errors = [], []
    for k in ks:
        h = 0.2 * 2.0**-k
        final, _ = run(scene, integrator, params, state, h, round(t_final / h))
        attitude = reference.rotation_angle(r_ref, np.asarray(rb.rotation_matrix(final)[0]))
        omega = np.asarray(rb.body_angular_velocity(params, final)[0])
        hs.append(h)
        errors.append(max(attitude, np.linalg.norm(omega - omega_ref[-1]) / np.linalg.norm(omega_ref[-1])))
    return np.array(hs), np.array(errors)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(INTEGRATORS))
def test_asymmetric_top_convergence_order(name):
    integrator = INTEGRATORS[name]
    # h = 0.2 * 2^-k. For RK4 the finest step of k = 4..8 gives an error of ~4e-14, the
    # accuracy of the scipy reference itself (DOP853, rtol 1e-13), so RK4 is measured one
    # octave coarser, where its error (4e-8 .. 7e-13) is well above that floor.
    ks = range(3, 8) if integrator.order == 4 else range(4, 9)
    hs, errors = asymmetric_top_errors(integrator, ks=ks)
    slope = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    print(f"{name}: errors {errors}, slope {slope:.3f}")
    # Acceptance: measured slope within +-0.15 of the nominal order (1, 1, 4).
    assert abs(slope - integrator.order) <= 0.15, (slope, errors)


@pytest.mark.parametrize("name", list(INTEGRATORS))
def test_torque_free_world_angular_momentum_is_conserved(name):
    scene = free_body(((2.0, 0.3, -0.1), (0.3, 1.5, 0.2), (-0.1, 0.2, 3.0)))
    params = scene.params()
    state = scene.state(params, orientation=spatial.quat_from_axis_angle(jnp.array([1.0, 2, 3]), 0.7),
                        angular_velocity=(0.4, -1.3, 2.2))
    final, traj = run(scene, INTEGRATORS[name], params, state, 1e-2, 1000, save_every=10)
    l0 = np.asarray(state.angular_momentum[0])
    drift = np.max(np.linalg.norm(np.asarray(traj.angular_momentum[:, 0]) - l0, axis=-1)) / np.linalg.norm(l0)
    # Acceptance: Euler methods <= 1e-12 (L is the state), RK4 <= 1e-9.
    assert drift <= (1e-9 if name == "RK4" else 1e-12), drift
    # Sanity: the body really tumbled (the attitude moved a lot).
    assert float(spatial.rotation_angle(rb.rotation_matrix(state)[0], rb.rotation_matrix(final)[0])) > 0.5


def test_rk4_energy_and_unit_quaternion_over_long_run():
    scene = free_body(ASYM_INERTIA)
    params = scene.params()
    state = scene.state(params, body_angular_velocity=ASYM_OMEGA0)
    _, traj = run(scene, rb.integrators.RK4(), params, state, 1e-2, 10_000, save_every=100)
    e0 = float(rb.kinetic_energy(params, state)[0])
    energies = np.asarray(jax.vmap(lambda s: rb.kinetic_energy(params, s))(traj))[:, 0]
    # RK4 at h = 0.01 has local energy error ~h^5: 1e-9 relative over 100 s is generous.
    assert np.max(np.abs(energies / e0 - 1)) < 1e-9
    np.testing.assert_allclose(np.linalg.norm(traj.orientation[:, 0], axis=-1), 1.0, atol=1e-14)


def test_dzhanibekov_flip_time():
    scene = free_body(ASYM_INERTIA)
    params = scene.params()
    omega0 = np.array([1e-3, 1.0, 1e-3])
    state = scene.state(params, body_angular_velocity=omega0)
    h, n = 1e-3, 20_000
    _, traj = run(scene, rb.integrators.RK4(), params, state, h, n, save_every=1)
    omega_body = np.asarray(jax.vmap(lambda s: rb.body_angular_velocity(params, s))(traj))[:, 0]
    times = h * np.arange(1, n + 1)
    t_flip = reference.first_sign_change(times, omega_body[:, 1])
    # Acceptance: 14.906 s within 1e-3 relative. Also against scipy's DOP853 at rtol 1e-13.
    assert abs(t_flip - 14.906) / 14.906 < 1e-3, t_flip
    ref_times = np.linspace(0, 20, 200_001)
    omega_ref, _ = reference.torque_free_body_frame(ASYM_INERTIA, omega0, [1, 0, 0, 0], ref_times)
    t_ref = reference.first_sign_change(ref_times, omega_ref[:, 1])
    assert abs(t_flip - t_ref) < 1e-6, (t_flip, t_ref)


def test_explicit_euler_reorthonormalisation():
    scene = free_body(ASYM_INERTIA)
    params = scene.params()
    state = scene.state(params, body_angular_velocity=(0.5, 1.0, -0.7))

    def orthonormality_error(traj):
        a = np.asarray(traj.rotation[:, 0])
        return np.linalg.norm(np.einsum("tji,tjk->tik", a, a) - np.eye(3), axis=(1, 2))

    _, drifting = run(scene, rb.integrators.ExplicitEuler(reorthonormalize=False), params, state, 1e-2, 2000,
                      save_every=100)
    err = orthonormality_error(drifting)
    # A + dt w~ A stretches A by sqrt(1 + |w dt|^2) per step: the error grows steadily.
    assert np.all(np.diff(err) > 0) and err[-1] > 1e-2, err
    _, fixed = run(scene, rb.integrators.ExplicitEuler(), params, state, 1e-2, 2000, save_every=100)
    assert np.max(orthonormality_error(fixed)) <= 1e-12


def test_explicit_euler_is_the_seed_algorithm_step_for_step():
    """Seed 000's loop written out in numpy, against jaxrb's ExplicitEuler, with forces."""
    inertia_body = np.diag([1.0, 2.0, 3.0])
    mass, dt = 2.0, 0.01
    offsets_body = np.array([[0.1, 0.0, 0.0], [0.0, -0.2, 0.1]])
    forces_world = np.array([[0.0, 1.0, 0.5], [2.0, 0.0, -1.0]])

    def point_forces(t, params, state):
        rot = rb.rotation_matrix(state)[0]
        points = state.position[0][None] + spatial.matvec(rot[None], jnp.asarray(offsets_body))
        return points[None], jnp.asarray(forces_world)[None]

    scene = free_body(inertia_body, forces=[rb.PointForces(point_forces)], mass=mass)
    params = scene.params()
    state = scene.state(params, velocity=(0.3, 0, 0), angular_momentum=(0.2, -0.4, 1.0))
    final, _ = run(scene, rb.integrators.ExplicitEuler(), params, state, dt, 50)

    x, v, a, l_ = np.zeros(3), np.array([0.3, 0, 0]), np.eye(3), np.array([0.2, -0.4, 1.0])
    i_inv_body = np.linalg.inv(inertia_body)
    for _ in range(50):
        i_inv = a @ i_inv_body @ a.T
        omega = i_inv @ l_
        r = (a @ offsets_body.T).T
        tau = np.sum(np.cross(r, forces_world), axis=0)
        f = np.sum(forces_world, axis=0)
        x = x + dt * v
        v = v + dt * f / mass
        a = a + dt * np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]]) @ a
        l_ = l_ + dt * tau
        b1 = a[:, 0] / np.linalg.norm(a[:, 0])
        b2 = a[:, 1] - (b1 @ a[:, 1]) * b1
        b2 /= np.linalg.norm(b2)
        a = np.stack([b1, b2, np.cross(b1, b2)], axis=1)
    np.testing.assert_allclose(final.position[0], x, atol=1e-13)
    np.testing.assert_allclose(final.velocity[0], v, atol=1e-13)
    np.testing.assert_allclose(final.rotation[0], a, atol=1e-13)
    np.testing.assert_allclose(final.angular_momentum[0], l_, atol=1e-13)


def test_semi_implicit_euler_is_the_seed_update():
    """Seed 001's update written out in numpy (v, x with v_{n+1}, L, omega, rotate)."""
    inertia_body = np.diag([1.0, 2.0, 3.0])

    def wrench(t, params, state):
        return jnp.array([[0.0, 0.5, -1.0]]), jnp.array([[0.1, 0.2, -0.3]]) * jnp.cos(t)

    scene = free_body(inertia_body, forces=[rb.ExternalWrench(wrench)], mass=2.0)
    params = scene.params()
    state = scene.state(params, velocity=(0.3, 0, 0), body_angular_velocity=(0.5, -1.0, 0.2))
    dt = 0.01
    final, _ = run(scene, rb.integrators.SemiImplicitEuler(), params, state, dt, 50)
    x, v = np.zeros(3), np.array([0.3, 0, 0])
    a = np.eye(3)
    l_ = inertia_body @ np.array([0.5, -1.0, 0.2])
    for i in range(50):
        t = i * dt
        v = v + dt * np.array([0.0, 0.5, -1.0]) / 2.0
        x = x + dt * v
        l_ = l_ + dt * np.array([0.1, 0.2, -0.3]) * np.cos(t)
        omega = a @ np.linalg.inv(inertia_body) @ a.T @ l_
        theta = np.linalg.norm(omega) * dt
        k = omega / np.linalg.norm(omega)
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        a = (np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx) @ a
    np.testing.assert_allclose(final.position[0], x, atol=1e-13)
    np.testing.assert_allclose(rb.rotation_matrix(final)[0], a, atol=1e-12)
    np.testing.assert_allclose(final.angular_momentum[0], l_, atol=1e-13)


# ---------------------------------------------------------------------------- kinematics


def test_point_velocity_and_acceleration_match_finite_differences():
    def wrench(t, params, state):
        return jnp.array([[0.3, -0.1, 0.2]]), jnp.array([[0.4, 0.1, -0.2]])

    scene = free_body(((2.0, 0.3, 0.0), (0.3, 1.5, 0.1), (0.0, 0.1, 3.0)), gravity=(0, 0, -9.81),
                      forces=[rb.ExternalWrench(wrench)], mass=1.7)
    params = scene.params()
    state = scene.state(params, orientation=spatial.quat_from_axis_angle(jnp.array([1.0, -1, 2]), 0.4),
                        velocity=(0.5, -0.2, 1.0), angular_velocity=(1.2, -0.7, 2.0))
    points_body = jnp.array([[[0.3, -0.2, 0.5], [-0.4, 0.1, 0.0]]])  # (N=1, K=2, 3)
    delta = 1e-4
    step = rb.make_step(scene, rb.integrators.RK4(), delta)
    s1 = step(params, state)
    s2 = step(params, s1)
    x0, x1, x2 = (rb.kinematics.world_points(s, points_body) for s in (state, s1, s2))
    v_fd = (x2 - x0) / (2 * delta)
    a_fd = (x2 - 2 * x1 + x0) / delta**2
    v = rb.kinematics.world_point_velocities(params, s1, points_body)
    a = rb.kinematics.world_point_accelerations(scene, params, s1, points_body)
    # Central differences: truncation O(delta^2) ~ 1e-8; the second difference also
    # carries round-off ~1e-16/delta^2 = 1e-8. 1e-6 relative bounds both.
    np.testing.assert_allclose(v, v_fd, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(a, a_fd, rtol=1e-6, atol=1e-6)
    # Decomposition: a = a_cm + a_tan + a_cen, and a_cen points at the axis (r . a_cen = -|w x r|^2).
    a_cm, alpha = rb.dynamics.accelerations(scene, params, s1)
    omega = rb.angular_velocity(params, s1)
    r = x1 - s1.position[:, None]
    a_tan = rb.kinematics.tangential_acceleration(alpha[:, None], r)
    a_cen = rb.kinematics.centripetal_acceleration(omega[:, None], r)
    np.testing.assert_allclose(a_cm[:, None] + a_tan + a_cen, a, atol=1e-12)
    w_cross_r = spatial.cross(omega[:, None], r)
    np.testing.assert_allclose(spatial.dot(r, a_cen), -spatial.dot(w_cross_r, w_cross_r), atol=1e-12)


def test_omega_form_equals_derivative_of_l_form():
    """alpha = I^-1 (tau - w x I w) (seed 001) is d/dt (I^-1 L) along the L-form flow."""
    torque = jnp.array([[0.4, 0.1, -0.2]])
    scene = free_body(((2.0, 0.3, 0.0), (0.3, 1.5, 0.1), (0.0, 0.1, 3.0)),
                      forces=[rb.ExternalWrench(lambda t, p, s: (jnp.zeros((1, 3)), torque))])
    params = scene.params()
    state = scene.state(params, orientation=spatial.quat_from_axis_angle(jnp.array([0.0, 1, 1]), 1.0),
                        angular_velocity=(1.2, -0.7, 2.0))
    _, alpha = rb.dynamics.accelerations(scene, params, state)
    d = rb.dynamics.derivative(scene, params, state)
    tangent = rb.State(position=d.position, orientation=d.orientation, velocity=d.velocity,
                       angular_momentum=d.angular_momentum, time=jnp.ones(()))
    _, omega_dot = jax.jvp(lambda s: rb.angular_velocity(params, s), (state,), (tangent,))
    np.testing.assert_allclose(alpha, omega_dot, atol=1e-13)
    # Body-frame Euler equations give the same alpha, rotated (d/dt (A w_b) = A w_b').
    omega_b = rb.body_angular_velocity(params, state)
    tau_b = spatial.quat_rotate_inverse(state.orientation, torque)
    alpha_b = rb.dynamics.body_angular_acceleration(params.inertia, omega_b, tau_b)
    np.testing.assert_allclose(spatial.quat_rotate(state.orientation, alpha_b), alpha, atol=1e-13)


# -------------------------------------------------------------------------------- forces


def test_force_through_com_gives_no_spin_offset_force_gives_both():
    """Seed 000's force vs torque puzzle."""
    f = jnp.array([0.0, 3.0, 0.0])
    offset = jnp.array([0.5, 0.0, 0.0])

    def through_com(t, params, state):
        return state.position[:, None], f[None, None]

    def off_com(t, params, state):
        return (state.position + offset[None])[:, None], f[None, None]

    for fn, expect_torque in [(through_com, np.zeros(3)), (off_com, np.cross([0.5, 0, 0], [0, 3, 0]))]:
        scene = free_body((1.0, 1.0, 1.0), forces=[rb.PointForces(fn)], mass=2.0)
        params = scene.params()
        state = scene.state(params, position=(1.0, 2.0, 3.0))
        force, torque = rb.dynamics.wrench(scene, params, state)
        # The force counts fully towards F in both cases ...
        np.testing.assert_allclose(force[0], f, atol=1e-15)
        # ... and towards the torque only when it is off the centre of mass.
        np.testing.assert_allclose(torque[0], expect_torque, atol=1e-15)
        final, _ = run(scene, rb.integrators.RK4(), params, state, 0.01, 100)
        np.testing.assert_allclose(final.velocity[0], f / 2.0 * 1.0, atol=1e-12)
        spins = np.linalg.norm(final.angular_momentum[0]) > 1.0
        assert spins == bool(np.any(expect_torque))


def test_damping_decays_exponentially():
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.5), mass=2.0)], gravity=None,
                     forces=[rb.LinearDamping(), rb.AngularDamping()])
    params = scene.params(linear_damping=0.6, angular_damping=0.05)
    state = scene.state(params, velocity=(1.0, -2.0, 0.5), angular_velocity=(0.0, 3.0, -1.0))
    final, _ = run(scene, rb.integrators.RK4(), params, state, 1e-2, 300)
    t = 3.0
    i_ball = 0.4 * 2.0 * 0.25
    np.testing.assert_allclose(final.velocity[0], np.array([1.0, -2.0, 0.5]) * np.exp(-0.6 * t / 2.0), rtol=1e-9)
    np.testing.assert_allclose(rb.angular_velocity(params, final)[0],
                               np.array([0.0, 3.0, -1.0]) * np.exp(-0.05 * t / i_ball), rtol=1e-9, atol=1e-15)


def _used_params(scene):
    """Names of the Params fields the compiled step actually reads."""
    params = scene.params()
    state = scene.state(params, velocity=(1.0, 0, 0), angular_velocity=(0.1, 0.2, 0.3))
    fields = ["mass", "inertia", "gravity", "linear_damping", "angular_damping"]

    def step(*values):
        p = rb.Params(**dict(zip(fields, values, strict=True)))
        return rb.integrators.RK4().step(scene, p, state, 0.01)

    closed = jax.make_jaxpr(step)(*(getattr(params, f) for f in fields))
    used = {id(v) for eqn in closed.jaxpr.eqns for v in eqn.invars}
    return {f for f, v in zip(fields, closed.jaxpr.invars, strict=True) if id(v) in used}


def test_undeclared_forces_are_not_compiled():
    """Only declared force models reach the jaxpr: their parameters are read only then."""
    bare = free_body((1.0, 2.0, 3.0))
    assert _used_params(bare) == {"mass", "inertia"}
    assert _used_params(free_body((1.0, 2.0, 3.0), gravity=(0, 0, -9.81))) == {"mass", "inertia", "gravity"}
    damped = free_body((1.0, 2.0, 3.0), forces=[rb.LinearDamping(), rb.AngularDamping()])
    assert _used_params(damped) == {"mass", "inertia", "linear_damping", "angular_damping"}


@pytest.mark.slow
def test_rk4_is_fourth_order_in_position_velocity_attitude_and_momentum():
    """Time-dependent force and torque, so x, v and L all change: every field converges at 4."""
    scene, params, state, args = forced_setup()
    t_final = 2.0
    x_ref, v_ref, q_ref, l_ref = reference.forced_body_world_frame(*args, [0.0, t_final])
    hs, errors = [], {"x": [], "v": [], "q": [], "L": []}
    for k in range(5):
        h = 0.1 * 2.0**-k
        final, _ = run(scene, rb.integrators.RK4(), params, state, h, round(t_final / h))
        hs.append(h)
        errors["x"].append(np.linalg.norm(final.position[0] - x_ref[-1]))
        errors["v"].append(np.linalg.norm(final.velocity[0] - v_ref[-1]))
        errors["q"].append(reference.rotation_angle(reference.quat_to_matrix(q_ref[-1]),
                                                    np.asarray(rb.rotation_matrix(final)[0])))
        errors["L"].append(np.linalg.norm(final.angular_momentum[0] - l_ref[-1]))
    for field, err in errors.items():
        slope = np.polyfit(np.log(hs), np.log(err), 1)[0]
        # Errors run from ~1e-6 down to ~1e-11, above the reference's ~1e-13.
        assert abs(slope - 4) <= 0.15, (field, slope, err)


def test_nan_propagates_instead_of_resetting_the_attitude():
    """A blow-up must stay visible: normalisations keep NaN as NaN (never 'identity')."""
    np.testing.assert_array_equal(np.isnan(spatial.quat_normalize(jnp.array([jnp.nan, 0, 0, 0]))), True)
    assert np.isnan(spatial.safe_norm(jnp.array([jnp.nan, 1.0, 0.0])))

    def nan_torque(t, params, state):
        return jnp.zeros((1, 3)), jnp.full((1, 3), jnp.nan)

    scene = free_body((1.0, 2.0, 3.0), forces=[rb.ExternalWrench(nan_torque)])
    params = scene.params()
    state = scene.state(params, angular_velocity=(0.0, 1.0, 0.0))
    for integrator in INTEGRATORS.values():
        final, _ = run(scene, integrator, params, state, 1e-2, 5)
        assert np.all(np.isnan(final.orientation)), type(integrator).__name__


def test_explicit_euler_quaternion_is_continuous_through_half_turns():
    scene = free_body((1.0, 1.0, 1.0))
    params = scene.params()
    state = scene.state(params, angular_velocity=(0.0, 0.0, 1.0))
    _, traj = run(scene, rb.integrators.ExplicitEuler(), params, state, 1e-2, 1000, save_every=1)
    jumps = np.linalg.norm(np.diff(np.asarray(traj.orientation[:, 0]), axis=0), axis=-1)
    # One step turns by 0.01 rad, so |dq| ~ 0.005; a sign flip would be a jump of ~2.
    assert np.max(jumps) < 0.01


def test_rollout_time_is_exact_in_float32():
    scene = free_body((1.0, 2.0, 3.0))
    params = scene.params(dtype=jnp.float32)
    state = scene.state(params, dtype=jnp.float32)
    final, traj = run(scene, rb.integrators.SemiImplicitEuler(), params, state, 1e-3, 100_000, save_every=1000)
    assert final.time.dtype == jnp.float32
    # t = t0 + k dt with one rounding; t <- t + dt would be off by ~43 ms here.
    np.testing.assert_allclose(float(final.time), 100.0, rtol=1e-7)
    np.testing.assert_allclose(np.asarray(traj.time, dtype=float), np.arange(1, 101), rtol=1e-7)


def test_step_object_is_a_valid_jit_argument():
    scene = free_body((1.0, 2.0, 3.0))
    params = scene.params()
    state = scene.state(params, angular_velocity=(0.1, 0.2, 0.3))
    for integrator in INTEGRATORS.values():
        step = rb.make_step(scene, integrator, 1e-2)
        prepared = step.prepare(state)
        out = jax.jit(lambda stp, p, s: stp(p, s))(step, params, prepared)
        np.testing.assert_allclose(out.angular_momentum, step(params, prepared).angular_momentum)


@pytest.mark.parametrize("omega_h", [0.5, 4.0])
def test_rk4_at_large_spin_is_inaccurate_but_bounded(omega_h):
    """RK4's docstring: at large |w|h the energy error is O(1) but stays in the L-band."""
    scene = free_body(ASYM_INERTIA)
    params = scene.params()
    state = scene.state(params, body_angular_velocity=ASYM_OMEGA0)
    h = omega_h / np.linalg.norm(ASYM_OMEGA0)
    _, traj = run(scene, rb.integrators.RK4(), params, state, h, 10_000, save_every=10)
    energy = np.asarray(jax.vmap(lambda s: rb.kinetic_energy(params, s))(traj))[:, 0]
    l_sq = float(np.sum(np.asarray(state.angular_momentum[0]) ** 2))
    assert np.all(np.isfinite(energy))
    # 1e-12 relative slack for round-off at the band's edges.
    assert np.all(energy >= l_sq / (2 * 3.0) * (1 - 1e-12)) and np.all(energy <= l_sq / 2.0 * (1 + 1e-12))
    e0 = float(rb.kinetic_energy(params, state)[0])
    print(f"|w|h = {omega_h}: max |dE/E| = {np.max(np.abs(energy / e0 - 1)):.3f}")
    assert np.max(np.abs(energy / e0 - 1)) > 0.1  # genuinely inaccurate: documented, not hidden


def test_momenta_and_energies_of_stacked_members_are_each_members():
    """Called directly on an ensemble's stacked arrays (mass (B, N), positions (B, N, 3)),
    the helpers read bodies on the last axis, as ``jax.vmap`` gives them. ``linear_momentum``
    (and ``angular_momentum_about`` through it) had read mass's first axis as the bodies:
    member i took body i's mass where B == N, and a broadcast error came where not. A point
    given as a list keeps a float32 state float32 (it had promoted it to float64)."""
    scene = rb.Scene([rb.Body(f"b{i}", shape=rb.Sphere(0.1), mass=1.0) for i in range(3)])
    rng = np.random.default_rng(3)
    for members in (3, 4):
        params = jax.vmap(lambda m: scene.params(mass=m))(jnp.asarray(rng.uniform(1.0, 3.0, (members, 3))))
        states = jax.vmap(lambda x, v: scene.state(position=x, velocity=v))(
            jnp.asarray(rng.normal(size=(members, 3, 3))), jnp.asarray(rng.normal(size=(members, 3, 3))))
        point = [0.5, -1.0, 2.0]
        for helper in (rb.linear_momentum, rb.potential_energy, rb.kinetic_energy,
                       lambda p, s, point=point: rb.angular_momentum_about(p, s, point)):
            np.testing.assert_allclose(helper(params, states), jax.vmap(helper)(params, states), rtol=1e-15)
        momentum = np.asarray(params.mass)[..., None] * np.asarray(states.velocity)
        np.testing.assert_allclose(rb.linear_momentum(params, states), momentum, rtol=1e-15)
    params = scene.params(dtype=jnp.float32)
    state = scene.state(params, position=np.ones((3, 3)), velocity=np.ones((3, 3)))
    assert rb.angular_momentum_about(params, state, [0.0, 1.0, 0.0]).dtype == jnp.float32
