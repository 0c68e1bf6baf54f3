"""Every integrator against exact solutions, invariants and the extremes (issue: integrators).

Float64 unless a test says otherwise (conftest enables x64). References are the
closed forms of :mod:`jaxrb.exact` (Jacobi elliptic functions, attitude to ~1e-13 rad)
and scipy's DOP853; nothing here uses a jaxrb integrator as its own reference.
Each tolerance is stated with the figure measured when the test was written.
"""

import functools
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxrb as rb
from jaxrb import spatial
from tests import reference

ALL = {name: getattr(rb.integrators, name)() for name in rb.integrators.__all__ if name != "Integrator"}
NOMINAL_ORDER = {"ExplicitEuler": 1, "SemiImplicitEuler": 1, "ImplicitGyroscopic": 1, "ImplicitMidpoint": 2,
                 "SymplecticSplitting": 2, "SymmetricTopSplitting": 2, "RK4": 4, "RKMK4": 4}
SECOND_ORDER_OR_HIGHER = [name for name, order in NOMINAL_ORDER.items() if order >= 2]
CONSERVATIVE = ["ImplicitMidpoint", "SymplecticSplitting", "SymmetricTopSplitting"]
TOP_MOMENTS = (1.0, 2.0, 3.0)
TOP_OMEGA0 = np.array([-0.3, 0.9, -0.5])


def top(moments=TOP_MOMENTS, omega0=TOP_OMEGA0, dtype=None):
    scene = rb.Scene([rb.Body("body", mass=1.0, inertia=moments)], gravity=None)
    params = scene.params(dtype=dtype)
    return scene, params, scene.state(params, body_angular_velocity=omega0, dtype=dtype)


def trajectory(scene, integrator, params, state, dt, num_steps, save_every=1):
    step = rb.make_step(scene, integrator, dt)
    return rb.rollout(step, params, state, num_steps, save_every=save_every, include_initial=True)[1]


def energies(params, traj):
    return np.asarray(jax.vmap(rb.kinetic_energy, in_axes=(None, 0))(params, traj))[:, 0]


def momentum_error(traj):
    l_world = np.asarray(traj.angular_momentum[:, 0])
    return np.max(np.linalg.norm(l_world - l_world[0], axis=1)) / np.linalg.norm(l_world[0])


def test_every_integrator_is_covered():
    assert set(ALL) == set(NOMINAL_ORDER)
    for name, integrator in ALL.items():
        assert integrator.order == NOMINAL_ORDER[name]


# ------------------------------------------------------------------------- convergence


class NaiveLieRK4(rb.integrators.Integrator):
    """A Lie "RK4" without dexp^-1: stage attitudes exp(c dt w) q0, averaged slopes, one exp.

    Torque-free only. It looks fourth order but rotations do not commute: the test below
    shows it is second order, which is the mistake the RKMK4 convergence test must catch.
    """

    order: ClassVar[int] = 4

    def step(self, scene, params, state, dt):
        q0 = state.orientation

        def omega(q):
            return rb.angular_velocity(params, state.replace(orientation=q))

        def advance(rate, h):
            return spatial.quat_multiply(spatial.quat_exp(h * rate), q0)

        k1 = omega(q0)
        k2 = omega(advance(k1, 0.5 * dt))
        k3 = omega(advance(k2, 0.5 * dt))
        k4 = omega(advance(k3, dt))
        return state.replace(orientation=advance((k1 + 2 * k2 + 2 * k3 + k4) / 6.0, dt), time=state.time + dt)


def attitude_errors(integrator, t_final=10.0, ks=range(4, 9)):
    scene, params, state = top()
    exact = rb.exact.torque_free_top(TOP_MOMENTS, TOP_OMEGA0, np.array([0.0, t_final])).rotation[-1]
    hs, errors = [], []
    for k in ks:
        h = 0.2 * 2.0**-k
        n = round(t_final / h)
        final, _ = rb.rollout(rb.make_step(scene, integrator, h), params, state, n, save_every=n)
        hs.append(h)
        errors.append(reference.rotation_angle(exact, np.asarray(rb.rotation_matrix(final)[0])))
    return np.array(hs), np.array(errors)


@pytest.mark.parametrize("name", list(ALL))
def test_convergence_order_on_the_asymmetric_top(name):
    """I = diag(1,2,3), w0 = (-0.3, 0.9, -0.5), T = 10, h = 0.2 * 2^-k, k = 4..8."""
    hs, errors = attitude_errors(ALL[name])
    slope = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    print(f"{name}: errors {errors}, slope {slope:.3f}")
    # Measured slopes: 1.007 (ExplicitEuler), 1.020, 0.997, 2.000, 2.000, 3.943 (RK4), 4.068
    # (RKMK4). The closed form agrees with a 25-digit solve to 1.3e-15 rad, so what bends
    # the 4th-order fits at k = 8 (errors 2e-14 to 5e-14 after 12800 steps) is the
    # integrators' own float64 round-off, not the reference.
    assert abs(slope - NOMINAL_ORDER[name]) <= 0.15, (slope, errors)


def test_naive_lie_rk4_is_caught_at_second_order():
    hs, errors = attitude_errors(NaiveLieRK4(), ks=range(2, 7))
    slope = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    # Measured 1.999: the commutator of the stage rotations enters at O(h^3) per step.
    assert abs(slope - 2.0) <= 0.15, (slope, errors)


# ------------------------------------------------------------------------ long horizon

LONG_STEPS = 100_000  # h = 0.01: 1000 s; the benchmark runs 1e6


@pytest.fixture(scope="module")
def long_runs():
    scene, params, state = top()
    out = {}
    for name in ("SymplecticSplitting", "ImplicitMidpoint", "RK4", "RKMK4", "SemiImplicitEuler", "ExplicitEuler"):
        traj = trajectory(scene, ALL[name], params, state, 0.01, LONG_STEPS, save_every=100)
        e = energies(params, traj)
        out[name] = (np.asarray(traj.time), np.abs(e / e[0] - 1.0), momentum_error(traj))
    return out


def test_long_horizon_energy(long_runs):
    times, split, _ = long_runs["SymplecticSplitting"]
    # Measured max 1.5e-7. The acceptance bound is 1e-6.
    assert split.max() <= 1e-6
    # No trend: the running maximum of |dE| stops growing. Fit it on log-log axes over
    # the last two decades (10 s to 1000 s); a drift ~ t would give slope 1.
    running = np.maximum.accumulate(split)
    late = times >= 10.0
    slope = np.polyfit(np.log(times[late]), np.log(running[late]), 1)[0]
    assert slope < 0.1, slope
    # Measured 5.9e-10 (RK4), 4.7e-10 (RKMK4), 1.3e-14 (ImplicitMidpoint: solver tolerance).
    assert long_runs["RK4"][1].max() <= 1e-8
    assert long_runs["RKMK4"][1].max() <= 1e-8
    assert long_runs["ImplicitMidpoint"][1].max() <= 1e-12


def test_long_horizon_world_angular_momentum(long_runs):
    # Each of these keeps L as the state or never updates it torque-free: exactly 0 drift.
    for name, (_, _, drift) in long_runs.items():
        assert drift <= 1e-12, (name, drift)


# --------------------------------------------------------------------------- extremes


@pytest.mark.parametrize("omega_h", [0.1, 0.5, 1.0, 2.0])
def test_high_spin(omega_h):
    """|w| h in {0.1, 0.5, 1, 2}, 1e4 steps of the asymmetric top (h = 0.01)."""
    h = 0.01
    omega0 = TOP_OMEGA0 / np.linalg.norm(TOP_OMEGA0) * omega_h / h
    scene, params, state = top(omega0=omega0)
    for name, integrator in ALL.items():
        traj = trajectory(scene, integrator, params, state, h, 10_000, save_every=10)
        for leaf in jax.tree.leaves(traj):
            assert np.all(np.isfinite(leaf)), (name, omega_h)
        if name in CONSERVATIVE:
            e = energies(params, traj)
            # Bounded, not drifting. Measured at |w|h = 2: 4.3e-2 (SymplecticSplitting), 7.0e-2
            # (SymmetricTopSplitting, whose energy error on this strongly asymmetric top is the
            # larger one at every |w|h: 3.8e-3 against 1.8e-4 at 0.5), 6e-13 (midpoint).
            bound = 1e-1 if name == "SymmetricTopSplitting" else 5e-2
            assert np.max(np.abs(e / e[0] - 1.0)) <= bound, (name, omega_h)
            assert momentum_error(traj) <= 1e-12, (name, omega_h)


def test_rkmk4_far_past_its_stability_limit_stays_finite_in_float32_and_differentiable():
    """RKMK4's truncated ``dexp^-1`` compounds the stages' rotation vectors (1e14 rad within
    one step at ``|w| dt = 100``): float32 attitudes turned NaN from ``|w| dt`` of about 150
    (28 of 50 spin directions at 200, all from 300), and its float64 gradient through 200
    steps was 3e55 at ``|w| dt = 3``, 2e236 at 4, NaN at 16. The stages now take the
    rotation vector of least angle (``_lie_group._shortest``): the state stays a rotation
    with the energy in ``[|L|^2/2 I_max, |L|^2/2 I_min]``; the gradient at 4 and 16 is
    0.53 and 1.97 (measured; RK4's at 3 is 1e59)."""
    scene = rb.Scene([rb.Body("b", mass=1.0, inertia=(1.0, 2.0, 3.0))], gravity=None)
    direction = np.array([-0.3, 0.9, -0.5]) / np.linalg.norm([-0.3, 0.9, -0.5])
    dt = 0.01
    params = scene.params(dtype=jnp.float32)
    step = rb.make_step(scene, rb.integrators.RKMK4(), dt)
    for omega_dt in (100.0, 300.0, 3000.0):
        state = scene.state(params, body_angular_velocity=direction * omega_dt / dt, dtype=jnp.float32)
        final, _ = rb.rollout(step, params, state, 100, save_every=100)
        assert np.all(np.isfinite(np.asarray(final.orientation))), omega_dt
        assert float(jnp.linalg.norm(final.orientation)) == pytest.approx(1.0, abs=1e-5)
        square = float(jnp.sum(state.angular_momentum.astype(jnp.float64) ** 2))
        energy = float(rb.kinetic_energy(params, final)[0])
        assert square / 6 * (1 - 1e-5) <= energy <= square / 2 * (1 + 1e-5), omega_dt
    params = scene.params()
    for omega_dt in (4.0, 16.0):
        state = scene.state(params, body_angular_velocity=direction * omega_dt / dt)

        def loss(momentum, state=state):
            final, _ = rb.rollout(step, params, state.replace(angular_momentum=momentum), 200, save_every=200)
            return jnp.sum(final.orientation[0] * jnp.array([1.0, 0.3, -0.2, 0.5]))

        assert float(jnp.max(jnp.abs(jax.grad(loss)(state.angular_momentum)))) < 10.0, omega_dt


def test_seed_explicit_euler_without_gram_schmidt_blows_up():
    """Seed 000's A <- A + dt w~ A stretches A by sqrt(1 + |w dt|^2) per step: at |w|h = 2
    it overflows to inf/NaN within 1e4 steps. Gram-Schmidt is what keeps it finite."""
    h = 0.01
    scene, params, state = top(omega0=TOP_OMEGA0 / np.linalg.norm(TOP_OMEGA0) * 2.0 / h)
    raw = trajectory(scene, rb.integrators.ExplicitEuler(reorthonormalize=False), params, state, h, 10_000, 10)
    assert not np.all(np.isfinite(np.asarray(raw.rotation)))
    kept = trajectory(scene, rb.integrators.ExplicitEuler(), params, state, h, 10_000, 10)
    assert np.all(np.isfinite(np.asarray(kept.rotation)))


def random_bodies(count, seed=0):
    rng = np.random.default_rng(seed)
    bodies = [(1.0, 2.0, 3.0)]
    while len(bodies) < count:
        m = rng.uniform(0.2, 3.0, 3)
        if 2 * m.max() <= m.sum():  # triangle inequality
            bodies.append(tuple(m))
    return bodies, rng


@pytest.mark.parametrize("omega_h", [0.5, 1.0, 2.0, 4.0])
def test_implicit_gyroscopic_never_gains_energy(omega_h):
    """E_{n+1} <= E_n (1 + 1e-12) at every step, |w| h up to 4.

    256 random bodies (a third with non-diagonal inertia) spinning about random axes, as
    one scene of 256 independent bodies, 200 steps: 51 200 steps per |w| h. Plain Newton
    from w_n failed on ~1 % of such steps at |w| h = 2, gaining energy up to 1000-fold.
    """
    rng = np.random.default_rng(1)
    inertias = []
    while len(inertias) < 256:
        m = rng.uniform(0.05, 3.0, 3)
        if 2 * m.max() <= m.sum():  # triangle inequality
            rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0] if len(inertias) % 3 == 0 else np.eye(3)
            inertias.append(rotation @ np.diag(m) @ rotation.T)
    directions = rng.normal(size=(256, 3))
    h = 0.01
    omega0 = directions / np.linalg.norm(directions, axis=1, keepdims=True) * omega_h / h
    scene = rb.Scene([rb.Body(f"b{i}", mass=1.0, inertia=inertia) for i, inertia in enumerate(inertias)],
                     gravity=None)
    params = scene.params()
    state = scene.state(params, body_angular_velocity=omega0)
    traj = trajectory(scene, rb.integrators.ImplicitGyroscopic(), params, state, h, 200)
    e = np.asarray(jax.vmap(rb.kinetic_energy, in_axes=(None, 0))(params, traj))  # (201, 256)
    rise = np.max(e[1:] / e[:-1] - 1)
    # Measured worst step: +3.3e-15 (round-off) at every |w| h; the bound allows 1e-12.
    assert rise <= 1e-12, rise


@pytest.mark.parametrize("omega_h", [3.0, 6.0])
def test_implicit_midpoint_keeps_the_energy_where_its_equation_has_no_root(omega_h):
    """Beyond |w| h = 2.5 the midpoint equation can have no root near P_n, and the last
    Newton iterate changed the energy up to 5x in one step. With the safeguard (the
    default) such a body turns by the root of a shorter step: energy kept at every step.
    256 random bodies, 20 steps; where Newton converges the values equal the unguarded
    ones to the last bit."""
    bodies, rng = random_bodies(256, seed=3)
    rotations = [np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in bodies]
    scene = rb.Scene([rb.Body(f"b{i}", mass=1.0, inertia=r @ np.diag(m) @ r.T)
                      for i, (m, r) in enumerate(zip(bodies, rotations, strict=True))], gravity=None)
    params = scene.params()
    directions = rng.normal(size=(256, 3))
    h = 0.01
    omega = directions / np.linalg.norm(directions, axis=1)[:, None] * omega_h / h
    state = scene.state(params, body_angular_velocity=omega)

    def worst_energy_change(integrator):
        traj = trajectory(scene, integrator, params, state, h, 20)
        e = np.asarray(jax.vmap(rb.kinetic_energy, in_axes=(None, 0))(params, traj))
        return np.max(np.abs(e[1:] / e[:-1] - 1)), traj

    guarded, traj = worst_energy_change(rb.integrators.ImplicitMidpoint())
    staged, _ = worst_energy_change(rb.integrators.ImplicitMidpoint(stages=3))
    unguarded, raw = worst_energy_change(rb.integrators.ImplicitMidpoint(safeguard=False))
    # Measured (|w| h = 3, 6): guarded 2.4e-15, 2.9e-13; stages=3 2.9e-15, 2.1e-12;
    # unguarded 0.29 and 2.6 (the test's teeth). First steps equal bitwise: 99.6 %, 96 %.
    assert guarded < 1e-11 and staged < 1e-11
    assert unguarded > 1e-3
    first = np.asarray(traj.orientation[1]) == np.asarray(raw.orientation[1])
    assert 0.5 < np.mean(np.all(first, axis=1)) < 1.0  # most steps converge, and equal bitwise


def test_implicit_midpoint_keeps_turning_where_its_full_step_has_no_root():
    """A body whose full step fails takes four exact steps of h / 4. It had turned by its
    last converged stage instead, none with stages=1: its body momentum did not change, the
    next step failed the same way, and the top (moments 1, 2, 3) stopped turning for good
    at |w| h = 6 while keeping its momentum and energy. Now it turns at every step, with
    its energy and world momentum kept."""
    direction = np.array([-0.3, 0.9, -0.5]) / np.linalg.norm([-0.3, 0.9, -0.5])
    for omega_h in (6.0, 30.0):
        scene, params, state = top((1.0, 2.0, 3.0), direction * omega_h)
        traj = trajectory(scene, rb.integrators.ImplicitMidpoint(), params, state, 1.0, 50)
        q = np.asarray(traj.orientation[:, 0])
        assert np.all(np.any(q[1:] != q[:-1], axis=1)), omega_h  # every step turns
        e = np.asarray(jax.vmap(rb.kinetic_energy, in_axes=(None, 0))(params, traj))[:, 0]
        np.testing.assert_allclose(e, e[0], rtol=1e-11)
        momentum = np.asarray(traj.angular_momentum[:, 0])
        np.testing.assert_allclose(momentum, np.broadcast_to(momentum[0], momentum.shape), rtol=1e-12)


def test_a_single_newton_step_can_multiply_the_energy():
    """The linearised gyroscopic step of MuJoCo and Bullet (one Newton iteration)."""
    moments = (2.49099822, 2.2632503, 0.46776277)  # a flat body, found by random search
    direction = np.array([0.30486202, -0.85947759, 0.41031382])
    h = 0.01
    scene, params, state = top(moments, direction * 2.0 / h)  # |w| h = 2
    e0 = float(rb.kinetic_energy(params, state)[0])
    single = rb.integrators.ImplicitGyroscopic(stages=1, iterations=1, safeguard=False)
    one = rb.make_step(scene, single, h)(params, state)
    converged = rb.make_step(scene, rb.integrators.ImplicitGyroscopic(), h)(params, state)
    ratio = float(rb.kinetic_energy(params, one)[0]) / e0
    print(f"single Newton step: E1/E0 = {ratio:.1f}")
    assert ratio > 3.0  # measured 230
    assert float(rb.kinetic_energy(params, converged)[0]) <= e0 * (1 + 1e-12)


def test_spinning_rod():
    """I = (1e-4, 1, 1 + 5e-5), w0 = (100, 1, 0), h = 0.01, 10 s: |w1| h = 1 about the minor axis."""
    scene, params, state = top((1e-4, 1.0, 1.0 + 5e-5), np.array([100.0, 1.0, 0.0]))
    report = {}
    for name, integrator in ALL.items():
        traj = trajectory(scene, integrator, params, state, 0.01, 1000, save_every=10)
        e = energies(params, traj)
        report[name] = (e[-1] / e[0], momentum_error(traj))
    print("E_end/E0, world L error:", {k: (f"{a:.4g}", f"{b:.1e}") for k, (a, b) in report.items()})
    ratio, drift = report["SymplecticSplitting"]
    assert ratio >= 0.99 and drift <= 1e-6  # measured 0.999995 and 0


def flip_times(times, values, count=3):
    signs = np.sign(values)
    idx = np.flatnonzero(signs[1:] != signs[:-1])[:count]
    return times[idx] - values[idx] * (times[idx + 1] - times[idx]) / (values[idx + 1] - values[idx])


@pytest.mark.parametrize("name", SECOND_ORDER_OR_HIGHER)
def test_dzhanibekov_flip_times(name):
    """I = (1, 2, 3), w0 = (1e-3, 1, 1e-3), h = 0.01: first three sign changes of w2."""
    omega0 = np.array([1e-3, 1.0, 1e-3])
    scene, params, state = top(omega0=omega0)
    traj = trajectory(scene, ALL[name], params, state, 0.01, 7200)
    omega2 = np.asarray(jax.vmap(rb.body_angular_velocity, in_axes=(None, 0))(params, traj))[:, 0, 1]
    flips = flip_times(np.asarray(traj.time), omega2)
    # Measured within 7.3e-7 (splitting) to 7.2e-6 (midpoint) relative: what remains is
    # mostly the rounding of the targets to 1 ms (the exact first flip is 14.9059389 s).
    np.testing.assert_allclose(flips, [14.906, 42.437, 69.968], rtol=1e-3)


def heavy_top_scene(mgl=4.905):
    def gravity_torque(t, params, state):
        axis = rb.rotation_matrix(state)[:, :, 2]  # symmetry axis, world frame
        down = jnp.zeros_like(axis).at[:, 2].set(-1.0)
        return jnp.zeros_like(axis), mgl * spatial.cross(axis, down)

    # Inertia about the pivot: with the pivot fixed, L_pivot' = tau_pivot is the free
    # body's equation with the pivot inertia, so the translational part is left idle.
    return rb.Scene([rb.Body("top", mass=1.0, inertia=(1.0, 1.0, 0.5))], gravity=None,
                    forces=[rb.ExternalWrench(gravity_torque)])


def test_heavy_top_against_closed_form():
    """I1 = 1, I3 = 0.5 about the pivot, Mgl = 4.905, w3 = 20, theta0 = 0.6; h = 0.01, 10 s."""
    scene = heavy_top_scene()
    params = scene.params()
    theta0 = 0.6
    state = scene.state(params, orientation=spatial.quat_from_axis_angle(jnp.array([1.0, 0.0, 0.0]), theta0),
                        body_angular_velocity=(0.0, 0.0, 20.0))
    traj = trajectory(scene, rb.integrators.RK4(), params, state, 0.01, 1000)
    exact = rb.exact.heavy_symmetric_top(1.0, 0.5, 4.905, 20.0, theta0, np.asarray(traj.time))
    assert exact.nutation_period == pytest.approx(0.684114, rel=1e-6)
    cos_theta = np.asarray(rb.rotation_matrix(traj)[:, 0, 2, 2])
    error = np.max(np.abs(cos_theta - exact.cos_theta))
    print(f"RK4 heavy top: max |cos theta - exact| = {error:.2e}")
    assert error <= 1e-3  # measured 1.9e-6


# ---------------------------------------------------------------------------- forces


def test_forced_convergence_orders_with_springs_damping_and_time():
    """Position-, velocity- and time-dependent forces and torques: every field at its order.

    This checks the kick-drift-kick composition (second order also with damping) and
    RKMK4's stages, against an independent scipy solve of the world-frame equations.
    """
    mass, k_spring, c_lin, c_ang = 1.3, 4.0, 0.3, 0.2
    inertia = np.array([[2.0, 0.3, 0.0], [0.3, 1.5, 0.1], [0.0, 0.1, 3.0]])

    def user_wrench(t, params, state):
        force = -k_spring * state.position
        torque = jnp.stack([0.5 * jnp.cos(t), -0.3 * jnp.sin(2 * t), 0.2 + 0.0 * t])[None]
        return force, torque

    scene = rb.Scene([rb.Body("body", mass=mass, inertia=inertia)], gravity=(0.0, 0.0, -9.81),
                     forces=[rb.ExternalWrench(user_wrench), rb.LinearDamping(), rb.AngularDamping()])
    params = scene.params(linear_damping=c_lin, angular_damping=c_ang)
    x0, v0, l0 = np.array([0.1, 0.2, 0.3]), np.array([1.0, 0.0, -0.5]), np.array([0.5, 2.0, -1.0])
    q0 = np.asarray(spatial.quat_from_axis_angle(jnp.array([1.0, -1.0, 0.5]), 0.8))
    state = scene.state(params, position=x0, velocity=v0, orientation=q0, angular_momentum=l0)

    inertia_inv = np.linalg.inv(inertia)

    def rhs(t, y):
        x, v, q, l_world = y[:3], y[3:6], y[6:10], y[10:]
        r = reference.quat_to_matrix(q)
        omega = r @ inertia_inv @ r.T @ l_world
        force = -k_spring * x - c_lin * v + mass * np.array([0.0, 0.0, -9.81])
        torque = np.array([0.5 * np.cos(t), -0.3 * np.sin(2 * t), 0.2]) - c_ang * omega
        dq = 0.5 * reference._qmul(np.concatenate([[0.0], omega]), q)
        return np.concatenate([v, force / mass, dq, torque])

    t_final = 2.0
    sol = solve_ivp(rhs, (0.0, t_final), np.concatenate([x0, v0, q0, l0]), method="DOP853", rtol=1e-13, atol=1e-14)
    y = sol.y[:, -1]
    x_ref, v_ref, r_ref, l_ref = y[:3], y[3:6], reference.quat_to_matrix(y[6:10]), y[10:]
    for name in ("ImplicitGyroscopic", "ImplicitMidpoint", "SymplecticSplitting", "RKMK4"):
        hs, errors = [], {"x": [], "v": [], "q": [], "L": []}
        for k in range(5):
            h = 0.05 * 2.0**-k
            final, _ = rb.rollout(rb.make_step(scene, ALL[name], h), params, state, round(t_final / h),
                                  save_every=round(t_final / h))
            hs.append(h)
            errors["x"].append(np.linalg.norm(final.position[0] - x_ref))
            errors["v"].append(np.linalg.norm(final.velocity[0] - v_ref))
            errors["q"].append(reference.rotation_angle(r_ref, np.asarray(rb.rotation_matrix(final)[0])))
            errors["L"].append(np.linalg.norm(final.angular_momentum[0] - l_ref))
        for field, err in errors.items():
            slope = np.polyfit(np.log(hs), np.log(err), 1)[0]
            # Errors stay far above the reference's ~1e-12; measured within 0.041 of the order.
            assert abs(slope - NOMINAL_ORDER[name]) <= 0.15, (name, field, slope, err)


# --------------------------------------------------------------------------- float32


@pytest.mark.parametrize("name", list(ALL))
def test_float32_unit_quaternion_after_1e5_steps_and_tiny_steps(name):
    scene, params, state = top(dtype=jnp.float32)
    integrator = ALL[name]
    traj = trajectory(scene, integrator, params, state, 0.01, 100_000, save_every=1000)
    norm_error = np.max(np.abs(np.linalg.norm(np.asarray(traj.orientation[:, 0], dtype=np.float64), axis=-1) - 1))
    assert norm_error <= 1e-6, norm_error  # renormalised every step: float32 round-off
    # h = 1e-6: updates are ~1e-6 of the state, near float32's resolution. Nothing may
    # blow up: finite, unit quaternion, energy within float32 round-off accumulation.
    tiny = trajectory(scene, integrator, params, state, 1e-6, 10_000, save_every=100)
    for leaf in jax.tree.leaves(tiny):
        assert np.all(np.isfinite(leaf))
    e = energies(params, tiny)
    assert np.max(np.abs(e / e[0] - 1)) <= 1e-3  # 1e4 steps x 6e-8 worst-case rounding


# ------------------------------------------------------------------------- validation


def test_invalid_integrator_options():
    with pytest.raises(ValueError, match="positive integer"):
        rb.integrators.ImplicitMidpoint(iterations=0)
    with pytest.raises(ValueError, match="positive integer"):
        rb.integrators.ImplicitGyroscopic(iterations=2.5)
    with pytest.raises(ValueError, match="stages"):
        rb.integrators.ImplicitGyroscopic(stages=0)
    with pytest.raises(ValueError, match="stages"):
        rb.integrators.ImplicitMidpoint(stages=-1)
    with pytest.raises(ValueError, match="permutation"):
        rb.integrators.SymplecticSplitting(axes=(0, 0, 1))
    # Refused at construction, not at trace time ("Indexer must have integer type").
    with pytest.raises(ValueError, match="permutation"):
        rb.integrators.SymplecticSplitting(axes=(0, 1, 2.0))
    with pytest.raises(ValueError, match="positive integer"):
        rb.integrators.ImplicitGyroscopic(iterations=True)


def test_integer_options_of_any_integer_type_are_accepted():
    # A NumPy integer is a positive integer (it was refused), and a list of axes is taken
    # as the tuple it means (it passed the check, then failed at step time: unhashable).
    gyro = rb.integrators.ImplicitGyroscopic(iterations=np.int64(4), stages=np.int32(2))
    assert (gyro.iterations, gyro.stages) == (4, 2) and type(gyro.iterations) is int
    assert rb.integrators.ImplicitMidpoint(iterations=np.int64(5)).iterations == 5
    split = rb.integrators.SymplecticSplitting(axes=[2, 1, 0])
    assert split.axes == (2, 1, 0) and hash(split) == hash(rb.integrators.SymplecticSplitting(axes=(2, 1, 0)))
    # A NumPy array and a range too (refused as "not a permutation of (0, 1, 2)").
    assert rb.integrators.SymplecticSplitting(axes=np.array([2, 1, 0])) == split
    assert rb.integrators.SymplecticSplitting(axes=range(3)).axes == (0, 1, 2)
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0)])
    params = scene.params(dtype=jnp.float64)
    state = scene.state(params, angular_velocity=(0.3, 2.0, 0.1))
    for integrator in (gyro, split):
        out = rb.make_step(scene, integrator, 1e-3)(params, state)
        assert np.all(np.isfinite(np.asarray(out.orientation)))


SYMMETRIC_DIRECTIONS = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]


def _inertia_from_entries(entries):
    """The symmetric ``(3, 3)`` with ``entries`` at SYMMETRIC_DIRECTIONS' places."""
    inertia = jnp.zeros((3, 3), entries.dtype)
    for (i, j), value in zip(SYMMETRIC_DIRECTIONS, entries, strict=True):
        inertia = inertia.at[i, j].set(value).at[j, i].set(value)
    return inertia


@functools.cache
def _splitting_inertia_gradient(dt, num_steps, dtype, integrator="SymplecticSplitting"):
    """``(entries, q0, l0, weights) -> d(weights . q(T)) / d entries`` of a torque-free body
    under ``integrator``, compiled once for every inertia (the scene's is replaced)."""
    scene = rb.Scene([rb.Body("body", mass=1.0, inertia=(1.0, 2.0, 3.0))], gravity=None)
    step = rb.make_step(scene, ALL[integrator], dt)
    params = scene.params(dtype=dtype)

    def loss(entries, q0, l0, weights):
        p = params.replace(inertia=_inertia_from_entries(entries)[None])
        state = scene.state(p, orientation=q0, dtype=dtype).replace(angular_momentum=l0[None])
        final, _ = rb.rollout(step, p, state, num_steps)
        return weights @ final.orientation[0]

    return jax.jit(jax.grad(loss))


def _flow_inertia_derivative(moments, axis, angle, duration=1.0):
    """The inertia (principal ``moments`` turned by ``angle`` about ``axis``) as its six
    entries, a start ``(q0, l0)``, loss weights, and the flow's derivative of
    ``weights . q(duration)`` in the entries: central differences (1e-5) of scipy's DOP853
    solution of the world-frame equations, a smooth function of the inertia everywhere
    (repeated moments or not)."""
    rotation = np.asarray(reference.quat_to_matrix(np.concatenate(
        [[np.cos(angle / 2)], np.sin(angle / 2) * np.asarray(axis) / np.linalg.norm(axis)])))
    inertia0 = rotation @ np.diag(moments) @ rotation.T
    entries0 = np.array([inertia0[i, j] for i, j in SYMMETRIC_DIRECTIONS])
    q0 = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
    l0 = np.array([1.0, 0.5, 2.0])  # world angular momentum, held fixed as the inertia varies
    weights = np.array([0.3, 1.0, 2.0, -1.0])

    def reference_loss(entries):
        inertia = np.zeros((3, 3))
        for (i, j), value in zip(SYMMETRIC_DIRECTIONS, entries, strict=True):
            inertia[i, j] = inertia[j, i] = value
        zero = lambda t: np.zeros(3)  # noqa: E731
        q = reference.forced_body_world_frame(1.0, inertia, zero, zero, np.zeros(3), np.zeros(3), q0, l0,
                                              np.array([0.0, duration]))[2][-1]
        return weights @ q

    eps = 1e-5
    expected = np.array([(reference_loss(entries0 + eps * e) - reference_loss(entries0 - eps * e)) / (2 * eps)
                         for e in np.eye(6)])
    return entries0, q0, l0, weights, expected


@pytest.mark.parametrize("moments, axis, angle", [
    ((1.0, 1.0, 2.0), (0.0, 0.0, 1.0), 0.0),  # an axisymmetric body in its principal frame
    ((1.0, 1.0, 1.0), (0.0, 0.0, 1.0), 0.0),  # a sphere
    ((0.5, 1.5, 1.5), (1.0, -2.0, 0.5), 0.7),  # a rotated axisymmetric body: no zero entries
], ids=["axisymmetric", "sphere", "rotated"])
def test_splitting_derivatives_in_the_inertia_at_repeated_moments_are_the_flows(moments, axis, angle):
    """At repeated principal moments the principal axes are not unique, and the splitting's
    derivative in a symmetry-breaking direction of the inertia (I_01 of a sphere) was 0,
    while the flow's is not. Reference: central differences of scipy's DOP853 solution of
    the world-frame equations (a smooth function of the inertia there). The splitting's
    derivative converges to it at second order."""
    entries0, q0, l0, weights, expected = _flow_inertia_derivative(moments, axis, angle)
    duration = 1.0
    assert abs(expected[3]) > 0.05  # the loss does depend on the symmetry-breaking entry I_01

    def gradient(dt, dtype=jnp.float64):
        args = [jnp.asarray(x, dtype) for x in (entries0, q0, l0, weights)]
        return np.asarray(_splitting_inertia_gradient(dt, round(duration / dt), dtype)(*args), float)

    coarse, fine = gradient(1e-2), gradient(5e-3)
    scale = np.max(np.abs(expected))
    # Measured when written (axisymmetric, sphere, rotated): the coarse step's largest error
    # 1.9e-5, 4.8e-5, 8.7e-6 of the largest entry; the ratio of the two steps' errors 4.000
    # (second order); float32 within 8e-7, 2.2e-6, 7.5e-7 of float64. Before the repeated
    # moments' coupling, I_01 of the first two got 0 instead of -0.358 and 0.865.
    assert np.max(np.abs(coarse - expected)) < 2e-4 * scale
    error_ratio = np.max(np.abs(coarse - expected)) / np.max(np.abs(fine - expected))
    assert 3.9 < error_ratio < 4.1
    single = gradient(1e-2, jnp.float32)
    assert np.all(np.isfinite(single))
    np.testing.assert_allclose(single, coarse, atol=2e-5 * scale)


def test_splitting_inertia_gradients_of_an_ensemble_equal_each_members():
    """The repeated moments' coupling under vmap (an ensemble of inertias, one of them a
    sphere's) with its derivative: a zero made as a constant there failed jax's
    linearisation ("broadcast_dimensions must have length equal to operand ndim")."""
    gradient = _splitting_inertia_gradient(1e-2, 10, jnp.float64)
    entries = jnp.array([[1.0, 1.0, 1.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0, 0.1, 0.0, -0.2]])
    q0, l0, weights = jnp.array([1.0, 0.0, 0.0, 0.0]), jnp.array([1.0, 0.5, 2.0]), jnp.array([0.3, 1.0, 2.0, -1.0])
    batched = jax.jit(jax.vmap(gradient, in_axes=(0, None, None, None)))(entries, q0, l0, weights)
    for k in range(2):
        np.testing.assert_allclose(batched[k], gradient(entries[k], q0, l0, weights), rtol=1e-12, atol=1e-14)
    assert float(jnp.abs(batched[0, 3])) > 1e-3  # the sphere's symmetry-breaking derivative


def _inertia_gradient_is_symmetric(gradient):
    gradient = np.asarray(gradient)
    assert np.all(np.isfinite(gradient)) and np.max(np.abs(gradient)) > 1e-3
    # Measured: asymmetric by at most 4.4e-16 (round-off). Before, every integrator's free
    # body gradient below was asymmetric by 1.9 to 2.0 (absolute; the initial state's
    # ``L = I w`` too read the inertia as it was).
    np.testing.assert_allclose(gradient, gradient.T, rtol=0, atol=1e-13 * np.max(np.abs(gradient)))


@pytest.mark.parametrize("name", sorted(ALL))
def test_inertia_gradients_are_symmetric_so_a_gradient_step_keeps_the_inertia_symmetric(name):
    """Every step reads the inertia's symmetric part (``state.body_inertia``), so the
    gradient in ``params.inertia`` is symmetric. Read as it was, ``I^-1`` gave RK4 the
    rank-one gradient ``-a w^T``: one plain gradient step on ``params.inertia`` made it
    asymmetric, and the integrators split it differently between ``I_ij`` and ``I_ji``."""
    inertia = np.array([[2.0, 0.1, -0.05], [0.1, 2.5, 0.2], [-0.05, 0.2, 3.0]])
    scene = rb.Scene([rb.Body("body", mass=1.0, inertia=inertia)], gravity=None)
    step = rb.make_step(scene, ALL[name], 1e-2)

    def loss(p):
        state = scene.state(p, orientation=spatial.quat_normalize(jnp.array([0.9, 0.1, -0.3, 0.2])),
                            angular_velocity=(0.4, -1.0, 0.7), dtype=jnp.float64)
        final, _ = rb.rollout(step, p, step.prepare(state), 20)
        return jnp.sum(final.orientation[0] * jnp.array([0.3, 1.0, 2.0, -1.0])) + jnp.sum(final.angular_momentum[0])

    _inertia_gradient_is_symmetric(jax.grad(loss)(scene.params(dtype=jnp.float64)).inertia[0])


def test_inertia_gradients_through_a_frictional_impact_are_symmetric():
    """The same through the contact solve, which reads the world inertia and its inverse:
    a spinning box landing on a corner with friction. Before, the gradient's largest
    asymmetry was 6.1 (its largest entry 11.4; the symmetric parts agree)."""
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.3)], gravity=None,
                     ground=rb.Plane(), contacts="all")
    q = spatial.quat_normalize(jnp.array([0.9, 0.1, -0.3, 0.2]))
    corners = jnp.array([[sx * 0.1, sy * 0.2, sz * 0.3] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    height = -jnp.min(spatial.quat_rotate(q[None], corners)[:, 2])

    def loss(p):
        state = scene.state(p, position=jnp.stack([0.0, 0.0, height]), orientation=q, velocity=(1.0, 0.5, -2.0),
                            angular_velocity=(3.0, -1.0, 5.0), dtype=jnp.float64)
        after = rb.contact.resolve_impacts(scene, p, state)
        return jnp.sum(after.velocity[0] * jnp.array([1.0, -2.0, 0.5])) + jnp.sum(after.angular_momentum[0])

    params = scene.params(friction=0.5, restitution=0.5, dtype=jnp.float64)
    _inertia_gradient_is_symmetric(jax.jit(jax.grad(loss))(params).inertia[0])


@pytest.mark.parametrize("moments", [(1.0, 1.0, 1.8), (1.0, 1.8, 1.8), (1.0, 1.0, 1.0)],
                         ids=["smaller-pair", "larger-pair", "sphere"])
def test_symmetric_top_splitting_derivatives_at_repeated_moments_are_its_maps(moments):
    """At exactly repeated moments the principal axes in the pair's plane are held fixed and
    a symmetry-breaking perturbation enters through the repeated moments' coupling. Its
    smaller pair's block was applied outside the chain, where the perturbed map has it in
    k_0's turn in the middle: the gradient of a top with two equal smaller moments was
    2.5e-4 of the largest entry off the central differences of the integrator's own map
    (dt = 0.05; stop 89's review), the larger pair's and the sphere's 1e-9. Now all three
    agree with the map (measured 6.4e-10 or better) and stay within dt^2 of the flow's
    derivative (scipy; measured 9.9e-5, 7.7e-5 and 1.5e-10)."""
    entries0, q0, l0, weights, expected = _flow_inertia_derivative(moments, (1.0, -2.0, 0.5), 0.7)
    dt, steps = 0.05, 20
    scene = rb.Scene([rb.Body("body", mass=1.0, inertia=(1.0, 2.0, 3.0))], gravity=None)
    step = rb.make_step(scene, ALL["SymmetricTopSplitting"], dt)
    params = scene.params()

    @jax.jit
    def loss(entries):
        p = params.replace(inertia=_inertia_from_entries(entries)[None])
        state = scene.state(p, orientation=q0).replace(angular_momentum=jnp.asarray(l0)[None])
        return jnp.asarray(weights) @ rb.rollout(step, p, state, steps)[0].orientation[0]

    entries0 = jnp.asarray(entries0)
    gradient = np.asarray(jax.jit(jax.grad(loss))(entries0))
    eps = 1e-6
    central = np.array([(loss(entries0 + eps * e) - loss(entries0 - eps * e)) / (2 * eps) for e in jnp.eye(6)])
    scale = np.max(np.abs(central))
    print(moments, np.max(np.abs(gradient - central)) / scale, np.max(np.abs(gradient - expected)) / scale)
    assert np.max(np.abs(gradient - central)) < 1e-7 * scale
    assert np.max(np.abs(gradient - expected)) < 1e-3 * scale


@pytest.mark.parametrize("delta", [1e-3, 1e-7])
def test_symmetric_top_splitting_inertia_derivatives_stay_accurate_at_nearly_repeated_moments(delta):
    """Moments (1, 1 + delta, 1.8), turned so that no entry is zero, dt = 0.01 over 1 s,
    against the flow's derivative (scipy). SymplecticSplitting splits the nearly degenerate
    pair, whose axes turn at ~1/delta with the inertia: its derivative carries an
    O(dt^2 / delta) error (its documented limit; this setup shows it: 2.6e-2 of the largest
    entry at delta = 1e-3, 2.7e2 at 1e-7). SymmetricTopSplitting keeps the pair together:
    measured 3.9e-6 of the largest entry at both deltas."""
    entries0, q0, l0, weights, expected = _flow_inertia_derivative((1.0, 1.0 + delta, 1.8), (1.0, -2.0, 0.5), 0.7)
    args = [jnp.asarray(x) for x in (entries0, q0, l0, weights)]
    scale = np.max(np.abs(expected))
    error = {name: np.max(np.abs(np.asarray(_splitting_inertia_gradient(1e-2, 100, jnp.float64, name)(*args))
                                 - expected)) / scale for name in ("SymplecticSplitting", "SymmetricTopSplitting")}
    print(delta, error)
    assert error["SymmetricTopSplitting"] < 1e-5
    if delta < 1e-6:
        assert error["SymplecticSplitting"] > 1.0  # the limit this integrator is for


@pytest.mark.parametrize("moments", [(1.0, 1.0, 1.8), (1.0, 1.8, 1.8)], ids=["oblate", "prolate"])
def test_symmetric_top_splitting_is_exact_for_symmetric_tops(moments):
    """With two equal moments the split's two corrections commute (one is zero), so the
    step is the exact flow at any dt: 100 steps of 0.1 s (|omega| dt = 0.26) against the
    closed form, measured within 1.5e-14 rad. SymplecticSplitting, second order, is 0.05
    (oblate) and 0.10 rad (prolate) off at this step. Nearly symmetric (1, 1.05, 1.8) it is
    not exact, but 290x closer to the closed form than SymplecticSplitting at dt = 0.01 over
    10 s (measured 1.7e-6 against 4.8e-4 rad)."""
    omega0 = np.array([0.3, 2.5, -0.5])

    def error(moments, integrator, dt, steps):
        scene, params, state = top(moments, omega0)
        final, _ = rb.rollout(rb.make_step(scene, ALL[integrator], dt), params, state, steps)
        exact = rb.exact.torque_free_top(np.asarray(moments), omega0, np.array([dt * steps])).orientation[0]
        q = np.asarray(final.orientation[0])
        return 2 * min(np.linalg.norm(q - exact), np.linalg.norm(q + exact))

    assert error(moments, "SymmetricTopSplitting", 0.1, 100) < 1e-12
    assert error(moments, "SymplecticSplitting", 0.1, 100) > 1e-4
    # The same top turned in its body frame (a full inertia tensor, principal axes found by
    # the step), from a turned attitude, against scipy's DOP853 of the world-frame equations
    # (rtol 1e-13): measured 6.2e-13 (oblate) and 2.4e-12 rad (prolate), the reference's own error;
    # SymplecticSplitting 0.085 and 0.10 rad.
    axis_quat = np.array([0.8, 0.2, -0.5, 0.3]) / np.linalg.norm([0.8, 0.2, -0.5, 0.3])
    turn = np.asarray(reference.quat_to_matrix(axis_quat))
    inertia = turn @ np.diag(moments) @ turn.T
    q0 = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
    scene = rb.Scene([rb.Body("body", mass=1.0, inertia=inertia)], gravity=None)
    params = scene.params()
    state = scene.state(params, orientation=q0, body_angular_velocity=omega0)
    final, _ = rb.rollout(rb.make_step(scene, ALL["SymmetricTopSplitting"], 0.1), params, state, 100)
    zero = lambda t: np.zeros(3)  # noqa: E731
    expected = reference.forced_body_world_frame(1.0, inertia, zero, zero, np.zeros(3), np.zeros(3), q0,
                                                 np.asarray(state.angular_momentum[0]), np.array([0.0, 10.0]))[2][-1]
    q = np.asarray(final.orientation[0])
    assert 2 * min(np.linalg.norm(q - expected), np.linalg.norm(q + expected)) < 1e-10
    near = (1.0, 1.05, 1.8)
    assert error(near, "SymmetricTopSplitting", 0.01, 1000) < error(near, "SymplecticSplitting", 0.01, 1000) / 20
