"""The speed/accuracy benchmark (rb.tradeoff) on a scene it was not tuned for.

Two bodies (a box and a capsule) under gravity, linear damping, a spring to the origin
and a time-dependent torque. Float64 (conftest). The sweep is run once per module.
"""

import dataclasses
import json
import math
import warnings

import jax.numpy as jnp
import matplotlib
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxrb as rb
from jaxrb import _tradeoff as tradeoff
from jaxrb import spatial
from tests import reference

matplotlib.use("Agg")

STIFFNESS = 15.0  # N/m, spring from each centre of mass to the world origin
TORQUE_SCALE = np.array([1.0, 0.05])  # per body
T_FINAL = 2.0
NUM_COMPARE = 10
DTS = [0.04 / 2**k for k in range(7)]  # 50 .. 3200 steps
CANDIDATES = [rb.integrators.RK4(), rb.integrators.SemiImplicitEuler(), rb.integrators.ExplicitEuler()]


def torque_np(t):
    return np.array([0.4 * np.cos(2 * t), -0.3 * np.sin(t), 0.2 * np.cos(t)])


def spring_and_torque(t, params, state):
    torque = jnp.stack([0.4 * jnp.cos(2 * t), -0.3 * jnp.sin(t), 0.2 * jnp.cos(t)])
    return -params.extra["stiffness"] * state.position, torque[None, :] * jnp.asarray(TORQUE_SCALE)[:, None]


def two_body_scene():
    scene = rb.Scene(
        [rb.Body("box", shape=rb.Box((0.2, 0.3, 0.5)), mass=2.0),
         rb.Body("capsule", shape=rb.Capsule(0.1, 0.3), mass=0.7)],
        gravity=(0.0, 0.0, -9.81),
        forces=[rb.LinearDamping(), rb.ExternalWrench(spring_and_torque)],
    )
    params = scene.params(linear_damping={"box": 0.3, "capsule": 0.1}, extra={"stiffness": jnp.asarray(STIFFNESS)})
    tilt = np.asarray(spatial.quat_from_axis_angle(jnp.array([1.0, 1.0, 0.0]), 0.6))
    state = scene.state(params, position={"box": (0.5, 0.0, 1.0), "capsule": (-0.3, 0.4, 0.2)},
                        velocity={"box": (0.0, 1.0, 0.5), "capsule": (0.5, 0.0, -0.2)},
                        orientation={"capsule": tilt},
                        body_angular_velocity={"box": (0.4, 1.0, -0.6), "capsule": (1.0, -0.5, 0.3)})
    return scene, params, state


@pytest.fixture(scope="module")
def sweep():
    scene, params, state = two_body_scene()
    result = tradeoff.tradeoff(scene, params, state, T_FINAL, integrators=CANDIDATES, dts=DTS,
                               repeats=2, num_compare=NUM_COMPARE)
    print(result)
    return scene, params, state, result


def rows_of(result, name):
    return [r for r in result.rows if r["integrator"] == name]


# ------------------------------------------------------------------------ reference


def scipy_solution(params, state, times):
    """The same scene written out independently in numpy, by DOP853 at rtol 1e-13."""
    mass = np.asarray(params.mass)
    inverse_inertia = np.linalg.inv(np.asarray(params.inertia))
    damping = np.asarray(params.linear_damping)
    gravity = np.asarray(params.gravity)

    def rhs(t, y):
        out = []
        for i, body in enumerate(y.reshape(2, 13)):
            x, v, q, l_world = body[:3], body[3:6], body[6:10], body[10:]
            r = reference.quat_to_matrix(q)
            omega = r @ inverse_inertia[i] @ r.T @ l_world
            w, qv = q[0], q[1:]  # (0, omega) q / 2
            dq = 0.5 * np.concatenate([[-omega @ qv], w * omega + np.cross(omega, qv)])
            force = mass[i] * gravity - damping[i] * v - STIFFNESS * x
            out.append(np.concatenate([v, force / mass[i], dq, TORQUE_SCALE[i] * torque_np(t)]))
        return np.concatenate(out)

    y0 = np.concatenate([np.concatenate([np.asarray(state.position[i]), np.asarray(state.velocity[i]),
                                         np.asarray(state.orientation[i]), np.asarray(state.angular_momentum[i])])
                         for i in range(2)])
    sol = solve_ivp(rhs, (0.0, times[-1]), y0, method="DOP853", t_eval=times, rtol=1e-13, atol=1e-14)
    assert sol.success
    return sol.y.T.reshape(len(times), 2, 13)


def test_reference_agrees_with_an_independent_scipy_solve():
    scene, params, state = two_body_scene()
    times = tradeoff.comparison_times(state, T_FINAL, NUM_COMPARE)
    ref = tradeoff.reference_solution(scene, params, state, T_FINAL, num_compare=NUM_COMPARE).trajectory
    expected = scipy_solution(params, state, times)
    worst = {}
    worst["x"] = np.max(np.abs(np.asarray(ref.position) - expected[..., :3]))
    worst["v"] = np.max(np.abs(np.asarray(ref.velocity) - expected[..., 3:6]))
    worst["L"] = np.max(np.abs(np.asarray(ref.angular_momentum) - expected[..., 10:]))
    worst["q"] = max(reference.rotation_angle(reference.quat_to_matrix(expected[k, i, 6:10]),
                                              np.asarray(spatial.quat_to_matrix(ref.orientation[k, i])))
                     for k in range(len(times)) for i in range(2))
    print({k: f"{v:.1e}" for k, v in worst.items()})
    # Acceptance: 1e-9 in m, m/s, kg m^2/s and rad. Both sides run at ~1e-12 tolerance on
    # O(1) states over 2 s (measured <= 1e-10), so 1e-9 catches any modelling difference.
    for field, value in worst.items():
        assert value <= 1e-9, (field, value)


# ------------------------------------------------------------------------ convergence


def fitted_slope(rows, metric, result, low=10.0, high=0.5):
    """Log-log slope of ``metric`` over the rows in the asymptotic, resolved range.

    Kept: errors above ``low`` x the reference floor (an upper estimate of the
    reference's own error) and below ``high`` (an attitude error saturates at pi, so a
    first-order method's coarsest steps, at ~1.5 rad here, are outside its asymptotic
    regime; below 0.5 rad the angle is within 4% of linear in the error).
    """
    floor = result.reference_floor[metric]
    kept = [r for r in rows if low * floor < r[metric] < high]
    assert len(kept) >= 3, (metric, [r[metric] for r in rows])
    return np.polyfit(np.log([r["dt"] for r in kept]), np.log([r[metric] for r in kept]), 1)[0], len(kept)


@pytest.mark.parametrize("name, order", [("RK4", 4), ("SemiImplicitEuler", 1)])
def test_convergence_slopes(sweep, name, order):
    *_, result = sweep
    for metric in ("attitude_error", "position_error"):
        slope, used = fitted_slope(rows_of(result, name), metric, result)
        print(f"{name} {metric}: slope {slope:.3f} over {used} step sizes")
        # Acceptance: the nominal order +-0.3 (measured 4.00 and 4.01; 1.00 and 1.00).
        assert abs(slope - order) <= 0.3, (name, metric, slope)


@pytest.mark.parametrize("name", ["RK4", "SemiImplicitEuler", "ExplicitEuler"])
def test_errors_shrink_monotonically(sweep, name):
    *_, result = sweep
    rows = sorted(rows_of(result, name), key=lambda r: -r["dt"])
    assert [r["steps"] for r in rows] == [round(T_FINAL / dt) for dt in DTS]
    for metric in ("position_error", "velocity_error", "attitude_error"):
        floor = 10 * result.reference_floor[metric]
        resolved = [r[metric] for r in rows if r[metric] > floor]
        assert all(b < a for a, b in zip(resolved, resolved[1:], strict=False)), (name, metric, resolved)
    assert not any(r["failed"] for r in rows)


# ------------------------------------------------------------------------ result API


def test_pareto_rows_are_non_dominated(sweep):
    *_, result = sweep
    for metric in ("attitude_error", "energy_error"):
        front = result.pareto(metric)
        assert front and [r["cost"] for r in front] == sorted(r["cost"] for r in front)
        ok = [r for r in result.rows if not r["failed"]]
        for f in front:
            assert not any(r["cost"] <= f["cost"] and r[metric] <= f[metric]
                           and (r["cost"] < f["cost"] or r[metric] < f[metric]) for r in ok)
        for r in ok:  # and everything off the front is dominated by a row on it
            if not any(r is f for f in front):
                assert any(f["cost"] <= r["cost"] and f[metric] <= r[metric] for f in front)


def test_cheapest_meets_the_tolerance(sweep):
    *_, result = sweep
    tolerance = 1e-6
    best = result.cheapest(tolerance)
    assert best is not None and best["attitude_error"] <= tolerance
    assert all(r["cost"] >= best["cost"] for r in result.rows if r["attitude_error"] <= tolerance)
    print(f"cheapest to 1e-6 rad: {best['integrator']} at dt = {best['dt']:.4g} s")
    assert result.cheapest(1e-30) is None
    position = result.cheapest(1e-3, metric="position_error")
    assert position is not None and position["position_error"] <= 1e-3
    with pytest.raises(ValueError, match="Unknown metric"):
        result.cheapest(1e-3, metric="speed")


def test_table_json_and_plot(sweep, tmp_path):
    *_, result = sweep
    table = str(result)
    assert table.startswith("| integrator | dt (s) |") and table.count("\n| RK4 |") == len(DTS)
    data = json.loads(result.to_json())
    assert len(data["rows"]) == len(result.rows) and data["info"]["reference"]["solver"] == "Dopri8"
    np.testing.assert_allclose(data["times"], tradeoff.comparison_times(sweep[2], T_FINAL, NUM_COMPARE))
    for row in result.rows:
        assert row["compile_time"] > 0 and row["cost"] > 0 and math.isfinite(row["attitude_error"])

    ax = tradeoff.plot_tradeoff(result)
    labels = [line.get_label() for line in ax.get_lines()]
    assert {"RK4", "SemiImplicitEuler", "ExplicitEuler", "Pareto front"} <= set(labels)
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
    path = tmp_path / "tradeoff.png"
    ax.figure.savefig(path)
    assert path.stat().st_size > 10_000
    import matplotlib.pyplot as plt

    plt.close(ax.figure)
    # Each line joins its runs in order of work, however dts was ordered (the rows follow dts).
    shuffled = dataclasses.replace(result, rows=[result.rows[k] for k in np.random.default_rng(0).permutation(
        len(result.rows))])
    ax = tradeoff.plot_tradeoff(shuffled)
    names = {r["integrator"] for r in result.rows}
    for line in [line for line in ax.get_lines() if line.get_label() in names]:
        steps = {r["cost"]: r["steps"] for r in result.rows if r["integrator"] == line.get_label()}
        drawn = [steps[c] for c in line.get_xdata()]
        assert drawn == sorted(drawn) and len(drawn) > 1, line.get_label()
    plt.close(ax.figure)


def test_failed_rows_are_never_chosen():
    _, params, state = two_body_scene()
    trajectory = rb.State(position=jnp.full((3, 2, 3), jnp.nan), orientation=jnp.ones((3, 2, 4)) / 2,
                          velocity=jnp.zeros((3, 2, 3)), angular_momentum=jnp.zeros((3, 2, 3)), time=jnp.zeros(3))
    metrics = tradeoff._row_metrics(params, trajectory, trajectory)
    assert metrics["failed"] and all(math.isinf(metrics[m]) for m in tradeoff.METRICS)
    # A run that blew up but stayed finite (a stiff spring's RK4 at omega dt = 5 reached
    # errors of 1e53 with its attitude error below pi, and was called the cheapest).
    reference_run = dataclasses.replace(trajectory, position=jnp.zeros((3, 2, 3)))
    for blown_up in (1e53, 1e300):
        diverged = dataclasses.replace(reference_run, position=reference_run.position.at[-1, 0, 0].set(blown_up))
        metrics_diverged = tradeoff._row_metrics(params, diverged, reference_run)
        assert metrics_diverged["failed"] and all(math.isinf(metrics_diverged[m]) for m in tradeoff.METRICS)
    near = dataclasses.replace(reference_run, position=reference_run.position.at[-1, 0, 0].set(1e3))
    assert not tradeoff._row_metrics(params, near, reference_run)["failed"]  # a large error, still measured
    good = {**{m: 1e-3 for m in tradeoff.METRICS}, "failed": False, "cost": 1.0, "integrator": "A"}
    bad = {**metrics, "cost": 1e-3, "integrator": "B"}
    result = tradeoff.TradeoffResult(rows=[good, bad], times=np.array([1.0]))
    assert result.pareto() == [good] and result.cheapest(1.0) is good
    assert json.loads(result.to_json())["rows"][1]["attitude_error"] is None
    # A tie in cost goes to the smaller error, the row on the Pareto front (it went to the first row).
    worse = {**good, "attitude_error": 1e-3, "integrator": "C"}
    better = {**good, "attitude_error": 1e-5, "integrator": "D"}
    tied = tradeoff.TradeoffResult(rows=[worse, better], times=np.array([1.0]))
    assert tied.pareto() == [better] and tied.cheapest(1e-2) is better


# ------------------------------------------------------------------------ defaults, errors


def test_default_integrators_are_every_exported_one():
    names = [type(i).__name__ for i in tradeoff.default_integrators()]
    expected = []
    for name in rb.integrators.__all__:
        try:
            getattr(rb.integrators, name)()
        except TypeError:  # the abstract Integrator, or one that needs arguments
            continue
        expected.append(name)
    assert names == expected and {"ExplicitEuler", "SemiImplicitEuler", "RK4"} <= set(names)


def test_default_sweep_is_geometric_and_divides():
    counts = tradeoff._step_counts(None, 3.0, 20)
    assert counts == [20 * 2**k for k in range(8)]
    with pytest.warns(UserWarning, match="using dt"):
        assert tradeoff._step_counts([0.07], 1.0, 10) == [10]  # 14.3 steps -> 10
    assert tradeoff._step_counts([0.1, 0.1 + 1e-15], 1.0, 10) == [10]
    # A float32 start time, 0.1 -> 0.10000000149: its rounding is no reason to change dt.
    t0 = float(np.float32(0.1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert tradeoff._step_counts([0.05], 1.1 - t0, 20, slack=4 * float(np.finfo(np.float32).eps) * t0) == [20]
    # A dt of the whole span, whose duration rounds below it (0.3 - 0.1 = 0.19999999999999998),
    # had been refused as longer than the span.
    assert tradeoff._step_counts([0.2], 0.3 - 0.1, 1) == [1]
    with pytest.raises(ValueError, match=r"dts must be a list of step sizes \(s\), got an array of shape \(1, 2\)"):
        tradeoff._step_counts([[0.1, 0.05]], 1.0, 1)  # a TypeError about 0-dimensional arrays


def test_a_scene_with_contacts_is_refused():
    # Its reference (ode.solve, no contacts) fell through the ground: errors of 0.74 m.
    scene = rb.Scene([rb.Body("ball", shape=rb.Sphere(0.1), mass=1.0)], ground=rb.Plane(), contacts="all")
    params = scene.params(restitution=0.8)
    state = scene.state(params, position=(0.0, 0.0, 0.15))
    with pytest.raises(ValueError, match="contact pairs"):
        tradeoff.tradeoff(scene, params, state, 0.4, integrators=[rb.integrators.SemiImplicitEuler()], dts=[0.01])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"t_final": 0.0}, "later than the state's time"),
        ({"t_final": -1.0}, "later than the state's time"),
        ({"t_final": float("inf")}, "finite"),
        ({"dts": [0.0]}, "positive"),
        ({"dts": [5.0]}, "at most"),
        ({"integrators": [rb.integrators.RK4]}, "write RK4()"),
        ({"integrators": ["RK4"]}, "rb.integrators instances"),
        ({"integrators": []}, "empty"),
        ({"dts": []}, "dts is empty"),  # had computed the reference, then returned no rows
        ({"repeats": 0}, "repeats"),
        ({"num_compare": 0}, "num_compare"),
        # Two rows of the same name and work, drawn as one line by plot_tradeoff.
        ({"integrators": [rb.integrators.RK4(), rb.integrators.RK4()]}, "same integrator more than once"),
    ],
)
def test_bad_input_raises(kwargs, match):
    scene, params, state = two_body_scene()
    kwargs = {"t_final": 1.0, "integrators": [rb.integrators.RK4()], "dts": [0.1], **kwargs}
    t_final = kwargs.pop("t_final")
    with pytest.raises(ValueError, match=match):
        tradeoff.tradeoff(scene, params, state, t_final, **kwargs)


def test_comparison_times_checks_its_input():
    """It had checked nothing: 0 times raised an IndexError, 2.5 gave three uneven times,
    an earlier t_final times running backwards."""
    scene, params, state = two_body_scene()
    np.testing.assert_allclose(rb.comparison_times(state, 0.2, np.int64(2)), [0.1, 0.2])
    # A JAX scalar t_final (it raised a TypeError: the times had become an immutable JAX array).
    np.testing.assert_allclose(rb.comparison_times(state, jnp.asarray(0.2), 2), [0.1, 0.2])
    for t_final, num_compare, message in [(0.2, 0, "num_compare"), (0.2, 2.5, "num_compare"),
                                          (0.2, True, "num_compare"), (-1.0, 2, "later than the state's time"),
                                          (np.nan, 2, "finite")]:
        with pytest.raises(ValueError, match=message):
            rb.comparison_times(state, t_final, num_compare)


def test_bad_objects_and_references_raise():
    scene, params, state = two_body_scene()
    with pytest.raises(ValueError, match="rb.Scene"):
        tradeoff.tradeoff(None, params, state, 1.0)
    prepared = rb.make_step(scene, rb.integrators.ExplicitEuler(), 0.1).prepare(state)
    with pytest.raises(ValueError, match="rotation matrix"):
        tradeoff.tradeoff(scene, params, prepared, 1.0)
    short = jnp.zeros((3, 2, 3))
    bad_reference = rb.State(position=short, orientation=jnp.zeros((3, 2, 4)), velocity=short,
                             angular_momentum=short, time=jnp.zeros(3))
    with pytest.raises(ValueError, match="stacked at the 10 comparison times"):
        tradeoff.tradeoff(scene, params, state, 1.0, integrators=[rb.integrators.RK4()], dts=[0.1],
                          reference=bad_reference, num_compare=10)
    with pytest.raises(ValueError, match="reference must be"):
        tradeoff.tradeoff(scene, params, state, 1.0, integrators=[rb.integrators.RK4()], dts=[0.05], reference=3)
    # The reference solves' step limit is the caller's (a long horizon had no way to raise it).
    with pytest.raises(ValueError, match="max_steps must be a positive integer"):
        tradeoff.tradeoff(scene, params, state, 1.0, integrators=[rb.integrators.RK4()], dts=[0.1], max_steps=0)
    # A stacked State saved for another t_final (every 0.2 s, not 0.1 s) was taken silently.
    ten = jnp.zeros((10, 2, 3))
    elsewhere = rb.State(position=ten, orientation=jnp.zeros((10, 2, 4)), velocity=ten, angular_momentum=ten,
                         time=0.2 * jnp.arange(1, 11))
    with pytest.raises(ValueError, match="saved at other times"):
        tradeoff.tradeoff(scene, params, state, 1.0, integrators=[rb.integrators.RK4()], dts=[0.1],
                          reference=elsewhere, num_compare=10)


def test_precomputed_reference_gives_the_same_rows(sweep):
    scene, params, state, result = sweep
    precomputed = tradeoff.reference_solution(scene, params, state, T_FINAL, num_compare=NUM_COMPARE)
    again = tradeoff.tradeoff(scene, params, state, T_FINAL, integrators=[rb.integrators.RK4()], dts=[DTS[2]],
                              reference=precomputed, repeats=1, num_compare=NUM_COMPARE)
    assert again.reference_floor is None
    (row,) = again.rows
    (same,) = [r for r in rows_of(result, "RK4") if r["steps"] == row["steps"]]
    for metric in tradeoff.METRICS:
        assert row[metric] == pytest.approx(same[metric], rel=1e-9)
    assert rb.reference_solution is tradeoff.reference_solution  # public, as the message says
    assert rb.comparison_times is tradeoff.comparison_times
    with pytest.raises(ValueError, match=r"saved at other times.*rb\.reference_solution"):
        tradeoff.tradeoff(scene, params, state, T_FINAL, integrators=[rb.integrators.RK4()], dts=[DTS[2]],
                          reference=precomputed, num_compare=5)


def test_float32_scene_runs_with_a_float32_reference():
    scene, _, _ = two_body_scene()
    params = scene.params(linear_damping={"box": 0.3, "capsule": 0.1}, extra={"stiffness": jnp.asarray(STIFFNESS)},
                          dtype=jnp.float32)
    state = scene.state(params, position={"box": (0.5, 0.0, 1.0)}, body_angular_velocity={"box": (0.4, 1.0, -0.6)},
                        dtype=jnp.float32)
    result = tradeoff.tradeoff(scene, params, state, 1.0, integrators=[rb.integrators.RK4()], dts=[0.01],
                               repeats=np.int64(1), num_compare=5)  # a NumPy integer had been refused
    (row,) = result.rows
    assert json.loads(result.to_json())["info"]["repeats"] == 1
    assert result.info["dtype"] == "float32" and result.info["reference"]["rtol"] == 1e-6
    # RK4 at dt = 0.01 is accurate to ~1e-8 in exact arithmetic; in float32 both it and
    # the reference (Dopri8 at rtol 1e-6) sit at ~1e-6: the row is finite and that small.
    assert not row["failed"] and row["attitude_error"] < 1e-4 and row["position_error"] < 1e-4
    print({m: f"{row[m]:.1e}" for m in tradeoff.METRICS}, result.reference_floor)
