"""Ensembles sharded over several devices give the same numbers as on one device.

Asking for two CPU devices must happen before JAX starts, so the check runs in a
subprocess. The errors of ``shard_ensemble`` run here, on whatever devices exist.
"""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrb as rb

SCRIPT = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_num_cpu_devices", 2)
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp, numpy as np
    import jaxrb as rb

    assert len(jax.devices()) == 2, jax.devices()
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0)], forces=[rb.LinearDamping()])
    envs = 8
    params = jax.vmap(lambda m: scene.params(mass=m, linear_damping=0.1))(jnp.linspace(0.5, 2.0, envs))
    state = jax.vmap(lambda w: scene.state(params=None, velocity=(1.0, 0.0, 2.0),
                                           body_angular_velocity=jnp.stack([w, 2.0, -1.0])))(
        jnp.linspace(-1.0, 1.0, envs))
    step = rb.make_step(scene, rb.integrators.RK4(), 1e-3)
    run = jax.jit(jax.vmap(lambda p, s: rb.rollout(step, p, s, 200, save_every=200)[0]))
    single = run(params, state)
    sharded_params, sharded_state = rb.shard_ensemble((params, state))
    assert len(sharded_state.position.sharding.device_set) == 2
    sharded = run(sharded_params, sharded_state)
    # The result stays split over both devices: each ran its half of the ensemble.
    assert len(sharded.position.sharding.device_set) == 2
    assert sharded.position.addressable_shards[0].data.shape == (envs // 2, 1, 3)
    for a, b in zip(jax.tree.leaves(single), jax.tree.leaves(sharded)):
        # Same arithmetic on each environment, only placed differently: bitwise equal
        # up to the order XLA picks for fused operations (1e-15 in float64).
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-13)
    # Gradients through a sharded ensemble work as well.
    loss = lambda p: jnp.sum(run(p, sharded_state).position[..., 2])
    g_single = jax.grad(lambda p: jnp.sum(run(p, state).position[..., 2]))(params)
    g_sharded = jax.grad(loss)(sharded_params)
    np.testing.assert_allclose(np.asarray(g_sharded.mass), np.asarray(g_single.mass), rtol=1e-12, atol=1e-14)
    print("ok")
    """
)


def test_sharded_ensemble_equals_single_device():
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stderr[-3000:]


def test_shard_ensemble_refuses_unbatched_or_uneven_input():
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    state = scene.state()
    with pytest.raises(ValueError, match="leading ensemble axis"):
        rb.shard_ensemble(state)  # State.time is a scalar: not batched
    batched = jax.tree.map(lambda x: jnp.broadcast_to(x, (4, *x.shape)), state)
    with pytest.raises(ValueError, match="one ensemble size"):
        rb.shard_ensemble((batched, jnp.zeros((3, 2))))
    fake_devices = jax.devices() * 3  # three "devices" cannot split 4 environments
    with pytest.raises(ValueError, match="does not split evenly over 3 devices"):
        rb.shard_ensemble(batched, devices=fake_devices)
    placed = rb.shard_ensemble(batched)
    assert jnp.array_equal(placed.position, batched.position)
    one = rb.shard_ensemble(batched, devices=jax.devices()[0])  # a bare device had raised a TypeError
    assert jnp.array_equal(one.position, batched.position)


# ------------------------------------------------------------------ branches in ensembles


def _first(x, y):
    return jnp.sin(x) * y, x


def _second(x, y):
    return x * y, -x


def _reference(pred, x, y):
    return jax.lax.cond(pred, _first, _second, x, y)


def _counted_cond(calls, recompute_in_reverse=False):
    """``branch`` of ``_first`` and ``_second``; the first reports each run of itself (a host callback)."""
    from jaxrb._branch import branch

    def taken(x, y):
        jax.debug.callback(lambda: calls.append(1))
        return _first(x, y)

    def f(pred, x, y):
        return branch(pred, taken, _second, x, y, recompute_in_reverse=recompute_in_reverse)

    return f


def test_branch_agrees_with_cond_on_the_edge_cases_a_review_found():
    """Each had differed from lax.cond (stop 88's review): no array operand under vmap
    (ValueError), a non-bool pred in the per-member form (-1 took the false branch), a
    branch returning a Python True (AttributeError), Python-scalar tangents (AttributeError)."""
    from jaxrb._branch import branch, members_differentiated

    pred, a = jnp.array([True, False, True]), jnp.array([1.0, 2.0])
    for operand in ((), (None,)):
        def run(cond, q, operand=operand):
            return cond(q, lambda *_: a * 2, lambda *_: a - 1, *operand)

        np.testing.assert_array_equal(jax.vmap(lambda q: run(branch, q))(pred),
                                      jax.vmap(lambda q: run(jax.lax.cond, q))(pred))
    x, q = jnp.array([3.0, 2.0]), jnp.array([-1, 0])
    for transform in (lambda f: jax.vmap(f), lambda f: jax.vmap(jax.grad(f, 1))):
        results = [transform(lambda q, o, c=c: c(q, lambda o: o**2, lambda o: o * 2, o))(q, x)
                   for c in (branch, jax.lax.cond)]
        np.testing.assert_array_equal(*results)
    with members_differentiated():
        np.testing.assert_allclose(jax.grad(lambda o: branch(jnp.float32(0.5), jnp.sin, jnp.cos, o))(1.0), np.cos(1.0))
        np.testing.assert_allclose(jax.jvp(lambda y: branch(True, lambda y: 2.0 * y, lambda y: 3.0 * y, y),
                                           (1.0,), (1.0,))[1], 2.0)
    assert bool(branch(jnp.bool_(True), lambda o: True, lambda o: o > 0, jnp.float32(1.0)))
    tangents = jax.jvp(lambda y: jax.vmap(lambda p: branch(p, lambda y: 2.0 * y, lambda y: 3.0 * y, y))(pred),
                       (1.0,), (1.0,))[1]
    np.testing.assert_array_equal(tangents, [2.0, 3.0, 2.0])


def test_branch_matches_cond_per_member_and_skips_a_branch_no_member_takes():
    calls = []
    f = _counted_cond(calls)
    x, y = jnp.array([0.3, -1.2, 2.0]), jnp.array([1.5, 0.7, -0.4])
    for pred in ([True, False, True], [True, True, True], [False, False, False]):
        pred = jnp.array(pred)
        calls.clear()
        got = jax.jit(jax.vmap(f))(pred, x, y)
        jax.block_until_ready(got)
        want = jax.vmap(_reference)(pred, x, y)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g, w)
        # The first branch runs once for the whole ensemble when some member takes it, and
        # not at all when none does (a vmapped lax.cond would run it either way).
        assert len(calls) == (1 if bool(jnp.any(pred)) else 0)
    # The predicate unbatched, the operands batched: one branch.
    got = jax.vmap(f, in_axes=(None, 0, 0))(jnp.array(False), x, y)
    np.testing.assert_array_equal(got[0], x * y)


@pytest.mark.parametrize("recompute_in_reverse", [False, True])
def test_branch_derivatives_are_those_of_cond(recompute_in_reverse):
    f = _counted_cond([], recompute_in_reverse)
    loss = lambda g: lambda p, x, y: jnp.sum(g(p, x, y)[0] + 2.0 * g(p, x, y)[1])  # noqa: E731
    pred, x, y = jnp.array([True, False, True]), jnp.array([0.3, -1.2, 2.0]), jnp.array([1.5, 0.7, -0.4])
    for argnums in (1, 2):
        want = jax.vmap(jax.grad(loss(_reference), argnums))(pred, x, y)
        np.testing.assert_allclose(jax.vmap(jax.grad(loss(f), argnums))(pred, x, y), want, rtol=1e-15)
        np.testing.assert_allclose(jax.grad(lambda x, y: jnp.sum(jax.vmap(loss(f))(pred, x, y)), argnums - 1)(x, y),
                                   want, rtol=1e-15)
        np.testing.assert_allclose(jax.jacfwd(lambda x, y: jax.vmap(loss(f))(pred, x, y), argnums - 1)(x, y),
                                   jnp.diag(want), rtol=1e-15)
    # Second order, through the checkpointed linearisation too.
    for p in (True, False):
        want = jax.hessian(loss(_reference), (1, 2))(p, x, y)
        np.testing.assert_allclose(jax.hessian(loss(f), (1, 2))(p, x, y), want, rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize("recompute_in_reverse", [False, True])
def test_the_derivative_of_a_vmapped_branch_skips_a_branch_no_member_takes(recompute_in_reverse):
    """``grad`` and ``jacfwd`` of an ensemble's loss, and per-member gradients, run a branch
    only where some member takes it, as the forward does (``vmap`` batches the derivative's
    rule). Until 2026-12-03 the rule's cond became a select and every member ran both
    branches' derivatives: the first branch ran with no member taking it. Nested ``vmap``s:
    once for the whole ensemble."""
    calls = []
    f = _counted_cond(calls, recompute_in_reverse)
    member = lambda p, x, y: f(p, x, y)[0] + 2.0 * f(p, x, y)[1]  # noqa: E731
    member_ref = lambda p, x, y: _reference(p, x, y)[0] + 2.0 * _reference(p, x, y)[1]  # noqa: E731
    x, y = jnp.array([[0.3, -1.2, 2.0], [0.5, 0.1, -0.7]]), jnp.array([[1.5, 0.7, -0.4], [0.2, -2.0, 1.1]])
    nested = lambda g: lambda x, y, p: jnp.sum(jax.vmap(jax.vmap(g))(p, x, y))  # noqa: E731
    flat = lambda g: lambda x, y, p: jnp.sum(jax.vmap(g)(p[0], x[0], y[0]))  # noqa: E731
    for loss in (nested, flat):
        for derivative in (jax.grad, jax.jacfwd):
            compiled = jax.jit(derivative(loss(member), (0, 1)))
            for pred in ([[False] * 3] * 2, [[True] * 3] * 2, [[False] * 3, [False, True, False]]):
                pred = jnp.array(pred)
                jax.block_until_ready(compiled(x, y, pred))
                calls.clear()
                got = jax.block_until_ready(compiled(x, y, pred))
                want = derivative(loss(member_ref), (0, 1))(x, y, pred)
                for g, w in zip(got, want, strict=True):
                    np.testing.assert_allclose(g, w, rtol=1e-15, atol=1e-15)
                # The first branch runs (in the forward, in its derivative) if and only if
                # some member takes it.
                taken = bool(jnp.any(pred if loss is nested else pred[0]))
                assert (len(calls) > 0) == taken, (pred, loss, derivative, len(calls))
    # Per-member gradients, traced in one go, skip it too.
    per_member = jax.jit(jax.vmap(jax.grad(member, (1, 2))))
    pred = jnp.zeros(3, bool)
    calls.clear()
    got = per_member(pred, x[0], y[0])
    want = jax.vmap(jax.grad(member_ref, (1, 2)))(pred, x[0], y[0])
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-15, atol=1e-15)
    assert not calls


@pytest.mark.parametrize("recompute_in_reverse", [False, True])
def test_a_vmapped_program_traced_before_its_vmap_skips_in_its_derivative_where_told(recompute_in_reverse):
    """A ``vmap`` over a loop (or a ``jit``) batches the rules after they were traced for one
    member, so they cannot see it: there the derivative ran both branches for every member,
    unless the caller says it is an ensemble's (``members_differentiated``, as ``rollout``
    does). Values as ``lax.cond``'s either way."""
    from jaxrb._branch import members_differentiated

    calls = []
    f = _counted_cond(calls, recompute_in_reverse)

    def looped(g):
        def member(p, x, y):  # three steps of a loop whose body holds the branch
            def body(c, _):
                a, b = g(p, c, y)
                return c + 0.1 * a + 0.2 * b, None
            return jnp.sum(jax.lax.scan(body, x, None, length=3)[0])
        return lambda x, y, p: jnp.sum(jax.vmap(member)(p, x, y))

    x, y = jnp.array([0.3, -1.2, 2.0]), jnp.array([1.5, 0.7, -0.4])
    for told in (False, True):
        for pred in ([False] * 3, [False, True, False]):
            pred = jnp.array(pred)
            with members_differentiated(told):
                compiled = jax.jit(jax.grad(looped(f), (0, 1)))
                got = compiled(x, y, pred)
            calls.clear()
            got = jax.block_until_ready(compiled(x, y, pred))
            want = jax.grad(looped(_reference), (0, 1))(x, y, pred)
            for g, w in zip(got, want, strict=True):
                np.testing.assert_allclose(g, w, rtol=1e-14, atol=1e-15)
            if told or bool(jnp.any(pred)):
                assert (len(calls) > 0) == bool(jnp.any(pred)), (told, pred, len(calls))
            else:  # not told: the first branch's derivative runs though no member takes it
                assert len(calls) > 0


@pytest.mark.parametrize("recompute_in_reverse", [False, True])
def test_a_branch_not_taken_leaks_no_nan_into_an_ensembles_gradient(recompute_in_reverse):
    """Members that disagree run both branches' derivatives, each branch for every member.
    A branch run where it is not taken may have an infinite derivative there (here sqrt at
    0); the select drops its value, but reverse mode transposes the branch, and the zero
    cotangent times that infinity was NaN in the member's gradient (found by a fuzz of
    float32 box drops: 17 of 64 members' gradients all NaN under ``vmap(grad)``, each
    finite alone). Each branch now sees the tangents of the members that take it only.
    Gradients as each member's own, in reverse and forward mode, and in a loop that
    ``rollout``'s way (``members_differentiated``) makes per-member."""
    from jaxrb._branch import branch, members_differentiated

    def member(x):
        return branch(x > 0.0, jnp.sqrt, lambda v: 3.0 * v, x, recompute_in_reverse=recompute_in_reverse)

    def looped(x):
        return jax.lax.scan(lambda c, _: (c + member(x), None), 0.0, None, length=2)[0]

    x = jnp.array([4.0, 0.0, 9.0])
    own = np.array([jax.grad(member)(v) for v in x])
    np.testing.assert_array_equal(own, [0.25, 3.0, 1.0 / 6.0])
    np.testing.assert_array_equal(jax.jit(jax.vmap(jax.grad(member)))(x), own)
    np.testing.assert_array_equal(jax.grad(lambda x: jnp.sum(jax.vmap(member)(x)))(x), own)
    np.testing.assert_array_equal(jnp.diag(jax.jacfwd(jax.vmap(member))(x)), own)
    with members_differentiated():
        looped_grad = jax.jit(jax.grad(lambda x: jnp.sum(jax.vmap(looped)(x))))(x)
    np.testing.assert_array_equal(looped_grad, 2.0 * own)


def test_the_per_member_switch_clamps_its_index_as_lax_switch_does():
    """``member_switch``'s per-member form takes an index out of range as ``lax.switch``
    does: clamped to the first or the last branch (before, an index past the last took the
    first branch's value, or zeros where no member took the first)."""
    from jaxrb._branch import member_switch

    branches = [lambda x: x + 1.0, lambda x: 2.0 * x, lambda x: x - 3.0]
    index = jnp.array([-2, 0, 1, 2, 7])
    x = jnp.array([0.5, -1.0, 2.0, 4.0, 1.5])
    got = jax.vmap(lambda i, x: member_switch(i, branches, x, per_member=True))(index, x)
    want = jax.vmap(lambda i, x: jax.lax.switch(i, branches, x))(index, x)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got, [1.5, 0.0, 4.0, 1.0, -1.5])


def test_rollout_tells_the_derivative_rules_whether_it_is_vmapped():
    """``rollout`` reads the ``vmap`` outside its ``jit`` and traces its loop in the
    per-member form when its params or state are batched (and only then)."""
    from jaxrb import _branch

    seen = []
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)

    def recorded():  # a new step function each time, so that rollout traces it afresh
        return lambda p, s: (seen.append(_branch._MEMBERS.get()), step(p, s))[1]

    params, state = scene.params(), scene.state()
    states = jax.tree.map(lambda x: jnp.stack([x, x]), state)
    masses = jax.vmap(lambda m: scene.params(mass=m))(jnp.array([1.0, 2.0]))
    for run, want in ((lambda f: rb.rollout(f, params, state, 2), False),
                      (lambda f: jax.vmap(lambda s: rb.rollout(f, params, s, 2))(states), True),
                      (lambda f: jax.vmap(lambda p: rb.rollout(f, p, state, 2))(masses), True),
                      (lambda f: jax.grad(lambda p: jnp.sum(jax.vmap(
                          lambda s: rb.rollout(f, p, s, 2)[0].position)(states)))(params), True)):
        seen.clear()
        run(recorded())
        # (The first entry is rollout's check of the step's output, outside its jit.)
        assert len(seen) > 1 and all(x == want for x in seen[1:]), (want, seen)
    assert not _branch._MEMBERS.get()


def test_a_step_tells_the_derivative_rules_whether_it_is_vmapped(monkeypatch):
    """``Step.__call__`` does as ``rollout`` does, for a ``vmap`` of a step itself: the rules
    traced with the derivative of a vmapped step take the per-member form."""
    from jaxrb import _branch

    seen = []
    real = _branch._per_member
    monkeypatch.setattr(_branch, "_per_member", lambda p: (seen.append(_branch._MEMBERS.get()), real(p))[1])
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    params = scene.params()
    step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
    states = jax.vmap(lambda z: step.prepare(scene.state(params, position=jnp.stack([0.0, 0.0, z]))))(
        jnp.array([0.1, 0.5]))
    # Traced only: the rules are traced with the derivative, nothing to compile. (The
    # unbatched form: every single-body gradient test; rollout's choice of form: above.)
    jax.make_jaxpr(jax.grad(lambda p: jnp.sum(jax.vmap(step, (None, 0))(p, states).position)))(params)
    assert seen and all(seen), seen
    assert not _branch._MEMBERS.get()


@pytest.mark.slow
def test_an_ensembles_gradient_through_contacts_is_its_members_gradients():
    """Members in different contact states at once (one flying, one bouncing, one resting,
    one sliding), so that every per-member branch of the contact step's derivative runs
    mixed: the ensemble's gradient is the sum of the members' own."""
    with jax.enable_x64(True):
        scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
        step = rb.make_step(scene, rb.integrators.SymplecticSplitting(), 1e-3)
        params = scene.params(restitution=0.8, friction=0.5, dtype=jnp.float64)
        starts = [((0.0, 0.0, 0.6), (0.0, 0.0, 0.0)), ((0.0, 0.0, 0.105), (0.3, 0.0, -0.5)),
                  ((0.0, 0.0, 0.1), (0.0, 0.0, 0.0)), ((0.0, 0.0, 0.1), (1.0, 0.0, 0.0))]
        states = [step.prepare(scene.state(params, position=x, velocity=v)) for x, v in starts]

        def member_loss(p, s):
            traj = rb.rollout(step, p, s, 60)[1]
            return jnp.sum(traj.position[:, 0, :]) + jnp.sum(traj.velocity[:, 0, :])

        batched = jax.tree.map(lambda *x: jnp.stack(x), *states)
        got = jax.jit(jax.grad(lambda p, s: jnp.sum(jax.vmap(member_loss, (None, 0))(p, s)), (0, 1)))(params, batched)
        grad_member = jax.jit(jax.grad(member_loss, (0, 1)))
        members = [grad_member(params, s) for s in states]
        want_params = jax.tree.map(lambda *g: sum(g), *[m[0] for m in members])
        want_states = jax.tree.map(lambda *g: jnp.stack(g), *[m[1] for m in members])
        for g, w in zip(jax.tree.leaves((got[0], got[1])), jax.tree.leaves((want_params, want_states)), strict=True):
            if jnp.issubdtype(jnp.result_type(w), jnp.floating):
                np.testing.assert_allclose(g, w, rtol=1e-10, atol=1e-12)
        assert np.all(np.isfinite(got[0].restitution)) and float(jnp.abs(got[0].restitution[0])) > 0


def test_the_gradient_of_a_sum_over_an_ensemble_with_batched_params_is_its_members_gradients():
    """``jax.grad`` of a loss summed over ``jax.vmap`` whose params are built per member
    (mass and restitution from the member's own parameters): it equals each member's own
    gradient. It had failed to trace (a ``broadcast_in_dim`` TypeError in the rollout's
    linearisation, found by a fuzz: a ``custom_jvp``, since removed, that tied the initial
    state's tangent to the params' was batched with tangents where its primals were not);
    ``jax.vmap(jax.grad)`` had worked. The scene has no contacts: the failure was in the loop common to all (the
    fuzz's ball-and-box scene with contacts: the same values both ways after the fix)."""
    with jax.enable_x64(True):
        scene = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0),
                          rb.Body("b", shape=rb.Box((0.1, 0.1, 0.1)), mass=2.0)])
        step = rb.make_step(scene, rb.integrators.SemiImplicitEuler(), 1e-3)

        def loss(theta):
            mass, e = theta[0], theta[1]
            params = scene.params(dtype=jnp.float64)
            params = params.replace(mass=params.mass.at[0].set(mass), inertia=params.inertia.at[1].multiply(e))
            state = scene.state(params, position=[[0.0, 0.0, 0.12], [0.5, 0.0, 0.11]],
                                velocity=jnp.stack([jnp.stack([0.3 * mass, 0.0, -1.0]), jnp.array([0.0, 0.0, -0.5])]),
                                angular_velocity=[[0.0, 0.0, 0.0], [1.0, 2.0, 0.5]])
            final = rb.rollout(step, params, step.prepare(state), 40)[0]
            return jnp.sum(final.position) + jnp.sum(final.velocity) + 0.1 * jnp.sum(final.angular_momentum)

        thetas = jnp.array([[1.0, 0.8], [1.5, 0.5]])
        got = jax.grad(lambda t: jnp.sum(jax.vmap(loss)(t)))(thetas)
        want = jax.vmap(jax.grad(loss))(thetas)
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)
        assert np.all(np.abs(np.asarray(want)) > 0)


def _primitive_count(jaxpr, name: str) -> int:
    """How many ``name`` equations a jaxpr holds, sub-jaxprs (cond branches, scans) included."""
    count = 0
    for eqn in jaxpr.eqns:
        count += eqn.primitive.name == name
        for value in eqn.params.values():
            for sub in value if isinstance(value, (list, tuple)) else [value]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    count += _primitive_count(inner, name)
    return count


def test_branch_batching_puts_each_branch_in_the_program_once():
    """With a batched predicate, the batching rule's cond for each branch binds that branch
    alone, not a cond of both with a constant predicate."""
    from jaxrb._branch import branch

    def f(pred, x):
        return branch(pred, jnp.sin, jnp.cos, x)

    pred, x = jnp.array([True, False, True]), jnp.array([0.3, -1.2, 2.0])
    vmapped = jax.make_jaxpr(jax.vmap(f))(pred, x).jaxpr
    assert _primitive_count(vmapped, "sin") == 1 and _primitive_count(vmapped, "cos") == 1
    np.testing.assert_allclose(jax.vmap(f)(pred, x), jnp.where(pred, jnp.sin(x), jnp.cos(x)), rtol=1e-15)


def test_branch_joins_weak_types_and_refuses_mismatched_branches():
    from jaxrb._branch import branch

    x = jnp.asarray(2.0, jnp.float32)
    for pred in (True, False):
        got = branch(jnp.asarray(pred), lambda x: 1.0, lambda x: x, x)  # a Python float against float32
        assert got.dtype == jnp.float32 and not jax.typeof(got).weak_type
        assert float(got) == (1.0 if pred else 2.0)
        batched = jax.vmap(lambda p: branch(p, lambda x: 1.0, lambda x: x, x))(jnp.array([pred, not pred]))
        assert batched.dtype == jnp.float32 and not jax.typeof(batched).weak_type
    with pytest.raises(TypeError, match="same shapes and dtypes"):
        branch(jnp.asarray(True), lambda x: x, lambda x: jnp.stack([x, x]), x)
    with pytest.raises(TypeError, match="same structure"):
        branch(jnp.asarray(True), lambda x: (x, x), lambda x: x, x)


@pytest.mark.slow
def test_contact_ensemble_equals_its_members_run_one_by_one():
    """A vmapped rollout (bouncing balls at different heights, some in flight and some in
    contact at each step, and a box stack with different frictions) equals each member's
    own rollout: the ensemble's shared branches change no value. (To rounding: XLA compiles
    the batched arithmetic into other kernels, 4e-12 relative apart on the stack.)"""
    ball = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(ball, rb.integrators.SymplecticSplitting(), 1e-2)
    params = ball.params(restitution=0.8, friction=0.3)
    states = [step.prepare(ball.state(params, position=(0.0, 0.0, z), velocity=(0.5, 0.0, 0.0)))
              for z in (0.1, 0.3, 0.6, 1.1)]
    batched = jax.tree.map(lambda *x: jnp.stack(x), *states)
    run = lambda s: rb.rollout(step, params, s, 60)[1].position  # noqa: E731
    together = jax.jit(jax.vmap(run))(batched)
    for i, s in enumerate(states):
        np.testing.assert_allclose(together[i], jax.jit(run)(s), rtol=1e-10, atol=1e-14)

    box = rb.Box((0.1, 0.1, 0.1))
    stack = rb.Scene([rb.Body(f"box{i}", shape=box, mass=1.0) for i in range(2)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(stack, rb.integrators.SymplecticSplitting(), 1e-3)
    state = step.prepare(stack.state(stack.params(), position=[[0.0, 0.0, 0.1], [0.02, 0.0, 0.3005]],
                                     velocity=[[0.0, 0.0, 0.0], [0.3, 0.0, -0.2]]))
    mus = jnp.array([0.0, 0.4, 0.9])
    run = lambda mu: rb.rollout(step, stack.params(friction=mu), state, 40)[1].position  # noqa: E731
    together = jax.jit(jax.vmap(run))(mus)
    for i, mu in enumerate(mus):
        np.testing.assert_allclose(together[i], jax.jit(run)(mu), rtol=1e-10, atol=1e-14)
