"""The dynamic pytrees, ``Params`` and ``State``, and the quantities derived from them.

Both are arrays only, with a leading body axis of length ``N``. Changing their values
never recompiles a step; changing their shapes or dtypes does. Derived quantities
(angular velocity, rotation matrix, world inertia, energies, momenta) are computed by
the functions below, never stored, so they cannot go stale.

Frames: ``_world`` quantities are in the inertial frame; ``Params.inertia`` is in the
body frame, about the centre of mass. The body frame's origin is the centre of mass.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import spatial

__all__ = [
    "Params",
    "State",
    "rotation_matrix",
    "body_inertia",
    "inverse_inertia_body",
    "world_inertia",
    "inverse_world_inertia",
    "angular_velocity",
    "body_angular_velocity",
    "translational_kinetic_energy",
    "rotational_kinetic_energy",
    "kinetic_energy",
    "potential_energy",
    "total_energy",
    "linear_momentum",
    "angular_momentum_about",
]


class Params(eqx.Module):
    """Physical parameters: everything a user may want to differentiate or fit.

    Attributes:
        mass: ``(N,)`` kg.
        inertia: ``(N, 3, 3)`` kg m^2, body frame, about the centre of mass.
        gravity: ``(3,)`` m/s^2, world frame. Used only if the scene declares gravity.
        linear_damping: ``(N,)`` N s/m; force ``-c v``. Used only if the scene declares
            :class:`jaxrb.LinearDamping`.
        angular_damping: ``(N,)`` N m s; torque ``-c omega``. Used only if the scene
            declares :class:`jaxrb.AngularDamping`.
        extra: any pytree of arrays, passed untouched to user force functions (their
            own differentiable parameters). ``None`` by default.
        restitution: ``(P,)`` dimensionless, in ``[0, 1]``, one per contact pair in
            ``scene.contact_pairs`` order: Newton's coefficient, the ratio of separating
            to approaching normal velocity at an impact. ``(0,)`` without contacts.
        friction: ``(P,)`` dimensionless, ``>= 0``: Coulomb's coefficient per contact pair
            (one value for static and kinetic friction). ``(0,)`` without contacts.
    """

    mass: Float[Array, " n"] = eqx.field(converter=jnp.asarray)
    inertia: Float[Array, "n 3 3"] = eqx.field(converter=jnp.asarray)
    gravity: Float[Array, "3"] = eqx.field(converter=jnp.asarray)
    linear_damping: Float[Array, " n"] = eqx.field(converter=jnp.asarray)
    angular_damping: Float[Array, " n"] = eqx.field(converter=jnp.asarray)
    extra: Any = None
    restitution: Float[Array, " p"] = eqx.field(converter=jnp.asarray, default=())
    friction: Float[Array, " p"] = eqx.field(converter=jnp.asarray, default=())

    def replace(self, **changes) -> Params:
        """A copy with some fields changed, e.g. ``params.replace(mass=params.mass * 2)``.

        Not validated here (it works on traced values): a step checks the shapes when it is
        traced, and :meth:`jaxrb.Scene.check_params` checks the values.
        """
        return _replace(self, changes)


class State(eqx.Module):
    """The state of ``N`` rigid bodies (seed 000's state: x_CM, v_CM, orientation, L).

    Attributes:
        position: ``(N, 3)`` m, centre of mass, world frame.
        orientation: ``(N, 4)`` unit quaternion ``(w, x, y, z)``, body to world.
        velocity: ``(N, 3)`` m/s, centre-of-mass velocity, world frame.
        angular_momentum: ``(N, 3)`` kg m^2/s, about the centre of mass, world frame.
            It is the state variable (seeds 000 and 001): torque-free, it is constant
            by construction, whatever the integrator does to the attitude.
        time: ``()`` s.
        rotation: ``(N, 3, 3)`` or ``None``. Only the seed-000 integrator
            (:class:`jaxrb.integrators.ExplicitEuler`) carries its rotation matrix ``A``
            here, because it updates ``A`` itself (``A <- A + dt w~ A``); then this
            matrix, not the quaternion, is the body's attitude.
        contact_impulse: ``(C, 3)`` or ``None``. In a scene with contacts, the impulses
            (N s; normal, tangent, tangent) of each contact slot in the last step, kept to
            warm-start the next step's solver. :meth:`jaxrb.Step.prepare` adds it.
    """

    position: Float[Array, "n 3"] = eqx.field(converter=jnp.asarray)
    orientation: Float[Array, "n 4"] = eqx.field(converter=jnp.asarray)
    velocity: Float[Array, "n 3"] = eqx.field(converter=jnp.asarray)
    angular_momentum: Float[Array, "n 3"] = eqx.field(converter=jnp.asarray)
    time: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    rotation: Float[Array, "n 3 3"] | None = None
    contact_impulse: Float[Array, "c 3"] | None = None

    def replace(self, **changes) -> State:
        """A copy with some fields changed, e.g. ``state.replace(velocity=v)``. Only
        ``rotation`` and ``contact_impulse`` may be ``None``."""
        return _replace(self, changes)


def _replace(module, changes: dict):
    """``dataclasses.replace``, with a message naming the field where an array is required
    and ``None`` was given (the converter's own error named none)."""
    optional = {f.name for f in dataclasses.fields(module) if f.default is None}
    for name, value in changes.items():
        if value is None and name not in optional:
            kind = type(module).__name__
            raise ValueError(f"{kind}.replace({name}=None): {kind}.{name} is required, an array; "
                             f"only {sorted(optional) or 'no field'} may be None")
    return dataclasses.replace(module, **changes)


def rotation_matrix(state: State) -> Float[Array, "n 3 3"]:
    """``A``: body-to-world rotation matrix (columns are the body axes in the world frame)."""
    if state.rotation is not None:
        return state.rotation
    return spatial.quat_to_matrix(state.orientation)


def body_inertia(params: Params) -> Float[Array, "n 3 3"]:
    """``I_body`` (kg m^2, body frame, about the centre of mass): ``params.inertia``'s symmetric part.

    Every step reads the inertia through this, so a result depends on the symmetric part
    alone, and its gradient in ``params.inertia`` is symmetric: a plain gradient step on
    ``params.inertia`` keeps it symmetric, and every integrator gives the same gradient
    entry by entry. (Read as it is, ``I^-1`` made RK4's gradient the rank-one ``-a w^T``,
    and the integrators differed in how they split it between ``I_ij`` and ``I_ji``.) The
    value of a symmetric ``params.inertia``, which ``Scene.params`` ensures, is unchanged to
    the last bit.
    """
    return 0.5 * (params.inertia + spatial.transpose(params.inertia))


def inverse_inertia_body(params: Params) -> Float[Array, "n 3 3"]:
    """``I_body^-1`` (kg^-1 m^-2), by the closed-form 3x3 inverse."""
    return spatial.inverse3(body_inertia(params))


def _to_world(rot, m_body):
    return spatial.matmul(spatial.matmul(rot, m_body), spatial.transpose(rot))


def _same_bodies(params: Params, state: State) -> None:
    """Raise unless ``params`` and ``state`` hold the same number of bodies (shapes only,
    so it works on traced values): one scene's params with another's state had broadcast
    silently (two bodies' energies from one body's state)."""
    n_params, n_state = jnp.shape(params.mass)[-1:], jnp.shape(state.position)[-2:-1]
    if n_params != n_state:
        raise ValueError(f"params hold {n_params[0] if n_params else '?'} bodies and the state "
                         f"{n_state[0] if n_state else '?'}: they must come from the same scene "
                         f"(scene.params(), scene.state()).")


def world_inertia(params: Params, state: State) -> Float[Array, "n 3 3"]:
    """``I = A I_body A^T`` (seed 000), kg m^2, world frame, about the centre of mass."""
    _same_bodies(params, state)
    return _to_world(rotation_matrix(state), body_inertia(params))


def inverse_world_inertia(params: Params, state: State) -> Float[Array, "n 3 3"]:
    """``I^-1 = A I_body^-1 A^T`` (seed 000's update of I^-1)."""
    _same_bodies(params, state)
    return _to_world(rotation_matrix(state), inverse_inertia_body(params))


def angular_velocity(params: Params, state: State) -> Float[Array, "n 3"]:
    """``omega = I^-1 L`` (rad/s, world frame), seed 000's ``omega <- I^-1 L``."""
    _same_bodies(params, state)
    rot = rotation_matrix(state)
    l_body = spatial.matvec(spatial.transpose(rot), state.angular_momentum)
    omega_body = spatial.matvec(inverse_inertia_body(params), l_body)
    return spatial.matvec(rot, omega_body)


def body_angular_velocity(params: Params, state: State) -> Float[Array, "n 3"]:
    """Angular velocity in the body frame, ``A^T omega`` (rad/s)."""
    _same_bodies(params, state)
    rot = rotation_matrix(state)
    l_body = spatial.matvec(spatial.transpose(rot), state.angular_momentum)
    return spatial.matvec(inverse_inertia_body(params), l_body)


def translational_kinetic_energy(params: Params, state: State) -> Float[Array, " n"]:
    """``m |v|^2 / 2`` per body (J)."""
    _same_bodies(params, state)
    return 0.5 * params.mass * spatial.dot(state.velocity, state.velocity)


def rotational_kinetic_energy(params: Params, state: State) -> Float[Array, " n"]:
    """``omega . L / 2 = L . I^-1 L / 2`` per body (J)."""
    return 0.5 * spatial.dot(angular_velocity(params, state), state.angular_momentum)


def kinetic_energy(params: Params, state: State) -> Float[Array, " n"]:
    """Translational plus rotational kinetic energy per body (J)."""
    return translational_kinetic_energy(params, state) + rotational_kinetic_energy(params, state)


def potential_energy(params: Params, state: State) -> Float[Array, " n"]:
    """Gravitational potential ``-m g . x`` per body (J), zero at the world origin."""
    _same_bodies(params, state)
    return -params.mass * spatial.dot(params.gravity[..., None, :], state.position)


def total_energy(params: Params, state: State) -> Float[Array, " n"]:
    """Kinetic plus gravitational potential energy per body (J).

    After a contact step the velocity is leapfrog's: a body resting under gravity shows
    ``g dt / 2`` (the closing half kick), and a body in contact can show a one-step gain of
    the order of ``m |v| |g| dt / 2``, 2e-5 J for a 2 kg capsule tipping over on the ground
    at dt = 1 ms. That is the time discretisation, not an impulse adding energy: over the
    same millisecond the gain was 7.5e-7 J at dt = 0.1 ms, and a loss at 0.01 ms
    (benchmarks/README.md, stop 87)."""
    return kinetic_energy(params, state) + potential_energy(params, state)


def linear_momentum(params: Params, state: State) -> Float[Array, "n 3"]:
    """``p = m v`` per body (kg m/s, world frame)."""
    _same_bodies(params, state)
    # [..., None]: stacked members (B, N) read as bodies on the last axis, as the energies do
    # (mass[:, None] had paired member i with body i where B == N, and failed where not).
    return params.mass[..., None] * state.velocity


def angular_momentum_about(
    params: Params, state: State, point: Float[Array, "3"] | None = None
) -> Float[Array, "n 3"]:
    """Angular momentum of each body about a fixed world ``point`` (default: origin).

    ``L_point = (x - point) x m v + L`` (kg m^2/s, world frame). Summed over bodies it is
    the quantity conserved by an isolated system.
    """
    if point is not None and np.shape(point) != (3,):
        raise ValueError(f"point must be one (3,) world point (m), got shape {np.shape(point)}.")
    if point is not None:  # in the state's dtype (a float64 point promoted a float32 state)
        point = jnp.asarray(point, state.position.dtype).reshape((1,) * (state.position.ndim - 1) + (3,))
    r = state.position if point is None else state.position - point
    return spatial.cross(r, linear_momentum(params, state)) + state.angular_momentum
