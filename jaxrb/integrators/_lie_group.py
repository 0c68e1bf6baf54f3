"""A fourth-order Lie-group method: Runge-Kutta-Munthe-Kaas (RKMK4) on SO(3)."""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp

from .. import spatial
from ..dynamics import linear_acceleration, wrench
from ..state import Params, State, inverse_inertia_body
from ._base import Integrator

__all__ = ["RKMK4", "dexp_inverse"]

# The classical Runge-Kutta tableau: stage nodes, stage coefficients a_{i,i-1}, weights.
_NODES = (0.0, 0.5, 0.5, 1.0)
_WEIGHTS = (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)


def dexp_inverse(theta, omega):
    """``dexp^-1_theta(omega) = omega - theta x omega / 2 + theta x (theta x omega) / 12``.

    The inverse of the derivative of the exponential map on so(3), as the Bernoulli
    series ``sum_k B_k / k! ad_theta^k`` truncated after ``k = 2`` (``B_3 = 0``, so the
    first dropped term is O(|theta|^4)). With ``theta = O(dt)`` inside a step, that
    error enters the step at O(dt^5): enough for order 4 (Munthe-Kaas 1999).
    """
    first = spatial.cross(theta, omega)
    return omega - 0.5 * first + spatial.cross(theta, first) / 12.0


def _shortest(theta):
    """The rotation vector of ``exp(theta)`` with the least angle: ``theta`` itself where
    ``|theta| <= pi``, else turned back along its axis by whole turns (``(..., 3)``, rad).

    The same rotation, so a stage's attitude is unchanged; but ``dexp^-1`` grows like
    ``|theta|^2``, and far past the step's stability limit the stages compounded it:
    ``|theta|`` 1.2e3, 1.5e7 and 1e14 in one step at ``|omega| dt = 100``, which overflowed
    float32 (NaN attitudes from ``|omega| dt`` of about 150). Below ``pi``, which is every
    stage of an accurate step, the values are untouched, bit for bit.
    """
    angle_sq = jnp.sum(theta * theta, axis=-1, keepdims=True)
    wrap = angle_sq > jnp.pi**2
    angle = jnp.sqrt(jnp.where(wrap, angle_sq, 1.0))
    turned = angle - 2.0 * jnp.pi * jnp.round(angle / (2.0 * jnp.pi))  # in [-pi, pi]
    return jnp.where(wrap, theta * (turned / angle), theta)


class RKMK4(Integrator):
    """Classical RK4 on the Lie algebra: the attitude moves only by exponentials.

    Write the attitude as ``q(t) = exp(theta(t)) q_n`` with ``theta`` in the world frame.
    Since ``A' = omega~ A``, ``theta`` obeys ``theta' = dexp^-1_theta(omega)`` with
    ``theta(t_n) = 0``, an ODE in a vector space, and (x, v, L) obey the usual L-form
    equations. The classical RK4 tableau is applied to all of it: stage attitudes are
    ``exp(theta_i) q_n``, and the step ends with ``q_{n+1} = exp(theta) q_n``.

    Without the ``dexp^-1`` correction (averaging the stage angular velocities and
    applying one exponential) the method is only second order, because rotations do
    not commute; ``tests/test_integrators.py`` builds that variant and measures slope 2.

    * Order 4 in x, v, L and the attitude.
    * Torque-free: world ``L`` exactly (``L' = 0`` in every stage) and ``|q| = 1`` to
      round-off (every attitude is an exponential of a unit quaternion), with no
      renormalisation doing any work. Energy is not conserved: O(dt^4) error with a
      slow drift (not symplectic).
    * Cost: four force evaluations and four quaternion exponentials per step.
    * Stability: explicit, so accuracy collapses once ``|omega| dt`` is of order 1 (the
      energy error exceeds 100% from about 2.5: ``benchmarks/work_precision.py``), but
      with ``L`` exact and the attitude a rotation the energy stays bounded in
      ``[|L|^2 / 2 I_max, |L|^2 / 2 I_min]``: no blow-up of the state. The truncated
      ``dexp^-1`` series grows like ``|theta|^2``, and the stages compound the rotation
      vector, so each stage takes the rotation vector of least angle (the same rotation;
      untouched below ``pi``): without that, float32 attitudes turned NaN from ``|omega|
      dt`` of about 150, and a gradient through 200 steps (inertia (1, 2, 3), one spin
      direction) was 3e55 at ``|omega| dt = 3`` and NaN at 16; now it is 0.019, 0.53 and
      1.97 at 3, 4 and 16 (9e15 at 100). Far past the limit such a gradient is finite but
      says little: differentiate at ``|omega| dt`` well below 2.5.
    """

    order: ClassVar[int] = 4

    def step(self, scene, params: Params, state: State, dt: float) -> State:
        q0 = state.orientation
        inverse_inertia = inverse_inertia_body(params)

        def stage(theta, position, velocity, angular_momentum, node):
            q = spatial.quat_multiply(spatial.quat_exp(theta), q0)
            at_stage = State(position, q, velocity, angular_momentum, state.time + node * dt)
            force, torque = wrench(scene, params, at_stage)

            def theta_rate(inverse_inertia, q, l_world, theta):
                # One body: omega = A I^-1 A^T L (world), then dexp^-1.
                omega = spatial.quat_rotate(q, spatial.matvec(inverse_inertia, spatial.quat_rotate_inverse(q, l_world)))
                return dexp_inverse(theta, omega)

            rate = jax.vmap(theta_rate)(inverse_inertia, q, angular_momentum, theta)
            return rate, velocity, linear_acceleration(params, force), torque

        zero = jnp.zeros_like(state.position)
        slopes = []
        increment = (zero, jnp.zeros_like(zero), jnp.zeros_like(zero), jnp.zeros_like(zero))
        for i, node in enumerate(_NODES):
            if i:
                a = node * dt  # the classical tableau: a_{i,i-1} = c_i, other a_ij = 0
                increment = tuple(a * k for k in slopes[-1])
            theta, dx, dv, dl = increment
            theta = _shortest(theta)
            slopes.append(stage(theta, state.position + dx, state.velocity + dv,
                                state.angular_momentum + dl, node))
        total = [sum(w * k[j] for w, k in zip(_WEIGHTS, slopes, strict=True)) for j in range(4)]
        theta, dx, dv, dl = (dt * t for t in total)
        theta = _shortest(theta)
        orientation = spatial.quat_normalize(spatial.quat_multiply(spatial.quat_exp(theta), q0))
        return State(
            position=state.position + dx,
            orientation=orientation,
            velocity=state.velocity + dv,
            angular_momentum=state.angular_momentum + dl,
            time=state.time + dt,
            rotation=None if state.rotation is None else spatial.quat_to_matrix(orientation),
        )
