"""jaxrb.identify: parameterisations, fits from random guesses on noisy data, identifiability.

Every scenario fits noisy synthetic measurements of a known truth, from an initial guess
drawn at random (seeded), in float64. The truth data come from an independent or finer
computation where one exists (the exact torque-free solution, a ten times finer step).
The acceptance's five scenarios are those of ``examples/identify_parameters.py`` (its
``--quick`` sizes), run here with every iterate kept and checked: one implementation,
which also keeps the example from rotting.
"""

from __future__ import annotations

import importlib.util
import pathlib

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrb as rb
from jaxrb.identify import FreeParameters, inertia_from_unconstrained, inertia_to_unconstrained

SIE = rb.integrators.SemiImplicitEuler()  # the contact drift of a sphere or a box: exact here
SPLIT = rb.integrators.SymplecticSplitting()
EXAMPLE = pathlib.Path(__file__).resolve().parents[1] / "examples" / "identify_parameters.py"


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("identify_example", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _scenario(example, name: str):
    """The example's scenario at its --quick sizes and seed 0 (as ``--quick`` runs it):
    ``(largest relative error, FitResult with every iterate)``."""
    return example.SCENARIOS[name](np.random.default_rng(0), True, progress=False, keep_iterates=True)


def _physical(params: Params) -> bool:  # noqa: F821 - annotation only
    inertia = np.asarray(params.inertia, float)
    moments = np.linalg.eigvalsh(inertia)
    triangle = np.all(moments[:, :2].sum(-1) >= moments[:, 2] * (1 - 1e-12))
    e = np.asarray(params.restitution, float)
    return bool(np.all(np.asarray(params.mass) > 0) and np.all(moments > 0) and triangle
                and np.all((e >= 0) & (e <= 1)) and np.all(np.asarray(params.friction) >= 0))


# --------------------------------------------------------------- parameterisation


def test_every_unconstrained_point_is_a_physical_body():
    rng = np.random.default_rng(0)
    z = jnp.asarray(rng.normal(scale=2.0, size=(2000, 6)))
    inertia = np.asarray(inertia_from_unconstrained(z))
    moments = np.linalg.eigvalsh(inertia)  # ascending; eigvalsh's error is ~eps * largest
    assert np.all(moments[:, 0] > 0)
    assert np.all(moments[:, 0] + moments[:, 1] >= moments[:, 2] * (1 - 1e-12))
    np.testing.assert_allclose(inertia, np.swapaxes(inertia, -1, -2))
    # and every physical body has its z: the maps are inverse (compared on the inertia:
    # z's smallest Cholesky entry carries the cancellation of tr(S) E - S)
    again = np.asarray(inertia_from_unconstrained(jnp.asarray(inertia_to_unconstrained(inertia))))
    scale = np.abs(inertia).max(axis=(1, 2), keepdims=True)
    np.testing.assert_array_less(np.abs(again - inertia) / scale, 1e-12)


def test_a_thin_rods_small_moment_survives_the_round_trip():
    """Each moment to its own relative precision, not the largest one's: the maps had
    computed ``I = tr(S) E - S`` and ``S = tr(I)/2 E - I``, whose cancellations returned a
    rod's small moment with a relative error of about eps I_max / I_min (8e-8 for
    diag(1e-10, 1, 1), 2.5e-10 for diag(1e-6, 1, 1))."""
    rotation = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
    for small in (1e-4, 1e-6, 1e-8, 1e-10):
        inertia = np.diag([small, 1.0, 1.0])
        again = np.asarray(inertia_from_unconstrained(jnp.asarray(inertia_to_unconstrained(inertia))))
        np.testing.assert_allclose(np.diag(again), np.diag(inertia), rtol=1e-13, atol=0)
        np.testing.assert_array_equal(again - np.diag(np.diag(again)), 0.0)
        # a rotated rod: its principal moments (eigvalsh: to ~eps of the largest) as a check of the whole map
        turned = rotation @ inertia @ rotation.T
        again = np.asarray(inertia_from_unconstrained(jnp.asarray(inertia_to_unconstrained(turned))))
        np.testing.assert_allclose(again, turned, rtol=0, atol=4e-16)


def test_extreme_coordinates_stay_finite_and_physical_in_float32():
    scene = rb.Scene([rb.Body("a", shape=rb.Box((0.1, 0.2, 0.3)), mass=1.0)], ground=rb.Plane(), contacts="all")
    space = FreeParameters(scene, scene.params(restitution=0.5, friction=0.5, dtype=jnp.float32),
                           ["mass", "inertia", "restitution", "friction"])
    for shift in (-30.0, -5.0, 0.0, 5.0, 30.0):
        z = jax.tree.map(lambda x, s=shift: x + jnp.asarray(s, x.dtype), space.unconstrained())
        params = space.physical(z)
        assert params.mass.dtype == jnp.float32
        for leaf in (params.mass, params.inertia, params.restitution, params.friction):
            assert np.all(np.isfinite(np.asarray(leaf)))
        e, mu = float(params.restitution[0]), float(params.friction[0])
        assert 0.0 <= e <= 1.0 and 0.0 <= mu <= 2.0 and float(params.mass[0]) >= 0.0
        grads = jax.grad(lambda z: jnp.sum(space.physical(z).inertia) + jnp.sum(space.physical(z).restitution))(z)
        assert all(np.all(np.isfinite(np.asarray(g))) for g in jax.tree.leaves(grads))


def test_inertia_to_unconstrained_refuses_what_it_cannot_invert():
    """Its docstring promised a ValueError for an asymmetric inertia; it had replaced one
    by its symmetric part without a word, returned NaN coordinates for a NaN inertia, and
    failed with NumPy's broadcasting messages for a wrong shape."""
    cases = [([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "not symmetric"),
             (np.full((3, 3), np.nan), "not finite"), (np.diag([1.0, np.inf, 1.0]), "not finite"),
             (np.ones(3), r"shape \(\.\.\., 3, 3\)"), (np.eye(4), r"shape \(\.\.\., 3, 3\)"),
             (np.diag([1.0, 1.0, 2.5]), "triangle inequality")]
    for inertia, message in cases:
        with pytest.raises(ValueError, match=message):
            inertia_to_unconstrained(inertia)
    inertia_to_unconstrained(np.eye(3) + 1e-12 * np.triu(np.ones((3, 3)), 1))  # round-off asymmetry is symmetric


def test_free_parameters_round_trip_and_masks():
    bodies = [rb.Body("a", shape=rb.Sphere(0.1), mass=1.0), rb.Body("b", shape=rb.Box((0.1, 0.2, 0.3)), mass=2.0)]
    scene = rb.Scene(bodies, ground=rb.Plane(), contacts="all")
    params = scene.params(restitution=0.6, friction=0.4, dtype=jnp.float64)
    space = FreeParameters(scene, params, {"mass": ["b"], "inertia": True, "restitution": [("b", "ground")],
                                           "friction": True})
    assert space.labels[0] == "mass[b]"
    assert "inertia[a].xy" in space.labels and "restitution[b-ground]" in space.labels
    back = space.physical(space.unconstrained())
    for field in ("mass", "inertia", "restitution", "friction"):
        np.testing.assert_allclose(getattr(back, field), getattr(params, field), rtol=1e-12, atol=1e-15)
    # fixed entries never move, whatever z is
    z = jax.tree.map(lambda x: x + 3.0, space.unconstrained())
    moved = space.physical(z)
    assert float(moved.mass[0]) == 1.0 and float(moved.mass[1]) != 2.0
    vector = space.to_vector(params)
    assert vector.shape == (len(space.labels),)
    np.testing.assert_allclose(space.to_vector(space.from_vector(vector * 1.5)), vector * 1.5)


@pytest.mark.parametrize(("free", "message"), [
    ("density", "Unknown parameter"),
    ({"mass": ["nobody"]}, "Unknown body name"),
    ({"restitution": [("a", "nobody")]}, "not a contact pair"),
    ({"mass": [False]}, "selects no entry"),
    ({"gravity": [True, False, True]}, "all three"),
    ({"extra": True}, "extra is None"),
    ({"mass": 0}, "a boolean mask of shape"),
    ({"mass": [5]}, "not a body of the scene"),
    ({"mass": np.array([0.5])}, "boolean mask or integer indices"),
    ({"restitution": ("a", "ground")}, "is a body, not a contact pair"),
    (["mass", {"restitution": True}], "takes field names only"),
])
def test_bad_free_specifications_are_explained(free, message):
    scene = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    with pytest.raises(ValueError, match=message):
        FreeParameters(scene, scene.params(restitution=0.5), free)


def test_what_a_scene_does_not_simulate_cannot_be_free():
    """An infinite friction_max made the friction NaN from the first iterate (inf * sigmoid);
    gravity free in a scene built with gravity=None, or a damping without its force model,
    was accepted and the fit "converged" at once with a zero gradient."""
    scene = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    params = scene.params(friction=0.5)
    for bound in (float("inf"), float("nan"), 0.0, True, "2"):
        with pytest.raises(ValueError, match="friction_max must be a positive, finite number"):
            FreeParameters(scene, params, "friction", friction_max=bound)
    assert FreeParameters(scene, params, "friction", friction_max=np.float32(3.0)).labels
    weightless = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0)], gravity=None)
    for field, missing in [("gravity", "gravity=None"), ("linear_damping", "no rb.LinearDamping"),
                           ("angular_damping", "no rb.AngularDamping")]:
        with pytest.raises(ValueError, match=f"free includes '{field}', but .*{missing}"):
            FreeParameters(weightless, weightless.params(), field)
    damped = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0)], forces=[rb.LinearDamping()])
    assert FreeParameters(damped, damped.params(linear_damping=0.1), "linear_damping").labels


def test_masks_and_indices_as_arrays_select_what_they_say():
    """A NumPy or JAX boolean array is a mask, an integer array a list of indices (a JAX
    mask was once read as indices, and NumPy indices as a mask)."""
    scene = rb.Scene([rb.Body(n, shape=rb.Sphere(0.1), mass=1.0) for n in "abc"])
    params = scene.params(dtype=jnp.float64)
    for which in (np.array([0, 1, 2]), jnp.array([0, 1, 2]), [0, 1, 2], np.ones(3, bool), ["a", "b", "c"]):
        assert FreeParameters(scene, params, {"mass": which}).labels == ("mass[a]", "mass[b]", "mass[c]")
    for which in (jnp.array([True, False, True]), np.array([True, False, True]), [True, False, True],
                  np.flatnonzero([True, False, True]), {"a", "c"}):
        assert FreeParameters(scene, params, {"mass": which}).labels == ("mass[a]", "mass[c]")
    # Forward mode differentiates the coordinates that move a free value, one per label
    # (not the 3 coordinates of mass, nor 6 per body of the inertia).
    for free in ({"mass": ["b"]}, {"inertia": ["c"], "gravity": True}, {"mass": [0, 2], "inertia": True}):
        space = FreeParameters(scene, params, free)
        assert len(space.moving()) == len(space.labels)
    space = FreeParameters(scene, params, {"mass": ["b"], "inertia": ["c"]})
    flat, unravel = jax.flatten_util.ravel_pytree(space.unconstrained())
    moved = space.physical(unravel(flat.at[space.moving()].add(0.1)))
    assert float(moved.mass[1]) != 1.0 and not np.allclose(moved.inertia[2], params.inertia[2])
    assert np.all(np.asarray(moved.mass)[[0, 2]] == 1.0) and np.all(moved.inertia[:2] == params.inertia[:2])


def test_a_guess_on_the_boundary_is_refused():
    scene = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    with pytest.raises(ValueError, match=r"strictly inside \(0, 1\)"):
        FreeParameters(scene, scene.params(restitution=1.0), "restitution")
    flat = scene.params().replace(inertia=jnp.asarray([np.diag([1.0, 1.0, 2.5])]))
    with pytest.raises(ValueError, match="triangle inequality"):
        FreeParameters(scene, flat, "inertia")


def test_guesses_must_be_finite_symmetric_and_floating():
    """Params.replace does not check values: an infinite mass or a NaN inertia had been
    taken as a guess (unconstrained coordinates inf or NaN), an asymmetric inertia had been
    replaced by its symmetric part without a word, and an integer leaf of extra had failed
    inside optax (reduce_on_plateau) or jacfwd."""
    scene = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    params = scene.params(restitution=0.5, dtype=jnp.float64)
    bad = [(params.replace(mass=jnp.asarray([np.inf])), "mass", "free mass is not finite"),
           (params.replace(inertia=jnp.full((1, 3, 3), np.nan)), "inertia", "free inertia is not finite"),
           (params.replace(restitution=jnp.asarray([np.nan])), "restitution", "free restitution is not finite"),
           (params.replace(inertia=jnp.asarray([[[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])), "inertia",
            "not symmetric"),
           (params.replace(extra={"k": jnp.asarray(3)}), "extra", r"extra\['k'\] has dtype int"),
           (params.replace(extra={"k": jnp.asarray([1.0, np.inf])}), "extra", "free extra is not finite")]
    for guess, free, message in bad:
        for for_fit in (True, False):
            with pytest.raises(ValueError, match=message):
                FreeParameters(scene, guess, free, for_fit=for_fit)
    # Round-off asymmetry (an inertia rotated into a frame) is a symmetric inertia.
    rotated = params.inertia.at[0, 0, 1].add(1e-12)
    assert FreeParameters(scene, params.replace(inertia=rotated), "inertia").labels


def test_identifiability_at_the_edge_of_a_fits_domain():
    """The report moves the physical values themselves, so it is defined where a fit
    cannot start: at e = 0 (scene.params()'s default, which it had refused as "not
    strictly inside (0, 1) for a fit"), a friction above friction_max, a flat plate."""
    scene = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    plate = jnp.asarray([np.diag([1.0, 1.0, 2.0])])
    for e, mu in ((0.0, 2.5), (1.0, 0.0)):
        params = scene.params(restitution=e, friction=mu, dtype=jnp.float64).replace(inertia=plate)

        def residuals(p, d):
            return jnp.concatenate([jnp.stack([2.0 * p.restitution[0] - d, p.friction[0] - d]), p.inertia[0, 2]])

        report = rb.identify.identifiability(residuals, scene, params, ["restitution", "friction", "inertia"],
                                             data=1.0)
        # In labels order: inertia xx yy zz xy xz yz, restitution, friction.
        np.testing.assert_allclose(report.values, [1.0, 1.0, 2.0, 0.0, 0.0, 0.0, e, mu])
        expected = np.zeros((5, 8))
        expected[0, 6], expected[1, 7], expected[2, 4], expected[3, 5], expected[4, 2] = 2.0, 1.0, 1.0, 1.0, 1.0
        np.testing.assert_allclose(report.jacobian, expected, atol=1e-12)
        with pytest.raises(ValueError, match="for a fit"):  # a fit still cannot start there
            FreeParameters(scene, params, ["restitution", "friction", "inertia"])


def test_fit_options_and_a_guess_without_a_finite_loss_are_explained():
    """A damping <= 0 or NaN had been accepted: fit_least_squares then took a step against
    the gradient as "converged", or rejected every step to max_steps. A loss NaN at the
    guess had reported loss inf and "the best finite iterate is returned" (there is none)."""
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    guess = scene.params(dtype=jnp.float64)
    residuals = lambda p, d: jnp.stack([jnp.log(p.mass[0]) - jnp.log(d)])  # noqa: E731
    for damping in (-1.0, 0.0, np.nan, np.inf, True, "1e-3"):
        with pytest.raises(ValueError, match="damping must be a positive, finite number"):
            rb.identify.fit_least_squares(residuals, scene, guess, "mass", data=50.0, damping=damping,
                                          progress=False)
    # A vector loss is refused batched as well (the batch's mean had averaged signed residuals
    # into one number, whose fit ran down to mass 0.035 where least squares gives [1, 3]).
    two = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0), rb.Body("b", shape=rb.Sphere(0.1), mass=1.0)])
    for data, batched in ((jnp.asarray([1.0, 2.0]), False), (jnp.asarray([[1.0, 2.0], [1.0, 4.0]]), True)):
        with pytest.raises(ValueError, match=r"must return one number, got shape \(2,\)"):
            rb.identify.fit(lambda p, d: p.mass - d, two, two.params(dtype=jnp.float64), "mass", data=data,
                            batched=batched, max_steps=5, progress=False)
    # A friction_max beside a FreeParameters had been ignored without a word.
    with pytest.raises(ValueError, match="whose own bound"):
        rb.identify.fit(lambda p: p.mass[0], scene, guess, FreeParameters(scene, guess, "mass", friction_max=1.0),
                        friction_max=3.0, progress=False)
    result = rb.identify.fit(lambda p: jnp.sqrt(p.mass[0] - 2.0), scene, guess, "mass", progress=False)
    assert not result.converged and result.steps == 0 and np.isnan(result.loss) and len(result.loss_history) == 0
    assert "the loss is nan at the initial guess" in result.message
    assert float(result.params.mass[0]) == 1.0


def test_a_levenberg_marquardt_fit_stopped_by_a_non_finite_simulation_is_not_converged():
    """Steps rejected for a NaN cost shrink until they pass the xtol test, which had been
    read as convergence: the fit stopped at m = 1.5 "converged" with a gradient of -0.75."""
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    guess = scene.params(dtype=jnp.float64)

    def residuals(p, target):  # the minimum, m = 2, lies beyond a NaN wall at m = 1.5
        return jnp.atleast_1d(jnp.where(p.mass[0] < 1.5, p.mass[0] - target, jnp.nan))

    result = rb.identify.fit_least_squares(residuals, scene, guess, "mass", data=2.0, progress=False)
    assert not result.converged and "not finite" in result.message, result.message
    assert 1.0 < float(result.params.mass[0]) < 1.5 and np.isfinite(result.loss)
    # A finite problem still converges by the step test where the gradient test is too strict.
    plain = rb.identify.fit_least_squares(lambda p, t: jnp.atleast_1d(p.mass[0] - t), scene, guess, "mass",
                                          data=2.0, gtol=0.0, progress=False)
    assert plain.converged and "xtol" in plain.message and abs(float(plain.params.mass[0]) - 2.0) < 1e-9


def test_a_fit_refuses_free_parameters_built_for_a_report_at_a_boundary():
    """FreeParameters(..., for_fit=False) (a report's, at e = 0) passed to a fit had started
    it at logit(0) = -inf: Levenberg-Marquardt returned e = 0 as "converged", Adam stalled."""
    scene = rb.Scene([rb.Body("a", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    params = scene.params(restitution=0.0, dtype=jnp.float64)
    space = FreeParameters(scene, params, "restitution", for_fit=False)
    residuals = lambda p, d: p.restitution - d  # noqa: E731
    with pytest.raises(ValueError, match=r"strictly inside \(0, 1\)"):
        rb.identify.fit_least_squares(residuals, scene, params, space, data=0.7, progress=False)
    with pytest.raises(ValueError, match=r"strictly inside \(0, 1\)"):
        rb.identify.fit(lambda p: jnp.sum((p.restitution - 0.7) ** 2), scene, params, space, progress=False)
    inside = FreeParameters(scene, params.replace(restitution=jnp.asarray([0.5])), "restitution", for_fit=False)
    result = rb.identify.fit_least_squares(residuals, scene, params, inside, data=0.7, progress=False)
    assert result.converged and abs(float(result.params.restitution[0]) - 0.7) < 1e-9


# ------------------------------------------------------------------ (a) bounce


@pytest.fixture(scope="module")
def bounce():
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(scene, SIE, 1e-2)

    def heights(params):
        state = scene.state(params, position=(0.0, 0.0, 1.1))
        return rb.rollout(step, params, state, 200)[1].position[:, 0, 2]

    truth = scene.params(restitution=0.8, dtype=jnp.float64)
    rng = np.random.default_rng(1)
    measured = heights(truth) + 1e-3 * rng.standard_normal(200)  # 1 mm noise
    guess = scene.params(restitution=float(rng.uniform(0.2, 0.95)), dtype=jnp.float64)
    return scene, heights, measured, guess


@pytest.mark.slow
def test_restitution_from_bounce_heights_with_adam(example):
    error, result = _scenario(example, "bounce")
    assert result.converged, result.message
    assert error < 0.01
    assert all(_physical(p) for p in result.iterates)
    assert result.loss_history[-1] < result.loss_history[0]
    with pytest.raises(ValueError, match="only rb.identify.fit_least_squares results"):
        result.identifiability()  # an optax fit keeps no Jacobian


@pytest.mark.slow
def test_restitution_from_bounce_heights_with_levenberg_marquardt(bounce):
    scene, heights, measured, guess = bounce
    residuals = lambda p, d: heights(p) - d  # noqa: E731
    result = rb.identify.fit_least_squares(residuals, scene, guess, "restitution", data=measured, progress=False)
    assert result.converged, result.message
    e = float(result.params.restitution[0])
    assert abs(e / 0.8 - 1) < 0.01
    report = rb.identify.identifiability(residuals, scene, result.params, "restitution", data=measured)
    assert report.identifiable
    # the truth lies within a few standard errors of the estimate
    assert abs(e - 0.8) < 5 * report.std[0]
    _assert_same_report(result.identifiability(), report)


def _assert_same_report(from_fit, direct):
    """``FitResult.identifiability`` (chain rule through the maps) against a new linearisation."""
    assert tuple(from_fit.labels) == tuple(direct.labels)
    np.testing.assert_allclose(from_fit.values, direct.values, rtol=1e-12)
    scale = np.max(np.abs(direct.jacobian), axis=0)
    np.testing.assert_allclose(from_fit.jacobian / scale, direct.jacobian / scale, rtol=0, atol=1e-7)
    np.testing.assert_allclose(from_fit.std, direct.std, rtol=1e-6)
    assert len(from_fit.unidentifiable) == len(direct.unidentifiable)


def test_report_from_a_fit_refuses_an_inertia_at_the_triangle_limit():
    """At I1 + I2 = I3 (a flat plate) the log-Cholesky map is flat: no silent inaccuracy."""
    scene = rb.Scene([rb.Body("plate", mass=1.0, inertia=(0.1, 0.2, 0.3 * (1 - 1e-13)))], gravity=None)
    params = scene.params(dtype=jnp.float64)
    space = rb.identify.FreeParameters(scene, params, "inertia")
    jac = np.random.default_rng(0).standard_normal((20, 6))
    result = rb.identify.FitResult(params, 0.0, np.zeros(1), True, 1, "", space, residuals=np.zeros(20),
                                   jacobian=jac)
    with pytest.raises(ValueError, match="triangle inequality's limit"):
        result.identifiability()
    nan = rb.identify.FitResult(params, 0.0, np.zeros(1), True, 1, "", space, residuals=np.zeros(20),
                                jacobian=np.full((20, 6), np.nan))
    with pytest.raises(ValueError, match="not finite"):
        nan.identifiability()


def test_report_from_a_fit_at_a_flat_map_relinearises():
    """Measured moments just beyond a flat plate's (I3 > I1 + I2): the fit ends at the triangle
    inequality's limit, where the chain rule cannot convert its Jacobian, and the report
    comes from a new linearisation in the physical parameters instead."""
    from jaxrb.identify._identifiability import FlatMapError, from_unconstrained_jacobian

    scene = rb.Scene([rb.Body("plate", mass=1.0, inertia=(0.2, 0.2, 0.2))], gravity=None)
    rows, cols = np.triu_indices(3)
    measured = np.zeros((20, 6))
    measured[:, [0, 3, 5]] = [0.1, 0.2, 0.301]  # xx, yy, zz: infeasible by 1e-3
    measured += 1e-4 * np.random.default_rng(4).standard_normal(measured.shape)

    def residuals(params, data):
        return (params.inertia[0][rows, cols][None, :] - data).ravel()

    guess = scene.params(dtype=jnp.float64)
    result = rb.identify.fit_least_squares(residuals, scene, guess, "inertia", data=measured, progress=False)
    with pytest.raises(FlatMapError):  # the chain rule is refused here ...
        from_unconstrained_jacobian(result.space, result.params, result.jacobian, result.residuals)
    report = result.identifiability()  # ... so this linearised again
    # (FreeParameters(scene, result.params, "inertia") would refuse a limit as a starting point.)
    direct = rb.identify.identifiability(residuals, scene, result.params, result.space, data=measured)
    np.testing.assert_array_equal(report.jacobian, direct.jacobian)
    np.testing.assert_array_equal(report.std, direct.std)
    # The linear residuals' Jacobian selects the six entries, whatever the point.
    names = ["xx", "xy", "xz", "yy", "yz", "zz"]  # the residuals' (triu) order
    selection = np.eye(6)[:, [names.index(label.split(".")[-1]) for label in report.labels]]
    np.testing.assert_allclose(report.jacobian, np.tile(selection, (20, 1)), rtol=0, atol=1e-12)


# ---------------------------------------------------------- (b) inertia ratios


@pytest.fixture(scope="module")
def tumbling():
    moments = np.array([0.1, 0.2, 0.3])
    omega0 = np.array([1.0, 0.3, 2.0])
    times = np.arange(1, 101) * 0.02
    exact = rb.exact.torque_free_top(moments, omega0, times)
    rng = np.random.default_rng(2)
    measured = exact.omega_body + 1e-3 * rng.standard_normal(exact.omega_body.shape)  # gyro noise, rad/s
    scene = rb.Scene([rb.Body("body", mass=1.0, inertia=(0.2, 0.2, 0.2))], gravity=None)
    step = rb.make_step(scene, SPLIT, 2e-3)

    def gyro(params):
        state = scene.state(params, body_angular_velocity=omega0)
        _, traj = rb.rollout(step, params, state, 1000, save_every=10)
        return jax.vmap(rb.body_angular_velocity, in_axes=(None, 0))(params, traj)[:, 0]

    guess_moments = rng.uniform(0.1, 0.3, 3)
    guess_moments[2] = min(guess_moments[2], 0.95 * (guess_moments[0] + guess_moments[1]))
    guess = scene.params(dtype=jnp.float64).replace(inertia=jnp.asarray(np.diag(guess_moments))[None])
    return scene, gyro, measured, guess, moments


def test_inertia_ratios_from_tumbling(example):
    error, result = _scenario(example, "tumbling")
    assert result.converged, result.message
    assert error < 0.01  # I2/I1 and I3/I1
    fitted = np.asarray(result.params.inertia[0])
    assert np.max(np.abs(fitted - np.diag(np.diag(fitted)))) < 0.01 * fitted[0, 0]
    assert all(_physical(p) for p in result.iterates)


def test_tumbling_cannot_tell_the_inertia_scale(tumbling):
    scene, gyro, measured, _, moments = tumbling
    truth = scene.params(dtype=jnp.float64).replace(inertia=jnp.asarray(np.diag(moments))[None])
    report = rb.identify.identifiability(lambda p, d: gyro(p) - d, scene, truth, "inertia", data=measured)
    assert len(report.unidentifiable) == 1
    _, direction = report.unidentifiable[0]
    # the direction is the inertia itself (all entries scaled together), in relative units
    relative = report.values / np.where(np.abs(report.values) > 0, np.abs(report.values), 1.0)
    assert abs(direction @ relative) / np.linalg.norm(relative) > 0.999
    assert "UNIDENTIFIABLE" in str(report) and "inertia[body].xx" in str(report)
    # The ratios the data do determine keep finite standard errors where every moment's is
    # inf: the delta method over the determined directions, against the covariance with
    # I_xx held at its value instead (another generalised inverse: the same for any
    # combination the data determine, as the ratios are).
    assert np.all(np.isinf(report.std[:3]))
    ratios = report.std_of(lambda v: v[1:3] / v[0])
    held = report.jacobian[:, 1:]
    covariance = report.sigma2 * np.linalg.inv(held.T @ held)
    np.testing.assert_allclose(ratios, np.sqrt(np.diag(covariance)[:2]) / report.values[0], rtol=1e-6)
    assert np.all(ratios > 0) and ratios.shape == (2,)
    np.testing.assert_allclose(report.std_of(lambda v: v[3:]), report.std[3:], rtol=1e-12)
    assert np.isinf(report.std_of(lambda v: v[0] + v[1]))


def test_free_fall_cannot_tell_the_mass():
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    step = rb.make_step(scene, SIE, 1e-2)
    truth = scene.params(dtype=jnp.float64)

    def heights(params):
        return rb.rollout(step, params, scene.state(params, velocity=(0.5, 0.0, 3.0)), 50)[1].position[:, 0]

    measured = heights(truth) + 1e-3 * np.random.default_rng(3).standard_normal((50, 3))
    report = rb.identify.identifiability(lambda p, d: heights(p) - d, scene, truth, ["mass", "gravity"],
                                         data=measured)
    assert len(report.unidentifiable) == 1
    _, direction = report.unidentifiable[0]
    assert abs(direction[0]) > 0.999 and report.labels[0] == "mass[ball]"
    assert np.isinf(report.std[0]) and np.all(np.isfinite(report.std[1:]))
    assert "+1.00 mass[ball]" in str(report)
    # The noise variance counts the 3 determined directions, not the 4 parameters (it had
    # divided by m - p = 146, 0.7% high): 1e-3 m of noise, measured sigma 1.08e-3.
    residual = np.asarray(heights(truth)).ravel() - np.asarray(measured).ravel()
    assert report.sigma2 == pytest.approx(residual @ residual / (residual.size - 3), rel=1e-12)


def _thrown_ball():
    """A ball thrown sideways in free fall (mass 1.3 kg): its scene, params and
    ``path(params) -> (60,)``, the positions of 20 steps of 10 ms."""
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    step = rb.make_step(scene, SIE, 1e-2)

    def path(params):
        return rb.rollout(step, params, scene.state(params, position=(0, 0, 1.0), velocity=(1.0, 0, 0)),
                          20)[1].position[:, 0].ravel()

    return scene, scene.params(mass=1.3, dtype=jnp.float64), path


def test_a_lone_parameter_at_rounding_level_is_unidentifiable():
    """The mass alone, from free fall: its sensitivity is rounding (1e-17 m per unit relative
    change), and with no other free parameter to be compared with, the relative test alone
    had reported it identifiable with a standard error of 3e13."""
    scene, truth, path = _thrown_ball()

    measured = path(truth) + 1e-3 * np.random.default_rng(0).standard_normal(60)
    report = rb.identify.identifiability(lambda p, d: path(p) - d, scene, truth, "mass", data=measured)
    assert report.singular_values[0] < 1e-12 < report.floor
    assert not report.identifiable and np.isinf(report.std[0])
    # The covariance covers the determined directions only: none here (it had been 1e28,
    # the pseudo-inverse keeping the rounding-level direction).
    assert np.all(report.covariance == 0.0)
    assert "rounding level" in str(report) and "mass[ball]" in str(report)
    # The same rollout sees gravity (one free field of three values): identifiable.
    seen = rb.identify.identifiability(lambda p, d: path(p) - d, scene, truth, "gravity", data=measured)
    assert seen.identifiable and seen.singular_values[-1] > 1e3 * seen.floor


def test_rounding_is_measured_against_the_measurements_alone():
    """The floor had been zero at an exact fit with the measurements inside the residuals
    (a design study on noise-free data; FitResult.identifiability), which reported the mass
    in free fall identifiable with a standard error of 0; and it had grown with every array
    in data, so that time stamps beside the measurements made gravity "unidentifiable"."""
    scene, truth, path = _thrown_ball()

    exact = np.asarray(path(truth))
    noise_free = lambda p: path(p) - exact  # noqa: E731
    with pytest.warns(UserWarning, match="no scale for rounding"):
        blind = rb.identify.identifiability(noise_free, scene, truth, "mass")
    assert blind.floor == 0.0
    sized = rb.identify.identifiability(noise_free, scene, truth, "mass", measurement_size=np.linalg.norm(exact))
    assert not sized.identifiable and sized.floor > 1e3 * sized.singular_values[0]
    fitted = rb.identify.fit_least_squares(lambda p, d: path(p) - d, scene, truth, "mass", data=exact,
                                           progress=False)
    report = fitted.identifiability()  # from the fit's Jacobian: the fit's data give the size
    assert not report.identifiable and np.isinf(report.std[0])
    # Time stamps (nanoseconds) beside the measurements: their size is not the residuals'.
    stamped = {"x": exact, "t_ns": 1e7 * np.arange(1, 21, dtype=float)}
    residuals = lambda p, d: path(p) - d["x"]  # noqa: E731
    swamped = rb.identify.identifiability(residuals, scene, truth, "gravity", data=stamped)
    assert not swamped.identifiable  # what measurement_size is for
    given = rb.identify.identifiability(residuals, scene, truth, "gravity", data=stamped,
                                        measurement_size=np.linalg.norm(exact))
    assert given.identifiable and given.floor == pytest.approx(np.sqrt(np.finfo(float).eps) * np.linalg.norm(exact))
    for bad in (-1.0, np.nan, np.inf, True, "1"):
        with pytest.raises(ValueError, match="measurement_size must be a finite number"):
            rb.identify.identifiability(residuals, scene, truth, "gravity", data=stamped, measurement_size=bad)


def test_fewer_residuals_than_parameters_leave_the_unseen_directions_unidentifiable():
    """With m < p residuals the SVD has only m singular values: the p - m directions the
    data cannot see are reported (singular value 0), and with no residual to spare
    (m <= the determined directions) the noise variance, covariance and standard errors
    are NaN, not zero."""
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    truth = scene.params(dtype=jnp.float64)

    def weight(params, measured):  # one residual: m g_z; 4 free scalars: mass, gravity
        return jnp.atleast_1d(params.mass[0] * params.gravity[2] - measured)

    report = rb.identify.identifiability(weight, scene, truth, ["mass", "gravity"], data=-9.81 + 0.01)
    assert report.singular_values.shape == (4,) and np.all(report.singular_values[1:] == 0.0)
    assert len(report.unidentifiable) == 3 and not report.identifiable
    # the weight sees m g_z only, through the relative changes of m and g_z alike (d ln m +
    # d ln g_z); g_x and g_y not at all
    np.testing.assert_allclose(np.abs(report.directions[0]), [0.5**0.5, 0, 0, 0.5**0.5], atol=1e-12)
    assert np.isnan(report.sigma2) and not np.any(np.isfinite(report.std))

    def three(params, measured):  # m == p: an exact fit, no degree of freedom left
        return params.gravity - measured

    exact = rb.identify.identifiability(three, scene, truth, "gravity", data=truth.gravity)
    assert exact.identifiable and np.isnan(exact.sigma2) and np.all(np.isnan(exact.std))


def test_a_fits_jacobian_converts_for_a_tiny_body_beside_gravity():
    """dr/dz -> dr/dtheta divides by the parameter maps' Jacobian, whose entries differ by
    the parameters' units: a 1 mm ball's inertia (4e-13 kg m^2) beside gravity once read
    as an inertia at the triangle inequality's limit. With the free values themselves as
    residuals, dr/dtheta is the identity."""
    from jaxrb.identify._identifiability import from_unconstrained_jacobian

    scene = rb.Scene([rb.Body("grain", shape=rb.Sphere(0.5e-3), mass=4.1e-6)])
    params = scene.params(dtype=jnp.float64)
    space = FreeParameters(scene, params, ["inertia", "gravity"])
    flat, unravel = jax.flatten_util.ravel_pytree(space.unconstrained())
    jac_z = np.asarray(jax.jacfwd(lambda x: space.to_vector(space.physical(unravel(x))))(flat))
    report = from_unconstrained_jacobian(space, params, jac_z, np.zeros(jac_z.shape[0]),
                                         measurement_size=float(np.linalg.norm(space.to_vector(params))))
    np.testing.assert_allclose(report.jacobian, np.eye(len(space.labels)), atol=1e-9)


def test_non_finite_sensitivities_are_named():
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    truth = scene.params(dtype=jnp.float64)

    def residuals(params, measured):  # sqrt at 0: a finite value with an infinite slope
        return jnp.stack([jnp.sqrt(params.gravity[0]), params.mass[0] - measured, params.gravity[2]])

    with pytest.raises(ValueError, match=r"residuals 0 \(of 3\) or their sensitivities are not finite"):
        rb.identify.identifiability(residuals, scene, truth, ["mass", "gravity"], data=1.0)
    result = rb.identify.fit_least_squares(residuals, scene, truth, ["mass", "gravity"], data=1.0, progress=False)
    assert not result.converged and "Jacobian is not finite at the initial guess" in result.message
    loss = lambda p, d: jnp.sum(residuals(p, d) ** 2)  # noqa: E731
    result = rb.identify.fit(loss, scene, truth, ["mass", "gravity"], data=1.0, progress=False)
    assert not result.converged and "the gradient became nan" in result.message


def test_a_negative_loss_converges_as_a_positive_one():
    """The default optimiser halves its step on plateaus. optax's ``reduce_on_plateau``
    counted an improvement where ``value < (1 - rtol) best``, above the best for a negative
    loss, so its step never shrank: ``|log m - log 3| - 1`` ran 2000 steps unconverged with
    the mass off by 5.6e-4 (7e-9 at offset 0)."""
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    guess = scene.params(dtype=jnp.float64)
    for offset in (0.0, -1.0, -1e-3):
        result = rb.identify.fit(lambda p, c=offset: jnp.abs(jnp.log(p.mass[0]) - jnp.log(3.0)) + c, scene, guess,
                                 "mass", max_steps=2000, progress=False)
        assert result.converged and result.steps < 400, (offset, result.message)
        assert abs(float(result.params.mass[0]) - 3.0) < 1e-6, offset


def test_levenberg_marquardt_keeps_a_mass_positive_at_the_edge_of_its_range():
    """Gauss-Newton steps in log-mass can be huge (about -1/m where the residual is ``m + 1``,
    minimal at m = 0): ``exp`` underflowed and the fit returned a mass of exactly 0 as
    converged. The mass now stays in the dtype's normal range."""
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    result = rb.identify.fit_least_squares(lambda p: p.mass + 1.0, scene, scene.params(dtype=jnp.float64), "mass",
                                           max_steps=50, keep_iterates=True, progress=False)
    masses = np.asarray([float(p.mass[0]) for p in result.iterates])
    assert np.all(masses > 0) and float(result.params.mass[0]) > 0, masses


def test_patience_counts_steps():
    """Converged after ``patience`` steps that moved less than xtol (not patience - 1: with
    patience=1 an iterate was compared with itself and the first step "converged")."""
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)])
    guess = scene.params(dtype=jnp.float64)
    loss = lambda p: (p.mass[0] - 5.0) ** 2  # noqa: E731
    one = rb.identify.fit(loss, scene, guess, "mass", patience=1, max_steps=500, progress=False)
    assert one.converged and one.steps > 1 and abs(float(one.params.mass[0]) - 5.0) < 1e-3
    with pytest.raises(ValueError, match="patience must be a positive integer"):
        rb.identify.fit(loss, scene, guess, "mass", patience=0, progress=False)


# ------------------------------------------------------------ (c) mass, collision


@pytest.mark.slow
def test_mass_from_a_collision(example):
    error, result = _scenario(example, "collision")
    assert result.converged, result.message
    assert error < 0.02  # mass[unknown]; truth 0.4
    assert float(result.params.mass[0]) == 1.0  # fixed
    assert abs(float(result.params.restitution[0]) / 0.9 - 1) < 0.01
    assert all(_physical(p) for p in result.iterates)
    report = result.identifiability()  # from the fit's Jacobian (checked in the next test)
    assert report.identifiable and tuple(report.labels) == ("mass[unknown]", "restitution[known-unknown]")
    assert abs(float(result.params.mass[1]) - 0.4) < 5 * report.std[0]


def test_report_from_a_fit_matches_a_new_linearisation():
    """Log mass with a fixed entry, sigmoid e and scaled-sigmoid mu, on closed-form residuals
    (cheap to compile): the chain rule through the maps against a new forward-mode Jacobian."""
    balls = [rb.Body(name, shape=rb.Sphere(0.1), mass=1.0) for name in ("known", "unknown")]
    scene = rb.Scene(balls, gravity=None, contacts=[("known", "unknown")])
    t = jnp.linspace(0.0, 1.0, 40)

    def residuals(params, data):
        m, e, mu = params.mass[1], params.restitution[0], params.friction[0]
        model = jnp.stack([jnp.exp(-t / m) * e, jnp.sin(3 * t * mu) + m * e * t], -1)
        return model - data

    truth = scene.params(restitution=0.7, friction=0.3, dtype=jnp.float64).replace(mass=jnp.asarray([1.0, 0.5]))
    data = residuals(truth, 0.0) + 1e-3 * np.random.default_rng(7).standard_normal((40, 2))
    free = {"mass": ["unknown"], "restitution": True, "friction": True}
    guess = truth.replace(mass=jnp.asarray([1.0, 0.8]), restitution=jnp.asarray([0.5]), friction=jnp.asarray([0.5]))
    result = rb.identify.fit_least_squares(residuals, scene, guess, free, data=data, progress=False)
    assert result.converged, result.message
    direct = rb.identify.identifiability(residuals, scene, result.params, free, data=data)
    _assert_same_report(result.identifiability(), direct)


# --------------------------------------------------------- (d) friction, sliding


@pytest.mark.slow
def test_friction_from_a_sliding_box(example):
    error, result = _scenario(example, "sliding")
    assert result.converged, result.message
    assert error < 0.02  # truth 0.4
    assert all(_physical(p) for p in result.iterates)


# ------------------------------------------------ (e) full inertia, known torques


def test_full_inertia_from_known_torques(example):
    """The data from a ten times finer step than the model's; all six entries within 2%."""
    error, result = _scenario(example, "torques")
    assert result.converged, result.message
    assert error < 0.02
    assert all(_physical(p) for p in result.iterates)
    report = result.relinearise(result.params, None)  # a new linearisation, physical parameters
    assert report.identifiable  # with known torques the scale is determined
    _assert_same_report(result.identifiability(), report)  # through the log-Cholesky map


@pytest.mark.slow
def test_fit_over_many_experiments_is_vmapped(bounce):
    """Two drops from different heights, one loss: the mean over the vmapped experiments."""
    scene, _, _, guess = bounce
    step = rb.make_step(scene, SIE, 1e-2)

    def heights(params, z0):
        state = scene.state(params, position=jnp.stack([0.0, 0.0, z0]))
        return rb.rollout(step, params, state, 100)[1].position[:, 0, 2]

    truth = scene.params(restitution=0.7, dtype=jnp.float64)
    drops = jnp.asarray([0.8, 1.2])
    measured = jax.vmap(heights, in_axes=(None, 0))(truth, drops)
    data = (drops, measured)
    result = rb.identify.fit_least_squares(lambda p, d: heights(p, d[0]) - d[1], scene, guess, "restitution",
                                           data=data, batched=True, progress=False)
    assert abs(float(result.params.restitution[0]) - 0.7) < 1e-6  # noise-free data: exact
