"""rb.ode.solve_with_impacts: slow (plastic) impacts and short flights, against closed forms.

A ball of radius R dropped from height H above the ground (centre at H + R) first hits at
``t_0 = sqrt(2 H / g)`` with speed ``v_0 = sqrt(2 g H)``. Impact ``n`` approaches at
``v_0 e^n`` and, if that is above the restitution threshold, leaves at ``v_0 e^(n+1)``,
so the next impact comes ``2 v_0 e^(n+1) / g`` later. An approach slower than the
threshold is plastic (``e = 0``): the ball stays on the ground.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrb as rb

jax.config.update("jax_enable_x64", True)

G = 9.81
R = 0.1
H = 1.0
# Penetration allowed: each event after a restart below the ground comes a few ulps
# (3.6e-15 m) deeper, so any real miss (a pass through the ground) is far larger.
DEPTH = 1e-6


def ball_scene():
    return rb.Scene([rb.Body("ball", shape=rb.Sphere(R), mass=1.0)], gravity=(0, 0, -G), ground=rb.Plane(),
                    contacts="all")


def closed_form_impacts(e, n):
    """The first ``n`` impact times (s) and approach speeds (m/s) of the elastic bounce sequence."""
    v0 = np.sqrt(2 * G * H)
    speeds = v0 * e ** np.arange(n)
    times = np.sqrt(2 * H / G) + np.concatenate([[0.0], np.cumsum(2 * speeds[1:] / G)])
    return times, speeds


def assert_above_ground(sol):
    heights = np.asarray(sol.after_impact.position[:, 0, 2]) - R
    assert heights.min() >= -DEPTH, heights
    assert float(sol.final.position[0, 2]) - R >= -DEPTH


def test_slow_impacts_are_plastic_and_the_ball_rests():
    """e = 0.5, default threshold 0.25 m/s: impacts 0-4 bounce (closed-form times and
    rebound speeds), impact 5 approaches at v_0 / 32 = 0.138 m/s and is plastic, after
    which the ball stays on the ground (vz ~ 0, no sinking)."""
    e, threshold = 0.5, rb.ContactSettings().restitution_threshold
    scene = ball_scene()
    params = scene.params(restitution=e)
    state = scene.state(params, position=(0, 0, H + R))
    sol = rb.ode.solve_with_impacts(scene, params, state, 1.5, max_impacts=8)
    times, speeds = closed_form_impacts(e, 8)
    bouncing = int(np.sum(speeds > threshold))
    assert bouncing == 5  # the sequence this test is about: 5 bounces, then a plastic impact
    # Every located impact is counted; after the plastic one the ball rests, and resting
    # contact on this path is a sequence of impacts (each within atol of the ground).
    assert int(sol.num_impacts) == 8
    # The eight impacts are spent by t = 1.0 s, short of t1 = 1.5 s, and the result says so.
    assert float(sol.final.time) < 1.5 and not bool(sol.reached_t1)
    found = np.asarray(sol.impact_times)
    np.testing.assert_allclose(found[: bouncing + 1], times[: bouncing + 1], rtol=1e-9)
    vz = np.asarray(sol.after_impact.velocity[:, 0, 2])
    np.testing.assert_allclose(vz[:bouncing], speeds[1 : bouncing + 1], rtol=1e-6)
    # Plastic: the slow impact and every later one leave the ball at rest. (The later ones
    # are the resting ball caught again a few ulps below the ground, ~3e-8 s apart.)
    np.testing.assert_allclose(vz[bouncing:], 0.0, atol=1e-9)
    assert np.all(found[bouncing:] < times[bouncing] + 1e-6)
    assert abs(float(sol.final.velocity[0, 2])) <= 1e-9
    assert_above_ground(sol)


def test_short_flights_after_root_finding_are_not_missed():
    """e = 0.5, threshold 0 (every impact elastic) up to t1 = 1.36 s, after the flights'
    accumulation point t_0 + 2 v_0 e / (g (1 - e)) = 1.3546 s: all 16 allowed impacts are
    found at their closed-form times, however short the flight (the 16th follows a 28 us
    flight, shorter than the first adaptive step), and the ball never passes the ground."""
    e, t1, max_impacts = 0.5, 1.36, 16
    scene = ball_scene()
    params = scene.params(restitution=e)
    state = scene.state(params, position=(0, 0, H + R))
    sol = rb.ode.solve_with_impacts(scene, params, state, t1, max_impacts=max_impacts,
                                    contact=rb.ContactSettings(restitution_threshold=0.0))
    times, speeds = closed_form_impacts(e, max_impacts)
    expected = int(np.sum(times < t1))
    assert int(sol.num_impacts) == min(expected, max_impacts) == max_impacts
    # The last flights are 1e-9 m high. An event a few ulps (depth ~3.6e-15 m) below the
    # ground adds ~e g depth / v to a rebound: 1.3e-10 m/s at the 16th's 1.4e-4 m/s.
    np.testing.assert_allclose(np.asarray(sol.impact_times), times, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(sol.after_impact.velocity[:, 0, 2]), e * speeds, rtol=1e-6, atol=1e-9)
    assert_above_ground(sol)


def test_a_scene_with_contacts_is_refused_by_the_contact_free_solve_and_bad_input_by_this_one():
    """rb.ode.solve has no contacts: a ball dropped on the ground there fell through it (z = -3.8 m
    after 1 s, against a ground at 0.1) without a word. solve_with_impacts refuses an end time not
    after the start and contact settings of the wrong type."""
    scene = ball_scene()
    params = scene.params(restitution=0.8)
    state = scene.state(params, position=(0, 0, H + R))
    with pytest.raises(ValueError, match="solve_with_impacts"):
        rb.ode.solve(scene, params, state, 1.0)
    with pytest.raises(ValueError, match="later than the state's time"):
        rb.ode.solve_with_impacts(scene, params, state, 0.0)
    with pytest.raises(ValueError, match="rb.ContactSettings"):
        rb.ode.solve_with_impacts(scene, params, state, 1.0, contact="pgs")
    with pytest.raises(ValueError, match="atol = 1e-16 is below what float64 resolves"):
        rb.ode.solve_with_impacts(scene, params, state, 1.0, atol=1e-16)
    for count in (0, 2.0, True):
        with pytest.raises(ValueError, match="max_impacts must be a positive integer"):
            rb.ode.solve_with_impacts(scene, params, state, 1.0, max_impacts=count)
    # A count of any integer type (np.int64 from a config array had been refused).
    assert int(rb.ode.solve_with_impacts(scene, params, state, 0.5, max_impacts=np.int64(1)).num_impacts) == 1
    # Traced: an end time before the start had returned the start state, no impact, no error.
    solve = jax.jit(lambda s, t1: rb.ode.solve_with_impacts(scene, params, s, t1, max_impacts=2).final.time)
    with pytest.raises(Exception, match="need t1 > state.time"):
        jax.block_until_ready(solve(state.replace(time=jnp.asarray(2.0)), 1.0))


def test_float32_impacts_with_the_default_tolerances():
    """In float32 (JAX's default) the float64 defaults (1e-10, 1e-12) are under the dtype's
    rounding, and the impacts' root finder failed inside a callback; the defaults are now
    the dtype's (1e-6, 1e-6), and an atol under 4 eps is refused. The first six impact
    times against the closed form t_k = t_1 (1 + 2 e + ... + 2 e^(k-1)): measured 1.1e-5 s."""
    scene = ball_scene()
    params = scene.params(restitution=0.8, dtype=jnp.float32)
    state = scene.state(params, position=(0, 0, H + R))
    assert state.position.dtype == jnp.float32
    result = rb.ode.solve_with_impacts(scene, params, state, 3.5, max_impacts=6)
    with pytest.raises(ValueError, match="below what float32 resolves"):
        rb.ode.solve_with_impacts(scene, params, state, 1.0, atol=1e-7)
    t1 = np.sqrt(2 * H / G)
    expected = t1 * (1 + np.concatenate([[0.0], np.cumsum([2 * 0.8**k for k in range(1, 6)])]))
    assert int(result.num_impacts) == 6
    np.testing.assert_allclose(result.impact_times, expected, atol=1e-4)


def test_two_balls_cannot_pass_through_each_other_between_step_ends():
    """diffrax sees a gap only at its steps' ends, and free flight is so smooth that its
    steps grew tenfold at a time: two balls meeting head-on (no gravity) passed through
    each other unseen with t1 = 10 s, and the impact was found or not depending on t1.
    Body-body pairs now bound each segment's steps; elastic, equal masses: A stops at
    x = 0.8 m when they meet (t = 0.8 s), B leaves at 1 m/s."""
    scene = rb.Scene([rb.Body("a", shape=rb.Sphere(R), mass=1.0), rb.Body("b", shape=rb.Sphere(R), mass=1.0)],
                     gravity=None, contacts="all")
    params = scene.params(restitution=1.0, friction=0.0)
    state = scene.state(params, position=[(0, 0, 0), (1, 0, 0)], velocity=[(1, 0, 0), (0, 0, 0)])
    for t1 in (2.0, 10.0):
        result = rb.ode.solve_with_impacts(scene, params, state, t1, max_impacts=2)
        assert int(result.num_impacts) == 1, (t1, result.impact_times)
        assert bool(result.reached_t1) and float(result.final.time) == t1
        np.testing.assert_allclose(result.impact_times[0], 0.8, rtol=0, atol=1e-9)
        np.testing.assert_allclose(result.final.position[:, 0], [0.8, 1.0 + (t1 - 0.8)], rtol=0, atol=1e-8)


def test_grazes_are_located():
    """Two balls passing with their closest approach overlapping (no gravity), a sample of
    start offsets (stop 92's review):
    - 1 cm of overlap: where a solver step ended past the closest approach, the gap there
      was negative but already rising, and Newton's method, started at the step's end,
      walked away from the root: 12 of 41 offsets failed with "the maximum number of steps
      was reached in the nonlinear solver" (the first three here). The root finder now
      keeps the step as a bracket (``jaxrb._bracketed_root.SafeguardedNewton``).
    - 1 mm: steps of up to 0.1 m of relative travel saw no overlap at either end, and 27 of
      41 passes went unseen. The travel is now bounded so that a graze deeper than 0.1 mm
      shows at a step's end."""
    scene = rb.Scene([rb.Body("a", shape=rb.Sphere(R), mass=1.0), rb.Body("b", shape=rb.Sphere(R), mass=1.0)],
                     gravity=None, contacts="all")
    params = scene.params(restitution=1.0, friction=0.0)

    @jax.jit
    def first_impact(x0, sideways):
        state = scene.state(params, position=jnp.stack([jnp.stack([x0, 0.0, 0.0]), jnp.stack([1.0, sideways, 0.0])]),
                            velocity=[(1.0, 0.0, 0.0), (0.0, 0.0, 0.0)])
        result = rb.ode.solve_with_impacts(scene, params, state, 3.0, max_impacts=2)
        return result.num_impacts, result.impact_times[0]

    for overlap, offsets in ((0.01, (-0.075, -0.085, -0.095)), (0.001, np.linspace(0.0, -0.1, 9))):
        sideways = 2 * R - overlap
        for x0 in offsets:
            count, time = first_impact(jnp.asarray(x0), jnp.asarray(sideways))
            assert int(count) == 1, (overlap, x0)
            np.testing.assert_allclose(time, 1.0 - np.sqrt(4 * R**2 - sideways**2) - x0, rtol=0, atol=1e-10)


def test_impacts_50_microns_apart_are_located_apart():
    """Two balls dropped side by side, one 5e-5 m higher (they never meet). Every slot within
    the contact step's touching distance (0.1 mm) had taken part in an event's impact: the
    higher ball bounced at the lower one's instant, 1.1e-5 s early, one impact was reported
    instead of two, and its next apex was 1.8e-5 m high (stop 92's review)."""
    scene = rb.Scene([rb.Body("a", shape=rb.Sphere(R), mass=1.0), rb.Body("b", shape=rb.Sphere(R), mass=1.0)],
                     ground=rb.Plane(), contacts=[("a", "ground"), ("b", "ground")])
    e, above = 0.8, 5e-5
    params = scene.params(restitution=e, friction=0.0)
    state = scene.state(params, position=[(0, 0, H + R), (1.0, 0, H + above + R)])
    result = rb.ode.solve_with_impacts(scene, params, state, 0.6, max_impacts=4,
                                       contact=rb.ContactSettings(restitution_threshold=0.0))
    assert int(result.num_impacts) == 2
    np.testing.assert_allclose(result.impact_times[:2], np.sqrt(2 * np.asarray([H, H + above]) / G), rtol=0,
                               atol=1e-12)
    height = np.asarray(result.final.position[:, 2]) - R
    apex = height + np.asarray(result.final.velocity[:, 2]) ** 2 / (2 * G)
    np.testing.assert_allclose(apex, e**2 * np.asarray([H, H + above]), rtol=0, atol=1e-12)


def test_impacts_are_located_late_in_time_and_far_from_the_origin():
    """One ulp of t moves a gap by its rate times it, and one ulp of a large coordinate is
    above atol: a float64 drop started at t = 1e4 s, and a float32 drop from 20 m, had
    failed in the root finder ("the maximum number of steps was reached")."""
    scene = ball_scene()
    for start, height, dtype, atol in ((1e4, 1.0, jnp.float64, 1e-9), (0.0, 20.0, jnp.float32, 1e-5)):
        params = scene.params(restitution=0.8, dtype=dtype)
        state = scene.state(params, position=(0, 0, height + R), time=start)
        fall = np.sqrt(2 * height / G)
        result = rb.ode.solve_with_impacts(scene, params, state, start + 1.2 * fall, max_impacts=1)
        assert int(result.num_impacts) == 1
        np.testing.assert_allclose(float(result.impact_times[0]) - start, fall, rtol=0, atol=atol)


def test_one_pairs_start_overlap_does_not_delay_another_pairs_impact():
    """The event measured every pair's gap from one reference, the smallest start gap's:
    a ball resting 8e-6 m into the ground (within the slop) made a ball falling beside it
    land 8e-6 m deep, 8e-6 s late."""
    scene = rb.Scene([rb.Body("a", shape=rb.Sphere(R), mass=1.0), rb.Body("b", shape=rb.Sphere(R), mass=1.0)],
                     gravity=None, ground=rb.Plane(), contacts=[("a", "ground"), ("b", "ground")])
    params = scene.params(restitution=1.0)
    state = scene.state(params, position=[(0, 0, R - 8e-6), (1, 0, 0.5 + R)], velocity=[(0, 0, 0), (0, 0, -1.0)])
    result = rb.ode.solve_with_impacts(scene, params, state, 1.0, max_impacts=1)
    np.testing.assert_allclose(result.impact_times[0], 0.5, rtol=0, atol=1e-12)
    assert abs(float(result.after_impact.position[0, 1, 2]) - R) < 1e-12


@pytest.mark.slow
def test_gradients_through_located_impacts_match_closed_forms_and_finite_differences():
    """Reverse mode through the event path differentiates the impact time too (the root
    finder's implicit derivative), and forward mode runs with ``diffrax.ForwardMode()``
    (it had no ``adjoint=``: ``jax.jacfwd`` failed on diffrax's checkpointed loop). A ball
    thrown sideways (2 m/s) from 1 m onto the ground, sliding through its impact (mu = 0.05),
    and flying on to t = 1 s. Closed forms: the impact at ``t_0 = sqrt(2 h0 / g)``, so
    ``d t_0 / d h0 = t_0 / (2 h0)``; the first apex ``e^2 h0``. The rest against central
    differences (step 1e-6, no contact switches within it); measured 3.6e-8 relative."""
    scene = ball_scene()

    def outputs(x, adjoint=None):
        e, mu, mass, vx, h0 = x
        params = scene.params(restitution=e, friction=mu, mass=mass)
        state = scene.state(params, position=(0, 0, h0 + R), velocity=(vx, 0.0, 0.0))
        sol = rb.ode.solve_with_impacts(scene, params, state, 1.0, max_impacts=2, adjoint=adjoint)
        end, apex = sol.final, sol.after_impact.velocity[0, 0, 2] ** 2 / (2 * G)
        return jnp.stack([end.position[0, 0], end.position[0, 2], end.velocity[0, 0], end.angular_momentum[0, 1],
                          sol.impact_times[0], apex])

    x = jnp.array([0.8, 0.05, 1.3, 2.0, 1.0])
    e, h0 = 0.8, 1.0
    reverse = np.asarray(jax.jacrev(outputs)(x))
    t0 = np.sqrt(2 * h0 / G)
    np.testing.assert_allclose(reverse[4], [0, 0, 0, 0, t0 / (2 * h0)], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(reverse[5], [2 * e * h0, 0, 0, 0, e**2], rtol=1e-9, atol=1e-12)
    # The sliding impulse mu (1 + e) m v0 depends on mu: friction's gradient is not zero.
    assert abs(reverse[0, 1]) > 1.0 and abs(reverse[3, 1]) > 1.0
    run = jax.jit(outputs)
    step = 1e-6
    central = np.stack([(run(x.at[i].add(step)) - run(x.at[i].add(-step))) / (2 * step) for i in range(5)], axis=1)
    np.testing.assert_allclose(reverse, central, rtol=1e-6, atol=1e-8)
    forward = np.asarray(jax.jacfwd(lambda x: outputs(x, adjoint=diffrax.ForwardMode()))(x))
    np.testing.assert_allclose(forward, reverse, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="adjoint must be a diffrax adjoint instance"):
        outputs(x, adjoint="forward")


def test_a_touching_starts_impact_time_has_the_derivative_of_its_height():
    """A ball launched up at 1 m/s from exactly touching the ground lands at ``2 v / g``, and
    ``d t / d h0 = 1 / sqrt(v^2 + 2 g h0) = 1 / v``. The event's level below a touching start
    once carried the start gap's derivative, so the floor moved with the start: the
    derivative came out 0 at ``h0 = 0`` (stop 97's review), while ``h0 = 1e-9`` gave 1."""
    scene = ball_scene()
    settings = rb.ContactSettings(restitution_threshold=0.0)

    def impact_time(h0):
        params = scene.params(restitution=0.8, friction=0.0)
        state = scene.state(params, position=jnp.stack([0.0, 0.0, h0 + R]), velocity=(0.0, 0.0, 1.0))
        return rb.ode.solve_with_impacts(scene, params, state, 0.3, max_impacts=1, contact=settings).impact_times[0]

    np.testing.assert_allclose(float(jax.jit(impact_time)(0.0)), 2.0 / G, rtol=1e-12)
    gradient = jax.jit(jax.grad(impact_time))
    for h0 in (0.0, 1e-9):
        np.testing.assert_allclose(float(gradient(h0)), 1.0 / np.sqrt(1.0 + 2 * G * h0), rtol=1e-9)
