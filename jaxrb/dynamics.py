"""Newton-Euler equations of motion.

Two equivalent forms (seeds 000 and 001):

* **L-form** (the state form): ``x' = v``, ``v' = F/m``, ``L' = tau``, ``omega = I^-1 L``
  with ``I^-1 = A I_body^-1 A^T``, and the attitude follows ``A' = omega~ A`` (or
  ``q' = (0, omega) q / 2``). Torque-free, ``L`` is constant exactly.
* **omega-form**: ``alpha = I^-1 (tau - omega x I omega)`` (seed 001, Newton-Euler), with the
  gyroscopic term ``omega x I omega``; for integrators that step the angular velocity.

Only the force models a scene declares are traced: a scene without forces adds nothing.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from . import spatial
from .state import Params, State, angular_velocity, inverse_inertia_body, world_inertia

if TYPE_CHECKING:
    from .scene import Scene

__all__ = [
    "wrench",
    "linear_acceleration",
    "angular_acceleration",
    "body_angular_acceleration",
    "accelerations",
    "StateDerivative",
    "derivative",
    "stage_derivative",
]


def wrench(scene: Scene, params: Params, state: State) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"]]:
    """Total force (N) and torque about the centre of mass (N m), world frame, ``(N, 3)`` each.

    The sum runs over ``scene.force_models``, a static tuple: models the scene does not
    declare are not in the compiled step at all.
    """
    force = jnp.zeros_like(state.velocity)
    torque = jnp.zeros_like(state.angular_momentum)
    for model in scene.force_models:
        f, t = model.wrench(params, state)
        force = force + f
        torque = torque + t
    return force, torque


def linear_acceleration(params: Params, force: Float[Array, "n 3"]) -> Float[Array, "n 3"]:
    """``a_cm = F / M`` (m/s^2)."""
    return force / params.mass[..., None]


def angular_acceleration(
    inertia_world: Float[Array, "n 3 3"],
    omega: Float[Array, "n 3"],
    torque: Float[Array, "n 3"],
) -> Float[Array, "n 3"]:
    """``alpha = I^-1 (tau - omega x I omega)`` (rad/s^2), all in one frame (seed 001)."""
    gyroscopic = spatial.cross(omega, spatial.matvec(inertia_world, omega))
    return spatial.matvec(spatial.inverse3(inertia_world), torque - gyroscopic)


def body_angular_acceleration(
    inertia_body: Float[Array, "n 3 3"],
    omega_body: Float[Array, "n 3"],
    torque_body: Float[Array, "n 3"],
) -> Float[Array, "n 3"]:
    """Euler's equations in the body frame, ``I_b w_b' = tau_b - w_b x I_b w_b``.

    The same formula as :func:`angular_acceleration`; in the body frame ``I_b`` is constant.
    """
    return angular_acceleration(inertia_body, omega_body, torque_body)


def accelerations(scene: Scene, params: Params, state: State) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"]]:
    """Centre-of-mass acceleration (m/s^2) and angular acceleration (rad/s^2), world frame."""
    force, torque = wrench(scene, params, state)
    omega = angular_velocity(params, state)
    return (
        linear_acceleration(params, force),
        angular_acceleration(world_inertia(params, state), omega, torque),
    )


class StateDerivative(eqx.Module):
    """Time derivative of a :class:`State` in L-form (same shapes as the state)."""

    position: Float[Array, "n 3"]
    orientation: Float[Array, "n 4"]
    velocity: Float[Array, "n 3"]
    angular_momentum: Float[Array, "n 3"]


def quat_derivative(omega: Float[Array, "n 3"], q: Float[Array, "n 4"]) -> Float[Array, "n 4"]:
    """``q' = (0, omega) q / 2`` for a world-frame angular velocity ``omega``."""
    omega_quat = jnp.concatenate([jnp.zeros_like(omega[..., :1]), omega], axis=-1)
    return 0.5 * spatial.quat_multiply(omega_quat, q)


def derivative(scene: Scene, params: Params, state: State) -> StateDerivative:
    """The L-form right-hand side ``(x', q', v', L') = (v, (0, omega) q / 2, F/m, tau)``."""
    force, torque = wrench(scene, params, state)
    omega = angular_velocity(params, state)
    return StateDerivative(
        position=state.velocity,
        orientation=quat_derivative(omega, state.orientation),
        velocity=linear_acceleration(params, force),
        angular_momentum=torque,
    )


def stage_derivative(scene: Scene, params: Params, state: State) -> State:
    """The L-form right-hand side as a ``State`` of rates, defined off the unit sphere too.

    Returns ``State(position=v, orientation=q', velocity=F/m, angular_momentum=tau,
    time=1)``, so Runge-Kutta stages are tree maps over states (RK4, and the diffrax
    vector field of :mod:`jaxrb.ode`).

    Stage quaternions ``q + c dt k`` are not unit. Forces and ``omega`` are evaluated at
    the normalised attitude, and ``q' = (0, omega) q / 2`` uses the raw ``q``. This is a
    smooth ODE on R^4 whose exact flow keeps ``|q|`` (the product of a pure quaternion
    with ``q`` is orthogonal to ``q``), so plain RK4 on it keeps its fourth order.
    Normalising the stage quaternions instead would change the stage slopes by O(dt^2)
    and cost two orders.
    """
    q_raw = state.orientation
    norm = spatial.safe_norm(q_raw, keepdims=True)
    unit = dataclasses.replace(state, orientation=q_raw / norm)
    force, torque = wrench(scene, params, unit)

    def kinematics(mass, inverse_inertia_body, q_unit, q, velocity, angular_momentum, f):
        # One body: omega = A I_body^-1 A^T L and q' = (0, omega) q_raw / 2. Vmapped over
        # the body axis for the component-major code XLA then emits (see SemiImplicitEuler).
        l_body = spatial.quat_rotate_inverse(q_unit, angular_momentum)
        omega = spatial.quat_rotate(q_unit, spatial.matvec(inverse_inertia_body, l_body))
        return quat_derivative(omega, q), f / mass

    q_dot, acceleration = jax.vmap(kinematics)(
        params.mass, inverse_inertia_body(params), unit.orientation, q_raw, state.velocity,
        state.angular_momentum, force,
    )
    return State(
        position=state.velocity,
        orientation=q_dot,
        velocity=acceleration,
        angular_momentum=torque,
        time=jnp.ones_like(state.time),
    )
