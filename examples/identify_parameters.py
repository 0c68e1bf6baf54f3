"""Fit a body's physical parameters to noisy measurements: five scenarios with jaxrb.identify.

Each scenario simulates a known truth, adds measurement noise, draws a random initial
guess and fits, then prints the truth, the fit, its standard error and the relative error:

    bounce     restitution from a ball's heights (1 mm noise)             Adam
    tumbling   inertia ratios from a gyro on a tumbling body              Levenberg-Marquardt
    collision  a ball's mass (and e) from its collision with a known ball Levenberg-Marquardt
    sliding    the friction coefficient from a sliding box's track        Levenberg-Marquardt
    torques    the full 3x3 inertia from known applied torques            Levenberg-Marquardt

Run:  python examples/identify_parameters.py [scenario ...] [--quick] [--seed N]
(all scenarios by default; ``--quick`` shortens the records for CI).

Each scenario is a function ``(rng, quick, **fit_options) -> (error, result)``: the largest
relative error of what it recovers, and the ``rb.identify.FitResult``. ``fit_options`` go
to the fit (``tests/test_identify.py`` runs every scenario with ``keep_iterates=True`` and
checks each iterate).
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)  # identification wants float64 sensitivities

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxrb as rb  # noqa: E402

SIE = rb.integrators.SemiImplicitEuler()
SPLIT = rb.integrators.SymplecticSplitting()


def report(name, truth, fitted, std):
    truth, fitted, std = (np.atleast_1d(np.asarray(x, float)) for x in (truth, fitted, std))
    for t, f, s in zip(truth, fitted, std, strict=True):
        print(f"  {name:<22} truth {t: .5f}  fit {f: .5f} +- {s:.1e}  error {abs(f / t - 1):.2e}")


def bounce(rng, quick, **fit_options):
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(scene, SIE, 1e-2)
    n = 120 if quick else 200

    def heights(params):
        return rb.rollout(step, params, scene.state(params, position=(0.0, 0.0, 1.1)), n)[1].position[:, 0, 2]

    truth = scene.params(restitution=0.8, dtype=jnp.float64)
    measured = heights(truth) + 1e-3 * rng.standard_normal(n)
    guess = scene.params(restitution=rng.uniform(0.2, 0.95), dtype=jnp.float64)
    result = rb.identify.fit(lambda p, d: jnp.mean((heights(p) - d) ** 2), scene, guess, "restitution", data=measured,
                             **fit_options)
    print(result)
    info = rb.identify.identifiability(lambda p, d: heights(p) - d, scene, result.params, "restitution", data=measured)
    report("restitution", 0.8, result.params.restitution, info.std)
    return abs(float(result.params.restitution[0]) / 0.8 - 1), result


def tumbling(rng, quick, **fit_options):
    moments, omega0 = np.array([0.1, 0.2, 0.3]), np.array([1.0, 0.3, 2.0])
    samples = 50 if quick else 100
    exact = rb.exact.torque_free_top(moments, omega0, np.arange(1, samples + 1) * 0.02)
    measured = exact.omega_body + 1e-3 * rng.standard_normal(exact.omega_body.shape)
    scene = rb.Scene([rb.Body("body", mass=1.0, inertia=(0.2, 0.2, 0.2))], gravity=None)
    step = rb.make_step(scene, SPLIT, 2e-3)

    def gyro(params):
        _, traj = rb.rollout(step, params, scene.state(params, body_angular_velocity=omega0), 10 * samples,
                             save_every=10)
        return jax.vmap(rb.body_angular_velocity, in_axes=(None, 0))(params, traj)[:, 0]

    guess = scene.params(dtype=jnp.float64).replace(inertia=jnp.asarray(np.diag(rng.uniform(0.12, 0.22, 3)))[None])
    result = rb.identify.fit_least_squares(lambda p, d: gyro(p) - d, scene, guess, "inertia", data=measured,
                                           **fit_options)
    # Moments 1:2:3 are a flat plate's (I1 + I2 = I3), where the log-Cholesky map is flat:
    # there the report linearises the residuals again instead of reusing the fit's Jacobian.
    info = result.identifiability()
    print(info)
    fitted = np.diag(np.asarray(result.params.inertia[0]))
    # Each moment's standard error is inf (the scale is not determined), their ratios' is not.
    ratio_std = info.std_of(lambda v: v[1:3] / v[0])  # v: the free values, in info.labels' order
    report("I2/I1, I3/I1", moments[1:] / moments[0], fitted[1:] / fitted[0], ratio_std)
    return float(np.max(np.abs((fitted[1:] / fitted[0]) / (moments[1:] / moments[0]) - 1))), result


def collision(rng, quick, **fit_options):
    balls = [rb.Body(name, shape=rb.Sphere(0.1), mass=1.0) for name in ("known", "unknown")]
    scene = rb.Scene(balls, gravity=None, contacts=[("known", "unknown")])
    step = rb.make_step(scene, SIE, 1e-2)
    n = 70 if quick else 100

    def track(params):
        state = scene.state(params, position=[[-0.5, 0, 0], [0.5, 0, 0]], velocity=[[2.0, 0, 0], [0, 0, 0]])
        return rb.rollout(step, params, state, n)[1].position[:, :, 0]

    truth = scene.params(restitution=0.9, dtype=jnp.float64).replace(mass=jnp.asarray([1.0, 0.4]))
    measured = track(truth) + 1e-3 * rng.standard_normal((n, 2))
    guess = truth.replace(mass=jnp.asarray([1.0, rng.uniform(0.1, 3.0)]), restitution=jnp.asarray([0.5]))
    free = {"mass": ["unknown"], "restitution": True}
    result = rb.identify.fit_least_squares(lambda p, d: track(p) - d, scene, guess, free, data=measured, **fit_options)
    info = result.identifiability()  # from the fit's last Jacobian: no new compilation
    report("mass[unknown]", 0.4, result.params.mass[1], info.std[0])
    report("restitution", 0.9, result.params.restitution, info.std[1])
    return abs(float(result.params.mass[1]) / 0.4 - 1), result


def sliding(rng, quick, **fit_options):
    scene = rb.Scene([rb.Body("box", shape=rb.Box((0.1, 0.1, 0.1)), mass=1.0)], ground=rb.Plane(), contacts="all")
    step = rb.make_step(scene, SIE, 1e-2)
    n = 80 if quick else 100

    def track(params):
        state = scene.state(params, position=(0.0, 0.0, 0.1), velocity=(3.0, 0.0, 0.0))
        return rb.rollout(step, params, state, n)[1].position[:, 0, 0]

    truth = scene.params(friction=0.4, dtype=jnp.float64)
    measured = track(truth) + 1e-3 * rng.standard_normal(n)
    guess = scene.params(friction=rng.uniform(0.1, 0.8), dtype=jnp.float64)  # a cube tips over above mu = 1
    result = rb.identify.fit_least_squares(lambda p, d: track(p) - d, scene, guess, "friction", data=measured,
                                           **fit_options)
    info = result.identifiability()  # from the fit's last Jacobian: no new compilation
    report("friction", 0.4, result.params.friction, info.std)
    return abs(float(result.params.friction[0]) / 0.4 - 1), result


def torques(rng, quick, **fit_options):
    rot = np.asarray(rb.spatial.quat_to_matrix(rb.spatial.quat_from_axis_angle(np.array([1.0, 2.0, 2.0]) / 3, 0.7)))
    truth_inertia = rot @ np.diag([0.2, 0.3, 0.4]) @ rot.T

    def torque(t, params, state):
        tau = jnp.stack([jnp.sin(3 * t), jnp.cos(2 * t), 0.5 + jnp.sin(5 * t)])[None]
        return jnp.zeros_like(tau), tau

    scene = rb.Scene([rb.Body("body", mass=1.0, inertia=truth_inertia)], gravity=None,
                     forces=[rb.ExternalWrench(torque)])
    steps = 500 if quick else 1000

    def gyro(params, dt, n):
        _, traj = rb.rollout(rb.make_step(scene, SPLIT, dt), params, scene.state(params), n, save_every=n // 50)
        return jax.vmap(rb.body_angular_velocity, in_axes=(None, 0))(params, traj)[:, 0]

    truth = scene.params(dtype=jnp.float64)
    measured = gyro(truth, 2e-4, 10 * steps) + 1e-3 * rng.standard_normal((50, 3))  # a 10x finer step
    guess = truth.replace(inertia=jnp.asarray(np.diag(rng.uniform(0.2, 0.4, 3)))[None])
    residuals = lambda p, d: gyro(p, 2e-3, steps) - d  # noqa: E731
    result = rb.identify.fit_least_squares(residuals, scene, guess, "inertia", data=measured, **fit_options)
    info = result.identifiability()  # from the fit's last Jacobian: no new compilation
    fitted = np.asarray(result.params.inertia[0])
    upper = np.triu_indices(3)
    std = info.std[[0, 3, 4, 1, 5, 2]]  # labels xx yy zz xy xz yz -> upper triangle xx xy xz yy yz zz
    report("inertia xx xy xz yy yz zz", truth_inertia[upper], fitted[upper], std)
    print(f"  identifiable: {info.identifiable}")
    return float(np.max(np.abs(fitted - truth_inertia) / np.abs(truth_inertia))), result


SCENARIOS = {"bounce": bounce, "tumbling": tumbling, "collision": collision, "sliding": sliding, "torques": torques}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenarios", nargs="*", help=f"any of {list(SCENARIOS)} (default: all)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    unknown = sorted(set(args.scenarios) - set(SCENARIOS))
    if unknown:
        parser.error(f"unknown scenario(s) {unknown}; choose from {list(SCENARIOS)}")
    errors = {}
    for name in args.scenarios or list(SCENARIOS):
        print(f"\n== {name}")
        errors[name], _ = SCENARIOS[name](np.random.default_rng(args.seed), args.quick)
    print("\nlargest relative error per scenario: " + ", ".join(f"{k} {v:.1e}" for k, v in errors.items()))
    return errors


if __name__ == "__main__":
    main()
