"""Measure the speed/accuracy trade of jaxrb's integrators on the user's own scene.

``tradeoff(scene, params, state, t_final)`` runs every candidate integrator at every
time step of a sweep from the user's ``(params, state)`` to ``t_final``, compares each
run with an accurate adaptive reference (:func:`jaxrb.ode.solve` with Dopri8 at tight
tolerance) at a fixed grid of comparison times, and times the compiled rollout. The
result answers "which integrator and ``dt`` reach my tolerance at the least cost?"
(:meth:`TradeoffResult.cheapest`) and draws the work-precision front
(:func:`plot_tradeoff`).

Comparison times: ``num_compare`` evenly spaced times ``t0 + k (t_final - t0) / num_compare``,
``k = 1 .. num_compare``, the last being ``t_final``. Every ``dt`` is rounded so that the
number of steps is a multiple of ``num_compare``; a rollout then records exactly these
times with ``save_every``. Errors are the maximum over these times and over bodies.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import platform
import time
import warnings
from typing import Any

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from . import integrators as _integrators
from . import ode, spatial
from .integrators import Integrator
from .scene import Scene
from .simulate import make_step, rollout
from .state import (
    Params,
    State,
    angular_momentum_about,
    kinetic_energy,
    potential_energy,
    rotation_matrix,
)

__all__ = [
    "METRICS",
    "TradeoffResult",
    "comparison_times",
    "default_integrators",
    "plot_tradeoff",
    "reference_solution",
    "tradeoff",
]

#: The error measures of a row, with their units (for tables and plot labels).
METRICS: dict[str, str] = {
    "attitude_error": "rad",
    "position_error": "m",
    "velocity_error": "m/s",
    "angular_momentum_error": "relative",
    "energy_error": "relative",
}


def default_integrators() -> list[Integrator]:
    """One instance of every integrator :mod:`jaxrb.integrators` exports, built with no arguments.

    Read from ``jaxrb.integrators.__all__``, so integrators added later are picked up.
    Classes that need arguments (or are abstract) are skipped.
    """
    found = []
    for name in _integrators.__all__:
        cls = getattr(_integrators, name)
        if not (isinstance(cls, type) and issubclass(cls, Integrator)) or cls is Integrator:
            continue
        try:
            found.append(cls())
        except TypeError:  # needs constructor arguments, or is abstract
            continue
    return found


def comparison_times(state: State, t_final: float, num_compare: int = 20) -> np.ndarray:
    """``(num_compare,)`` absolute times (s): ``t0 + k (t_final - t0) / num_compare``, ``k = 1 .. num_compare``.

    Raises ``ValueError`` unless ``num_compare`` is a positive integer and ``t_final`` a
    finite time later than ``state.time`` (0 had raised an IndexError, 2.5 given three
    uneven times, and an earlier t_final times running backwards)."""
    num_compare = _check_comparison_times(state, t_final, num_compare)
    t0, t_final = float(state.time), float(t_final)  # a JAX scalar t_final made the times immutable
    times = t0 + (t_final - t0) * np.arange(1, num_compare + 1) / num_compare
    times[-1] = t_final  # exactly, so that the reference ends where the rollouts do
    return times


def _reference_tolerance(dtype) -> float:
    # The tightest tolerance the dtype supports with margin: Dopri8 reaches ~1e-13 in
    # float64 before round-off dominates; in float32 (eps 1.2e-7) 1e-6 is the limit.
    return 1e-12 if jnp.dtype(dtype) == jnp.float64 else 1e-6


#: The reference solves' default step limit (:func:`reference_solution`, :func:`tradeoff`).
_REFERENCE_MAX_STEPS = 65_536


def reference_solution(
    scene: Scene,
    params: Params,
    state: State,
    t_final: float,
    *,
    num_compare: int = 20,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = _REFERENCE_MAX_STEPS,
) -> ode.Solution:
    """The reference :func:`tradeoff` compares against: Dopri8 saved at :func:`comparison_times`.

    Default tolerance: ``rtol = atol = 1e-12`` in float64 and ``1e-6`` in float32. Steps
    end on the comparison times (``step_to_ts=True``), so the saved states have the
    solver's full accuracy rather than its interpolant's. Compute it once and pass it as
    ``tradeoff(..., reference=...)`` to compare several candidate sets.
    """
    _check_common(scene, params, state, t_final, num_compare)
    default = _reference_tolerance(state.position.dtype)
    return ode.solve(
        scene, params, state, t_final,
        solver=diffrax.Dopri8(),
        rtol=default if rtol is None else rtol,
        atol=default if atol is None else atol,
        ts=comparison_times(state, t_final, num_compare),
        step_to_ts=True,
        max_steps=max_steps,
    )


# ----------------------------------------------------------------------------- metrics


def _total_energy_and_scale(params: Params, trajectory: State):
    """Per time: total kinetic + gravitational energy (J), and ``sum(T + |V|)`` as its scale."""
    kinetic = jax.vmap(kinetic_energy, in_axes=(None, 0))(params, trajectory)
    potential = jax.vmap(potential_energy, in_axes=(None, 0))(params, trajectory)
    return jnp.sum(kinetic + potential, axis=-1), jnp.sum(kinetic + jnp.abs(potential), axis=-1)


def _world_angular_momentum(params: Params, trajectory: State):
    """Per time: total angular momentum about the world origin, ``sum (x x m v + L)`` (kg m^2/s)."""
    return jnp.sum(jax.vmap(angular_momentum_about, in_axes=(None, 0))(params, trajectory), axis=-2)


def _relative(difference: np.ndarray, scale: float) -> float:
    # A reference whose quantity is 0 throughout (a scene at rest) has no relative error:
    # report the absolute one instead of dividing by zero.
    return float(np.max(difference) / scale) if scale > 0 else float(np.max(difference))


#: An error (m, m/s, rad, or relative) beyond which a run counts as failed: no simulation
#: is being measured any more, and a log axis spanning 300 decades crashed matplotlib.
DIVERGED = 1e30
_FAILED_ROW = {**{m: math.inf for m in METRICS}, "failed": True}


def _row_metrics(params: Params, trajectory: State, reference: State) -> dict[str, Any]:
    """Errors of ``trajectory`` against ``reference`` (both ``(T, N, ...)`` per field), max over times and bodies.

    Returns the :data:`METRICS` plus ``failed``: any NaN or infinite value in the state or
    an error, or an error beyond :data:`DIVERGED` (a run that blew up but stayed finite:
    a stiff spring's RK4 at ``omega dt = 5`` reached errors of 1e53 and was once called
    the cheapest, while its attitude error stayed below pi; stop 97's review). Failed runs
    get infinite errors, so they are never the cheapest nor on the front.
    """
    leaves = [trajectory.position, trajectory.orientation, trajectory.velocity, trajectory.angular_momentum]
    failed = not all(bool(jnp.all(jnp.isfinite(x))) for x in leaves)
    if failed:
        return _FAILED_ROW.copy()
    angle = spatial.rotation_angle(rotation_matrix(reference), rotation_matrix(trajectory))
    energy, _ = _total_energy_and_scale(params, trajectory)
    energy_ref, energy_scale = _total_energy_and_scale(params, reference)
    momentum = _world_angular_momentum(params, trajectory)
    momentum_ref = _world_angular_momentum(params, reference)

    def distance(a, b):
        return np.linalg.norm(np.asarray(a, dtype=float) - np.asarray(b, dtype=float), axis=-1)

    errors = {
        "attitude_error": float(np.max(np.asarray(angle))),
        "position_error": float(np.max(distance(trajectory.position, reference.position))),
        "velocity_error": float(np.max(distance(trajectory.velocity, reference.velocity))),
        "angular_momentum_error": _relative(distance(momentum, momentum_ref),
                                            float(np.max(np.linalg.norm(np.asarray(momentum_ref), axis=-1)))),
        "energy_error": _relative(np.abs(np.asarray(energy, dtype=float) - np.asarray(energy_ref, dtype=float)),
                                  float(np.max(np.asarray(energy_scale)))),
    }
    if not all(math.isfinite(e) and e <= DIVERGED for e in errors.values()):
        return _FAILED_ROW.copy()
    return {**errors, "failed": False}


# ----------------------------------------------------------------------------- result


@dataclasses.dataclass
class TradeoffResult:
    """The measured rows of :func:`tradeoff` and what they were measured against.

    Attributes:
        rows: one dict per (integrator, dt) with ``integrator`` (name), ``order``, ``dt`` (s,
            as run), ``steps``, the :data:`METRICS` (max over comparison times and bodies:
            ``attitude_error`` rad (atan2 form), ``position_error`` m, ``velocity_error``
            m/s, ``angular_momentum_error`` (world, about the origin, summed over bodies,
            relative to the reference's largest), ``energy_error`` (kinetic +
            gravitational, relative to the reference's ``max_t sum(T + |V|)``)),
            ``failed`` (NaN or inf, or an error beyond :data:`DIVERGED`), ``compile_time``
            (s, tracing + XLA compile) and
            ``cost`` (wall seconds per simulated second of the compiled rollout, best of
            ``repeats``).
        times: the comparison times (s).
        reference_floor: the same metrics for a Dopri8 solve at 10x looser tolerance
            against the reference, an upper estimate of the reference's own error (errors
            below it are not resolved); ``None`` for a reference passed in.
        info: the reference's settings, the device and library versions.
    """

    rows: list[dict[str, Any]]
    times: np.ndarray
    reference_floor: dict[str, float] | None = None
    info: dict[str, Any] = dataclasses.field(default_factory=dict)

    def _ok(self, metric: str) -> list[dict[str, Any]]:
        if metric not in METRICS:
            raise ValueError(f"Unknown metric {metric!r}; choose one of {list(METRICS)}.")
        return [r for r in self.rows if not r["failed"] and math.isfinite(r[metric])]

    def pareto(self, metric: str = "attitude_error") -> list[dict[str, Any]]:
        """The rows no other row beats in both ``metric`` and ``cost``, cheapest first.

        Failed rows are excluded. A row is on the front if every cheaper row has a
        strictly larger error.
        """
        front, best = [], math.inf
        for row in sorted(self._ok(metric), key=lambda r: (r["cost"], r[metric])):
            if row[metric] < best:
                front.append(row)
                best = row[metric]
        return front

    def cheapest(self, tolerance: float, metric: str = "attitude_error") -> dict[str, Any] | None:
        """The least-cost row whose ``metric`` is at most ``tolerance``, or ``None`` if no row reaches it."""
        meeting = [r for r in self._ok(metric) if r[metric] <= tolerance]
        # Ties in cost go to the smaller error, as on the Pareto front.
        return min(meeting, key=lambda r: (r["cost"], r[metric])) if meeting else None

    def to_markdown(self, metric: str = "attitude_error") -> str:
        """A Markdown table of every row; ``*`` marks the Pareto front of ``metric`` against cost."""
        front = {id(r) for r in self.pareto(metric)}
        header = ["integrator", "dt (s)", "steps", *(f"{m.replace('_', ' ')} ({u})" for m, u in METRICS.items()),
                  "cost (s/s)", "compile (s)", "front"]
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for r in self.rows:
            errors = ["failed" if r["failed"] else f"{r[m]:.2e}" for m in METRICS]
            lines.append("| " + " | ".join([r["integrator"], f"{r['dt']:.4g}", str(r["steps"]), *errors,
                                             f"{r['cost']:.2e}", f"{r['compile_time']:.2f}",
                                             "*" if id(r) in front else ""]) + " |")
        if self.reference_floor is not None:
            floor = ", ".join(f"{m} {v:.1e}" for m, v in self.reference_floor.items())
            lines.append(f"\nReference floor (errors below it are not resolved): {floor}.")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.to_markdown()

    def to_json(self) -> str:
        """Rows, comparison times, reference floor and settings as JSON (non-finite numbers as ``null``)."""

        def clean(value):
            if isinstance(value, dict):
                return {k: clean(v) for k, v in value.items()}
            if isinstance(value, list | tuple):
                return [clean(v) for v in value]
            if isinstance(value, float | np.floating):
                return float(value) if math.isfinite(value) else None
            if isinstance(value, np.integer):
                return int(value)
            return value

        return json.dumps(clean({"rows": self.rows, "times": self.times.tolist(),
                                 "reference_floor": self.reference_floor, "info": self.info}),
                          indent=2, allow_nan=False)


# ----------------------------------------------------------------------------- checks


def _check_common(scene, params, state, t_final, num_compare) -> None:
    ode.check_inputs(scene, params, state, "rb.tradeoff")
    if scene.contact_pairs:
        # The reference (ode.solve) has no contacts: it would pass through the ground.
        raise ValueError(
            f"rb.tradeoff measures free motion, and this scene has contact pairs {list(scene.contact_pairs)}: "
            "its reference solution would ignore them. Build the scene without contacts, or compare a "
            "contact scene's runs with rb.ode.solve_with_impacts yourself."
        )
    _check_comparison_times(state, t_final, num_compare)


def _check_comparison_times(state, t_final, num_compare) -> int:
    """``num_compare`` as an int, or a ``ValueError`` for it or for ``t_final``."""
    if isinstance(num_compare, (bool, np.bool_)) or not isinstance(num_compare, numbers.Integral) or num_compare < 1:
        raise ValueError(f"num_compare must be a positive integer, got {num_compare!r}.")
    try:
        t_final = float(t_final)
    except (TypeError, ValueError):
        raise ValueError(f"t_final must be a time in seconds, got {t_final!r}.") from None
    if not math.isfinite(t_final) or t_final <= float(state.time):
        raise ValueError(
            f"t_final = {t_final} s must be finite and later than the state's time {float(state.time)} s."
        )
    return int(num_compare)


def _candidates(integrators) -> list[Integrator]:
    if integrators is None:
        return default_integrators()
    integrators = list(integrators)
    if not integrators:
        raise ValueError("integrators is empty; pass None for every integrator jaxrb has.")
    for candidate in integrators:
        if isinstance(candidate, type) and issubclass(candidate, Integrator):
            raise ValueError(f"integrators must be instances: write {candidate.__name__}(), not {candidate.__name__}.")
        if not isinstance(candidate, Integrator):
            raise ValueError(f"integrators must be rb.integrators instances (e.g. rb.integrators.RK4()), "
                             f"got {candidate!r}.")
    repeated = sorted({repr(c) for i, c in enumerate(integrators) if c in integrators[:i]})
    if repeated:
        # Two rows of the same name and the same work, which plot_tradeoff drew as one line.
        raise ValueError(f"integrators lists the same integrator more than once: {repeated}. List each once.")
    return integrators


def _step_counts(dts, duration: float, num_compare: int, slack: float = 0.0) -> list[int]:
    """Steps per run: ``duration / dt`` rounded to a multiple of ``num_compare`` (at least one of each).

    ``slack`` (s): the duration's own rounding, below which no ``dt`` counts as changed."""
    if dts is None:
        # A geometric sweep: one step per comparison interval, then halving 7 times.
        return [num_compare * 2**k for k in range(8)]
    counts = []
    dts = np.atleast_1d(np.asarray(dts, dtype=float))
    if dts.ndim != 1:
        raise ValueError(f"dts must be a list of step sizes (s), got an array of shape {dts.shape}.")
    if dts.size == 0:
        raise ValueError("dts is empty; pass None for the default sweep of step sizes.")
    for dt in dts:
        # A dt of the whole span passes though the duration's rounding puts it a hair above.
        if not (math.isfinite(dt) and 0 < dt <= duration * (1 + 1e-9) + slack):
            raise ValueError(f"Every dt must be positive and at most t_final - state.time = {duration} s, got {dt}.")
        n = num_compare * max(1, round(duration / (dt * num_compare)))
        if abs(duration / n - dt) > 1e-9 * dt + slack / n:
            warnings.warn(
                f"dt = {dt} s does not give a whole number of steps per comparison interval "
                f"({duration} s / {num_compare} intervals); using dt = {duration / n} s ({n} steps).",
                stacklevel=3,
            )
        counts.append(n)
    return list(dict.fromkeys(counts))  # drop duplicates made by rounding, keep the order


def _check_saved_times(saved: np.ndarray, times: np.ndarray, num_compare: int) -> None:
    # Saved times carry the state's dtype: compare to its resolution, not float64's.
    resolution = 4 * float(np.finfo(saved.dtype).eps) * float(np.max(np.abs(times)))
    if saved.shape != times.shape or not np.allclose(saved, times, rtol=0, atol=resolution):
        raise ValueError("The reference was saved at other times than comparison_times(state, t_final, "
                         f"{num_compare}); build it with rb.reference_solution(...).")


def _reference_trajectory(reference, num_compare: int, times: np.ndarray) -> State:
    if isinstance(reference, ode.Solution):
        if reference.trajectory is None:
            raise ValueError("The reference Solution has no trajectory: solve it with ts=comparison_times(...).")
        _check_saved_times(np.asarray(reference.ts), times, num_compare)
        return reference.trajectory
    if isinstance(reference, State):
        if reference.position.ndim != 3 or reference.position.shape[0] != num_compare:
            raise ValueError(f"A reference State must be stacked at the {num_compare} comparison times, leading "
                             f"axis {num_compare}; got position shape {reference.position.shape}.")
        # Its own times, as a Solution's: one saved for another t_final was taken silently,
        # and RK4's position error came out 12.8 m instead of 2.4e-15 (stop 97's review).
        _check_saved_times(np.asarray(reference.time), times, num_compare)
        return reference
    raise ValueError(f"reference must be an rb.ode.Solution or a stacked rb.State, got {type(reference).__name__}.")


# ----------------------------------------------------------------------------- tradeoff


def _time_rollout(scene, integrator, dt, num_steps, save_every, params, state, repeats):
    """Compile the rollout once, then return (trajectory, compile seconds, best run seconds)."""
    step = make_step(scene, integrator, dt)

    def run(p, s):
        return rollout(step, p, s, num_steps, save_every=save_every)[1]

    start = time.perf_counter()
    compiled = jax.jit(run).lower(params, state).compile()
    compile_time = time.perf_counter() - start
    trajectory = jax.block_until_ready(compiled(params, state))  # warm-up, untimed
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(params, state))
        best = min(best, time.perf_counter() - start)
    return trajectory, compile_time, best


def _names(candidates: list[Integrator]) -> list[str]:
    # The class name, or the full repr where two candidates share a class (different options).
    classes = [type(c).__name__ for c in candidates]
    return [n if classes.count(n) == 1 else repr(c) for n, c in zip(classes, candidates, strict=True)]


def tradeoff(
    scene: Scene,
    params: Params,
    state: State,
    t_final: float,
    *,
    integrators=None,
    dts=None,
    reference=None,
    repeats: int = 3,
    num_compare: int = 20,
    max_steps: int = _REFERENCE_MAX_STEPS,
) -> TradeoffResult:
    """Run every candidate integrator at every ``dt`` on this scene and measure error and cost.

    Args:
        scene, params, state: the user's own scene and starting point. ``state.time`` is
            the start; a state prepared for ``ExplicitEuler`` (carrying ``rotation``) is refused.
        t_final: end time (s), later than ``state.time``.
        integrators: instances from :mod:`jaxrb.integrators`; default
            :func:`default_integrators` (every integrator jaxrb exports).
        dts: time steps (s). Each is rounded so that the run has a whole number of steps
            per comparison interval (a warning says when this changes it; rows hold the
            ``dt`` actually run). Default: ``(t_final - t0) / (num_compare 2^k)``, ``k = 0 .. 7``.
        reference: a precomputed :func:`reference_solution` (or a ``State`` stacked at
            :func:`comparison_times`); default: computed here.
        repeats: timed calls of each compiled rollout; the best is kept.
        num_compare: number of comparison times.
        max_steps: the reference solves' step limit (:func:`reference_solution`); raise it
            for long horizons, where diffrax stops with "maximum number of solver steps".

    Returns:
        A :class:`TradeoffResult`. Costs are measured on whatever device JAX uses, with
        whatever else runs on it: compare rows of one result, not across machines.
        ``dt`` is static in a step, so every row compiles its own rollout (about a
        second each on a CPU; the ``compile_time`` column): the default sweep of every
        integrator at 8 step sizes takes a minute or two, mostly compiling.
    """
    _check_common(scene, params, state, t_final, num_compare)
    candidates = _candidates(integrators)
    if isinstance(repeats, bool) or not isinstance(repeats, numbers.Integral) or repeats < 1:
        raise ValueError(f"repeats must be a positive integer, got {repeats!r}.")
    repeats = int(repeats)  # a NumPy integer would not go into the JSON
    t0 = float(state.time)
    duration = float(t_final) - t0
    # A float32 start time (0.1 -> 0.10000000149) moves the duration by its rounding.
    slack = 4 * float(np.finfo(np.asarray(state.time).dtype).eps) * abs(t0)
    counts = _step_counts(dts, duration, num_compare, slack)
    times = comparison_times(state, float(t_final), num_compare)

    info: dict[str, Any] = {
        "t0": t0, "t_final": float(t_final), "num_compare": num_compare, "repeats": repeats,
        "dtype": str(state.position.dtype), "device": str(jax.devices()[0]), "jax": jax.__version__,
        "diffrax": diffrax.__version__, "python": platform.python_version(),
    }
    floor = None
    if reference is None:
        tol = _reference_tolerance(state.position.dtype)
        reference = reference_solution(scene, params, state, t_final, num_compare=num_compare, rtol=tol, atol=tol,
                                       max_steps=max_steps)
        looser = reference_solution(scene, params, state, t_final, num_compare=num_compare,
                                    rtol=10 * tol, atol=10 * tol, max_steps=max_steps)
        floor = {m: v for m, v in _row_metrics(params, looser.trajectory, reference.trajectory).items()
                 if m in METRICS}
        info["reference"] = {"solver": "Dopri8", "rtol": tol, "atol": tol, "num_steps": int(reference.num_steps)}
    reference_trajectory = _reference_trajectory(reference, num_compare, times)

    rows = []
    for name, integrator in zip(_names(candidates), candidates, strict=True):
        for n in counts:
            dt = duration / n
            trajectory, compile_time, best = _time_rollout(
                scene, integrator, dt, n, n // num_compare, params, state, repeats
            )
            rows.append({
                "integrator": name,
                "order": getattr(integrator, "order", None),
                "dt": dt,
                "steps": n,
                **_row_metrics(params, trajectory, reference_trajectory),
                "compile_time": compile_time,
                "cost": best / duration,
            })
    return TradeoffResult(rows=rows, times=times, reference_floor=floor, info=info)


# ----------------------------------------------------------------------------- plot


def plot_tradeoff(result: TradeoffResult, metric: str = "attitude_error", ax=None):
    """Error against cost, log-log: one line per integrator over its ``dt`` sweep, the Pareto front in black.

    Failed runs and zero errors (which a log axis cannot show) are left out. Returns the
    matplotlib ``Axes``.
    """
    import matplotlib.pyplot as plt  # lazily: matplotlib is needed only to plot

    front = result.pareto(metric)  # also validates the metric name
    if ax is None:
        _, ax = plt.subplots(figsize=(6.4, 4.8))
    for name in dict.fromkeys(r["integrator"] for r in result.rows):
        # In order of work: the rows follow the order of ``dts`` as given, and an unsorted
        # ``dts`` drew a zig-zag line (a non-monotone trade that was not measured).
        rows = sorted((r for r in result._ok(metric) if r["integrator"] == name and r[metric] > 0),
                      key=lambda r: (r["steps"], r["cost"]))
        if rows:
            ax.plot([r["cost"] for r in rows], [r[metric] for r in rows], marker="o", label=name)
    shown = [r for r in front if r[metric] > 0]
    if shown:
        ax.plot([r["cost"] for r in shown], [r[metric] for r in shown], color="black", linestyle="--",
                linewidth=1, marker="o", markersize=10, markerfacecolor="none", label="Pareto front")
    if result.reference_floor is not None and result.reference_floor[metric] > 0:
        ax.axhline(result.reference_floor[metric], color="grey", linestyle=":", linewidth=1,
                   label="reference floor")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("cost (wall seconds per simulated second)")
    ax.set_ylabel(f"{metric.replace('_', ' ')} ({METRICS[metric]})")
    ax.legend(fontsize="small")
    ax.grid(True, which="both", alpha=0.3)
    return ax
