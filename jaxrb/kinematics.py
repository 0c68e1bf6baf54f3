"""Kinematics of points fixed on a rigid body (seeds 000 and 001, "offset kinematics").

For a point at offset ``r`` from the centre of mass (world frame, ``r = A r_body``)::

    x = x_cm + r                                  (seed 000: x_i = x_CM + A r_i)
    v = v_cm + omega x r                           (seed 001, offset velocity)
    a = a_cm + alpha x r + omega x (omega x r)     (seed 001, offset acceleration)
      = a_cm + a_tan + a_cen

Shapes: body quantities ``(N, 3)``, points ``(N, 3)`` or ``(N, K, 3)`` (K points per body).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from . import spatial
from .dynamics import accelerations
from .state import Params, State, angular_velocity, rotation_matrix

__all__ = [
    "point_velocity",
    "tangential_acceleration",
    "centripetal_acceleration",
    "point_acceleration",
    "world_points",
    "world_point_velocities",
    "world_point_accelerations",
]


def point_velocity(v_cm, omega, r) -> Float[Array, "... 3"]:
    """``v = v_cm + omega x r`` (m/s). All world frame; broadcasts."""
    return v_cm + spatial.cross(omega, r)


def tangential_acceleration(alpha, r) -> Float[Array, "... 3"]:
    """``a_tan = alpha x r`` (m/s^2)."""
    return spatial.cross(alpha, r)


def centripetal_acceleration(omega, r) -> Float[Array, "... 3"]:
    """``a_cen = omega x (omega x r)`` (m/s^2), pointing towards the rotation axis."""
    return spatial.cross(omega, spatial.cross(omega, r))


def point_acceleration(a_cm, alpha, omega, r) -> Float[Array, "... 3"]:
    """``a = a_cm + alpha x r + omega x (omega x r)`` (m/s^2)."""
    return a_cm + tangential_acceleration(alpha, r) + centripetal_acceleration(omega, r)


def _per_point(body_array, points):
    # Insert the K axis when points are (N, K, 3).
    return body_array[:, None, :] if points.ndim == 3 else body_array


def _offsets(state: State, points_body) -> Float[Array, "..."]:
    points_body = jnp.asarray(points_body, dtype=state.position.dtype)
    if points_body.ndim not in (2, 3) or points_body.shape[0] != state.position.shape[0] or points_body.shape[-1] != 3:
        raise ValueError(f"points_body must be (N, 3) or (N, K, 3) body-frame offsets (m) with N = "
                         f"{state.position.shape[0]} bodies, got shape {points_body.shape}.")
    rot = rotation_matrix(state)
    rot = rot[:, None] if points_body.ndim == 3 else rot
    return spatial.matvec(rot, points_body)


def world_points(state: State, points_body) -> Float[Array, "... 3"]:
    """World positions of body-fixed points ``x = x_cm + A r_body`` (m).

    ``points_body``: ``(N, 3)`` or ``(N, K, 3)`` offsets from the centre of mass, body frame.
    """
    offsets = _offsets(state, points_body)
    return _per_point(state.position, offsets) + offsets


def world_point_velocities(params: Params, state: State, points_body) -> Float[Array, "... 3"]:
    """World velocities (m/s) of body-fixed points."""
    omega = angular_velocity(params, state)
    r = _offsets(state, points_body)
    return point_velocity(_per_point(state.velocity, r), _per_point(omega, r), r)


def world_point_accelerations(scene, params: Params, state: State, points_body) -> Float[Array, "... 3"]:
    """World accelerations (m/s^2) of body-fixed points, from the scene's forces."""
    a_cm, alpha = accelerations(scene, params, state)
    omega = angular_velocity(params, state)
    r = _offsets(state, points_body)
    return point_acceleration(_per_point(a_cm, r), _per_point(alpha, r), _per_point(omega, r), r)
