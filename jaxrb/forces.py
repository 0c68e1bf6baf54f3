"""Force models: each turns ``(params, state)`` into a per-body wrench ``(F, tau)``.

``F`` is the total force (N) on each body's centre of mass and ``tau`` the total torque
(N m) about that centre of mass, both in the world frame, shapes ``(N, 3)``.

Force models are static parts of a scene (frozen, hashable): a scene lists the models it
needs and the compiled step contains those and nothing else. Their numerical
coefficients live in :class:`jaxrb.Params`, so they can be differentiated and fitted.

Seed 000's "force vs torque puzzle" -- is a force applied off the centre of mass
counted twice, once to accelerate the centre and once to spin the body? -- is answered
by :func:`point_forces_to_wrench`: yes, and that is right. The same force ``f`` at
offset ``r`` contributes ``f`` to ``F`` and ``r x f`` to ``tau``; a force through the
centre of mass contributes no torque.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax.numpy as jnp
from jaxtyping import Array, Float

from . import spatial
from .state import Params, State, angular_velocity

__all__ = [
    "ForceModel",
    "Gravity",
    "LinearDamping",
    "AngularDamping",
    "PointForces",
    "ExternalWrench",
    "point_forces_to_wrench",
]

Wrench = tuple[Float[Array, "n 3"], Float[Array, "n 3"]]


def point_forces_to_wrench(
    position: Float[Array, "n 3"],
    points: Float[Array, "n k 3"],
    forces: Float[Array, "n k 3"],
) -> Wrench:
    """Sum forces applied at world points into a wrench (seeds 000 and 001).

    ``F = sum_i f_i`` and ``tau = sum_i r_i x f_i`` with ``r_i = p_i - x_cm``.

    Args:
        position: ``(N, 3)`` centres of mass (m, world).
        points: ``(N, K, 3)`` application points (m, world).
        forces: ``(N, K, 3)`` forces (N, world).
    """
    r = points - position[:, None, :]
    return jnp.sum(forces, axis=1), jnp.sum(spatial.cross(r, forces), axis=1)


class ForceModel:
    """Base class. Subclasses are frozen dataclasses with a ``wrench`` method."""

    def wrench(self, params: Params, state: State) -> Wrench:  # pragma: no cover - abstract
        raise NotImplementedError


@dataclasses.dataclass(frozen=True)
class Gravity(ForceModel):
    """Uniform gravity, ``F = m g`` with ``g = params.gravity``; no torque.

    A scene's ``gravity=`` argument adds this model; you need not list it yourself.
    """

    def wrench(self, params: Params, state: State) -> Wrench:
        force = params.mass[..., None] * params.gravity[..., None, :]
        return force, jnp.zeros_like(force)


@dataclasses.dataclass(frozen=True)
class LinearDamping(ForceModel):
    """Viscous drag on the centre of mass, ``F = -c v`` with ``c = params.linear_damping``."""

    def wrench(self, params: Params, state: State) -> Wrench:
        force = -params.linear_damping[:, None] * state.velocity
        return force, jnp.zeros_like(force)


@dataclasses.dataclass(frozen=True)
class AngularDamping(ForceModel):
    """Viscous torque ``tau = -c omega`` with ``c = params.angular_damping``."""

    def wrench(self, params: Params, state: State) -> Wrench:
        torque = -params.angular_damping[:, None] * angular_velocity(params, state)
        return jnp.zeros_like(torque), torque


def _check_shape(name: str, value, expected: tuple[int, ...], dtype) -> Array:
    value = jnp.asarray(value)
    if value.shape != expected:
        raise ValueError(
            f"{name} returned an array of shape {value.shape}; expected {expected}. "
            "User force functions return per-body arrays with the body axis first."
        )
    # A user function may build float64 constants under x64; keep the state's precision.
    return value.astype(dtype)


def _pair(model: str, what: str, out):
    """``out`` as two values, or a ``ValueError``: an array returned alone (the torque
    forgotten) had been unpacked along its body axis, and the error then named a shape
    the function did not return."""
    if not isinstance(out, (tuple, list)) or len(out) != 2:
        got = f"an array of shape {jnp.shape(out)}" if hasattr(out, "shape") else repr(type(out).__name__)
        raise ValueError(f"{model} function must return a pair {what}, got {got}.")
    return out


@dataclasses.dataclass(frozen=True)
class PointForces(ForceModel):
    """Forces applied at world points, from a user function.

    ``fn(t, params, state) -> (points, forces)`` with ``points`` and ``forces`` of shape
    ``(N, K, 3)`` (m and N, world frame): ``K`` forces per body. Use a zero force for
    bodies with fewer. ``fn`` must be a pure JAX function; it is traced into the step.
    """

    fn: Callable

    def wrench(self, params: Params, state: State) -> Wrench:
        points, forces = _pair("PointForces", "(points, forces)", self.fn(state.time, params, state))
        points = jnp.asarray(points)
        n = state.position.shape[0]
        if points.ndim != 3 or points.shape[0] != n or points.shape[2] != 3:
            raise ValueError(
                f"PointForces function returned points of shape {points.shape}; "
                f"expected (N={n}, K, 3)."
            )
        dtype = state.position.dtype
        forces = _check_shape("PointForces function (forces)", forces, points.shape, dtype)
        return point_forces_to_wrench(state.position, points.astype(dtype), forces)


@dataclasses.dataclass(frozen=True)
class ExternalWrench(ForceModel):
    """A force and torque per body from a user function.

    ``fn(t, params, state) -> (F, tau)``, each ``(N, 3)``, world frame, torque about the
    centre of mass. ``fn`` must be a pure JAX function; it is traced into the step.
    """

    fn: Callable

    def wrench(self, params: Params, state: State) -> Wrench:
        force, torque = _pair("ExternalWrench", "(F, tau)", self.fn(state.time, params, state))
        n = state.position.shape[0]
        dtype = state.position.dtype
        force = _check_shape("ExternalWrench function (force)", force, (n, 3), dtype)
        torque = _check_shape("ExternalWrench function (torque)", torque, (n, 3), dtype)
        return force, torque
