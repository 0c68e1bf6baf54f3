"""A solve's own colours (jaxrb.contact._recolour): only the touching pairs, coloured again."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrb as rb
from jaxrb.contact import _step
from jaxrb.contact._layout import build_layout
from jaxrb.contact._recolour import active_colours, solve_colours


def _scene(shapes):
    bodies = [rb.Body(f"b{i}", shape=s, mass=1.0) for i, s in enumerate(shapes)]
    return rb.Scene(bodies, ground=rb.Plane(), contacts="all")


CUBE = rb.Box((0.1, 0.1, 0.1))


@pytest.mark.parametrize("shapes", [[CUBE] * 5, [CUBE] * 13, [rb.Sphere(0.1)] * 6],
                         ids=["5 boxes", "13 boxes", "6 balls"])
def test_a_solves_colours_hold_each_touching_pair_once_and_no_body_twice(shapes):
    """For random sets of active slots: the first ``visits`` colours hold every slot of
    every pair with an active slot, once, and nothing else; the slots of one pair come in
    their order; no two slots of a colour move the same body; the later colours are
    padding only; and there are at most ``K`` visits for each static colour of pairs."""
    layout = build_layout(_scene(shapes))
    c = layout.num_slots
    body_a, body_b, pair = np.asarray(layout.body_a), np.asarray(layout.body_b), np.asarray(layout.pair)
    colour = jax.jit(lambda a: active_colours(layout, a))
    rng = np.random.default_rng(0)
    for density in (0.0, 0.05, 0.3, 1.0):
        for _ in range(5):
            active = rng.random(c) < density
            table, visits = colour(jnp.asarray(active))
            table, visits = np.asarray(table), int(visits)
            touching = set(pair[active])
            placed = [s for s in table[:visits].reshape(-1) if s < c]
            assert sorted(placed) == [s for s in range(c) if pair[s] in touching]
            assert np.all(table[visits:] == c)
            assert visits <= len(layout.pair_colours) * max(g.slots for g in layout.groups)
            for row in table[:visits]:
                moved = [b for s in row if s < c for b in (body_a[s], body_b[s]) if b < layout.num_bodies]
                assert len(moved) == len(set(moved)), row
            order = {}
            for k, row in enumerate(table[:visits]):
                for s in row[row < c]:
                    order.setdefault(pair[s], []).append((k, s))
            assert all([s for _, s in v] == sorted(s for _, s in v) for v in order.values())


def test_a_resting_stack_is_swept_in_two_colours_of_pairs():
    """The 5-box stack with all pairs: its static colouring has 20 colours (each box is in
    five pairs of four slots); at rest it touches along a chain (ground, box 0, ..., box 4),
    whose five pairs two colours hold: 8 visits a sweep."""
    layout = build_layout(_scene([CUBE] * 5))
    n = layout.num_bodies
    chain = {(0, n), (0, 1), (1, 2), (2, 3), (3, 4)}
    active = np.array([(a, b) in chain for a, b in zip(layout.body_a, layout.body_b, strict=True)])
    _, visits = active_colours(layout, jnp.asarray(active))
    assert len(layout.colours) == 20 and int(visits) == 8
    # Under vmap each member has its own colours.
    _, both = jax.vmap(lambda a: active_colours(layout, a))(jnp.stack([jnp.asarray(active), jnp.zeros_like(active)]))
    np.testing.assert_array_equal(both, [8, 0])


def test_pairs_of_different_sizes_keep_the_static_colours():
    """Balls (one slot a pair) beside a box (four): each colour of pairs would take four
    visits, so the layout's static colours are swept."""
    layout = build_layout(_scene([rb.Sphere(0.1), rb.Sphere(0.1), CUBE]))
    colours = solve_colours(layout, jnp.ones(layout.num_slots, bool))
    np.testing.assert_array_equal(colours, np.asarray(layout.colours))


def test_sweeps_that_end_at_their_tolerance_visit_the_first_colours_only():
    """``(table, visits)``: the while loop of a step's solve visits the first ``visits``
    colours; the scan that is differentiated visits them all (in a solve's own colours the
    rest are padding, so both agree there)."""
    from jaxrb.contact._solver import Bodies, frames, pad_slots, sweeps

    inv_inertia = jnp.eye(3)[None] * jnp.asarray([10.0, 10.0, 0.0, 0.0])[:, None, None]
    bodies = Bodies(jnp.asarray([1.0, 1.0, 0.0, 0.0]), inv_inertia,
                    jnp.asarray([[0.0, 0.0, -0.5], [0.0, 0.0, -0.5], [0, 0, 0], [0, 0, 0]]), jnp.zeros((4, 3)))
    points = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    f = frames(bodies, [0, 1], [2, 2], points, jnp.asarray([[0.0, 0.0, 1.0]] * 2),
               jnp.asarray([[0.0, 0.0, 0.1], [1.0, 0.0, 0.1], [0, 0, 0], [0, 0, 0]]))
    target, mu, active, lam = pad_slots(jnp.zeros(2), jnp.zeros(2), jnp.asarray([True, True]), jnp.zeros((2, 3)))
    table = jnp.asarray([[0], [1]])
    ended = sweeps(bodies, f, (table, jnp.asarray(1)), target, mu, active, lam, 20, tolerance=0.0, early_exit=True)
    np.testing.assert_allclose(ended[0].velocity[:2, 2], [0.0, -0.5])  # slot 1 never visited
    scanned = sweeps(bodies, f, (table, jnp.asarray(1)), target, mu, active, lam, 20, tolerance=0.0)
    np.testing.assert_allclose(scanned[0].velocity[:2, 2], [0.0, 0.0])


def test_a_stack_solved_in_its_own_colours_moves_as_in_the_static_ones(monkeypatch):
    """Float64, the 5-box stack settling from rest with sweeps run to convergence: the same
    velocities and positions with the step's own colours as with the static ones (only the
    order of the Gauss-Seidel updates differs)."""
    scene = _scene([CUBE] * 5)
    params = scene.params(friction=0.5, dtype=jnp.float64)
    state = scene.state(params, position=[[0.0, 0.0, 0.1 + 0.2 * i] for i in range(5)])
    settings = rb.ContactSettings(iterations=400, tolerance=1e-13)

    def run():
        step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3, contact=settings)
        return jax.jit(lambda p, s: rb.rollout(step, p, s, 20, save_every=20)[0])(params, step.prepare(state))

    own = run()
    monkeypatch.setattr(_step, "solve_colours", lambda layout, active: jnp.asarray(layout.colours))
    static = run()
    np.testing.assert_allclose(own.velocity, static.velocity, atol=1e-9)
    np.testing.assert_allclose(own.position, static.position, atol=1e-12)
