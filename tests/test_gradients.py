"""Gradients through rollouts and impacts against closed forms and finite differences (float64).

Also see ``test_contact.py`` (bounce gradients in forward mode against finite differences,
the two-ball swap Jacobian with the impact inside a step, in both modes, with the time
of impact's derivative) and ``test_transforms.py``
(mass, inertia and initial-state gradients of smooth rollouts to 1e-6, checkpointing).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrb as rb

G = 9.81


def _differences_of(fn):
    """``at(x, eps, *args)``: central differences of ``fn(x, *args) -> (m,)`` in ``x: (k,)``,
    shape ``(m, k)``, all perturbations in one vmapped call. One compiled program serves
    every call of ``at`` (``args``, unbatched, are its arguments, not constants)."""
    shifted = jax.jit(lambda xs, args: jax.vmap(lambda x: fn(x, *args))(xs))

    def at(x, eps, *args):
        x = np.asarray(x, float)
        shifts = np.concatenate([np.eye(x.size), -np.eye(x.size)]) * eps
        values = np.asarray(shifted(jnp.asarray(x[None] + shifts), args))
        return ((values[: x.size] - values[x.size:]) / (2 * eps)).T

    return at


def _central_differences(fn, x, eps):
    """Central differences of ``fn: (k,) -> (m,)`` at ``x``, shape ``(m, k)``."""
    return _differences_of(fn)(x, eps)


def test_apex_heights_have_the_analytic_derivative_in_restitution():
    """h_n = e^(2n) h0, so dh_n/de = 2n e^(2n-1) h0; the impacts fall inside steps."""
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    dt = 1e-2
    step = rb.make_step(scene, rb.integrators.SemiImplicitEuler(), dt)
    e0, h0 = 0.8, 1.0
    t1 = np.sqrt(2 * h0 / G)  # first impact
    impacts = t1 + np.cumsum([0.0] + [2 * e0**k * t1 for k in range(1, 3)])
    apex_steps = np.round((impacts + e0 ** np.arange(1, 4) * t1) / dt).astype(int)  # one per flight

    def apexes(e):
        params = scene.params(restitution=0.5, dtype=jnp.float64).replace(restitution=e[None])
        state = scene.state(params, position=(0.0, 0.0, 0.1 + h0))
        _, traj = rb.rollout(step, params, state, int(apex_steps[-1]))
        z, vz = traj.position[apex_steps - 1, 0, 2], traj.velocity[apex_steps - 1, 0, 2]
        return z - 0.1 + vz**2 / (2 * G)  # the flight's apex, from its energy

    e = jnp.asarray(e0)
    n = np.arange(1, 4)
    np.testing.assert_allclose(apexes(e), e0 ** (2 * n) * h0, rtol=1e-9)
    derivative = jax.jit(jax.jacfwd(apexes))(e)
    np.testing.assert_allclose(derivative, 2 * n * e0 ** (2 * n - 1) * h0, rtol=1e-4)  # measured: 3e-14


def test_gravity_force_and_damping_gradients_match_finite_differences():
    """A smooth rollout: d/d(gravity, applied force amplitude, damping) to 1e-6."""

    def push(t, params, state):
        amplitude = params.extra
        force = jnp.stack([amplitude[0] * jnp.sin(2 * t), amplitude[1], 0.0 * t])[None]
        torque = jnp.stack([0.0 * t, amplitude[2] * jnp.cos(3 * t), 0.1 + 0.0 * t])[None]
        return force, torque

    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=2.0)],
                     forces=[rb.ExternalWrench(push), rb.LinearDamping(), rb.AngularDamping()])
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-2)
    base = scene.params(dtype=jnp.float64, extra=jnp.asarray([1.0, -0.5, 0.3]))
    state = scene.state(base, velocity=(1.0, 0.0, 2.0), angular_velocity=(0.5, 2.0, -1.0))

    def final(x):
        params = base.replace(gravity=x[:3], extra=x[3:6], linear_damping=x[6:7], angular_damping=x[7:8])
        end, _ = rb.rollout(step, params, state, 100)
        return jnp.concatenate([end.position[0], end.orientation[0], end.angular_momentum[0]])

    x0 = jnp.asarray([0.3, -0.2, -9.81, 1.0, -0.5, 0.3, 0.2, 0.05])
    jac = np.asarray(jax.jit(jax.jacrev(final))(x0))
    fd = _central_differences(final, x0, 1e-6)
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-9)
    assert np.all(np.max(np.abs(fd), axis=0) > 1e-3)  # every parameter matters


@pytest.mark.slow
def test_friction_gradients_across_contact_match_finite_differences():
    """A box sliding to rest: d(x)/d(mu, v0) while sliding and at rest, against central differences.

    (Reverse mode through friction is in ``test_contact.py``'s bounce test; forward mode
    here compiles in a third of the time.)
    """
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.1, 0.1)), mass=1.0)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(scene, rb.integrators.SemiImplicitEuler(), 1e-2)

    def slide(x):
        params = scene.params(friction=0.5, dtype=jnp.float64).replace(friction=x[:1])
        state = scene.state(params, position=(0.0, 0.0, 0.1), velocity=jnp.stack([x[1], 0.0, 0.0]))
        end, traj = rb.rollout(step, params, state, 100)
        return jnp.stack([end.position[0, 0], traj.position[29, 0, 0]])  # at rest (t = 1 s), sliding (0.3 s)

    x0 = jnp.asarray([0.4, 3.0])
    jac = np.asarray(jax.jit(jax.jacfwd(slide))(x0))
    fd = _central_differences(slide, x0, 1e-6)
    np.testing.assert_allclose(jac, fd, rtol=1e-4)
    # And they are the physics. Sliding, x = v0 t - mu g t^2 / 2 (exact under the step's
    # kick-drift-kick); at rest, x = v0^2 / (2 mu g) up to the stopping step's O(h).
    t = 0.3
    np.testing.assert_allclose(jac[1], [-G * t**2 / 2, t], rtol=1e-6)
    np.testing.assert_allclose(jac[0], [-9.0 / (2 * 0.16 * G), 3.0 / (0.4 * G)], rtol=0.03)


def test_a_box_spinning_as_it_slides_on_a_face_has_the_gradients_of_finite_differences():
    """Four corners on a face make the resting solve's normal impulses redundant: the
    sweep's Jacobian at the solution has eigenvalue 1 along a redistribution of the
    corners' loads, which changes the friction's torque once the corners slip different
    ways (the box spins). The frozen derivative did not forget the warm start along it:
    after 60 steps its derivatives were up to 2.8e-6 off central differences (the mass
    derivative of the summed positions 1.6e-3 relative after 200). Such a solve now takes
    the sweeps' own derivative."""
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.15, 0.05)), mass=1.0)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)

    def slide(x):
        params = scene.params(friction=0.3, dtype=jnp.float64).replace(friction=x[:1], mass=x[1:2])
        state = scene.state(params, position=(0.0, 0.0, 0.0497), velocity=jnp.stack([x[2], 0.0, 0.0]),
                            angular_velocity=jnp.stack([0.0, 0.0, x[3]]))
        end, _ = rb.rollout(step, params, step.prepare(state), 60)
        return jnp.concatenate([end.position[0, :2], end.orientation[0, 3:]])

    x0 = jnp.asarray([0.3, 1.0, 3.0, 5.0])
    jac = np.asarray(jax.jit(jax.jacfwd(slide))(x0))
    fd = _central_differences(slide, x0, 1e-6)
    assert np.abs(fd[:, 1]).max() > 1e-4  # the mass matters: the inertia is held
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-8)  # measured 2.6e-10; 2.8e-6 before


@pytest.mark.slow
def test_rolling_cylinder_gradients_match_finite_differences_and_the_closed_form():
    """A can (r = 0.1 m) launched at v0 = 2 m/s without spin, mu = 0.3, from two starts
    that share the compiled programs (derivative, differences). Lying on the ground, on its two rim slots: it slides
    until t_r = v0 / (3 mu g) = 0.227 s, then rolls at 2 v0 / 3. Standing on its base
    (h_c = 0.15 m; mu h_c is under the square stance's r / sqrt(2)), on its five slots: it
    slides upright until v0 / (mu g) = 0.680 s. d(x)/d(mu, v0) against central
    differences (1e-4 relative, measured 2e-8) and the physics: sliding (t = 0.1 s),
    x = v0 t - mu g t^2 / 2 (1e-6); at t = 1 s, rolling, x = 2 v0 t / 3 + v0^2 / (18 mu g),
    and at rest, x = v0^2 / (2 mu g), within 1% (measured 0.4% and 0.1%: the step in
    which the motion changes)."""
    scene = rb.Scene([rb.Body("can", shape=rb.Cylinder(0.1, 0.15), mass=1.0)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
    lying = rb.spatial.quat_from_axis_angle(jnp.array([1.0, 0.0, 0.0]), np.pi / 2)  # axis along y
    starts = ((lying, jnp.asarray(0.1)), (jnp.array([1.0, 0.0, 0.0, 0.0]), jnp.asarray(0.15)))

    def slide(x, orientation, height):
        params = scene.params(friction=0.3, restitution=0.0, dtype=jnp.float64).replace(friction=x[:1])
        state = scene.state(params, position=jnp.stack([0.0, 0.0, height]), orientation=orientation,
                            velocity=jnp.stack([x[1], 0.0, 0.0]))
        end, traj = rb.rollout(step, params, state, 1000)
        return jnp.stack([end.position[0, 0], traj.position[99, 0, 0]])  # at t = 1 s, and sliding (0.1 s)

    # The start is an argument, not a constant, so both starts run the same two programs.
    x0 = np.array([0.3, 2.0])
    derivative, differences = jax.jit(jax.jacfwd(slide)), _differences_of(slide)
    jac = np.concatenate([np.asarray(derivative(jnp.asarray(x0), *start)) for start in starts])
    fd = np.concatenate([differences(x0, 1e-6, *start) for start in starts])
    np.testing.assert_allclose(jac, fd, rtol=1e-4)
    mu, v0, t = 0.3, 2.0, 0.1
    np.testing.assert_allclose(jac[[1, 3]], [[-G * t**2 / 2, t]] * 2, rtol=1e-6)
    np.testing.assert_allclose(jac[0], [-v0**2 / (18 * mu**2 * G), 2.0 / 3.0 + v0 / (9 * mu * G)], rtol=1e-2)
    np.testing.assert_allclose(jac[2], [-v0**2 / (2 * mu**2 * G), v0 / (mu * G)], rtol=1e-2)


@pytest.mark.slow
def test_two_ball_collision_gradients_match_finite_differences():
    """Masses, restitution and approach speed through a collision that falls inside a step."""
    scene = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0), rb.Body("b", shape=rb.Sphere(0.1), mass=1.0)],
                     gravity=None, contacts=[("a", "b")])
    step = rb.make_step(scene, rb.integrators.SemiImplicitEuler(), 1e-2)

    def after(x):
        params = scene.params(restitution=0.5, dtype=jnp.float64).replace(mass=x[:2], restitution=x[2:3])
        state = scene.state(params, position=[[-0.5, 0, 0], [0.5, 0, 0]],
                            velocity=jnp.stack([jnp.stack([x[3], 0.0, 0.0]), jnp.zeros(3)]))
        end, _ = rb.rollout(step, params, state, 60)
        return end.position[:, 0]

    x0 = jnp.asarray([1.0, 0.4, 0.9, 2.1])  # impact at t = 0.8 / 2.1 = 0.381 s: mid-step
    jac = np.asarray(jax.jit(jax.jacfwd(after))(x0))
    fd = _central_differences(after, x0, 1e-6)
    np.testing.assert_allclose(jac, fd, rtol=1e-4, atol=1e-9)
    # Closed form: v_b' = (1 + e) m_a v / (m_a + m_b); x_b(T) = 0.5 + v_b' (T - t_c).
    t_c, total = 0.8 / 2.1, 0.6
    m_a, m_b, v, e = 1.0, 0.4, 2.1, 0.9
    dxb_de = m_a * v / (m_a + m_b) * (total - t_c)
    np.testing.assert_allclose(jac[1, 2], dxb_de, rtol=1e-9)
    # In v, the time of impact's derivative too: d t_c / dv = -t_c / v.
    v_b = (1 + e) * m_a * v / (m_a + m_b)
    dxb_dv = (1 + e) * m_a / (m_a + m_b) * (total - t_c) + v_b * t_c / v
    np.testing.assert_allclose(jac[1, 3], dxb_dv, rtol=1e-9)


@pytest.mark.slow
def test_gradients_through_an_impact_on_a_resting_body_match_differences_and_the_closed_form():
    """A 0.5 kg box dropped flat from h = 0.3 m onto a 1000 kg table that rests on the
    ground (dt = 10 ms, the impact inside a step): d(z, v_z)/d(e, m, h) of the box in its
    first flight back up (T = 0.4 s), in forward mode, against central differences and the
    two-body closed form. With v = sqrt(2 g h), t_c = v / g, tau = T - t_c and
    r = (M e - m) / (M + m): v_z = r v - g tau and z = z_c + r v tau - g tau^2 / 2.

    The table's resting solve and its plastic stop on the ground must not leak into the
    box's derivatives (they did into its values until 2026-12-02: apex 0.5535 h0, not
    0.6386). Against differences 1e-4 (measured 4.1e-5, in m: the resting sweeps stop at
    the default tolerance sqrt(eps), and with ``tolerance=1e-15`` the gap is 3.6e-7); against
    the closed form 1e-6 in e (measured 7e-9) and 1e-4 in m and h (measured 4e-6 and 2e-6:
    the closed form leaves out the table's recoil into the ground)."""
    big, m, e, h, dt, steps = 1000.0, 0.5, 0.8, 0.3, 1e-2, 40
    bodies = [rb.Body("table", shape=rb.Box((0.3, 0.3, 0.05)), mass=big),
              rb.Body("box", shape=rb.Box((0.05, 0.05, 0.1)), mass=m)]
    scene = rb.Scene(bodies, ground=rb.Plane(), contacts=[("table", "ground"), ("box", "table")])
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), dt)

    def landed(x):
        base = scene.params(friction=0.5, restitution=0.8, dtype=jnp.float64)
        params = base.replace(restitution=base.restitution.at[1].set(x[0]), mass=base.mass.at[1].set(x[1]))
        position = jnp.stack([jnp.array([0.0, 0.0, 0.05]), jnp.stack([0.0, 0.0, 0.2 + x[2]])])
        end, _ = rb.rollout(step, params, step.prepare(scene.state(params, position=position)), steps)
        return jnp.stack([end.position[1, 2], end.velocity[1, 2]])

    x0 = jnp.asarray([e, m, h])
    jac = np.asarray(jax.jit(jax.jacfwd(landed))(x0))
    np.testing.assert_allclose(jac, _central_differences(landed, x0, 1e-6), rtol=1e-4)
    v = np.sqrt(2 * G * h)
    tau, r = steps * dt - v / G, (big * e - m) / (big + m)
    dr = np.array([big / (big + m), -big * (1 + e) / (big + m) ** 2])  # in e, m
    closed = np.array([[v * tau * dr[0], v * tau * dr[1], r * G * tau / v - r + G * tau / v],
                       [v * dr[0], v * dr[1], (r + 1) * G / v]])
    np.testing.assert_allclose(jac[:, 0], closed[:, 0], rtol=1e-6)
    np.testing.assert_allclose(jac[:, 1:], closed[:, 1:], rtol=1e-4)


@pytest.mark.slow
def test_stack_gradients_match_finite_differences_where_the_sweeps_have_not_converged():
    """A box pushed across another one, whose 4 PGS sweeps a step do not converge (the lower
    box creeps 1.8e-4 m in 0.15 s): the solver's derivative must still be the derivative of
    what it computed (measured 2e-8 relative). Freezing the sweeps' Jacobian at their last
    iterate (the fast path, right where they have converged) was 0.2-0.5% off here, and 10x
    off for the lower box. (Until 2026-12-02 this ran the default 20 sweeps, which did not
    converge only because the pair's manifold fell to one edge point now and then: see
    jaxrb.collision._box.EDGE_PREFERENCE. With its four points they nearly converge: the
    lower box's derivative in mu fell from over 1e-4 to 6e-6 m, too small to test this.)"""
    box = rb.Box((0.1, 0.1, 0.1))
    scene = rb.Scene([rb.Body("low", shape=box, mass=1.0), rb.Body("top", shape=box, mass=1.0)],
                     ground=rb.Plane(), contacts="all")
    step = rb.make_step(scene, rb.integrators.SemiImplicitEuler(), 1e-2, contact=rb.ContactSettings(iterations=4))

    def pushed(x):
        params = scene.params(dtype=jnp.float64).replace(friction=jnp.stack([x[0], x[0], x[0]]))  # 3 pairs
        velocity = jnp.stack([jnp.zeros(3), jnp.stack([x[1], 0.0, 0.0])])
        state = scene.state(params, position=((0.0, 0.0, 0.1), (0.0, 0.0, 0.3)), velocity=velocity)
        end, traj = rb.rollout(step, params, state, 40)
        return jnp.stack([traj.position[15, 1, 0], traj.position[15, 0, 0], end.position[1, 0]])

    x0 = jnp.asarray([0.4, 1.0])
    jac = np.asarray(jax.jit(jax.jacfwd(pushed))(x0))
    forward, eps = jax.jit(pushed), 1e-6  # not vmapped: compiles in half the time
    fd = np.stack([(np.asarray(forward(x0.at[i].add(eps))) - np.asarray(forward(x0.at[i].add(-eps)))) / (2 * eps)
                   for i in range(2)], -1)
    assert abs(fd[1, 0]) > 1e-4  # the lower box is dragged: the sweeps have not converged
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-9)


def test_an_implicit_roots_derivatives_to_second_order():
    """``jaxrb._implicit.implicit_root`` (the time of impact's derivative rule), on the root
    ``r = sqrt(p)`` of ``r^2 - p``: first derivative ``1/(2 sqrt p)``, second
    ``-p^(-3/2)/4``, by every composition of the modes, and under vmap. The rule had used
    the root without its tangent, so second derivatives came out 0 (stop 92's review)."""
    from jaxrb._implicit import implicit_root

    def root(p):
        return implicit_root(lambda r, p: r * r - p, jnp.sqrt(jax.lax.stop_gradient(p)), p, 1.0)

    p = jnp.asarray(2.0)
    np.testing.assert_allclose(jax.grad(root)(p), 0.5 / np.sqrt(2.0), rtol=1e-14)
    for second in (jax.grad(jax.grad(root)), jax.jacfwd(jax.jacrev(root)), jax.jacfwd(jax.jacfwd(root))):
        np.testing.assert_allclose(second(p), -0.25 * 2.0**-1.5, rtol=1e-14)
    np.testing.assert_allclose(jax.vmap(jax.grad(jax.grad(root)))(jnp.asarray([1.0, 4.0])), [-0.25, -0.25 / 8],
                               rtol=1e-14)
