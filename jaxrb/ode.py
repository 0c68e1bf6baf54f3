"""The diffrax bridge: adaptive, error-controlled solves of a scene's equations of motion.

The fixed-step integrators of :mod:`jaxrb.integrators` advance the state by a chosen
``dt``. Here the same Newton-Euler L-form equations (seeds 000 and 001)::

    x' = v,   v' = F / m,   L' = tau,   q' = (0, omega) q / 2,   omega = A I_body^-1 A^T L

are handed to `diffrax <https://docs.kidger.site/diffrax/>`_, whose embedded Runge-Kutta
pairs pick their own step sizes to meet a tolerance. Use it as an accurate reference (the
work-precision benchmark in :func:`jaxrb.tradeoff` does), or when a tolerance is easier to
state than a step size.

Supported and tested solvers (order of the propagated solution / of the embedded error
estimate): ``diffrax.Tsit5()`` (5 / 4, the default), ``diffrax.Dopri5()`` (5 / 4) and
``diffrax.Dopri8()`` (8 / 7). Other explicit adaptive diffrax solvers run too, with
diffrax's default controller coefficients.

Everything composes with ``jax.jit``, ``jax.vmap`` and ``jax.grad``: the scene is static,
``params``, ``state`` and the tolerances are traced (new values never recompile), and
gradients flow through the solve (discretise-then-optimise,
``diffrax.RecursiveCheckpointAdjoint`` by default; ``diffrax.ForwardMode()`` for
``jax.jacfwd``).
"""

from __future__ import annotations

import dataclasses
import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import spatial
from ._static import positive_count, static_switch
from .dynamics import stage_derivative
from .scene import Scene
from .state import Params, State

__all__ = ["OdeState", "VectorField", "vector_field", "default_controller", "Solution", "solve", "check_inputs"]


class OdeState(eqx.Module):
    """The part of a :class:`jaxrb.State` that diffrax integrates; time is diffrax's ``t``.

    Attributes:
        position: ``(N, 3)`` m, centre of mass, world frame.
        orientation: ``(N, 4)`` quaternion ``(w, x, y, z)``, body to world. Inside a solve
            it is a vector of R^4 whose norm the exact flow keeps; it is normalised only
            when a :class:`jaxrb.State` is handed back.
        velocity: ``(N, 3)`` m/s, world frame.
        angular_momentum: ``(N, 3)`` kg m^2/s, about the centre of mass, world frame.
    """

    position: Float[Array, "n 3"]
    orientation: Float[Array, "n 4"]
    velocity: Float[Array, "n 3"]
    angular_momentum: Float[Array, "n 3"]

    @classmethod
    def from_state(cls, state: State) -> OdeState:
        return cls(state.position, state.orientation, state.velocity, state.angular_momentum)

    def to_state(self, t, *, normalize: bool = True) -> State:
        """A :class:`jaxrb.State` at time ``t`` (s); the quaternion is normalised unless told not to."""
        q = spatial.quat_normalize(self.orientation) if normalize else self.orientation
        return State(
            position=self.position,
            orientation=q,
            velocity=self.velocity,
            angular_momentum=self.angular_momentum,
            time=jnp.asarray(t, dtype=self.position.dtype),
        )


class VectorField(eqx.Module):
    """``f(t, y, params) -> dy/dt`` for ``diffrax.ODETerm``; ``y`` and ``dy/dt`` are :class:`OdeState`.

    Forces come from the scene's declared force models (:func:`jaxrb.dynamics.wrench`)
    with ``state.time = t``, so user force functions see the solver's time. Forces and
    ``omega`` are evaluated at the normalised quaternion while ``q'`` multiplies the raw
    ``q``: a smooth ODE on R^4 whose exact flow keeps ``|q|`` constant, so the solver's
    order is unchanged (the same right-hand side as :class:`jaxrb.integrators.RK4`'s stages).
    The scene is a static field: equal scenes share compiled code.
    """

    scene: Scene = eqx.field(static=True)

    def __call__(self, t, y: OdeState, params: Params) -> OdeState:
        derivative = stage_derivative(self.scene, params, y.to_state(t, normalize=False))
        return OdeState.from_state(derivative)


def vector_field(scene: Scene) -> VectorField:
    """The L-form right-hand side of ``scene`` as a diffrax vector field.

    Example::

        term = diffrax.ODETerm(rb.ode.vector_field(scene))
        sol = diffrax.diffeqsolve(term, diffrax.Tsit5(), t0, t1, None, rb.ode.OdeState.from_state(state),
                                  args=params, stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-10))
    """
    _check_scene(scene, "vector_field")
    return VectorField(scene)


# Step-size controller coefficients per solver. diffrax's PIDController takes
# h_new = h * safety * err_n^-(pcoeff + icoeff)/k * err_{n-1}^(pcoeff/k), with k the error
# order (5 for Tsit5 and Dopri5, 8 for Dopri8); its own default is plain I control
# (pcoeff = 0, icoeff = 1), and its docs give no per-solver advice beyond listing PI
# choices from the literature. So these are the defaults of the solvers' reference codes
# (Hairer's DOPRI5 and DOP853, and OrdinaryDiffEq.jl's Tsit5), rewritten in diffrax's
# parametrisation (beta1 = (pcoeff + icoeff)/k, beta2 = pcoeff/k):
# * Tsit5: PI with beta1 = 0.7/k, beta2 = 0.4/k -> pcoeff 0.4, icoeff 0.3 (also the first
#   PI choice the diffrax docs list).
# * Dopri5: DOPRI5's beta = 0.04, beta1 = 1/5 - 0.75 * 0.04 -> pcoeff 0.2, icoeff 0.65.
# * Dopri8: DOP853 uses I control, with the step ratio bounded to [1/3, 6].
# Why PI: the proportional term damps the accept/reject oscillation of the step size,
# and a tumbling body's error estimate swings with its attitude. Measured on the
# asymmetric top of tests/test_ode.py (T = 10 s, rtol 1e-10): Tsit5 336 steps, 8 rejected,
# attitude error 3.4e-11 rad, against 292 steps, 21 rejected, 9.5e-11 with plain I
# control (slightly less error per step: 292 steps at order 5 would give ~4.7e-11);
# Dopri5 300 / 19 / 5.3e-10 against 292 / 24 / 6.7e-10; Dopri8 44 / 5 / 7.6e-11 either way.
_PID_COEFFICIENTS: dict[type, dict[str, float]] = {
    diffrax.Tsit5: {"pcoeff": 0.4, "icoeff": 0.3},
    diffrax.Dopri5: {"pcoeff": 0.2, "icoeff": 0.65},
    diffrax.Dopri8: {"pcoeff": 0.0, "icoeff": 1.0, "factormin": 1.0 / 3.0, "factormax": 6.0},
}


def _checked_solver(solver):
    """``solver``, or Tsit5 for ``None``; a string or a class had failed inside diffrax."""
    return _diffrax_instance("solver", solver, diffrax.AbstractSolver, diffrax.Tsit5,
                             "a diffrax solver instance, e.g. diffrax.Tsit5() or diffrax.Dopri8()")


def _checked_adjoint(adjoint):
    """``adjoint``, or ``RecursiveCheckpointAdjoint`` for ``None``; the string "forward" had
    failed deep inside diffrax."""
    return _diffrax_instance("adjoint", adjoint, diffrax.AbstractAdjoint, diffrax.RecursiveCheckpointAdjoint,
                             "a diffrax adjoint instance, e.g. diffrax.ForwardMode() for jax.jacfwd, or "
                             "diffrax.RecursiveCheckpointAdjoint() (the default)")


def _diffrax_instance(name, value, kind, default, expected):
    if value is None:
        return default()
    if not isinstance(value, kind):
        raise ValueError(f"{name} must be {expected}, got {value!r}.")
    return value


def default_controller(solver, rtol: float, atol: float, dtmax=None) -> diffrax.PIDController:
    """The step-size controller :func:`solve` uses when none is given (see ``_PID_COEFFICIENTS``).

    ``rtol`` is relative and ``atol`` absolute, in each component's own unit (m, m/s,
    kg m^2/s, and 1 for the quaternion), in diffrax's RMS norm over the whole state.
    ``dtmax``: the longest step (s), or ``None``.
    """
    for solver_type, coefficients in _PID_COEFFICIENTS.items():
        if isinstance(solver, solver_type):
            return diffrax.PIDController(rtol=rtol, atol=atol, dtmax=dtmax, **coefficients)
    return diffrax.PIDController(rtol=rtol, atol=atol, dtmax=dtmax)


class Solution(eqx.Module):
    """The result of :func:`solve`.

    Attributes:
        final: the :class:`jaxrb.State` at ``t1``, quaternion normalised.
        trajectory: the states at ``ts`` stacked along a new leading axis
            (``(len(ts), N, ...)`` per field, quaternions normalised), or ``None``.
        ts: the save times (s), or ``None``.
        stats: diffrax's statistics (``num_steps``, ``num_accepted_steps``,
            ``num_rejected_steps``, ``max_steps``).
        result: a ``diffrax.RESULTS`` value; ``diffrax.RESULTS.successful`` unless the
            solve failed with ``throw=False``.
        interpolation: diffrax's dense interpolation (``dense=True``), else ``None``.
    """

    final: State
    trajectory: State | None
    ts: Float[Array, " t"] | None
    stats: dict
    result: diffrax.RESULTS
    interpolation: diffrax.DenseInterpolation | None

    @property
    def num_steps(self):
        """Number of steps taken, accepted and rejected."""
        return self.stats["num_steps"]

    def evaluate(self, t) -> State:
        """The state at time ``t`` (s; a scalar or a 1-D array of times) from dense output.

        The same interpolant as saving at ``ts`` (see :func:`solve`); its quaternion is
        normalised. Needs ``solve(..., dense=True)``. ``t`` must lie in the solve's
        interval ``[state.time, t1]``: a concrete time outside it is refused (the
        interpolant gives NaN there), a traced one gives NaN.
        """
        if self.interpolation is None:
            raise ValueError("This Solution has no dense output: call rb.ode.solve(..., dense=True).")
        t = jnp.asarray(t, dtype=self.final.time.dtype)
        if t.ndim > 1:
            raise ValueError(f"evaluate takes a scalar time or a 1-D array of times, got shape {t.shape}.")
        times, start, end = (_concrete(x) for x in (t, self.interpolation.t0, self.interpolation.t1))
        if times is not None and start is not None and end is not None:
            outside = times[(times < start) | (times > end)]
            if outside.size:
                raise ValueError(f"evaluate: t = {outside.tolist()[:4]} s lies outside the solve's interval "
                                 f"[{float(start)}, {float(end)}] s, where there is no dense output.")

        def at(time):
            return self.interpolation.evaluate(time).to_state(time)

        return jax.vmap(at)(t) if t.ndim == 1 else at(t)


# -------------------------------------------------------------------------------- checks


def _check_scene(scene, where: str) -> None:
    if not isinstance(scene, Scene):
        raise ValueError(f"{where} needs an rb.Scene, got {type(scene).__name__}.")


def _concrete(x) -> np.ndarray | None:
    """``x`` as a numpy array if its value is known now (not a tracer), else ``None``."""
    try:
        return np.asarray(x, dtype=float)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError, TypeError):
        return None


def check_inputs(scene, params, state, where: str) -> None:
    """Raise ``ValueError`` unless ``(scene, params, state)`` can be integrated as a quaternion ODE."""
    _check_scene(scene, where)
    if not isinstance(params, Params):
        raise ValueError(f"{where} needs rb.Params (from scene.params()), got {type(params).__name__}.")
    if not isinstance(state, State):
        raise ValueError(f"{where} needs an rb.State (from scene.state()), got {type(state).__name__}.")
    scene.check_inputs(params, state)
    if state.rotation is not None:
        raise ValueError(
            "This state carries a rotation matrix (State.rotation, used by rb.integrators.ExplicitEuler), "
            f"which is then the attitude. {where} integrates the quaternion: pass "
            "state.replace(orientation=rb.spatial.matrix_to_quat(state.rotation), rotation=None)."
        )


def _check_positive(name: str, value, what: str = "tolerance") -> None:
    v = _concrete(value)
    if v is not None and not (v.shape == () and np.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive, finite {what}, got {value!r}.")


def _check_times(t0, t1, ts, where: str = "rb.ode.solve") -> None:
    """Raise for ``t1 <= t0`` and for save times that are not increasing inside ``[t0, t1]``.

    Done in Python when the values are concrete; traced times (a ``jit``/``vmap`` over the
    state) are checked inside the computation by :func:`_runtime_checks` instead.
    """
    t0_value, t1_value = _concrete(t0), _concrete(t1)
    if t1_value is not None:
        if t1_value.shape != () or not np.isfinite(t1_value):
            raise ValueError(f"t1 must be a finite scalar time (s), got {t1!r}.")
        if t0_value is not None and t0_value.shape == () and not t1_value > t0_value:
            raise ValueError(
                f"t1 = {float(t1_value)} s must be later than the state's time {float(t0_value)} s: "
                f"{where} integrates forward in time."
            )
    if ts is None:
        return
    if np.ndim(ts) != 1 or np.shape(ts)[0] == 0:
        raise ValueError(f"ts must be a non-empty 1-D array of save times (s), got shape {np.shape(ts)}.")
    ts_value = _concrete(ts)
    if ts_value is None:
        return
    if not np.all(np.isfinite(ts_value)) or np.any(np.diff(ts_value) <= 0):
        raise ValueError(f"ts must be finite and strictly increasing, got {ts_value}.")
    if t0_value is not None and t0_value.shape == () and ts_value[0] < t0_value:
        raise ValueError(f"ts starts at {ts_value[0]} s, before the state's time {float(t0_value)} s.")
    if t1_value is not None and ts_value[-1] > t1_value:
        raise ValueError(f"ts ends at {ts_value[-1]} s, after t1 = {float(t1_value)} s. Pass t1 >= max(ts).")


def _runtime_checks(x, t0, t1, ts, rtol, atol, where: str = "rb.ode.solve"):
    """``x``, with the conditions of :func:`_check_times` and :func:`_check_positive` on
    the times and tolerances checked inside the computation (``equinox.error_if``) where
    any of them is traced (a ``jit`` or ``vmap`` over them): Python cannot see those."""
    if all(v is None or _concrete(v) is not None for v in (t0, t1, ts, rtol, atol)):
        return x
    bad = ~(t1 > t0) | ~(jnp.isfinite(rtol) & (rtol > 0)) | ~(jnp.isfinite(atol) & (atol > 0))
    if ts is not None:
        bad = bad | jnp.any(ts < t0) | jnp.any(ts > t1) | jnp.any(jnp.diff(ts) <= 0)
    return eqx.error_if(
        x, bad,
        f"{where}: need t1 > state.time, save times ts strictly increasing inside [state.time, t1], and "
        "positive, finite rtol and atol.",
    )


# --------------------------------------------------------------------------------- solve


def solve(
    scene: Scene,
    params: Params,
    state: State,
    t1,
    *,
    solver=None,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    dt0=None,
    ts=None,
    step_to_ts: bool = False,
    dense: bool = False,
    max_steps: int = 16_384,
    controller=None,
    adjoint=None,
    throw: bool = True,
) -> Solution:
    """Solve the scene's equations of motion from ``state`` (at ``state.time``) to ``t1`` adaptively.

    Args:
        scene: the static scene (its declared forces are the only ones evaluated).
        params: :class:`jaxrb.Params` (traced: new values never recompile).
        state: the initial :class:`jaxrb.State`; ``state.time`` (s) is the start time. A
            state carrying a rotation matrix (from :class:`jaxrb.integrators.ExplicitEuler`)
            is refused, because there the matrix, not the quaternion, is the attitude.
        t1: end time (s), later than ``state.time``.
        solver: a diffrax solver; ``diffrax.Tsit5()`` by default. Tested: ``Tsit5`` (order 5,
            error estimate of order 4), ``Dopri5`` (5/4) and ``Dopri8`` (8/7).
        rtol, atol: relative and absolute tolerance of the local error, per step, in each
            component's unit (m, m/s, kg m^2/s; 1 for the quaternion). The global error is
            typically ~``rtol`` times the horizon in natural time units; in float32 go no
            tighter than ~1e-6.
        dt0: initial step (s); ``None`` lets diffrax choose it.
        ts: 1-D array of save times (s), strictly increasing, inside ``[state.time, t1]``.
            The states there come from the solver's dense interpolant (diffrax documents
            5th-order interpolation for Tsit5 and Dopri5, 8th for Dopri8). Its error
            constant is larger than the step's, which shows between a high-order solver's
            long steps: measured 1.2e-9 rad for Dopri8 at rtol 1e-10 on the tumbling top,
            against 8e-11 at step endpoints.
        step_to_ts: make a step end on every time in ``ts`` (diffrax's
            ``ClipStepSizeController(..., step_ts=ts)``), so the saved states are step
            endpoints with the solver's full accuracy. Costs at most ``len(ts)`` extra steps.
        dense: keep the dense interpolant, for :meth:`Solution.evaluate`.
        max_steps: the most steps the solve may take (static; an error if exceeded with
            ``throw=True``). Also sizes the checkpointing of reverse-mode gradients.
        controller: a diffrax step-size controller; default :func:`default_controller`
            (a PID controller with coefficients tuned per solver).
        adjoint: how reverse mode differentiates the solve; default
            ``diffrax.RecursiveCheckpointAdjoint()`` (exact gradient of the computed
            solution). ``diffrax.BacksolveAdjoint(...)`` solves the adjoint ODE backwards
            instead (less memory, gradient accurate only to the tolerance). Forward mode
            (``jax.jvp``, ``jax.jacfwd``) needs ``adjoint=diffrax.ForwardMode()``.
        throw: raise if the solve fails (e.g. ``max_steps`` reached). With ``False`` the
            failure is reported in ``Solution.result``.

    Returns:
        A :class:`Solution`. The returned quaternions are normalised: a projection onto
        the unit sphere whose change is of the size of the solver's own error, so it does
        not change the order of accuracy.
    """
    check_inputs(scene, params, state, "rb.ode.solve")
    if scene.contact_pairs:
        raise ValueError(
            "rb.ode.solve integrates the equations of motion without contacts, and this scene declares "
            f"contact pairs {list(scene.contact_pairs)}: its bodies would pass through each other. Use "
            "rb.ode.solve_with_impacts (impacts located by events, no resting contact), rb.make_step "
            "(impacts, friction and resting contact), or a Scene without contacts= for the free motion."
        )
    _check_positive("rtol", rtol)
    _check_positive("atol", atol)
    if dt0 is not None:
        _check_positive("dt0", dt0, "initial step (s), or None to let diffrax choose it")
    max_steps = positive_count("max_steps", max_steps)
    step_to_ts, dense, throw = (static_switch(name, value) for name, value in
                                (("step_to_ts", step_to_ts), ("dense", dense), ("throw", throw)))
    dtype = state.position.dtype
    t0 = jnp.asarray(state.time, dtype=dtype)
    _check_times(t0, t1, ts)
    t1 = jnp.asarray(t1, dtype=dtype)
    ts = None if ts is None else jnp.asarray(ts, dtype=dtype)

    solver = _checked_solver(solver)
    if controller is None:
        # Arrays, not Python floats: a float would be a static argument of diffrax's jit,
        # and every new tolerance would recompile.
        controller = default_controller(solver, jnp.asarray(rtol, dtype), jnp.asarray(atol, dtype))
    if step_to_ts:
        if ts is None:
            raise ValueError("step_to_ts=True needs save times ts.")
        controller = diffrax.ClipStepSizeController(controller, step_ts=ts)
    adjoint = _checked_adjoint(adjoint)

    y0 = _runtime_checks(OdeState.from_state(state), t0, t1, ts, rtol, atol)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(VectorField(scene)),
        solver,
        t0=t0,
        t1=t1,
        dt0=dt0,
        y0=y0,
        args=params,
        # Not SaveAt(subs=...): BacksolveAdjoint refuses it. With ts, ys holds the states at
        # ts followed by the state at t1.
        saveat=diffrax.SaveAt(t1=True, ts=ts, dense=dense),
        stepsize_controller=controller,
        adjoint=adjoint,
        max_steps=max_steps,
        throw=throw,
    )
    final = jax.tree.map(lambda x: x[-1], sol.ys).to_state(t1)
    trajectory = None
    if ts is not None:
        trajectory = jax.vmap(lambda y, t: y.to_state(t))(jax.tree.map(lambda x: x[:-1], sol.ys), ts)
    interpolation = sol.interpolation if dense else None
    return Solution(final=final, trajectory=trajectory, ts=ts, stats=sol.stats, result=sol.result,
                    interpolation=interpolation)


class ImpactSolution(eqx.Module):
    """The result of :func:`solve_with_impacts`.

    Attributes:
        final: the :class:`jaxrb.State` at ``t1`` (or at the last impact, if
            ``max_impacts`` impacts happen before ``t1``: see ``reached_t1``).
        impact_times: ``(max_impacts,)`` s, the located impacts (``inf`` after the last).
        after_impact: a :class:`jaxrb.State` with a leading ``(max_impacts,)`` axis: the
            state just after each impact (rows past ``num_impacts`` hold ``final``, the
            state at ``t1``).
        num_impacts: ``()`` int, how many impacts were located before ``t1``.
        reached_t1: ``()`` bool, whether the solve got to ``t1``. ``False`` when the
            ``max_impacts`` impacts were spent first (``final`` is then the state after the
            last of them): raise ``max_impacts``, or call again from ``final``. In an
            ensemble (``vmap``) it tells which members stopped short.
    """

    final: State
    impact_times: Array
    after_impact: State
    num_impacts: Array
    reached_t1: Array


def solve_with_impacts(
    scene: Scene,
    params: Params,
    state: State,
    t1,
    *,
    max_impacts: int = 16,
    solver=None,
    rtol: float | None = None,
    atol: float | None = None,
    max_steps: int = 4096,
    contact=None,
    adjoint=None,
) -> ImpactSolution:
    """Adaptive solve between impacts, with each impact located by a diffrax ``Event``.

    The event is the smallest signed distance of the scene's contact pairs crossing zero
    downwards; diffrax locates it to the solver's tolerance inside the step where it
    crossed, with a root finder that keeps it bracketed there (Newton's method safeguarded
    by bisection; Newton's alone, started at the step's end, had walked away from the root
    where the distance was already rising again, as in a graze, and failed). At each event the impact
    law of :func:`jaxrb.contact.resolve_impacts` is applied (Newton's restitution with the
    seed's impulse, friction bounded by ``mu j``), and the solve restarts, up to
    ``max_impacts`` times (a static ``lax.scan``). A touching
    slot approaching slower than ``contact.restitution_threshold`` (m/s) gets a plastic
    impulse (``e = 0``), as in :class:`jaxrb.ContactSettings`; every located impact thus
    leaves its touching slots separating or at rest.

    Resting contact is not modelled on this path: use :func:`jaxrb.make_step` for that. A
    body brought to rest on a contact sinks again under gravity, and is caught by the next
    event a few ulps of its coordinates below its restart level (3.6e-15 m in float64,
    every ~3e-8 s under 1 g), so the remaining impacts are spent there and the solve ends
    at the last one (``final.time < t1``).

    ``rtol`` and ``atol`` (default 1e-10 and 1e-12 in float64, 1e-6 and 1e-6 in float32)
    are the solver's tolerances and the root finder's, whose ``atol`` (m of gap, s of
    time) must be above the rounding of a gap: in float32 an ``atol`` of 1e-7 (under one
    ulp of a 1 m coordinate) failed to converge, so an ``atol`` under ``4 eps`` of the
    dtype is refused. A gap's rounding grows with the coordinates and with the time (one
    ulp of ``t`` moves a gap by its rate times it): the event divides each pair's gap by
    its closing speed where that exceeds 1 m/s (a time to impact, s), and each segment's
    root finder uses at least ``4 eps (max(|x|, 1 m) + |t1|)``. A float64 drop started at
    ``t = 1e4`` s, or a float32 one from 20 m, had failed with "the maximum number of
    steps was reached in the nonlinear solver". Measured in float32 with the defaults: the
    first six impacts of a ball dropped from 1 m, e = 0.8, within 1.1e-5 s of the closed
    form (1.4e-5 s before the event was scaled to a time).

    Body-body pairs bound the solver's step: a gap is seen only at step ends, and free
    flight is so smooth that the controller lengthens its steps tenfold at a time, so two
    balls could pass through each other between two ends (the impact was found or not
    depending on ``t1``). Each segment's steps are at most a travel ``s`` over the fastest
    relative surface speed of a body-body pair at its start (linear speed plus
    ``|L| / I_min``, a bound on ``|omega|`` along torque-free motion, times the bounding
    radius). ``s`` is the scene's thinnest contact size (the smallest radius, half extent
    or cylinder half-length), and at most ``sqrt(8 * 1e-4 m * (r_a + r_b))`` over the
    pairs' bounding radii (1.3 cm for two 0.1 m balls): two spheres that graze are then
    seen wherever they overlap by more than 1e-4 m at their closest approach (where the
    thinnest size alone bounded the steps, 27 of 41 passes overlapping by 1 mm went
    unseen). For other shapes the bounding radii understate how sharply the gap curves (at a
    box's edge), and this bound is a heuristic. Relative motion under uniform gravity keeps that speed; other forces may
    change it within a segment, and the bound does not see that. Plane pairs need no
    bound (a body past a plane stays past it).

    Gradients: reverse mode (``jax.grad``) by default, through each segment's solve
    (``diffrax.RecursiveCheckpointAdjoint``) and through each located impact time (the
    root finder's implicit derivative), so they account for the time of impact: the
    derivatives of the apex heights and impact times of a bounce match their closed forms
    (``tests/test_ode_impacts.py``). Forward mode (``jax.jvp``, ``jax.jacfwd``, and so
    least-squares fits) needs ``adjoint=diffrax.ForwardMode()``.

    Raises ``ValueError`` if a pair overlaps at a concrete start by more than
    ``contact.penetration_slop`` (there is no event to find from there, and no penetration
    correction). Raises (inside ``jit``, via ``equinox``) if a touching pair still approaches
    after an impulse (faster than ``sqrt(eps)`` times the approach speed it had before),
    e.g. when ``contact.impact_iterations`` sweeps are too few for a chain of touching bodies.
    """
    from ._bracketed_root import SafeguardedNewton
    from .contact import ContactSettings
    from .contact._penetration import thinnest_size
    from .contact._step import TOUCHING, _bounding_radius, _Ctx, _pair_gaps, impact_law, layout_of

    check_inputs(scene, params, state, "rb.ode.solve_with_impacts")
    if not scene.contact_pairs:
        raise ValueError("solve_with_impacts needs a scene with contact pairs (Scene(..., contacts=...)).")
    max_impacts = positive_count("max_impacts", max_impacts)  # np.int64 too (it had been refused)
    settings = contact if contact is not None else ContactSettings()
    if not isinstance(settings, ContactSettings):
        raise ValueError(f"contact must be an rb.ContactSettings(...), got {contact!r}.")
    _check_times(jnp.asarray(state.time, state.position.dtype), t1, None, "rb.ode.solve_with_impacts")
    dtype = state.position.dtype
    double = jnp.finfo(dtype).bits == 64
    rtol = (1e-10 if double else 1e-6) if rtol is None else rtol
    atol = (1e-12 if double else 1e-6) if atol is None else atol
    _check_positive("rtol", rtol)
    _check_positive("atol", atol)
    floor = 4 * float(jnp.finfo(dtype).eps)
    if _concrete(atol) is not None and float(atol) < floor:
        raise ValueError(f"atol = {atol!r} is below what {jnp.dtype(dtype).name} resolves in a gap or a time (4 eps = "
                         f"{floor:.2g}): the impacts' root finder cannot converge. Use atol >= {floor:.2g} (the "
                         f"default is {1e-12 if double else 1e-6:g}), or float64.")
    max_steps = positive_count("max_steps", max_steps)
    # A margin beyond any distance in the scene: every pair's separation is its true distance
    # (box pairs: the separating axes' lower bound, which has the same roots).
    ctx = _Ctx(scene, layout_of(scene), None, dataclasses.replace(settings, margin=1e6), 1.0)
    # An overlapping start has no event to find (its gap never crosses zero downwards), and
    # this path has no penetration correction: a ball started 1 cm into the ground bounced
    # about that depth, or spent every impact at t ~ 3e-8 s when at rest there.
    start_gaps = _concrete(_pair_gaps(ctx, state))
    if start_gaps is not None and np.min(start_gaps) < -settings.penetration_slop:
        worst = int(np.argmin(start_gaps))
        raise ValueError(f"Contact pair {scene.contact_pairs[worst]} overlaps by {-float(start_gaps[worst]):.3g} m "
                         "at the start: rb.ode.solve_with_impacts locates impacts from apart (or touching) bodies "
                         "and has no penetration correction. Start the bodies apart, or use rb.make_step.")
    t1 = jnp.asarray(t1, dtype)
    atol = jnp.asarray(atol, dtype)
    solver = _checked_solver(solver)
    adjoint = _checked_adjoint(adjoint)
    field = VectorField(scene)
    # Body-body pairs (static): their bodies and bounding radii, for the step bound below.
    pairs = [(scene.index(a), scene.index(b), _bounding_radius(scene, a), _bounding_radius(scene, b))
             for a, b in scene.contact_pairs if not scene.is_plane(b)]
    reach = np.zeros(scene.num_bodies)
    for a, b, r_a, r_b in pairs:
        reach[a], reach[b] = r_a, r_b
    thinnest = thinnest_size(scene) or min((min(r_a, r_b) for *_, r_a, r_b in pairs), default=1.0)
    # A graze: two spheres whose closest approach overlaps by d, seen at two step ends s of
    # relative travel apart, show no overlap at either end where d < s^2 / (8 (r_a + r_b)).
    # Under the thinnest size alone (s up to 0.1 m for 0.1 m balls) such grazes of up to 6 mm
    # passed unseen (27 of 41 start offsets at 1 mm; stop 92's review). So the travel is also
    # at most sqrt(8 TOUCHING (r_a + r_b)), over the pairs: an unseen graze overlaps by less
    # than the touching distance (0.1 mm).
    if pairs:
        thinnest = min(thinnest, math.sqrt(8 * TOUCHING * min(r_a + r_b for *_, r_a, r_b in pairs)))

    def segment_bounds(s: State):
        """The segment's longest step (s; ``inf`` without body-body pairs) and its root
        finder's ``atol``, from the state at its start. Not differentiated: they choose
        where the solver looks, not what it computes."""
        s = jax.lax.stop_gradient(s)
        if pairs:
            a, b = (np.asarray([pair[k] for pair in pairs]) for k in (0, 1))
            smallest = jnp.linalg.eigvalsh(jax.lax.stop_gradient(params.inertia))[:, 0]
            turning = jnp.linalg.norm(s.angular_momentum, axis=-1) / smallest * jnp.asarray(reach, dtype)
            relative = jnp.linalg.norm(s.velocity[a] - s.velocity[b], axis=-1) + turning[a] + turning[b]
            dtmax = thinnest / jnp.maximum(jnp.max(relative), thinnest / jnp.finfo(dtype).max)
        else:
            dtmax = jnp.asarray(jnp.inf, dtype)
        size = jnp.maximum(jnp.max(jnp.abs(s.position)), 1.0)
        return dtmax, jnp.maximum(atol, 4 * jnp.finfo(dtype).eps * (size + jnp.abs(t1)))

    def gaps_at(t, y):
        return _pair_gaps(ctx, y.to_state(t))

    def gap_rates(t, y):
        """Each pair's gap ``(P,)`` (m) and its rate along the free motion ``(P,)`` (m/s)."""
        return jax.jvp(lambda y: _pair_gaps(ctx, y.to_state(t)), (y,), (field(t, y, params),))

    # diffrax fires a direction=False event on a step whose condition is > 0 at its start
    # and <= 0 at its end. After an impact located by the root finder the restart gap is
    # often <= 0 by rounding (-3.6e-16 m, or exactly 0): a body that then rises and comes
    # back within the first step would cross unseen. So a restart at gap g0 <= 0 measures
    # the gap from ``g0 - depth`` instead of 0, where the condition starts at ``depth > 0``.
    # ``depth`` is 16 ulps of the coordinates (of the largest, or of 1 m if all are
    # smaller; 3.6e-15 m in float64): above the rounding of a gap, so noise cannot fire the
    # event, and small enough to change nothing measurable. (atol, 1e-12 m, was tried: each
    # such event then lets the body fall ``depth`` further, and the 16th impact of
    # tests/test_ode_impacts.py, at 1.4e-4 m/s, rebounded 7e-4 too fast.)
    #
    # ``reference`` is per pair ``(P,)``: one pair's touching restart (or a start overlap
    # within the slop) must not move the others' zero, which had let a ball falling onto
    # the ground beside a ball resting 8e-6 m into it land 8e-6 m deep.
    #
    # Each pair's gap is divided by its closing speed where that exceeds 1 m/s, so the root
    # finder's |condition| < atol reads as seconds there: one ulp of t moves a gap by the
    # speed times it, which in metres no atol under that product could resolve.
    def condition(t, y, args, **kwargs):
        _, reference = args
        gaps, rates = gap_rates(t, y)
        scaled = (gaps - reference) / jnp.maximum(jnp.abs(rates), 1.0)
        # In JAX's default float type: diffrax's event root finding joins it with a Python
        # 0.0 in a cond, which failed for a float32 state with x64 switched on.
        return jnp.min(scaled).astype(jnp.result_type(float))

    term = diffrax.ODETerm(lambda t, y, args: field(t, y, args[0]))
    eps = jnp.finfo(dtype).eps

    def impulse(s: State, depth, gap_atol) -> State:
        """The impact at an event: the slots within ``touch`` (m) of touching. That is the
        event's own pair (located to the root finder's tolerance, ``gap_atol``, in seconds
        where the closing speed exceeds 1 m/s, or restarted ``depth`` deep), chains of
        bodies touching it, and pairs at rest within the slop; not a pair merely close. (The
        contact step's 0.1 mm had applied the impact of a ball 5e-5 m above the ground beside
        the one that landed, 1.1e-5 s early, and its next apex came out 1.8e-5 m high; stop
        92's review.)"""
        y = OdeState.from_state(s)
        _, before = gap_rates(s.time, y)
        touch = jax.lax.stop_gradient(depth + gap_atol * jnp.maximum(jnp.max(jnp.abs(before)), 1.0))
        s = impact_law(ctx, params, s, touching=touch)  # Newton's law, then plastic for slower slots
        gaps, after = gap_rates(s.time, OdeState.from_state(s))
        # Rounding leaves ~eps of the approach speed; more means the sweeps did not finish.
        tolerance = jnp.sqrt(eps) * jnp.max(jnp.abs(jnp.where(gaps <= touch, before, 0.0)))
        return eqx.error_if(
            s, jnp.any((gaps <= touch) & (after < -tolerance)),
            "rb.ode.solve_with_impacts: a touching pair still approaches after an impact's impulse "
            "(raise ContactSettings.impact_iterations for chains of touching bodies).",
        )

    def segment(carry, _):
        current, count = carry

        def advance(current):
            y0 = OdeState.from_state(current)
            start_gaps = gaps_at(current.time, y0)
            depth = 16 * eps * jnp.maximum(jnp.max(jnp.abs(current.position)), 1.0)
            # The event's level below a touching (or rounding-deep) start: a guard against
            # re-detecting the contact just left, not physics, so it carries no derivative.
            # With the start gap's, the floor moved with a touching start's height, and
            # d(impact time)/d(height) came out 0 instead of 1/v (stop 97's review).
            reference = jax.lax.stop_gradient(jnp.where(start_gaps > 0, 0.0, start_gaps - depth))
            dtmax, gap_atol = segment_bounds(current)
            controller = default_controller(solver, jnp.asarray(rtol, dtype), atol, dtmax=dtmax)
            event = diffrax.Event(condition, root_finder=SafeguardedNewton(atol=gap_atol), direction=False)
            sol = diffrax.diffeqsolve(term, solver, t0=current.time, t1=t1, dt0=None,
                                      y0=y0, args=(params, reference),
                                      saveat=diffrax.SaveAt(t1=True), stepsize_controller=controller,
                                      event=event, max_steps=max_steps, adjoint=adjoint)
            t_end = sol.ts[-1]
            after = jax.tree.map(lambda x: x[-1], sol.ys).to_state(t_end)
            hit = jnp.asarray(sol.event_mask)
            after = jax.lax.cond(hit, impulse, lambda s, *_: s, after, depth, gap_atol)
            return after, hit

        running = current.time < t1
        after, hit = jax.lax.cond(running, advance, lambda s: (s, jnp.zeros((), bool)), current)
        time = jnp.where(hit, after.time, jnp.inf)
        return (after, count + hit.astype(jnp.int32)), (time, after)

    start = _runtime_checks(dataclasses.replace(state, rotation=None, contact_impulse=None),
                            jnp.asarray(state.time, dtype), t1, None, rtol, atol, "rb.ode.solve_with_impacts")
    (final, count), (times, states) = jax.lax.scan(
        segment, (start, jnp.zeros((), jnp.int32)), None, length=max_impacts)
    # diffrax ends a segment that meets no event at t1 exactly; one whose event falls on t1
    # has reached it too.
    return ImpactSolution(final=final, impact_times=times, after_impact=states, num_impacts=count,
                          reached_t1=final.time >= t1)
