"""Symplectic splitting of the free rigid body (Dullweber, Leimkuhler & McLachlan 1997)."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import spatial
from ..inertia import principal_axes
from ..state import Params, State
from ._base import Integrator
from ._composition import kick_drift_kick

__all__ = ["SymplecticSplitting"]


def _axis_quat(axis: int, angle):
    """Quaternion of a rotation by ``angle`` (rad) about coordinate axis ``axis``."""
    half = 0.5 * angle
    vector = [jnp.zeros_like(half)] * 3
    vector[axis] = jnp.sin(half)
    return jnp.stack([jnp.cos(half), *vector], axis=-1)


def _rotate_about_axis(vector, axis: int, angle):
    """``Rot(e_axis, angle) @ vector`` for a ``(3,)`` vector, in closed form."""
    i, j = (axis + 1) % 3, (axis + 2) % 3
    c, s = jnp.cos(angle), jnp.sin(angle)
    out = [vector[0], vector[1], vector[2]]
    out[i] = c * vector[i] - s * vector[j]
    out[j] = s * vector[i] + c * vector[j]
    return jnp.stack(out)


class SymplecticSplitting(Integrator):
    """DLM splitting of the free rigid body, with kick-drift-kick for forces.

    In the principal frame the kinetic energy ``T = sum_k P_k^2 / 2 I_k`` splits into
    three terms, and the flow of each alone is an exact rotation about one principal
    axis by ``dt P_k / I_k`` (``P`` the body momentum, which rotates the opposite way).
    The free step is the symmetric (Strang) composition::

        R_a(dt/2) R_b(dt/2) R_c(dt) R_b(dt/2) R_a(dt/2)

    with ``(a, b, c) = axes`` indexing the principal moments in ascending order. A
    non-diagonal body inertia is handled by going through its principal frame
    (:func:`jaxrb.principal_axes`). Forces and torques enter by kick-drift-kick
    (:mod:`jaxrb.integrators._composition`).

    * Order 2, symplectic and time-reversible (Dullweber, Leimkuhler & McLachlan,
      J. Chem. Phys. 107, 5840 (1997)).
    * Torque-free: world angular momentum exactly (each sub-flow is a rigid rotation of
      the body about its own axis, and ``L`` is never updated); ``|P|`` exactly; energy
      error O(dt^2), bounded with no drift (backward error analysis of a symplectic map).
    * Cost: two force evaluations (three with velocity-dependent forces), five
      axis rotations (five sin/cos pairs) and a 3x3 eigen-decomposition of the inertia
      per body (loop-invariant under ``lax.scan``, so XLA can hoist it).
    * Stability: no step-size limit; a fast spin about a principal axis is integrated
      exactly. The default ``axes = (0, 1, 2)`` (smallest moment outermost, largest
      innermost) gave the smallest energy error of the six orderings on both the
      asymmetric top ``I = (1, 2, 3)`` (max 1.5e-7 over 1e5 steps of 0.01 s; the worst
      ordering, 2.6e-5) and the spinning rod ``I = (1e-4, 1, 1 + 5e-5)``,
      ``omega = (100, 1, 0)`` (5e-6 over 10 s at dt = 0.01; the worst, 0.31).
    """

    axes: tuple[int, int, int] = eqx.field(default=(0, 1, 2), static=True)
    order: ClassVar[int] = 2

    def __check_init__(self):
        if sorted(self.axes) != [0, 1, 2]:
            raise ValueError(
                f"SymplecticSplitting(axes=...) must order the three principal axes, i.e. be a "
                f"permutation of (0, 1, 2); got {self.axes!r}."
            )

    def free_rotation(self, params: Params, orientation, angular_momentum, dt: float):
        """Torque-free attitude flow over ``dt`` at constant world ``L``; ``(N, 4)``."""
        outer, middle, inner = self.axes
        sequence = ((outer, 0.5), (middle, 0.5), (inner, 1.0), (middle, 0.5), (outer, 0.5))

        def rotate(inertia, q, l_world):
            moments, axes_matrix = principal_axes(inertia)
            principal = spatial.matrix_to_quat(axes_matrix)  # principal frame -> body frame
            q = spatial.quat_multiply(q, principal)  # principal frame -> world
            momentum = spatial.quat_rotate_inverse(q, l_world)
            for axis, fraction in sequence:
                angle = fraction * dt * momentum[axis] / moments[axis]
                q = spatial.quat_multiply(q, _axis_quat(axis, angle))
                momentum = _rotate_about_axis(momentum, axis, -angle)
            q = spatial.quat_multiply(q, spatial.quat_conjugate(principal))
            return spatial.quat_normalize(q)

        return jax.vmap(rotate)(params.inertia, orientation, angular_momentum)

    def step(self, scene, params: Params, state: State, dt: float) -> State:
        return kick_drift_kick(scene, params, state, dt, self.free_rotation)
