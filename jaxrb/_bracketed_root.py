"""A root finder that keeps its root bracketed: Newton's method safeguarded by bisection,
for diffrax's events.

diffrax locates an event inside the step whose condition went from positive at the step's
start to non-positive at its end, and hands its root finder that step as ``options=dict(
lower=t_start, upper=t_end)``. Newton's method, started at the step's end, is not bound to
that bracket: where the condition is below zero at the end but already rising again (the
bottom of a dip, as when two balls graze, or a spinning box's edge sweeps into the ground),
its steps lead away from the root and the solve failed with "the maximum number of steps
was reached in the nonlinear solver" (stop 92's review: 12 of 41 grazing passes of two
balls overlapping by 1 cm, 8 of 13 start angles of a spinning cube).

Here each iteration evaluates the function and its slope at the iterate, narrows the
bracket ``[lower, upper]`` (whose ends keep opposite signs) to the iterate's side, and
takes Newton's step where it stays in the bracket, or else bisects it (Numerical Recipes'
``rtsafe``). Near a simple root Newton's steps are taken and converge quadratically, as
before; the bracket makes every iterate stay in the step. The derivative of the root is
the implicit function theorem's, which ``optimistix.root_find`` computes from the root,
whichever finder found it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, PyTree, Scalar

__all__ = ["SafeguardedNewton"]


class _BracketState(eqx.Module):
    lower: Scalar  # the end where the function is positive
    upper: Scalar  # the end where it is zero or negative
    started: Bool[Array, ""]  # whether a step has been taken
    error: Float[Array, ""]  # the function at the last evaluated point
    step: Float[Array, ""]  # the length of the last step
    before: Float[Array, ""]  # the length of the step before it


class SafeguardedNewton(optx.AbstractRootFinder):
    """Newton's method kept in ``[lower, upper]`` (``options``) by bisection, for a scalar
    function positive at ``lower`` and zero or negative at ``upper`` (a diffrax event with
    ``direction=False``), started at ``y`` (diffrax: the step's end).

    Stops where the last step was shorter than ``atol`` and the function's magnitude is
    under ``atol`` (as ``optimistix.Newton`` with ``rtol = 0``), where the function is
    exactly zero, or where the bracket has closed to adjacent floating-point numbers. A
    bisection step shorter than ``atol`` leaves the root within ``atol`` of the iterate,
    however flat the function (a flat stretch just above zero, as the event has beside a
    body at rest, stopped a bracketed secant method 0.18 s early).
    """

    atol: float
    rtol: float = 0.0  # optimistix's interface asks for one; the test above takes none
    norm: ClassVar[Callable[[PyTree], Scalar]] = jnp.abs

    def init(self, fn, y, args, options: dict[str, Any], f_struct, aux_struct, tags) -> _BracketState:
        del fn, y, args, aux_struct, tags
        lower = jnp.asarray(options["lower"], f_struct.dtype)
        upper = jnp.asarray(options["upper"], f_struct.dtype)
        inf = jnp.asarray(jnp.inf, f_struct.dtype)
        return _BracketState(lower, upper, jnp.zeros((), bool), inf, inf, inf)

    def step(self, fn, y, args, options, state: _BracketState, tags):
        del options, tags
        y = jnp.clip(y, state.lower, state.upper)
        (f, aux), (slope, _) = jax.jvp(lambda t: fn(t, args), (y,), (jnp.ones_like(y),))
        positive = f > 0
        lower = jnp.where(positive, y, state.lower)
        upper = jnp.where(positive, state.upper, y)
        newton = y - f / jnp.where(slope != 0, slope, 1.0)
        # Newton's step only where it stays in the bracket and is under half the step before
        # the last (``rtsafe``'s test: else a slope near zero, or a step that fails to shrink,
        # would slow the search where bisection halves the bracket every time).
        inside = (slope != 0) & (newton >= lower) & (newton <= upper) & (jnp.abs(newton - y) <= 0.5 * state.before)
        new_y = jnp.where(f == 0, y, jnp.where(inside, newton, lower + 0.5 * (upper - lower)))
        return new_y, _BracketState(lower, upper, jnp.ones((), bool), f, jnp.abs(new_y - y), state.step), aux

    def terminate(self, fn, y, args, options, state: _BracketState, tags):
        del fn, y, args, options, tags
        small = (state.step < self.atol) & (jnp.abs(state.error) < self.atol)
        closed = jnp.nextafter(state.lower, state.upper) >= state.upper
        return state.started & (small | (state.error == 0) | closed), optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}
